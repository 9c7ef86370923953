"""The self-contained HTML report of a case: ``CASE_DIR/report.html``.

The first page is the clinical summary: the stenosis verdict beside the virtual duplex (ICA and CCA PSV and EDV,
their ratio, the SRU consensus grade, the pressure drop across the lesion), the diameter profile along the CCA and
ICA, the wall shear stress maps, the wall regions (CCA, bulb, ICA, ECA, stenosis) with the bifurcation
geometry, the inflow waveform and outlet split, the cycle state (the TAWSS change of each cycle from
the previous one), the grid convergence study of the wall indices (or a note that none was run), the wall
area exposed to low and oscillating shear and the statistics of each index per region, and a warning for
every stale, partial or failed result.  The detail of each stage follows.  Each part is built
from the files a stage wrote, whatever wrote them (``carotid run`` or the per-stage commands); a stage that
has not run yields a note instead of failing the report.  Pictures are PNG embedded as data URIs, so the
file can be mailed or archived alone.
"""

from __future__ import annotations

import base64
import html
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from carotid import __version__
from carotid.centerline import read_centerlines
from carotid.centerline.features import (BULB_EXCESS, BULB_WINDOW, CCA_WINDOW, DAUGHTER_START, DIRECTION_WINDOW,
                                        geometry_features)
from carotid.centerline.plaque import calcified
from carotid.errors import CarotidError, CarotidWarning
from carotid.flow.convergence import STATUS
from carotid.flow.indices import HIGH_OSI, LOW_TAWSS_PA, node_areas
from carotid.flow.regions import INDEX_UNITS, REGION_INDICES, REGION_NAMES, region_statistics, wall_regions
from carotid.io import atomic_path, read_image, read_record
from carotid.io.vtkfile import read_vtk
from carotid.report import figures
from carotid.report.checks import Check, quality_checks, stale_warnings, stenosis_category

# Colour-map clipping of the wall maps: the percentile of the values at the top colour (OSI keeps its
# natural range 0-0.5).
CLIP_PERCENTILE = 98.0
WALL_MAPS = (("TAWSS", "TAWSS (Pa)", "viridis"), ("OSI", "OSI (-)", "magma"), ("RRT", "RRT (1/Pa)", "magma"),
             ("ECAP", "ECAP (1/Pa)", "magma"))
REGION_COLOURS = ("#4c72b0", "#dd8452", "#55a868", "#8172b3", "#c44e52", "#937860")  # by REGION_NAMES
CATEGORY_CLASS = {"<50 %": "mild", "50-69 %": "moderate", ">=70 %": "severe", "near-occlusion": "severe"}

STYLE = """
body { font-family: system-ui, sans-serif; margin: 0.6em auto; max-width: 1360px; padding: 0 12px; color: #222; }
h1 { font-size: 1.35em; margin: 0.2em 0; } h1 small { font-weight: normal; color: #666; font-size: 0.65em; }
h2 { color: #b22; margin: 1.6em 0 0.4em; border-bottom: 1px solid #ddd; }
h3 { margin: 0.2em 0 0.3em; font-size: 1.05em; }
figure { margin: 0.3em 0; } figure img { max-width: 100%; }
figcaption { font-size: 0.8em; color: #555; }
table { border-collapse: collapse; margin: 0.3em 0 0.8em; font-size: 0.85em; }
caption { text-align: left; font-weight: 600; padding: 0.2em 0; }
td, th { border: 1px solid #ccc; padding: 0.15em 0.5em; text-align: left; vertical-align: top; }
th { background: #f6f6f6; font-weight: normal; }
.missing { color: #888; font-style: italic; }
.top { display: grid; grid-template-columns: 370px 1fr 340px; gap: 14px; align-items: start; }
.top figure img { max-height: 290px; }
.maps { display: grid; grid-template-columns: repeat(4, 1fr); gap: 8px; text-align: center; }
.maps figure img { max-height: 400px; width: auto; }
.more { display: grid; grid-template-columns: 1fr 1fr; gap: 14px; align-items: start; }
.more figure img { max-height: 560px; width: auto; }
.verdict table { font-size: 0.8em; margin: 0; } .verdict p { margin: 0.2em 0 0.4em; }
#duplex { margin-top: 0.4em; } #duplex p.missing { font-size: 0.75em; } #duplex td, #duplex th { white-space: nowrap; }
#duplex .cols { display: flex; gap: 12px; align-items: start; }
.verdict .grade { font-size: 1.9em; font-weight: 700; }
.badge { display: inline-block; padding: 0.1em 0.5em; border-radius: 4px; color: white; font-weight: 600; }
.mild { background: #2a7d2e; } .moderate { background: #c77800; } .severe { background: #b22; }
.warnings { background: #fff4e5; border-left: 4px solid #c77800; padding: 0.3em 0.8em; font-size: 0.85em; }
.warnings ul { margin: 0.2em 0; padding-left: 1.1em; } .ok { color: #2a7d2e; }
.fail { color: #b22; font-weight: 600; } .pass { color: #2a7d2e; }
"""


@dataclass
class Table:
    """A table: caption, column header (None for name-value rows), rows, and optional column groups (label,
    columns spanned) drawn above the header."""

    caption: str
    rows: list
    header: list | None = None
    groups: list | None = None


@dataclass
class Section:
    """One detail section: pictures (caption, PNG bytes), tables and notes."""

    title: str
    figures: list[tuple[str, bytes]] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    note: str = ""


# The JSON records of a case folder: Case attribute, file, and the stage that writes it.
RECORDS = (("record", "case.json", "`carotid run`"), ("segmentation", "segmentation/report.json", "segment stage"),
           ("geometry", "geometry.json", "centerlines stage"), ("surface_quality", "surface_quality.json",
                                                                 "surface stage"),
           ("mesh_quality", "mesh_quality.json", "mesh stage"), ("flow", "flow/summary.json", "simulate stage"),
           ("convergence", "flow/convergence.json", "convergence study (carotid simulate --convergence)"))


