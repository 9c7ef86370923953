"""The self-contained HTML report of a case: ``CASE_DIR/report.html``.

Each section is built from the files a stage wrote; a stage that has not run
yields a section that says so instead of failing the report.  Pictures are
PNG embedded as data URIs, so the file can be mailed or archived alone.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from carotid import __version__
from carotid.io import atomic_path, read_image
from carotid.report import figures

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { border-bottom: 2px solid #b22; } h2 { color: #b22; margin-top: 2em; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; vertical-align: top; }
.missing { color: #888; font-style: italic; }
"""


@dataclass
class Section:
    """One report section: pictures (caption, PNG bytes), tables (caption, rows) and a note."""

    title: str
    figures: list[tuple[str, bytes]] = field(default_factory=list)
    tables: list[tuple[str, list[tuple[str, object]]]] = field(default_factory=list)
    note: str = ""


def _read_json(path: Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {}


def flatten(data, prefix: str = "") -> list[tuple[str, object]]:
    """Nested dicts as (dotted key, value) rows; lists of numbers shortened."""
    rows = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += flatten(value, f"{name}.")
        else:
            if isinstance(value, float):
                value = f"{value:.4g}"
            elif isinstance(value, list) and any(isinstance(v, dict) for v in value):
                for number, item in enumerate(value):
                    label = item.get("name") or item.get("branch") or number if isinstance(item, dict) else number
                    rows += flatten(item, f"{name}.{label}.") if isinstance(item, dict) else [(f"{name}.{label}", item)]
                continue
            elif isinstance(value, list) and len(value) > 8:
                value = f"[{len(value)} values]"
            elif isinstance(value, list):
                value = ", ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in value)
            rows.append((name, value))
    return rows


def segmentation_section(case_dir: Path, record: dict) -> Section:
    """Input slices with the lumen contour, and the segmentation report."""
    section = Section("Segmentation")
    folder = case_dir / "segmentation"
    if not (folder / "mask.nii.gz").exists():
        section.note = "The segmentation stage has not run."
        return section
    report = _read_json(folder / "report.json")
    source = Path(record.get("input", ""))
    if source.exists():
        picture = figures.segmentation_slices(read_image(source), read_image(folder / "mask.nii.gz"))
        section.figures.append(("CT slices through the lumen centroid, lumen boundary in red", picture))
    else:
        section.note = f"Input image {source} not found: slices omitted."
    keep = ("method", "initialisation", "iterations", "converged", "lumen_volume_mm3", "seconds", "peak_rss_mb")
    section.tables.append(("Result", flatten({k: report[k] for k in keep if k in report})))
    section.tables.append(("Parameters", flatten(report.get("parameters", {}))))
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


def geometry_section(case_dir: Path) -> Section:
    """The clipped surface with its labelled caps and centerlines; stenosis and quality tables."""
    import pyvista as pv

    section = Section("Geometry: centerlines, stenosis and surface")
    geometry = _read_json(case_dir / "geometry.json")
    surface_path, centerline_path = case_dir / "surface.vtp", case_dir / "centerlines.vtp"
    if not surface_path.exists() and not centerline_path.exists():
        section.note = "The centerline and surface stages have not run."
        return section
    centerlines = pv.read(centerline_path) if centerline_path.exists() else None
    if surface_path.exists():
        surface = pv.read(surface_path)
        section.figures.append(("Lumen surface: wall and labelled caps (CellEntityIds), centerlines in black",
                                figures.surface_view(surface, centerlines)))
        section.figures.append(("Smallest angle of each surface triangle",
                                figures.histogram({"surface": _triangle_min_angles(surface)}, "degrees")))
    if "stenosis" in geometry:
        section.tables.append(("Stenosis", flatten(geometry["stenosis"])))
    section.tables.append(("Geometry", flatten({k: v for k, v in geometry.items() if k != "stenosis"})))
    section.tables.append(("Surface quality", flatten(_read_json(case_dir / "surface_quality.json"))))
    return section


def mesh_section(case_dir: Path) -> Section:
    """A cut through the volume mesh, a close-up of the wall layers, and the quality figures."""
    import pyvista as pv

    section = Section("Volume mesh")
    path = case_dir / "mesh.vtu"
    if not path.exists():
        section.note = "The mesh stage has not run."
        return section
    mesh = pv.read(path)
    section.figures.append(("Tetrahedra behind a plane through the mesh centre (layer and core regions)",
                            figures.mesh_cut_view(mesh)))
    section.figures.append(("Close-up of the wall layers", figures.mesh_cut_view(mesh, zoom=4.0)))
    section.tables.append(("Mesh quality", flatten(_read_json(case_dir / "mesh_quality.json"))))
    return section


def flow_section(case_dir: Path) -> Section:
    """Wall shear stress indices on the wall and the solver summary."""
    import pyvista as pv

    section = Section("Flow and wall shear stress")
    folder = case_dir / "flow"
    if not (folder / "summary.json").exists():
        section.note = "The flow stage has not run."
        return section
    indices_path = folder / "indices.vtp"
    if indices_path.exists():
        wall = pv.read(indices_path)
        for name, unit in (("TAWSS", "Pa"), ("OSI", ""), ("RRT", "1/Pa")):
            if name in wall.array_names:
                values = np.asarray(wall[name])
                clim = (0.0, float(np.percentile(values, 98)) or 1.0) if name != "OSI" else (0.0, 0.5)
                section.figures.append((f"{name} {unit}".strip(),
                                        figures.surface_view(wall, scalars=name, cmap="jet", clim=clim,
                                                             title=f"{name} {unit}".strip())))
    summary = _read_json(folder / "summary.json")
    section.tables.append(("Solver summary", flatten(summary)))
    return section


def parameters_section(record: dict) -> Section:
    """Stage timings and versions from ``case.json``."""
    section = Section("Run record")
    stages = {name: {"seconds": s.get("seconds"), "finished": s.get("finished")}
              for name, s in record.get("stages", {}).items()}
    section.tables.append(("Stages", flatten(stages)))
    section.tables.append(("Versions", flatten(record.get("versions", {}))))
    return section


def _section_html(section: Section) -> str:
    parts = [f"<section><h2>{html.escape(section.title)}</h2>"]
    if section.note:
        parts.append(f'<p class="missing">{html.escape(section.note)}</p>')
    for caption, png in section.figures:
        data = base64.b64encode(png).decode()
        parts.append(f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{data}">'
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    for caption, rows in section.tables:
        if rows:
            body = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
            parts.append(f"<table><caption>{html.escape(caption)}</caption>{body}</table>")
    parts.append("</section>")
    return "\n".join(parts)


def build_report(case_dir: str | Path) -> Path:
    """Write ``CASE_DIR/report.html`` from whatever the stages have produced; returns its path."""
    case_dir = Path(case_dir)
    record = _read_json(case_dir / "case.json")
    sections = [segmentation_section(case_dir, record), geometry_section(case_dir), mesh_section(case_dir),
                flow_section(case_dir), parameters_section(record)]
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>carotid report: {html.escape(case_dir.name)}"
            f"</title><style>{STYLE}</style></head><body><h1>carotid report: {html.escape(case_dir.name)}</h1>"
            f"<p>carotid {__version__}, written {stamp}. Geometry in mm (image LPS frame); flow in SI units.</p>"
            + "\n".join(_section_html(s) for s in sections) + "</body></html>")
    path = case_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text(page)
    return path


def run_stage(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``report`` stage of ``carotid run``."""
    build_report(case_dir)
