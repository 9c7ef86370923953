"""A cohort of scans nobody here made, run the way a new user runs one: ``carotid batch``, no seeds.

Every case of the second generator (``second_generator.py``, seeds given by ``--seeds``) is written as a
NIfTI image and listed in a manifest; one ``carotid batch`` run (two workers) takes the whole cohort from
scan to report with the demo's coarse settings (``cli.DEMO_CONFIG``: 0.8 mm surface edges, two wall layers,
one cardiac cycle), and no seed, stop point or parameter of its own.  Per case the script records whether
it finished, the stage and reason where it failed, the grade against the true lumen graded the same way
(``bench_segmentation.grade`` on the generator's level set: NASCET error in points), and what ``cohort.csv``
tells a user to doubt: the stenosis called calcified, the report's quality checks that failed, and the
flows rerun with RCR outlets after the prescribed split blew up (with their ICA PSV and pressure drop).

There is no peer: VMTK, SimVascular and 3D Slicer have no unattended scan-to-flow path to compare against.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_cohort.py [--seeds 0-47] [--workers 2]

Writes ``results/cohort.json`` (about 25 minutes for 48 cases on two cores).
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import git_state, write_results
from bench_segmentation import grade
from carotid.cli import DEMO_CONFIG
from carotid.config import Config
from carotid.io import write_image
from second_generator import make_second_phantom


def seed_list(text: str) -> list[int]:
    """``"0-47"`` or ``"2,3,40"`` (or both, comma-separated) as a list of seeds."""
    seeds = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds += list(range(int(first), int(last or first) + 1))
    return seeds


def prepare(seeds: list[int], folder: Path) -> dict:
    """Write each case's image and the manifest; grade each true lumen.  Returns ``{case_id: truth}``."""
    truths, rows = {}, ["case_id,image"]
    for seed in seeds:
        phantom = make_second_phantom(seed)
        write_image(phantom.image, folder / f"s{seed}.nii.gz")
        rows.append(f"s{seed},s{seed}.nii.gz")
        truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
        truths[f"s{seed}"] = {"seed": seed, "modality": phantom.info["parameters"]["modality"],
                              "stenosis_area": phantom.info["parameters"]["stenosis_area"],
                              "calcium": bool(phantom.info["parameters"]["calcium"]),
                              "nascet": truth["nascet"], "graded_branch": truth["graded_branch"]}
        print(f"s{seed}: written, true lumen graded NASCET {truth['nascet']}", flush=True)
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    (folder / "coarse.toml").write_text(Config(DEMO_CONFIG).to_toml())
    return truths


def main() -> None:
    """Run the cohort and write ``results/cohort.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-47", help="second-generator seeds, e.g. 0-47 or 2,3,40")
    parser.add_argument("--workers", type=int, default=2)
    options = parser.parse_args()
    git = git_state()
    with tempfile.TemporaryDirectory(prefix="carotid-cohort-") as tmp:
        inputs, out = Path(tmp) / "inputs", Path(tmp) / "out"
        inputs.mkdir()
        truths = prepare(seed_list(options.seeds), inputs)
        start = time.perf_counter()
        batch = subprocess.run([sys.executable, "-m", "carotid", "batch", "manifest.csv", "-o", str(out),
                                "--config", "coarse.toml", "--workers", str(options.workers)],
                               cwd=inputs, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        print(batch.stdout[-3000:], batch.stderr[-2000:], flush=True)
        with open(out / "cohort.csv", newline="") as handle:
            rows = list(csv.DictReader(handle))
    cases = []
    for row in rows:
        truth = truths[row["case_id"]]
        nascet = float(row["nascet"]) if row.get("nascet") else None
        cases.append({**truth, "case_id": row["case_id"], "status": row["status"],
                      "failed_stage": row["failed_stage"] or None, "reason": row["reason"] or None,
                      "nascet_graded": nascet, "stenosis_branch": row.get("stenosis_branch") or None,
                      "nascet_error_points": None if nascet is None or truth["nascet"] is None
                      else 100.0 * (nascet - truth["nascet"]),
                      "stenosis_category": row.get("stenosis_category") or None,
                      "stenosis_calcified": row.get("stenosis_calcified") == "True",
                      "checks_failed": int(row["checks_failed"]) if row.get("checks_failed") else None,
                      "failed_checks": row.get("failed_checks") or None,
                      "outlets_fallback": row.get("outlets_fallback") or None,
                      "ica_psv_cm_s": float(row["ica_psv_cm_s"]) if row.get("ica_psv_cm_s") else None,
                      "stenosis_pressure_drop_mmhg": float(row["stenosis_pressure_drop_mmhg"])
                      if row.get("stenosis_pressure_drop_mmhg") else None})
    errors = np.array([abs(c["nascet_error_points"]) for c in cases if c["nascet_error_points"] is not None])
    failed = [c for c in cases if c["status"] != "ok"]
    checks = [name for c in cases if c["failed_checks"] for name in c["failed_checks"].split("; ")]
    summary = {"cases": len(cases), "finished": len(cases) - len(failed),
               "failed": {c["case_id"]: f"{c['failed_stage']}: {c['reason']}" for c in failed},
               "failed_by_stage": {stage: sum(c["failed_stage"] == stage for c in failed)
                                   for stage in sorted({c["failed_stage"] for c in failed})},
               "graded": int(len(errors)),
               "nascet_within_5_points": int(np.sum(errors <= 5.0)),
               "nascet_abs_error_median_points": float(np.median(errors)) if len(errors) else None,
               "nascet_abs_error_worst_points": float(errors.max()) if len(errors) else None,
               "nascet_within_5_points_by_calcified_flag": {
                   flag: [sum(1 for c in cases if c["stenosis_calcified"] == value and c["nascet_error_points"]
                              is not None and abs(c["nascet_error_points"]) <= 5.0),
                          sum(1 for c in cases if c["stenosis_calcified"] == value and c["nascet_error_points"]
                              is not None)]
                   for flag, value in (("calcified", True), ("not_calcified", False))},
               "outlets_fallback": sorted(c["case_id"] for c in cases if c["outlets_fallback"]),
               "cases_with_failed_checks": sum(1 for c in cases if c["checks_failed"]),
               "failed_checks": {name: checks.count(name) for name in sorted(set(checks))},
               "batch_exit_status": batch.returncode, "batch_seconds": seconds}
    print(summary, flush=True)
    write_results("cohort", {"git": git, "config": DEMO_CONFIG, "workers": options.workers, "cases": cases,
                             "summary": summary})


if __name__ == "__main__":
    main()