@dataclass
class Case:
    """The records of a case folder (each an empty dict when its stage, or the convergence study, has not run, or
    its file cannot be read), its centerlines, lumen surface, volume mesh and wall indices surface (None when
    missing or unreadable; each read once), and
    ``unreadable``: file name -> one sentence for each of them that exists but cannot be read."""

    dir: Path
    record: dict
    segmentation: dict
    geometry: dict
    surface_quality: dict
    mesh_quality: dict
    flow: dict
    convergence: dict = field(default_factory=dict)
    centerlines: object = None
    surface: object = None
    mesh: object = None
    wall: object = None
    unreadable: dict = field(default_factory=dict)

    @classmethod
    def read(cls, case_dir: Path) -> "Case":
        """Read every record of ``case_dir``; a file that cannot be read is entered in ``unreadable``."""
        unreadable = {}

        def attempt(name: str, read, *args):
            if not (case_dir / name).exists():
                return None
            try:
                return read(*args)
            except CarotidError as exc:
                unreadable[name] = f"{name} could not be read: {str(exc).removeprefix(f'{case_dir / name}: ')}"
                return None

        records = {key: attempt(name, read_record, case_dir / name, f"rerun the {stage}") or {}
                   for key, name, stage in RECORDS}
        # centerlines.vtp is read with geometry.json: an unreadable geometry.json is entered once, as itself
        centerlines = None if "geometry.json" in unreadable else \
            attempt("centerlines.vtp", read_centerlines, case_dir / "centerlines.vtp")
        surface = attempt("surface.vtp", read_vtk, case_dir / "surface.vtp", "surface", None,
                          "rerun the surface stage")
        mesh = attempt("mesh.vtu", read_vtk, case_dir / "mesh.vtu", "mesh", None, "rerun the mesh stage")
        wall = attempt("flow/indices.vtp", read_vtk, case_dir / "flow" / "indices.vtp", "wall indices", None,
                       "rerun the simulate stage")
        return cls(case_dir, **records, centerlines=centerlines, surface=surface, mesh=mesh, wall=wall,
                   unreadable=unreadable)

    def absent(self, stage: str, *names: str) -> str:
        """Why the files ``names`` of ``stage`` are not shown: the first that could not be read, else the stage
        has not run."""
        return next((self.unreadable[name] for name in names if name in self.unreadable),
                    f"The {stage} stage has not run") + "."

    def cap_names(self) -> dict[int, str]:
        """Cap id (``CellEntityIds`` 2, 3, ...) -> branch name, from ``geometry.json`` or the surface record."""
        caps = self.geometry.get("caps") or self.surface_quality.get("caps") or []
        return {int(cap["id"]): str(cap.get("name", cap["id"])) for cap in caps}


# Unit suffixes of record keys and how the tables print them.
_UNITS = (("_per_mm", "1/mm"), ("_m3s", "m³/s"), ("_mm3", "mm³"), ("_mm2", "mm²"), ("_mmhg", "mmHg"), ("_mm", "mm"),
          ("_deg", "°"), ("_pa", "Pa"), ("_mb", "MB"), ("_hu", "HU"), ("_cm_s", "cm/s"), ("_ml_s", "mL/s"),
          ("_m_s", "m/s"), ("_s", "s"))


def readable(key: str) -> str:
    """A dotted record key as a table label: words, with the unit suffix as a unit (``dt_s`` -> ``dt (s)``)."""
    parts, unit = [], ""
    for part in key.split("."):
        for suffix, name in _UNITS:
            if part.endswith(suffix) and len(part) > len(suffix):
                part, unit = part[: -len(suffix)], name
                break
        parts.append(part.replace("_", " "))
    text = " › ".join(parts)
    return f"{text} ({unit})" if unit else text


