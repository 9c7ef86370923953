"""``carotid batch``: a cohort of cases on Dask distributed.

Each stage of a case is a Dask task, submitted when the case's previous
stage has finished (``_drive``), so different cases run side by side and
every stage goes to whichever worker frees up first.  Bad input
(``CarotidError``) fails its case at once with the reason and is not
retried; any other exception is retried (``retries``) as possibly
transient, and fails the case if it persists.  One failed case
never stops the others.  Every stage goes through ``pipeline.run_stage``, so
finished stages are skipped when a batch is run again.  While it runs, a line
reports each finished case (with the quality checks that failed) and, at
least every ``PROGRESS_SECONDS``, the cases
finished, failed, running and waiting with the elapsed time and an ETA.  The
outcome is ``OUT_DIR/cohort.csv``, one row per case, numbers to
``SIGNIFICANT_DIGITS`` significant digits, and ``OUT_DIR/cohort.json``
describing its columns (unit, meaning) and the thresholds of the WSS columns.
"""

from __future__ import annotations

import csv
import io
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np

from carotid.centerline.plaque import CALCIFIED_MM, calcified
from carotid.config import Config
from carotid.errors import CarotidError, check_ranges
from carotid.flow.duplex import check_doppler
from carotid.flow.indices import HIGH_OSI, LOW_TAWSS_PA, area_fraction, node_areas
from carotid.flow.regions import INDEX_UNITS, REGION_INDICES, REGION_NAMES
from carotid.io import atomic_path, read_json, write_json
from carotid.io.vtkfile import read_vtk
from carotid.pipeline import PROGRESS_SECONDS, STAGES, format_duration, read_case, run_stage
from carotid.report.checks import quality_checks, stenosis_category
from carotid.segment.intensity import VALIDATED_CONTRAST_TO_NOISE

BATCH_RANGES = {"workers": (1, 256), "retries": (0, 100)}  # LocalCluster processes; retries of a stage
SIGNIFICANT_DIGITS = 4  # of the real numbers in cohort.csv
STAGE_NAMES = tuple(stage.name for stage in STAGES if stage.runner)

# The bifurcation geometry columns (geometry.json, carotid.centerline.features.bifurcation_geometry): column ->
# (dotted key path in it, unit, meaning).
GEOMETRY_KEYS = {
    "bifurcation_angle_deg": ("bifurcation_angle_deg", "deg", "angle between the ICA and ECA directions (principal "
                              "axes of the centerlines 1-3 CCA diameters from the bifurcation point)"),
    "ica_angle_deg": ("ica_angle_deg", "deg", "angle between the ICA direction and the CCA's continuation"),
    "eca_angle_deg": ("eca_angle_deg", "deg", "angle between the ECA direction and the CCA's continuation"),
    "ica_cca_area_ratio": ("ica_cca_area_ratio", "ratio", "ICA / CCA median section area (CCA 1-3 diameters below "
                           "the bifurcation point, ICA from 2 CCA diameters above to its end)"),
    "bifurcation_area_ratio": ("bifurcation_area_ratio", "ratio", "(ICA + ECA) / CCA median section area, sections "
                               "as ica_cca_area_ratio"),
    "bulb_diameter_ratio": ("bulb_diameter_ratio", "ratio", "largest ICA inscribed diameter 0.5-3 CCA diameters "
                            "above the bifurcation point over the CCA diameter"),
    "bulb_length_mm": ("bulb_end_mm", "mm", "arc length of the bulb region along the ICA from the bifurcation point"),
    **{f"{b.lower()}_{key}": (f"branches.{b}.{key}", unit, f"{b} {text}") for b in ("CCA", "ICA", "ECA")
       for key, unit, text in (("tortuosity", "ratio", "tortuosity, arc length / chord - 1 over the whole branch"),
                               ("planarity_deg", "deg", "planarity: angle of its direction out of the plane of the "
                                                        "other two branches' directions"))},
}
GEOMETRY_COLUMNS = {name: (unit, text) for name, (_, unit, text) in GEOMETRY_KEYS.items()}

