"""One full cardiac cycle on a patient-sized carotid mesh, from the scan, as a user runs it.

The demo phantom (stenosis 0.7, noise 20 HU) through ``carotid run`` with a 0.55 mm surface, 10 wall
layers (default thickness and growth; the first layer thins to a few um in the stenosis) and one cycle of the
built-in common carotid waveform with the default solver settings (implicit viscosity, sparse Cholesky
pressure solve): about 440k tetrahedra.  ``--quick``: a 0.8 mm surface, 2 layers, a twentieth of a cycle.

Figures: seconds per stage, steps, seconds per step, tetrahedron-steps per second, the range of the
adaptive step, mass balance and peak RSS, in a fresh process (``results/cycle.json``).  Target (issue 5):
>= 1.5M tetrahedron-steps per second, i.e. a cycle at dt 1e-4 s in under an hour on ~500k tetrahedra.

Usage (from the repository root)::

    /tmp/venv/bin/python benchmarks/bench_cycle.py [--quick]
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from _common import parse_args, run_isolated, write_results

TARGET_TET_STEPS_PER_S = 1.5e6
CONFIG = {"surface": {"target_edge_mm": 0.55}, "mesh": {"layers": 10},
          "simulate": {"cycles": 1.0, "output_every": 200}}
QUICK_CONFIG = {"surface": {"target_edge_mm": 0.8}, "mesh": {"layers": 2},
                "simulate": {"cycles": 0.05, "output_every": 50}}


def run_case(folder: str, config: dict) -> dict:
    """Phantom, then ``carotid run`` with ``config``; returns the flow summary and the stage seconds."""
    from carotid.config import Config
    from carotid.phantom import make_phantom, write_phantom
    from carotid.pipeline import run

    out = Path(folder)
    write_phantom(make_phantom(stenosis=0.7, noise=20.0, seed=0), out / "phantom")
    run(out / "phantom" / "image.nii.gz", out / "case", Config(config))
    record = json.loads((out / "case" / "case.json").read_text())
    return {"summary": json.loads((out / "case" / "flow" / "summary.json").read_text()),
            "seconds_by_stage": {name: stage["seconds"] for name, stage in record["stages"].items()},
            "mesh_quality": json.loads((out / "case" / "mesh_quality.json").read_text())}


def main() -> None:
    """Run the case once and write ``results/cycle.json``."""
    args = parse_args(__doc__.splitlines()[0])
    config = QUICK_CONFIG if args.quick else CONFIG
    with tempfile.TemporaryDirectory() as folder:
        measured = run_isolated(run_case, folder, config)
    result = measured["result"]
    summary, layer = result["summary"], result["mesh_quality"]["boundary_layer"]
    tets = summary["mesh"]["tetrahedra"]
    figures = {
        "config": config,
        "tetrahedra": tets,
        "nodes": summary["mesh"]["nodes"],
        "first_layer_mm": layer["first_height_mm"],
        "seconds_by_stage": result["seconds_by_stage"],
        "cycles": summary["cycles"],
        "steps": summary["steps"],
        "simulate_seconds": summary["seconds"],
        "seconds_per_step": summary["seconds_per_step"],
        "tet_steps_per_s": tets / summary["seconds_per_step"],
        "dt_s": summary["dt_s"],
        "mass_balance": summary["mass_balance"],
        "settings": summary["settings"],
        "peak_rss_mb": measured["peak_rss_mb"],
        "target": {"tet_steps_per_s": TARGET_TET_STEPS_PER_S,
                   "met": tets / summary["seconds_per_step"] >= TARGET_TET_STEPS_PER_S},
    }
    print(json.dumps(figures, indent=2))
    write_results("cycle", figures, args.quick)


if __name__ == "__main__":
    main()