def _value(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    if value is None:
        return "–"
    return str(value)


def flatten(data, prefix: str = "") -> list[tuple[str, str]]:
    """Nested dicts as (readable label, value) rows.

    Lists of up to 8 numbers are joined; longer lists (histograms, per-iteration traces) are left to
    the JSON records; lists of dicts are expanded under each item's name.
    """
    rows = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += flatten(value, f"{name}.")
        elif isinstance(value, list) and any(isinstance(v, dict) for v in value):
            for number, item in enumerate(value):
                label = (item.get("name") or item.get("branch") or number) if isinstance(item, dict) else number
                rows += flatten(item, f"{name}.{label}.") if isinstance(item, dict) else \
                    [(readable(f"{name}.{label}"), _value(item))]
        elif isinstance(value, list) and len(value) > 8:
            continue
        elif isinstance(value, list):
            rows.append((readable(name), ", ".join(_value(v) for v in value)))
        else:
            rows.append((readable(name), _value(value)))
    return rows


def active_parameters(params: dict) -> dict:
    """Parameters without those of a switched-off option: ``wall_*`` go when ``wall`` is false."""
    off = [key for key, value in params.items() if value is False]
    return {key: value for key, value in params.items() if not any(key.startswith(f"{flag}_") for flag in off)}


def checks_table(checks: list[Check]) -> Table:
    """Quality criteria of one stage with their value and a pass/fail flag."""
    rows = [(c.quantity, _value(c.value), c.criterion, "pass" if c.passed else "FAIL") for c in checks]
    stage = f" of the {checks[0].stage} stage" if checks else ""
    return Table(f"Quality checks{stage}", rows, ["quantity", "value", "criterion", "status"])


def find_image(case: Case) -> tuple[Path | None, str]:
    """The CT image a case was segmented from, checked against the segmentation grid.

    Candidates: ``case.json``'s ``input`` (``carotid run``), then ``segmentation/report.json``'s
    ``image.path`` (relative paths taken from the case folder).

    Returns
    -------
    (Path or None, str)
        The image, or None with the reason it is missing.
    """
    candidates = [case.record.get("input"), case.segmentation.get("image", {}).get("path")]
    for text in filter(None, candidates):
        path = Path(text) if Path(text).is_absolute() else case.dir / text
        if path.exists():
            return path, ""
    return None, ("the input CT image is not recorded in this case folder" if not any(candidates)
                  else f"the input CT image {next(filter(None, candidates))} is not found")


def exposure_rows(wall, regions: np.ndarray, names) -> list[tuple]:
    """The wall regions' table: area, area exposed to low TAWSS and high OSI, and each index's statistics.

    Parameters
    ----------
    wall : pyvista.PolyData
        ``flow/indices.vtp`` (point arrays ``TAWSS`` in Pa, ``OSI``, and the other indices present).
    regions : ndarray of int, shape (n_points,)
        Region code of each point, an index into ``names`` (:func:`carotid.flow.regions.wall_regions`).
    names : sequence of str
        Region names.

    Returns
    -------
    list of tuple
        Per region with wall area, then the whole wall: (region, area mm², % TAWSS < 0.4 Pa, % OSI > 0.2,
        % both, then mean, 5th and 95th percentile of each index of ``REGION_INDICES`` present), formatted;
        :func:`carotid.flow.regions.region_statistics` (area-weighted over the nodes).
    """
    area = node_areas(wall.points, wall.triangulate().faces.reshape(-1, 4)[:, 1:])
    present = [name for name in REGION_INDICES if name in wall.array_names]
    table = region_statistics({k: np.asarray(wall[k], dtype=float) for k in present}, area, regions, names)
    rows = []
    for name, entry in table.items():
        stats = [f"{entry[k][stat]:.3g}" if k in entry else "–" for k in present for stat in ("mean", "p5", "p95")]
        rows.append((name, f"{entry['area_mm2']:.0f}",
                     *(f"{100 * entry[f'{key}_area_fraction']:.1f}"
                       for key in ("low_tawss", "high_osi", "low_tawss_high_osi")), *stats))
    return rows


def exposure_header(wall) -> tuple[list[str], list[tuple[str, int]]]:
    """Column names of :func:`exposure_rows` for the indices ``wall`` holds, and their groups (label, span)."""
    header = ["region", "area (mm²)", f"TAWSS < {LOW_TAWSS_PA} Pa", f"OSI > {HIGH_OSI}", "both"]
    groups = [("", 2), ("% of the region's area", 3)]
    for name in REGION_INDICES:
        if name in wall.array_names:
            header += ["mean", "p5", "p95"]
            groups.append((f"{name} ({INDEX_UNITS[name]})" if INDEX_UNITS[name] else name, 3))
    return header, groups


def bifurcation_rows(geometry: dict | None) -> list[tuple]:
    """The bifurcation geometry table (quantity, value, definition) from
    :func:`carotid.centerline.features.bifurcation_geometry`; empty without it."""
    if not geometry or "reason" in geometry:
        return []

    def diameters(window):  # a landmark window in CCA radii, as CCA diameters
        return f"{window[0] / 2:g}-{window[1] / 2:g}"

    rows = [("bifurcation angle (°)", f"{geometry['bifurcation_angle_deg']:.1f}",
             f"ICA to ECA, principal axes over {diameters(DIRECTION_WINDOW)} CCA diameters from the bifurcation "
             "point"),
            ("ICA angle (°)", f"{geometry['ica_angle_deg']:.1f}", "ICA to the CCA's continuation"),
            ("ECA angle (°)", f"{geometry['eca_angle_deg']:.1f}", "ECA to the CCA's continuation"),
            ("ICA/CCA area ratio", f"{geometry['ica_cca_area_ratio']:.3f}",
             f"median section areas: CCA {diameters(CCA_WINDOW)} diameters below the bifurcation point, ICA from "
             f"{DAUGHTER_START / 2:g} CCA diameters above to its end"),
            ("bifurcation area ratio (ICA+ECA)/CCA", f"{geometry['bifurcation_area_ratio']:.3f}",
             "the same sections, ECA as the ICA"),
            ("bulb diameter ratio", f"{geometry['bulb_diameter_ratio']:.3f}",
             f"largest ICA diameter {diameters(BULB_WINDOW)} CCA diameters above the bifurcation point "
             f"({geometry['bulb_max_diameter_mm']:.2f} mm) over the CCA's ({geometry['cca_diameter_mm']:.2f} mm)"),
            ("bulb length (mm)", f"{geometry['bulb_end_mm']:.1f}",
             f"along the ICA, to where its radius is back within {100 * BULB_EXCESS:g} % of the ICA's "
             f"({geometry['ica_diameter_mm']:.2f} mm diameter)")]
    for name, branch in geometry["branches"].items():
        rows.append((f"{name} tortuosity", f"{branch['tortuosity']:.3f}", "arc length / chord - 1, whole branch"))
    for name, branch in geometry["branches"].items():
        rows.append((f"{name} planarity (°)", f"{branch['planarity_deg']:.1f}",
                     "angle of its direction out of the plane of the other two branches' directions"))
    return rows


def _flow_series(case: Case) -> dict | None:
    """Output times (s), inflow and outlet flows (mL/s) from the flow checkpoint."""
    from carotid.flow.output import load_checkpoint

    path = case.dir / "flow" / "checkpoint.npz"
    if not path.exists():
        return None
    records = [r for r in load_checkpoint(path)[1]["records"] if r["step"] > 0 and r.get("diagnostics")]
    if len(records) < 2:
        return None
    return {"time": np.array([r["time"] for r in records]),
            "inflow": 1e6 * np.array([r["diagnostics"]["inflow"] for r in records]),
            "outflow": 1e6 * np.array([r["diagnostics"]["outflow"] for r in records])}


def stenosis_location(stenosis: dict) -> str:
    """Where a graded stenosis lies, in words."""
    side = "proximal to" if stenosis["branch"] == "CCA" else "distal to"
    point = ", ".join(f"{v:.1f}" for v in stenosis["location_mm"])
    return (f"{stenosis['branch']}, {stenosis['arclength_from_bifurcation_mm']:.1f} mm {side} the bifurcation "
            f"(LPS {point} mm)")


def verdict_html(geometry: dict, absent: str = "The centerline stage has not run.") -> str:
    """The stenosis verdict: NASCET and ECST grades, category, diameters, location and the calcium there;
    ``absent`` says why an empty ``geometry`` is (:meth:`Case.absent`)."""
    grade = geometry.get("stenosis")
    if not grade:
        reason = "The centerline stage found no gradable branch." if geometry else absent
        return ('<div class="verdict"><h3>Stenosis</h3><p class="missing">No stenosis grading. '
                f"{html.escape(reason)}</p></div>")
    category = stenosis_category(grade["nascet"], grade["min_diameter_mm"], grade["distal_diameter_mm"])
    rows = [("ECST", f"{100 * grade['ecst']:.1f} %"),
            ("area reduction", f"{100 * grade['area_reduction']:.1f} %"),
            ("minimal diameter", f"{grade['min_diameter_mm']:.2f} mm"),
            ("distal ICA diameter (NASCET reference)", f"{grade['distal_diameter_mm']:.2f} mm"),
            ("local diameter (ECST reference)", f"{grade['local_diameter_mm']:.2f} mm"),
            ("location", stenosis_location(grade))]
    if grade.get("calcium_mm") is not None:
        rows.append(("calcium", "against the lumen at the stenosis" if grade["calcium_mm"] == 0 else
                     f"{grade['calcium_mm']:.1f} mm from the lumen at the stenosis"))
    notes = ("<p class='missing'>The narrowest section ends the measured branch: no distal reference, "
             "graded 0.</p>" if grade.get("distal_reference") == "none" else "")
    if calcified(grade):
        notes += ("<p class='missing'>Calcified stenosis: the calcium's blur hides the lumen's wall beside it, "
                  "so this grade is less certain than that of a soft plaque; read it against the image.</p>")
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return (f'<div class="verdict" id="verdict"><h3>Stenosis ({html.escape(grade["branch"])})</h3>'
            f'<div class="grade">NASCET {100 * grade["nascet"]:.1f} %</div>'
            f'<p><span class="badge {CATEGORY_CLASS[category]}">{html.escape(category)}</span> '
            f"NASCET category</p><table>{body}</table>{notes}</div>")


def duplex_html(flow: dict, absent: str = "The flow stage has not run.") -> str:
    """The virtual duplex of the first page (``flow/summary.json`` ``duplex``): ICA and CCA PSV and EDV, their
    ratio, the SRU consensus grade with each criterion's category, and the pressure drop across the stenosis;
    ``absent`` says why an empty ``flow`` is (:meth:`Case.absent`)."""
    duplex = flow.get("duplex") or {}
    if "gates" not in duplex:
        reason = f"None: {duplex.get('reason', 'summary.json predates it')}." if flow else f"None. {absent}"
        return (f'<div class="verdict" id="duplex"><h3>Virtual duplex</h3><p class="missing">{html.escape(reason)}'
                "</p></div>")
    ica, cca, sru, pressure = duplex["gates"]["ICA"], duplex["gates"]["CCA"], duplex["sru"], duplex["pressure"]
    ratio = pressure["ratio_mean"]
    rows = [("ICA PSV", f"{ica['psv_cm_s']:.0f} cm/s", sru["by_psv"]),
            ("ICA EDV", f"{ica['edv_cm_s']:.0f} cm/s", sru["by_edv"]),
            ("ICA/CCA PSV ratio", f"{duplex['psv_ratio']:.2f}", sru["by_ratio"]),
            ("CCA PSV / EDV", f"{cca['psv_cm_s']:.0f} / {cca['edv_cm_s']:.0f} cm/s", ""),
            ("pressure drop, mean / systole", f"{pressure['drop_mean_mmhg']:.1f} / "
             f"{pressure['drop_peak_systole_mmhg']:.1f} mmHg", ""),
            ("pressure ratio distal/proximal", "–" if ratio is None else f"{ratio:.3f} (mean)", ""),
            ("NASCET (geometry)", f"{100 * duplex['nascet']:.1f} %", duplex["nascet_category"])]
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td><td>{html.escape(c)}</td></tr>"
                   for k, v, c in rows)
    grade = sru["grade"]
    badge = CATEGORY_CLASS.get(grade, "mild" if grade == "normal" else "severe")
    where = (f"Gates (spheres of {ica['gate_radius_mm']:.2f} and {cca['gate_radius_mm']:.2f} mm on the axis): ICA "
             f"{ica['arclength_from_bifurcation_mm']:.1f} mm distal, CCA {cca['arclength_from_bifurcation_mm']:.1f} mm "
             "proximal to the bifurcation; SRU category of each criterion beside it. Pressures "
             + ("absolute (lumped outlets)." if ratio is not None else "relative (prescribed split): no ratio."))
    partial = (" Partial cycle: PSV and EDV of part of a cycle." if duplex.get("partial") else
               " First cycle, from rest: EDV read at the cycle's end." if duplex.get("first_cycle") else "")
    return (f'<div class="verdict" id="duplex"><h3>Virtual duplex (SRU consensus, Grant 2003)</h3>'
            f'<p><span class="badge {badge}">{html.escape(grade)}</span> SRU grade from the ICA PSV'
            f'{"" if sru["concordant"] else "; the criteria disagree"}</p><div class="cols"><table>{body}</table>'
            f'<p class="missing">{html.escape(where + partial)}</p></div></div>')