# The virtual duplex and the inflow calibration (flow/summary.json duplex and inflow_calibration,
# carotid.flow.duplex): column -> (dotted key path in summary.json, unit, meaning).
DUPLEX_KEYS = {
    "ica_psv_cm_s": ("duplex.gates.ICA.psv_cm_s", "cm/s", "ICA peak systolic velocity at the narrowest ICA section: "
                     "the largest speed in a Doppler gate on the axis over the last cycle"),
    "ica_edv_cm_s": ("duplex.gates.ICA.edv_cm_s", "cm/s", "ICA end-diastolic velocity in that gate (the foot of the "
                     "systolic upstroke)"),
    "cca_psv_cm_s": ("duplex.gates.CCA.psv_cm_s", "cm/s", "CCA peak systolic velocity, gate 20 mm proximal to the "
                     "bifurcation"),
    "cca_edv_cm_s": ("duplex.gates.CCA.edv_cm_s", "cm/s", "CCA end-diastolic velocity in that gate"),
    "psv_ratio": ("duplex.psv_ratio", "ratio", "ICA PSV / CCA PSV"),
    "sru_grade": ("duplex.sru.grade", "", "grade of the SRU consensus criteria (Grant et al. 2003) from the ICA PSV: "
                  "normal, <50 %, 50-69 %, >=70 % or near occlusion"),
    "sru_concordant": ("duplex.sru.concordant", "", "whether ICA PSV, ICA/CCA ratio and ICA EDV give the same SRU "
                       "category"),
    "stenosis_pressure_drop_mmhg": ("duplex.pressure.drop_mean_mmhg", "mmHg", "time-averaged pressure drop from the "
                                    "CCA gate to the ICA 3 diameters beyond the lesion"),
    "stenosis_pressure_drop_systole_mmhg": ("duplex.pressure.drop_peak_systole_mmhg", "mmHg",
                                            "that pressure drop at peak systole (the inflow's peak)"),
    "stenosis_pressure_ratio": ("duplex.pressure.ratio_mean", "ratio", "time-averaged distal / proximal pressure "
                                "across the stenosis (Pd/Pa); empty unless lumped outlets make pressures absolute"),
    "doppler_cca_psv_cm_s": ("inflow_calibration.target_psv_cm_s", "cm/s", "measured CCA PSV the inflow was "
                             "calibrated to (manifest or config); empty without calibration"),
    "doppler_cca_edv_cm_s": ("inflow_calibration.target_edv_cm_s", "cm/s", "measured CCA EDV the inflow was "
                             "calibrated to"),
    "inflow_mean_ml_s": ("inflow_calibration.mean_flow_ml_s", "mL/s", "mean flow of the calibrated inflow"),
}
DUPLEX_COLUMNS = {name: (unit, text) for name, (_, unit, text) in DUPLEX_KEYS.items()}
DOPPLER_COLUMNS = ("doppler_cca_psv", "doppler_cca_edv")
"""Optional manifest columns: the measured CCA PSV and EDV of a case, cm/s (both or neither)."""
MANIFEST_COLUMNS = ("case_id", "image", "config", *DOPPLER_COLUMNS)
"""Every column a manifest may have; any other (a misspelt ``Config``) is an error, not ignored."""

# The wall region columns (flow/summary.json regions.statistics, carotid.flow.regions), each "REGION_INDEX_STAT" with
# a unit suffix, or "REGION_area_mm2" and "REGION_..._area_fraction".
_SUFFIX = {"Pa": "_pa", "": "", "1/Pa": "_per_pa", "Pa/s": "_pa_per_s"}


def _region_keys() -> dict:
    """cohort.csv column -> (region, index or None, statistic) of the wall region statistics."""
    keys = {}
    for region in REGION_NAMES[:-1]:  # not "other"
        name = region.lower()
        keys[f"{name}_area_mm2"] = (region, None, "area_mm2")
        keys.update({f"{name}_{index.lower()}_{stat}{_SUFFIX[INDEX_UNITS[index]]}": (region, index, stat)
                     for index in REGION_INDICES for stat in ("mean", "p5", "p95")})
        keys.update({f"{name}_{fraction}_area_fraction": (region, None, f"{fraction}_area_fraction")
                     for fraction in ("low_tawss", "high_osi", "low_tawss_high_osi")})
    return keys


