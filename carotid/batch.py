"""``carotid batch``: a cohort of cases on Dask distributed.

Each case's stages are a chain of Dask tasks (stage *k* depends on stage
*k-1* of the same case only), so different cases run side by side on the
workers.  Bad input (``CarotidError``) fails its case at once with the
reason and is not retried; any other exception is retried (``retries``)
as possibly transient, and fails the case if it persists.  One failed case
never stops the others.  Every stage goes through ``pipeline.run_stage``, so
finished stages are skipped when a batch is run again.  The outcome is
``OUT_DIR/cohort.csv``, one row per case.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carotid.config import Config
from carotid.errors import CarotidError
from carotid.io import atomic_path
from carotid.pipeline import STAGES, read_case, run_stage

OSI_THRESHOLD = 0.2  # OSI above which wall is counted as oscillatory (osi_area_fraction)
COHORT_COLUMNS = ("case_id", "status", "failed_stage", "reason", "image", "lumen_volume_mm3", "nascet", "ecst",
                  "mesh_tetrahedra", "tawss_mean_pa", "osi_area_fraction", "seconds_total", "seconds_by_stage")


@dataclass(frozen=True)
class Case:
    """One row of a manifest: an identifier, an image and its configuration overrides."""

    case_id: str
    image: Path
    overrides: dict


def read_manifest(path: str | Path, default_config: str | Path | None = None) -> list[Case]:
    """Read a manifest CSV with columns ``case_id,image[,config]`` (paths relative to the manifest).

    A case's ``config`` (TOML) replaces ``default_config`` for that case.  Duplicate ids, missing
    columns and unreadable config files are errors; a missing *image* is not (that case fails alone).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CarotidError(f"{path}: cannot read the manifest ({exc.strerror})") from exc
    rows = list(csv.DictReader(io.StringIO(text)))
    if not rows or not {"case_id", "image"} <= set(rows[0]):
        raise CarotidError(f"{path}: a manifest needs a header with the columns case_id,image[,config] and rows")
    cases, seen = [], set()
    for line, row in enumerate(rows, start=2):
        case_id = (row["case_id"] or "").strip()
        if not case_id or case_id in seen or "/" in case_id:
            raise CarotidError(f"{path}:{line}: case_id {case_id!r} is empty, repeated or contains '/'")
        seen.add(case_id)
        config = (row.get("config") or "").strip() or default_config
        overrides = Config.from_toml(path.parent / config).sections if config else {}
        cases.append(Case(case_id, path.parent / row["image"].strip(), overrides))
    return cases


def _stage_task(case: Case, case_dir: str, stage_name: str, previous: dict | None) -> dict:
    """Run one stage of one case (a Dask task): ``{"status": "ok"|"failed", ...}``."""
    if previous is not None and previous["status"] != "ok":
        return previous
    stage = next(s for s in STAGES if s.name == stage_name)
    try:
        if not case.image.exists():
            raise CarotidError(f"{case.image}: no such file or folder")
        line = run_stage(stage, case.image, Path(case_dir), Config(case.overrides))
    except CarotidError as exc:
        return {"status": "failed", "failed_stage": stage_name, "reason": str(exc)}
    log = (previous or {}).get("log", []) + [line]
    return {"status": "ok", "log": log}


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def _osi_area_fraction(path: Path, threshold: float = OSI_THRESHOLD):
    """Fraction of the wall area where OSI exceeds ``threshold`` ("" when the flow stage has not run)."""
    if not path.exists():
        return ""
    import pyvista as pv

    from carotid.flow.indices import area_fraction

    wall = pv.read(path)
    areas = wall.compute_cell_sizes(length=False, volume=False)["Area"]
    osi = wall.point_data_to_cell_data()["OSI"] if "OSI" in wall.point_data else wall["OSI"]
    return float(area_fraction(np.asarray(osi), np.asarray(areas), threshold))


def case_summary(case: Case, case_dir: Path, outcome: dict) -> dict:
    """One ``cohort.csv`` row from a case's outcome and the result files it has."""
    record = read_case(case_dir) if (case_dir / "case.json").exists() else {"stages": {}}
    seconds = {name: stage["seconds"] for name, stage in record["stages"].items()}
    segmentation = _read_json(case_dir / "segmentation" / "report.json")
    stenosis = _read_json(case_dir / "geometry.json").get("stenosis", {})
    mesh = _read_json(case_dir / "mesh_quality.json")
    flow = _read_json(case_dir / "flow" / "summary.json")
    return {
        "case_id": case.case_id, "status": outcome["status"], "failed_stage": outcome.get("failed_stage", ""),
        "reason": outcome.get("reason", ""), "image": str(case.image),
        "lumen_volume_mm3": segmentation.get("lumen_volume_mm3", ""),
        "nascet": stenosis.get("nascet", ""), "ecst": stenosis.get("ecst", ""),
        "mesh_tetrahedra": mesh.get("elements", {}).get("tetrahedra", ""),
        "tawss_mean_pa": flow.get("indices", {}).get("TAWSS", {}).get("mean", ""),
        "osi_area_fraction": _osi_area_fraction(case_dir / "flow" / "indices.vtp"),
        "seconds_total": round(sum(seconds.values()), 3), "seconds_by_stage": json.dumps(seconds),
    }


def write_cohort(rows: list[dict], path: Path) -> Path:
    """Write ``cohort.csv`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=COHORT_COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
    return path


def run_batch(manifest: str | Path, out_dir: str | Path, *, scheduler: str | None = None, workers: int = 2,
              retries: int = 1, config: str | Path | None = None) -> list[dict]:
    """Run every case of a manifest on Dask and write ``OUT_DIR/cohort.csv``.

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

    Returns
    -------
    list of dict
        The cohort rows, in manifest order.
    """
    from dask.distributed import Client, LocalCluster

    cases = read_manifest(manifest, config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                  dashboard_address=None)
    with Client(scheduler or cluster) as client:
        finals = {}
        for case in cases:
            previous = None
            for stage in STAGES:
                if stage.runner:
                    previous = client.submit(_stage_task, case, str(out_dir / case.case_id), stage.name, previous,
                                             key=f"{case.case_id}/{stage.name}", retries=retries, pure=False)
            finals[case.case_id] = previous
        rows = []
        for case in cases:
            try:
                outcome = finals[case.case_id].result()
            except Exception as exc:  # an unexpected error that persisted through the retries
                outcome = {"status": "failed", "failed_stage": "", "reason": f"{type(exc).__name__}: {exc}"}
            rows.append(case_summary(case, out_dir / case.case_id, outcome))
    if cluster is not None:
        cluster.close()
    write_cohort(rows, out_dir / "cohort.csv")
    return rows