def calibration_rows(calibration: dict) -> list[tuple]:
    """The inflow calibration table (``summary.json`` ``inflow_calibration``): targets, what the inlet and the CCA
    gate reach, and the map ``a q + b``."""
    gate = (calibration.get("gate_psv_cm_s"), calibration.get("gate_edv_cm_s"))
    return [("CCA PSV (cm/s)", f"{calibration['target_psv_cm_s']:.1f}", f"{calibration['inlet_psv_cm_s']:.1f}",
             _value(gate[0])),
            ("CCA EDV (cm/s)", f"{calibration['target_edv_cm_s']:.1f}", f"{calibration['inlet_edv_cm_s']:.1f}",
             _value(gate[1])),
            ("mean flow (mL/s)", "", f"{calibration['mean_flow_ml_s']:.2f} (uncalibrated "
             f"{calibration['uncalibrated_mean_flow_ml_s']:.2f})", ""),
            ("map of the flow q (mL/s)", "", f"a = {calibration['a']:.3f}, b = {calibration['b_ml_s']:.2f}", "")]


def _figure(caption: str, png: bytes, element_id: str = "") -> str:
    data = base64.b64encode(png).decode()
    ident = f' id="{element_id}"' if element_id else ""
    return (f'<figure{ident}><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _table_html(table: Table) -> str:
    if not table.rows:
        return ""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header) if table.header else ""
    body = []
    for row in table.rows:
        cells = [f"<th>{html.escape(str(row[0]))}</th>" if not table.header else
                 f"<td>{html.escape(str(row[0]))}</td>"]
        for cell in row[1:]:
            flag = {"pass": ' class="pass"', "FAIL": ' class="fail"'}.get(str(cell), "")
            cells.append(f"<td{flag}>{html.escape(str(cell))}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    groups = "".join(f'<th colspan="{span}">{html.escape(label)}</th>' for label, span in table.groups or [])
    return (f"<table><caption>{html.escape(table.caption)}</caption>" + (f"<tr>{groups}</tr>" if groups else "")
            + (f"<tr>{head}</tr>" if head else "") + "".join(body) + "</table>")


def profile_figure(case: Case) -> bytes | None:
    """The diameter profile along the CCA and the graded branch, or None without centerlines."""
    from carotid.centerline.axes import arclength
    from carotid.centerline.features import grading_profiles

    if case.centerlines is None:
        return None
    branches = {b.name: b for b in case.centerlines.branches}
    grade = case.geometry.get("stenosis")
    name = grade["branch"] if grade else "ICA"
    target = branches.get(name)
    if target is None:
        return None
    parts = [(arclength(target.points), target)]
    if name != "CCA" and "CCA" in branches:  # the CCA runs to the bifurcation: negative distances
        cca = branches["CCA"]
        parts.insert(0, (arclength(cca.points) - arclength(cca.points)[-1], cca))
    s = np.concatenate([p[0] for p in parts])
    narrow, median = (2.0 * np.concatenate(profile) for profile in zip(*(grading_profiles(p[1]) for p in parts)))
    if name == "CCA":
        s = s - s[-1]
        grade = dict(grade, arclength_from_bifurcation_mm=-grade["arclength_from_bifurcation_mm"])
    label = "distance from the bifurcation (mm): CCA < 0 < " + name if name != "CCA" else \
        "distance from the bifurcation along the CCA (mm)"
    return figures.diameter_profile(s, narrow, median, grade, label)


def case_warnings(case: Case) -> list[str]:
    """Every unreadable record, stale result, partial result and failed quality check of a case, one sentence
    each."""
    warnings = [f"{message}." for message in case.unreadable.values()]
    warnings += stale_warnings(case.dir, case.record, case.geometry, case.segmentation, case.mesh_quality,
                              case.flow, case.surface, case.mesh)
    failed = [c for c in quality_checks(case.segmentation, case.surface_quality, case.mesh_quality, case.flow)
              if not c.passed]
    warnings += [f"{c.stage} quality check failed: {c.quantity} = {_value(c.value)} (criterion {c.criterion})."
                 for c in failed]
    if case.flow.get("partial"):
        warnings.append(f"The wall indices (TAWSS, OSI, RRT, ECAP) average only "
                        f"{case.flow['indices_cycle_fraction']:.2g} of a cardiac cycle: they are partial, not "
                        "comparable with the indices of a whole cycle.")
    return warnings


def summary_html(case: Case) -> str:
    """The clinical first page."""
    warnings = case_warnings(case)
    notes = "".join(f"<li>{html.escape(w)}</li>" for w in warnings) or '<li class="ok">No stale, partial or ' \
                                                                        "failed results.</li>"
    profile = profile_figure(case)
    top = [verdict_html(case.geometry, case.absent("centerline", "geometry.json")),
           "<div>" + (_figure("Lumen diameter along the CCA and the graded branch, with the stenosis and its references",
                              profile, "profile") if profile else
                      '<p class="missing">No centerlines: no diameter profile.</p>')
           + duplex_html(case.flow, case.absent("flow", "flow/summary.json")) + "</div>",
           f'<div class="warnings" id="warnings"><h3>Warnings</h3><ul>{notes}</ul></div>']
    parts = [f'<div class="top">{"".join(top)}</div>']

    wall = case.wall
    if wall is not None:
        maps = []
        for name, label, cmap in WALL_MAPS:
            if name not in wall.array_names:
                continue
            clim, clip = ((0.0, 0.5), "full range 0-0.5") if name == "OSI" else colour_range(np.asarray(wall[name]))
            maps.append(_figure(f"{label}: colour scale {clip}", figures.wall_map(wall, name, label, clim, cmap)))
        parts.append(f'<div class="maps" id="wss-maps">{"".join(maps)}</div>')
    else:
        reason = case.absent("flow", "flow/indices.vtp", "flow/summary.json")[:-1]
        parts.append(f'<p class="missing">{html.escape(reason)}: no wall shear stress maps.</p>')
    if case.flow:
        parts.append(convergence_html(case))

    left = []
    cl = case.centerlines
    geometry = geometry_features(cl) if cl is not None else {}
    surface = case.surface
    if surface is not None and cl is not None:
        ids = np.asarray(surface["CellEntityIds"])
        caps = case.cap_names()
        cap_ids = sorted(set(np.unique(ids).tolist()) - {1})
        regions = wall_regions(np.asarray(surface.cell_centers().points), cl, geometry)
        shown = np.unique(regions[ids == 1])
        labels = np.where(ids == 1, np.searchsorted(shown, regions), len(shown) + np.searchsorted(cap_ids, ids))
        legend = [(REGION_NAMES[code], REGION_COLOURS[code]) for code in shown]
        legend += [(f"{'inlet' if c == 2 else 'outlet'} {caps.get(c, c)}", "0.35" if c == 2 else "0.65")
                   for c in cap_ids]
        grade = case.geometry.get("stenosis")
        marker = (np.array(grade["location_mm"]), f"stenosis, NASCET {100 * grade['nascet']:.0f} %") \
            if grade else None
        left.append(_figure("Wall regions by the nearest centerline (bulb and stenosis from the radius profile), "
                            "caps, graded stenosis in red", figures.labelled_surface(surface, labels, legend, marker)))
    shape = geometry.get("bifurcation_geometry") or {}
    rows = bifurcation_rows(shape)
    left.append(_table_html(Table("Bifurcation geometry (Thomas et al. 2005, Lee et al. 2008)", rows,
                                  ["quantity", "value", "definition"])) if rows else
                '<p class="missing">No bifurcation geometry: the centerlines have no CCA, ICA and ECA, or are too '
                f"short for its landmarks. {html.escape(shape.get('reason', ''))}</p>")
    parts.append(f'<div class="more"><div>{"".join(left)}</div><div>{"".join(flow_summary_html(case))}</div></div>')
    if wall is not None and cl is not None and {"TAWSS", "OSI"} <= set(wall.array_names):
        rows = exposure_rows(wall, wall_regions(np.asarray(wall.points), cl, geometry), REGION_NAMES)
        parts.append(_table_html(Table(
            f"Wall regions: area with low TAWSS (< {LOW_TAWSS_PA} Pa), high OSI (> {HIGH_OSI}) and both, and the "
            "area-weighted mean and 5th and 95th percentiles of each index", rows, *exposure_header(wall))))
    return "\n".join(parts)


def flow_summary_html(case: Case) -> list[str]:
    """The inflow waveform, the outlet split achieved and the cycle state."""
    if not case.flow:
        return []
    caps = case.cap_names()
    outlets = case.flow.get("mass_balance", {}).get("outlets", {})
    lumped = (case.flow.get("outlets") or {}).get("parameters") is not None
    rows = [(caps.get(int(label), label), f"{100 * o['target_fraction']:.1f}",
             f"{100 * o['fraction_of_inflow_mean']:.1f}",
             "-" if o.get("error_max") is None else f"{100 * o['error_max']:.2g}")
            for label, o in outlets.items()]
    header = (["outlet", "calibration share (%)", "achieved, mean (%)", "(not imposed)"] if lumped else
              ["outlet", "target (%)", "achieved, mean (%)", "largest error (points of %)"])
    parts = [_table_html(Table("Outlet flow split (last cycle)", rows, header))]
    series = _flow_series(case)
    if series is not None:
        named = {"inflow (CCA)": (series["time"], series["inflow"])}
        for j, label in enumerate(outlets):
            named[f"outflow {caps.get(int(label), label)}"] = (series["time"], series["outflow"][:, j])
        parts.append(_figure("Inflow waveform and outlet flows as computed",
                             figures.time_series(named, "time (s)", "flow (mL/s)")))
    calibration = case.flow.get("inflow_calibration")
    if calibration:
        parts.append(_table_html(Table("Inflow calibrated to the measured CCA velocities (q -> a q + b on the inlet's "
                                       "Womersley centreline velocity)", calibration_rows(calibration),
                                       ["quantity", "measured", "inlet centreline", "CCA gate (simulated)"])))
    parts += cycle_state_html(case.flow)
    return parts


def colour_range(values: np.ndarray) -> tuple[tuple[float, float], str]:
    """Colour range of a wall map, 0 to the ``CLIP_PERCENTILE``-th percentile of the finite values, and its
    caption text.

    Parameters
    ----------
    values : ndarray, shape (n,)
        The mapped values (unit of the map); NaN values are left out.

    Returns
    -------
    clim : (float, float)
        The colour range, unit of ``values``.
    text : str
        The clipping value and the maximum, for the caption.
    """
    top_value = float(np.nanpercentile(values, CLIP_PERCENTILE)) or 1.0
    return (0.0, top_value), (f"clipped at the {CLIP_PERCENTILE:g}th percentile, {top_value:.3g}; "
                              f"maximum {np.nanmax(values):.3g}")


def _percent(fraction: float | None) -> str:
    """A fraction as a percentage to 3 significant digits, or a dash when it is missing."""
    return "–" if fraction is None else f"{100 * fraction:.3g}"


def cycle_state_html(flow: dict) -> list[str]:
    """The cycle state of ``flow/summary.json``: cycles run, what the indices average and the periodicity.

    The periodicity is the simulate stage's (``periodicity``, ``periodic``): the change of each whole cycle's
    TAWSS from the previous cycle's, judged against ``--periodic-tol``.

    Returns
    -------
    list of str
        HTML: the per-cycle table (two whole cycles or more) and a paragraph.
    """
    cycles = flow.get("cycles", 0.0)
    period = flow.get("time_s", 0.0) / cycles if cycles else 0.0
    note = flow.get("indices_note")
    state = f"{cycles:.2g} cardiac cycle(s) of {period:.3g} s run" + (f"; {note}. " if note else ". ")
    entries, periodic = flow.get("periodicity") or [], flow.get("periodic") or {}
    change = periodic.get("last_relative_change")
    if not periodic:
        state += "Cycle-to-cycle periodicity is not recorded: summary.json predates it (rerun the simulate stage)."
    elif change is None:
        state += (f"{len(entries)} whole cycle(s) run: periodicity is not assessed (it needs two whole cycles or "
                  "more; the first includes the start-up transient).")
    else:
        state += f"The TAWSS of the last cycle changed by {_percent(change)} % from the previous cycle's " \
                 f"({periodic.get('criterion', '')}): "
        state += ("not assessed, no tolerance set (--periodic-tol)." if periodic["status"] == "not assessed" else
                  f"{periodic['status']} against the tolerance of {_percent(periodic['tolerance'])} %.")
    parts = []
    if len(entries) >= 2:
        rows = [(e["cycle"], _value(e["tawss_mean_pa"]), _percent(e["relative_change"]), _percent(e["mean_change"]))
                for e in entries]
        parts.append(_table_html(Table("TAWSS of each whole cycle, change from the previous cycle", rows,
                                       ["cycle", "mean TAWSS (Pa)", "change, L2 (%)", "change of the mean (%)"])))
    parts.append(f'<p id="cycle-state">{html.escape(state)}</p>')
    return parts


def convergence_table(study: dict, quantity: str, unit: str) -> Table:
    """Per-branch grid convergence of the area-weighted mean of one wall index (``flow/convergence.json``).

    Parameters
    ----------
    study : dict
        ``flow/convergence.json`` (:func:`carotid.flow.convergence.run_convergence`).
    quantity : str
        ``"TAWSS"``, ``"OSI"`` or ``"RRT"``.
    unit : str
        Its unit (``"Pa"``, ``"-"``, ``"1/Pa"``).

    Returns
    -------
    Table
        Per branch and the whole wall: the mean on the case mesh (the coarsest level) and on the finest, the
        Richardson extrapolation, the apparent order, the fine-grid GCI (%) and the convergence status.
    """
    sizes = ", ".join(f"{level['h_mm']:.3g}" for level in study["levels"])
    rows = [(name, _value(row["phi_fine_to_coarse"][-1]), _value(row["phi_fine_to_coarse"][0]),
             _value(row["phi_ext21"]), _value(row["p"]), _percent(row["gci_fine21"]), row["status"])
            for name, row in study["branches"][quantity].items()]
    return Table(f"Grid convergence of the mean {quantity} per branch (Celik et al. 2008; meshes of h = {sizes} mm, "
                 "finest first; the case mesh is the coarsest)", rows,
                 ["region", f"case mesh ({unit})", f"finest mesh ({unit})", f"extrapolated ({unit})",
                  "apparent order", "GCI, finest (%)", "status"])


def convergence_html(case: Case) -> str:
    """The grid convergence study of the first page: the TAWSS table per branch and the per-node GCI map of TAWSS
    (``flow/convergence.json`` and ``flow/convergence.vtp``), or a note when no study was run."""
    if not case.convergence:
        return ('<p class="missing" id="convergence">No convergence study (carotid simulate --convergence): the '
                "discretisation error of the wall indices is not estimated.</p>")
    parts = [_table_html(convergence_table(case.convergence, "TAWSS", "Pa"))]
    path = case.dir / "flow" / "convergence.vtp"
    wall = read_vtk(path, "convergence map", remedy="rerun carotid simulate --convergence") if path.exists() else None
    gci = 100.0 * np.asarray(wall["TAWSS_GCI"], dtype=float) if wall is not None else np.array([np.nan])
    if np.isfinite(gci).any():
        wall.point_data["TAWSS_GCI_percent"] = gci
        clim, clip = colour_range(gci)
        parts.append(_figure(f"GCI of TAWSS at each wall node of the finest mesh (%): colour scale {clip}; grey: no "
                             "estimate (divergent or indeterminate)",
                             figures.wall_map(wall, "TAWSS_GCI_percent", "GCI of TAWSS (%)", clim, "magma")))
    else:
        parts.append('<p class="missing">No per-node GCI of TAWSS (flow/convergence.vtp missing, or no node '
                     "converges).</p>")
    return f'<div class="more" id="convergence"><div>{parts[0]}</div>{parts[1]}</div>'


def handles_removed_row(changes: list[dict]) -> dict:
    """``{"handles_removed": summary}`` of the segmentation's ``handles_removed`` record; empty without changes."""
    if not changes:
        return {}
    kinds = [c["kind"] for c in changes]
    return {"handles_removed": f"{sum(c['handles_removed'] for c in changes)}: {kinds.count('cut')} bridge(s) cut, "
                               f"{kinds.count('fill')} tunnel(s) filled, {sum(c['voxels'] for c in changes)} voxels "
                               "(places in report.json)"}


def segmentation_section(case: Case) -> Section:
    """Input slices with the lumen contour, and the segmentation record."""
    section = Section("Segmentation")
    folder = case.dir / "segmentation"
    if not (folder / "mask.nii.gz").exists():
        section.note = "The segmentation stage has not run."
        return section
    source, reason = find_image(case)
    mask = read_image(folder / "mask.nii.gz")
    image = read_image(source) if source is not None else None
    if image is not None and image.array.shape != mask.array.shape:
        image, reason = None, f"the image {source} is not on the segmentation grid"
    if image is not None:
        section.figures.append(("CT slices through the lumen centroid (axial: anterior up, patient's right on the "
                                "left), lumen boundary in red", figures.segmentation_slices(image, mask)))
    else:
        section.note = f"CT slices omitted: {reason}."
    report = case.segmentation
    keep = ("method", "initialisation", "iterations", "converged", "lumen_volume_mm3", "topology", "seconds",
            "peak_rss_mb", "intensity")
    result = {}
    for key in keep:
        if key in report:
            result[key] = report[key]
        if key == "initialisation" and report.get("seeds_mm"):  # the user's, or placed in the forking start
            result["seeds_mm"] = "; ".join("({:.1f}, {:.1f}, {:.1f})".format(*seed) for seed in report["seeds_mm"])
        if key == "topology":
            result.update(handles_removed_row(report.get("handles_removed") or []))
    section.tables.append(Table("Result", flatten(result)))
    section.tables.append(Table("Parameters", flatten(active_parameters(report.get("parameters", {})))))
    section.tables.append(checks_table(quality_checks(report, {}, {}, {})))
    return section


def _triangle_min_angles(surface) -> np.ndarray:
    """Smallest angle of each triangle of a PolyData, degrees, shape (n,)."""
    tri = surface.triangulate().faces.reshape(-1, 4)[:, 1:]
    p = surface.points[tri]
    angles = []
    for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        u, v = p[:, b] - p[:, a], p[:, c] - p[:, a]
        cos = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.min(angles, axis=0)


def geometry_section(case: Case) -> Section:
    """Branches, stenosis gradings, caps and the surface quality."""
    section = Section("Geometry: centerlines, stenosis and surface")
    geometry = case.geometry
    if not geometry and not (case.dir / "surface.vtp").exists():
        section.note = case.absent("centerline", "geometry.json")
        return section
    branch_rows = [(b["name"], f"{b['length_mm']:.1f}", f"{2 * b['mean_radius_mm']:.2f}",
                    f"{2 * b['min_radius_mm']:.2f}", f"{2 * b['max_radius_mm']:.2f}", f"{b['tortuosity']:.3f}",
                    f"{b['max_bend_deg']:.1f}") for b in geometry.get("branches", [])]
    section.tables.append(Table("Branches", branch_rows, ["branch", "length (mm)", "mean diameter (mm)",
                                                          "min diameter (mm)", "max diameter (mm)", "tortuosity",
                                                          "largest bend (°)"]))
    grade_rows = [(g["branch"], f"{100 * g['nascet']:.1f}", f"{100 * g['ecst']:.1f}",
                   f"{100 * g['area_reduction']:.1f}", f"{g['min_diameter_mm']:.2f}", f"{g['distal_diameter_mm']:.2f}",
                   f"{g['local_diameter_mm']:.2f}", f"{g['arclength_from_bifurcation_mm']:.1f}")
                  for g in geometry.get("stenoses", [])]
    section.tables.append(Table("Narrowest section of each branch", grade_rows,
                                ["branch", "NASCET (%)", "ECST (%)", "area reduction (%)", "minimal diameter (mm)",
                                 "distal diameter (mm)", "local diameter (mm)", "from the bifurcation (mm)"]))
    caps = geometry.get("caps") or case.surface_quality.get("caps") or []
    section.tables.append(Table("Caps (CellEntityIds: wall 1, inlet 2, outlets 3, 4, ...)",
                                [(c["id"], c.get("name", ""), f"{c['area']:.2f}", f"{c['equivalent_radius']:.2f}")
                                 for c in caps], ["id", "branch", "area (mm²)", "equivalent radius (mm)"]))
    skip = ("stenosis", "stenoses", "branches", "caps", "branch_names", "centerlines_file", "bifurcation_geometry")
    section.tables.append(Table("Centerline record", flatten({k: v for k, v in geometry.items() if k not in skip})))
    if case.surface is not None:
        section.figures.append(("Smallest angle of each surface triangle",
                                figures.histogram({"surface": _triangle_min_angles(case.surface)}, "degrees")))
    section.tables.append(checks_table(quality_checks({}, case.surface_quality, {}, {})))
    section.tables.append(Table("Surface record", flatten({k: v for k, v in case.surface_quality.items()
                                                           if k != "caps"})))
    return section


def mesh_section(case: Case) -> Section:
    """A cut through the volume mesh, a close-up of the wall layers, and the quality figures."""
    section = Section("Volume mesh")
    mesh = case.mesh
    if mesh is None:
        section.note = case.absent("mesh", "mesh.vtu")
        return section
    section.figures.append(("Tetrahedra behind a plane through the mesh centre (layer and core regions)",
                            figures.mesh_cut_view(mesh)))
    section.figures.append(("Close-up of the wall layers", figures.mesh_cut_view(mesh, zoom=4.0)))
    section.tables.append(checks_table(quality_checks({}, {}, case.mesh_quality, {})))
    section.tables.append(Table("Mesh record", flatten(case.mesh_quality)))
    return section


def flow_section(case: Case) -> Section:
    """The index statistics, the grid convergence of OSI and RRT with the study's levels, and the solver record."""
    section = Section("Flow and wall shear stress")
    summary = case.flow
    if not summary:
        section.note = case.absent("flow", "flow/summary.json")
        return section
    section.tables.append(checks_table(quality_checks({}, {}, {}, summary)))
    units = {"TAWSS": "Pa", "OSI": "-", "RRT": "1/Pa", "ECAP": "1/Pa", "transWSS": "Pa", "TWSSG": "Pa/s"}
    section.tables.append(Table("Wall indices over the wall nodes", [
        (f"{name} ({units.get(name, '')})", f"{v['min']:.3g}", f"{v['mean']:.3g}", f"{v['max']:.3g}")
        for name, v in summary.get("indices", {}).items()], ["index", "min", "mean", "max"]))
    study = case.convergence
    if study:
        section.tables += [convergence_table(study, "OSI", "-"), convergence_table(study, "RRT", "1/Pa")]
        section.tables.append(Table("Grid convergence levels (0 finest)", [
            (lv["level"], f"{lv['h_mm']:.3g}", lv["tetrahedra"], lv["nodes"], _value(lv["cycles"]),
             _value(lv["partial"]), lv["periodic"]["status"], _value(lv["seconds"])) for lv in study["levels"]],
            ["level", "h (mm)", "tetrahedra", "nodes", "cycles", "partial", "periodicity", "seconds (s)"]))
        section.tables.append(Table("Per-node GCI over the wall (finest mesh)", [
            (name, _percent(m["median_gci"]), *(_percent(m[status]) for status in STATUS))
            for name, m in study["map"].items()], ["index", "median GCI (%)", *(f"{s} (% of nodes)" for s in STATUS)]))
    shown = ("indices", "periodicity", "regions", "bifurcation_geometry", "probes")  # tabled on their own
    record = {k: v for k, v in summary.items() if k not in shown}
    record["mass_balance"] = {k: v for k, v in summary.get("mass_balance", {}).items() if k != "outlets"}
    section.tables.append(Table("Solver record", flatten(record)))
    return section


def parameters_section(case: Case) -> Section:
    """Stage timings and versions from ``case.json``."""
    section = Section("Run record")
    if "case.json" in case.unreadable:
        section.note = f"{case.unreadable['case.json']}."
        return section
    if not case.record:
        section.note = "No case.json: the case was built by the per-stage commands, which record no timings."
        return section
    section.tables.append(Table("Stages", [(name, _value(s.get("seconds")), s.get("finished", ""))
                                           for name, s in case.record.get("stages", {}).items()],
                                ["stage", "seconds (s)", "finished (UTC)"]))
    section.tables.append(Table("Versions", flatten(case.record.get("versions", {}))))
    return section


def _section_html(section: Section) -> str:
    parts = [f"<section><h2>{html.escape(section.title)}</h2>"]
    if section.note:
        parts.append(f'<p class="missing">{html.escape(section.note)}</p>')
    parts += [_figure(caption, png) for caption, png in section.figures]
    parts += [_table_html(table) for table in section.tables]
    parts.append("</section>")
    return "\n".join(parts)


def _guarded(build, *args) -> str:
    """The HTML of one part of the report, or a note naming the error that stopped it (and a CarotidWarning)."""
    try:
        result = build(*args)
    except Exception as exc:  # noqa: BLE001 - a broken record must not stop the rest of the report
        warnings.warn(f"the report's {build.__name__.replace('_', ' ')} could not be built ({type(exc).__name__}: "
                      f"{exc}): check the records it shows", CarotidWarning, stacklevel=2)
        return f'<p class="missing">This part could not be built: {html.escape(type(exc).__name__)}: ' \
               f"{html.escape(str(exc))}</p>"
    return result if isinstance(result, str) else _section_html(result)


def build_report(case_dir: str | Path) -> Path:
    """Write ``CASE_DIR/report.html`` from whatever the stages have produced; returns its path.

    Works on any case folder, whether ``carotid run`` or the per-stage commands built it: each part
    reads only the files it shows, and a part whose files are missing or unreadable says so.
    """
    case_dir = Path(case_dir)
    case = Case.read(case_dir)
    for message in case.unreadable.values():
        warnings.warn(message, CarotidWarning, stacklevel=2)
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    details = [_guarded(build, case) for build in (segmentation_section, geometry_section, mesh_section,
                                                   flow_section, parameters_section)]
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>carotid report: {html.escape(case_dir.name)}"
            f"</title><style>{STYLE}</style></head><body><h1>carotid report: {html.escape(case_dir.name)} "
            f"<small>carotid {__version__}, written {stamp}; geometry in mm (image LPS frame), flow in SI units"
            f"</small></h1>{_guarded(summary_html, case)}<h2>Details</h2>" + "\n".join(details) + "</body></html>")
    path = case_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def run_stage(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``report`` stage of ``carotid run``."""
    build_report(case_dir)