REGION_KEYS = _region_keys()
_STATS = {"mean": "area-weighted mean", "p5": "5th percentile (by area)", "p95": "95th percentile (by area)"}
_FRACTIONS = {"low_tawss_area_fraction": f"fraction of its area with TAWSS below {LOW_TAWSS_PA} Pa",
              "high_osi_area_fraction": f"fraction of its area with OSI above {HIGH_OSI}",
              "low_tawss_high_osi_area_fraction": f"fraction of its area with both TAWSS < {LOW_TAWSS_PA} Pa and OSI "
                                                  f"> {HIGH_OSI}"}
REGION_COLUMNS = {
    name: (("mm^2", f"{region} region: wall area") if stat == "area_mm2" else
           ("fraction", f"{region} region: {_FRACTIONS[stat]}") if index is None else
           (INDEX_UNITS[index], f"{region} region: {index}, {_STATS[stat]}"))
    for name, (region, index, stat) in REGION_KEYS.items()}

# Every cohort.csv column: (unit, meaning), written to cohort.json.  Empty cells: not available for that case.
COHORT_COLUMNS = {
    "case_id": ("", "case identifier from the manifest"),
    "status": ("", "ok, or failed"),
    "failed_stage": ("", "stage that failed (empty for an error outside the stages)"),
    "reason": ("", "why the case failed"),
    "image": ("", "input image"),
    "lumen_volume_mm3": ("mm^3", "lumen volume of the segmentation"),
    "lumen_contrast_to_noise": ("ratio", "lumen contrast over the noise in the lumen's core (segmentation "
                                         "report.json intensity); the segmentation's accuracy is measured down "
                                         f"to {VALIDATED_CONTRAST_TO_NOISE:g}"),
    "stenosis_branch": ("", "branch graded in nascet and ecst: the ICA, else the most narrowed branch; empty when "
                            "no carotid bifurcation was found"),
    "nascet": ("fraction", "NASCET stenosis degree of stenosis_branch, 1 - d_min / d_distal (diameters)"),
    "ecst": ("fraction", "ECST stenosis degree of stenosis_branch, 1 - d_min / d_local (diameters)"),
    "stenosis_category": ("", "NASCET category of stenosis_branch's grade, as in the report (near occlusion "
                              "overrides the percentage)"),
    "stenosis_calcium_mm": ("mm", "distance from the lumen's wall around the throat to the nearest calcium the "
                                  "segmentation took out; empty when none was found (which does not prove the "
                                  "plaque soft)"),
    "stenosis_calcified": ("", f"True when that calcium lies within {CALCIFIED_MM:g} mm of the lumen: the grade is "
                               "less certain"),
    "mesh_tetrahedra": ("count", "tetrahedra of the volume mesh"),
    "outlets": ("", "outlet model the flow ran with: murray or split (prescribed), resistance or rcr (lumped)"),
    "outlets_fallback": ("", "the configured prescribed split (murray or split) when it blew up and the flow was "
                             "rerun with RCR outlets calibrated for that split (simulate blow_up_fallback); empty "
                             "otherwise"),
    "checks_failed": ("count", "quality checks of the stages run that failed (the report's checks)"),
    "failed_checks": ("", "those checks, 'stage: quantity', separated by '; '"),
    "tawss_mean_pa": ("Pa", "time-averaged wall shear stress over the last cycle (or the part of it run: "
                            "indices_cycle_fraction), mean over the wall nodes"),
    "indices_cycle_fraction": ("fraction", "fraction of a cardiac cycle the wall indices average; under 1 the "
                                           "indices are partial, not comparable with those of a whole cycle"),
    "periodic_status": ("", "periodic or not periodic: the last cycle's TAWSS change against the simulate stage's "
                            "periodic_tol; not assessed without a tolerance or under two whole cycles"),
    "tawss_last_cycle_change": ("fraction", "area-weighted L2 relative change of the TAWSS of the last whole cycle "
                                            "from the previous cycle's; empty under two whole cycles"),
    "tawss_gci_percent": ("%", "fine-grid grid convergence index of the area-weighted mean TAWSS over the whole "
                               "wall (Celik et al. 2008, three meshes, Fs = 1.25; flow/convergence.json of "
                               "carotid simulate --convergence); empty without a study or when the meshes' "
                               "values diverge"),
    "osi_area_fraction": ("fraction", f"fraction of the wall area where the oscillatory shear index exceeds "
                                      f"{HIGH_OSI}"),
    "low_tawss_area_fraction": ("fraction", f"fraction of the wall area where the time-averaged wall shear stress "
                                            f"is below {LOW_TAWSS_PA} Pa"),
    **GEOMETRY_COLUMNS,
    **DUPLEX_COLUMNS,
    **REGION_COLUMNS,
    **{f"seconds_{name}": ("s", f"time the {name} stage took when it ran") for name in STAGE_NAMES},
    "seconds_total": ("s", "time of all the stages that ran"),
}


