"""Benchmark of ``carotid demo``: the whole chain on the built-in phantom, seconds per stage and peak memory.

Target (issue #6): the whole chain in <= 10 minutes on 2 cores.  The demo
runs in a fresh process (``run_isolated``) so its peak RSS is its own; the
per-stage seconds come from the ``case.json`` it writes.

Usage (from the repository root)::

    /tmp/venv/bin/python benchmarks/bench_demo.py [--quick]

``--quick`` is the same run (the demo is already coarse) written to ``demo_quick.json``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from _common import parse_args, run_isolated, write_results
from carotid.cli import main as carotid_main

TARGET_S = 600.0


def run_demo(out: str) -> dict:
    """Run ``carotid demo -o out`` and return its exit status and wall seconds."""
    start = time.perf_counter()
    code = carotid_main(["demo", "-o", out])
    return {"exit_status": code, "seconds": time.perf_counter() - start}


def main() -> None:
    """Run the demo once and write ``results/demo.json``."""
    args = parse_args(__doc__.splitlines()[0])
    with tempfile.TemporaryDirectory() as folder:
        measured = run_isolated(run_demo, folder)
        record = json.loads((Path(folder) / "case" / "case.json").read_text())
    seconds = measured["result"]["seconds"]
    figures = {
        "exit_status": measured["result"]["exit_status"],
        "seconds_total": seconds,
        "seconds_by_stage": {name: stage["seconds"] for name, stage in record["stages"].items()},
        "peak_rss_mb": measured["peak_rss_mb"],
        "target": {"seconds": TARGET_S, "met": seconds <= TARGET_S},
    }
    print(json.dumps(figures, indent=2))
    write_results("demo", figures, args.quick)


if __name__ == "__main__":
    main()