@dataclass(frozen=True)
class Case:
    """One row of a manifest: an identifier, an image and its configuration overrides."""

    case_id: str
    image: Path
    overrides: dict


def read_manifest(path: str | Path, default_config: str | Path | None = None) -> list[Case]:
    """Read a manifest CSV with columns ``case_id,image[,config][,doppler_cca_psv,doppler_cca_edv]`` (paths
    relative to the manifest).

    A case's ``config`` (TOML) replaces ``default_config`` (a path relative to the working directory) for
    that case; its ``doppler_cca_psv`` and ``doppler_cca_edv`` (cm/s, both or neither) set the simulate stage's
    calibrated inflow (:func:`carotid.flow.duplex.calibrate_inflow`).  Duplicate ids, missing columns, empty cells, rows with too many fields and unreadable config
    files are errors naming the manifest's line; a missing image *file* is not (that case fails alone).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CarotidError(f"{path}: cannot read the manifest ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise CarotidError(f"{path}: not a text (CSV) manifest") from None
    header = next(csv.reader(io.StringIO(text)), [])
    if not {"case_id", "image"} <= set(header):
        raise CarotidError(f"{path}: a manifest needs a header with the columns case_id,image[,config] and rows")
    unknown = [name for name in header if name not in MANIFEST_COLUMNS]
    if unknown:
        raise CarotidError(f"{path}: unknown column {', '.join(unknown)} (known: {', '.join(MANIFEST_COLUMNS)})")
    default = Config.from_toml(default_config).sections if default_config else {}
    cases, seen = [], set()
    reader = csv.DictReader(io.StringIO(text))
    for row in reader:
        line = reader.line_num
        if None in row:
            raise CarotidError(f"{path}:{line}: more fields than the header's {', '.join(reader.fieldnames)}")
        case_id = (row["case_id"] or "").strip()
        if not case_id or case_id in seen or "/" in case_id:
            raise CarotidError(f"{path}:{line}: case_id {case_id!r} is empty, repeated or contains '/'")
        seen.add(case_id)
        image = (row["image"] or "").strip()
        if not image:
            raise CarotidError(f"{path}:{line}: case {case_id} has no image")
        config = (row.get("config") or "").strip()
        try:
            overrides = Config.from_toml(path.parent / config).sections if config else default
        except CarotidError as exc:
            raise CarotidError(f"{path}:{line}: {exc}") from None
        doppler = [(row.get(name) or "").strip() for name in DOPPLER_COLUMNS]
        if any(doppler):
            try:
                psv, edv = (float(v) for v in doppler)
                check_doppler(psv, edv)
            except (ValueError, CarotidError) as exc:
                raise CarotidError(f"{path}:{line}: case {case_id}: {', '.join(DOPPLER_COLUMNS)} must be two "
                                   f"velocities in cm/s ({exc})") from None
            overrides = {**overrides, "simulate": {**overrides.get("simulate", {}), "doppler_cca_psv": psv,
                                                   "doppler_cca_edv": edv}}
        cases.append(Case(case_id, path.parent / image, overrides))
    if not cases:
        raise CarotidError(f"{path}: a manifest needs a header with the columns case_id,image[,config] and rows")
    return cases


class StageFailure(RuntimeError):
    """An unexpected error of one stage of one case: Dask retries it, and if it persists the case fails there."""

    def __init__(self, stage: str, reason: str):
        super().__init__(stage, reason)
        self.stage, self.reason = stage, reason


def _stage_task(case: Case, case_dir: str, stage_name: str, previous: dict | None) -> dict:
    """Run one stage of one case (a Dask task): ``{"status": "ok"|"failed", ...}``; ``StageFailure`` on an
    unexpected error.  ``previous`` is the outcome of the case's previous stage (None for the first)."""
    stage = next(s for s in STAGES if s.name == stage_name)
    try:
        if not case.image.exists():
            raise CarotidError(f"{case.image}: no such file or folder")
        line = run_stage(stage, case.image, Path(case_dir), Config(case.overrides))
    except CarotidError as exc:
        return {"status": "failed", "failed_stage": stage_name, "reason": str(exc)}
    except Exception as exc:  # noqa: BLE001 - anything else may be transient: retried, then the case's failure
        raise StageFailure(stage_name, f"{type(exc).__name__}: {exc}") from None
    log = (previous or {}).get("log", []) + [line]
    return {"status": "ok", "log": log}


def _wall_area_fractions(path: Path) -> tuple:
    """Fractions of the wall area (``indices.vtp``) with OSI above ``HIGH_OSI`` and with TAWSS below
    ``LOW_TAWSS_PA``; ``("", "")`` when the flow stage has not run."""
    if not path.exists():
        return "", ""
    try:
        wall = read_vtk(path, "wall indices")
    except CarotidError:  # a cohort row keeps its other columns; the report names the file
        return "", ""
    areas = node_areas(wall.points, wall.triangulate().faces.reshape(-1, 4)[:, 1:])
    osi, tawss = np.asarray(wall["OSI"]), np.asarray(wall["TAWSS"])
    return area_fraction(osi, areas, HIGH_OSI), area_fraction(-tawss, areas, -LOW_TAWSS_PA)  # -TAWSS above


def _lookup(record: dict, *keys: str):
    """``record[k0][k1]...``, or "" (an empty cell) when a key is missing."""
    for key in keys:
        if not isinstance(record, dict) or key not in record:
            return ""
        record = record[key]
    return record


def case_summary(case: Case, case_dir: Path, outcome: dict) -> dict:
    """One ``cohort.csv`` row from a case's outcome and the result files it has."""
    record = read_case(case_dir) if (case_dir / "case.json").exists() else {"stages": {}}
    seconds = {name: stage["seconds"] for name, stage in record["stages"].items()}
    segmentation = read_json(case_dir / "segmentation" / "report.json")
    geometry = read_json(case_dir / "geometry.json")
    stenosis = (geometry.get("stenosis") or {}) if geometry.get("bifurcation_mm") else {}
    mesh = read_json(case_dir / "mesh_quality.json")
    flow = read_json(case_dir / "flow" / "summary.json")
    periodic = flow.get("periodic", {})
    change = periodic.get("last_relative_change")  # None: under two whole cycles
    gci = read_json(case_dir / "flow" / "convergence.json").get("branches", {}).get("TAWSS", {}).get(
        "whole wall", {}).get("gci_fine21")
    osi, low_tawss = _wall_area_fractions(case_dir / "flow" / "indices.vtp")
    shape = geometry.get("bifurcation_geometry") or {}
    regions = flow.get("regions", {}).get("statistics", {})
    failed = [f"{c.stage}: {c.quantity}" for c in quality_checks(
        segmentation, read_json(case_dir / "surface_quality.json"), mesh, flow) if not c.passed]
    return {
        "case_id": case.case_id, "status": outcome["status"], "failed_stage": outcome.get("failed_stage", ""),
        "reason": outcome.get("reason", ""), "image": str(case.image),
        "lumen_volume_mm3": segmentation.get("lumen_volume_mm3", ""),
        "lumen_contrast_to_noise": _cell_value(_lookup(segmentation, "intensity", "contrast_to_noise")),
        "stenosis_branch": stenosis.get("branch", ""), "nascet": stenosis.get("nascet", ""),
        "ecst": stenosis.get("ecst", ""),
        "stenosis_category": stenosis_category(stenosis["nascet"], stenosis["min_diameter_mm"],
                                               stenosis["distal_diameter_mm"]) if stenosis else "",
        "stenosis_calcium_mm": _cell_value(stenosis.get("calcium_mm")),
        "stenosis_calcified": calcified(stenosis) if stenosis else "",
        "mesh_tetrahedra": mesh.get("elements", {}).get("tetrahedra", ""),
        "outlets": _lookup(flow, "outlets", "model"),
        "outlets_fallback": _lookup(flow, "outlets", "fallback", "from"),
        "checks_failed": len(failed), "failed_checks": "; ".join(failed),
        "tawss_mean_pa": flow.get("indices", {}).get("TAWSS", {}).get("mean", ""),
        "indices_cycle_fraction": flow.get("indices_cycle_fraction", ""),
        "periodic_status": periodic.get("status", ""),
        "tawss_last_cycle_change": "" if change is None else change,
        "tawss_gci_percent": "" if gci is None else 100.0 * gci,
        "osi_area_fraction": osi, "low_tawss_area_fraction": low_tawss,
        **{name: _lookup(shape, *key.split(".")) for name, (key, _, _) in GEOMETRY_KEYS.items()},
        **{name: _cell_value(_lookup(flow, *key.split("."))) for name, (key, _, _) in DUPLEX_KEYS.items()},
        **{name: _lookup(regions, region, *filter(None, (index, stat)))
           for name, (region, index, stat) in REGION_KEYS.items()},
        **{f"seconds_{name}": seconds.get(name, "") for name in STAGE_NAMES},
        "seconds_total": sum(seconds.values()),
    }


def _cell_value(value):
    """A record value as a cohort.csv value: None (not applicable) as an empty cell."""
    return "" if value is None else value


def _cell(value) -> str:
    """A cohort.csv cell: real numbers to ``SIGNIFICANT_DIGITS`` significant digits, integers and text as they are."""
    if isinstance(value, (float, np.floating)):
        return f"{value:.{SIGNIFICANT_DIGITS}g}"
    return str(value)


def write_cohort(rows: list[dict], path: Path) -> Path:
    """Write ``cohort.csv`` and, beside it, ``cohort.json`` (columns with unit and meaning, thresholds), atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(COHORT_COLUMNS))
            writer.writeheader()
            writer.writerows({k: _cell(v) for k, v in row.items()} for row in rows)
    write_json({"file": path.name, "significant_digits": SIGNIFICANT_DIGITS,
                "thresholds": {"osi": HIGH_OSI, "low_tawss_pa": LOW_TAWSS_PA},
                "columns": {name: {"unit": unit, "description": text}
                            for name, (unit, text) in COHORT_COLUMNS.items()}},
               path.with_suffix(".json"))
    return path


def _print_err(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _outcome(future) -> dict:
    """The outcome of a finished stage task's future."""
    try:
        return future.result()
    except StageFailure as exc:  # an unexpected error of a stage that persisted through the retries
        return {"status": "failed", "failed_stage": exc.stage, "reason": exc.reason}
    except Exception as exc:  # outside the stages (a worker that died)
        return {"status": "failed", "failed_stage": "", "reason": f"{type(exc).__name__}: {exc}"}


def _submit(client, case: Case, out_dir: Path, index: int, previous: dict | None, retries: int):
    """Submit stage ``STAGE_NAMES[index]`` of ``case`` as a Dask task (a future).  A later stage has the higher
    priority, so that cases already begun go on before new ones begin."""
    name = STAGE_NAMES[index]
    return client.submit(_stage_task, case, str(out_dir / case.case_id), name, previous, key=f"{case.case_id}/{name}",
                         retries=retries, pure=False, priority=index)


def _ended_line(row: dict) -> str:
    """What the progress line says of a case that ended, from its ``cohort.csv`` row: ``done``, with the
    quality checks that failed, or where and why it failed."""
    if row["status"] != "ok":
        return f"failed at {row['failed_stage'] or 'an unexpected error'}: {row['reason']}"
    count = row["checks_failed"]
    return "done" + (f"; {count} quality check{'s' if count > 1 else ''} failed: {row['failed_checks']}"
                     if count else "")


def _drive(client, cases: list[Case], out_dir: Path, retries: int, log: Callable[[str], None], every: float,
           ended: Callable[[Case, dict], str]) -> dict:
    """Run every case's stages in order, logging each case that ends (``batch: <id> <ended(case, outcome)>``)
    and, at least every ``every`` seconds, the cases done, failed, running (a stage of theirs on a worker) and
    waiting, the elapsed time and an ETA extrapolated from the fraction of stage tasks finished.

    Each stage is submitted when the case's previous stage has finished, with that stage's small outcome as a
    value, not as a Dask dependency: the scheduler places a task on a worker holding its dependencies, which
    would pin all of a case's stages to the worker of its first, and leave one worker idle while the other has
    cases queued behind a long flow run.  Tasks without dependencies wait on the scheduler and go to whichever
    worker frees up first.

    Returns
    -------
    dict
        Case id -> outcome.
    """
    from dask.distributed import wait

    start = last = time.monotonic()
    current = {case.case_id: (case, 0, _submit(client, case, out_dir, 0, None, retries)) for case in cases}
    outcomes, finished, total = {}, 0, len(cases) * len(STAGE_NAMES)
    while current:
        try:
            wait([future for _, _, future in current.values()], timeout=every, return_when="FIRST_COMPLETED")
        except TimeoutError:
            pass
        just_ended = []
        for case_id, (case, index, future) in list(current.items()):
            if future.status == "pending":
                continue
            finished += 1
            outcome = _outcome(future)
            if outcome["status"] == "ok" and index + 1 < len(STAGE_NAMES):
                current[case_id] = (case, index + 1, _submit(client, case, out_dir, index + 1, outcome, retries))
                continue
            total -= len(STAGE_NAMES) - 1 - index  # the stages a failed case does not run
            del current[case_id]
            outcomes[case_id] = outcome
            just_ended.append(case_id)
            log(f"batch: {case_id} {ended(case, outcome)}")
        now = time.monotonic()
        if just_ended or now - last >= every:
            running = {str(key).split("/")[0] for keys in client.processing().values() for key in keys} - set(outcomes)
            failed = sum(outcome["status"] != "ok" for outcome in outcomes.values())
            fraction = finished / total
            eta = format_duration((now - start) * (1 - fraction) / fraction) if fraction > 0 else "unknown"
            log(f"batch: {len(outcomes) - failed} of {len(cases)} cases done, {failed} failed, {len(running)} "
                f"running, {len(cases) - len(outcomes) - len(running)} waiting; {format_duration(now - start)} elapsed, "
                f"ETA {eta}")
            last = now
    return outcomes


def run_batch(manifest: str | Path, out_dir: str | Path, *, scheduler: str | None = None, workers: int = 2,
              retries: int = 1, config: str | Path | None = None,
              log: Callable[[str], None] = _print_err) -> list[dict]:
    """Run every case of a manifest on Dask and write ``OUT_DIR/cohort.csv`` and ``cohort.json``.

    Parameters
    ----------
    manifest : path
        CSV with ``case_id,image[,config]``.
    out_dir : path
        Each case goes to ``OUT_DIR/<case_id>``.
    scheduler : str, optional
        Address of a running Dask scheduler; a LocalCluster of ``workers`` processes otherwise.
    workers : int
        Worker processes of the LocalCluster (one thread each: the stages use numba/FFT threads).
    retries : int
        Extra attempts of a stage that failed with an unexpected (possibly transient) error.
    config : path, optional
        TOML config for every case without its own.
    log : callable
        Receives the progress lines (default: printed on stderr at once): one per case that ends (with the
        quality checks that failed) and a summary at least every ``PROGRESS_SECONDS``.

    Returns
    -------
    list of dict
        The cohort rows, in manifest order.
    """
    from dask.distributed import Client, LocalCluster

    check_ranges("batch", SimpleNamespace(workers=workers, retries=retries), BATCH_RANGES)
    cases = read_manifest(manifest, config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Dask's own logs (a retried task's traceback, a closed stream at shutdown) would bury the progress lines:
    # every failure is in the case's line and in cohort.csv.  The caller's logging is restored afterwards.
    dask_log = logging.getLogger("distributed")
    level = dask_log.level
    dask_log.setLevel(logging.CRITICAL)
    try:
        cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                      dashboard_address=None, silence_logs=logging.CRITICAL)
        with Client(scheduler or cluster) as client:
            log(f"batch: {len(cases)} cases, {len(cases) * len(STAGE_NAMES)} stage tasks")
            by_case = {}

            def ended(case: Case, outcome: dict) -> str:
                by_case[case.case_id] = case_summary(case, out_dir / case.case_id, outcome)
                return _ended_line(by_case[case.case_id])

            _drive(client, cases, out_dir, retries, log, PROGRESS_SECONDS, ended)
            rows = [by_case[case.case_id] for case in cases]
        if cluster is not None:
            cluster.close()
    finally:
        dask_log.setLevel(level)
    write_cohort(rows, out_dir / "cohort.csv")
    return rows
