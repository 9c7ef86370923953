"""Cost of the physiological outlets and of non-Newtonian blood, and the low-TAWSS area they move (issue 16).

The demo case (``make_phantom(stenosis=0.7, noise=20, seed=0)`` through the segment, centerlines, surface and
mesh stages at ``carotid demo``'s coarse settings: 0.8 mm surface, 2 wall layers) is built once; every run
below uses that SAME ``mesh.vtu``, each in a folder of its own (``mesh.vtu``, ``centerlines.vtp`` and
``geometry.json`` copied), one run at a time, in this process.

1. **Cost** (issue 16: "run times stay within 1.5x of the Newtonian fixed-split run on the same mesh").  Four
   variants: Newtonian + Murray's split (the reference), Carreau-Yasuda + split, Newtonian + RCR, Carreau + RCR
   (RCR calibrated for Murray's split, 93 mmHg mean, 40 mmHg pulse), from rest over the same simulated
   interval with the same FIXED step, so every variant takes the same number of steps.  Each variant is
   warmed up first (a few steps, discarded: numba compilation), then the variants are run round-robin
   ``REPEATS`` times (so a change of the machine's load hits all of them alike).  Per run: the wall seconds of
   the whole ``simulate`` call (set-up, Cholesky factorisation, RCR liftings, the loop, indices and summary),
   the seconds of its time loop (``summary.json`` ``seconds``), the loop's mean seconds per step and the
   median of the step-to-step intervals (taken by the ``progress`` callback; outputs and checkpoints every
   50 / 500 steps as in the demo fall on few steps, so the median is the bare step).  Each figure: min and
   median over the repeats, and the ratio of each to the reference's min and median.
2. **Low TAWSS** (issue 16: "on the demo case, report how the low-TAWSS area in the bulb changes from
   Newtonian").  Newtonian and Carreau-Yasuda, both under Murray's split, ``CYCLES`` whole cycles from rest
   at the default adaptive step; the indices of ``summary.json`` are those of the last whole cycle
   (``partial`` false is checked and recorded).  Per region (CCA, bulb, ICA, ECA, stenosis, whole wall): the
   area fraction with TAWSS < 0.4 Pa, the mean TAWSS and OSI, and the change Carreau - Newtonian; and the
   cost ratio of these whole-cycle runs (adaptive step, so their step counts differ).
3. **Where the step's time goes** (:func:`step_profile`): Newtonian and Carreau under the split, once each
   over the timing interval, with timers around the solver's methods.

Writes ``results/physiology.json`` after every run (``partial_run`` true until the end), with the git
commit, the load average at the start and end (and around each run), the protocol and all figures.

Usage (from the repository root; single-threaded, as the figures were taken)::

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        .venv/bin/python benchmarks/bench_physiology.py [--quick]

``--quick``: 0.01 cycle timing runs, one repeat, 0.05 cycle "cycle" runs (partial; smoke test only).
``--profile`` (after a full run): item 3 alone, on a newly built case, replacing ``step_profile`` in
``results/physiology.json``.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _common import git_state, parse_args, write_results

VARIANTS = (("newtonian", "murray"), ("carreau", "murray"), ("newtonian", "rcr"), ("carreau", "rcr"))
REFERENCE = VARIANTS[0]
TARGET_RATIO = 1.5
FIXED_DT_S = 5e-5          # below the demo's adaptive step at peak systole (6.6e-5 s), stable from rest
TIMING_CYCLES = 0.15       # 0.1376 s from rest: diastole and the systolic upstroke (peak at ~0.16 s)
REPEATS = 3
CYCLES = 3.0               # whole cycles of the low-TAWSS comparison; indices over the last one
SIM = {"output_every": 50, "checkpoint_every": 500}   # the demo's
REGIONS = ("CCA", "bulb", "ICA", "ECA", "stenosis", "other", "whole wall")
LOW_TAWSS_PA = 0.4


def build_case(folder: Path) -> dict:
    """The demo phantom through the segment, centerlines, surface and mesh stages (``carotid demo``'s config)."""
    from carotid.cli import DEMO_CONFIG
    from carotid.config import Config
    from carotid.phantom import make_phantom, write_phantom
    from carotid.pipeline import STAGES, read_case, run_stage

    write_phantom(make_phantom(stenosis=0.7, noise=20.0, seed=0), folder / "phantom")
    image, case = folder / "phantom" / "image.nii.gz", folder / "case"
    config = Config(DEMO_CONFIG)
    for stage in STAGES:
        if stage.name in ("simulate", "report"):
            continue
        print(run_stage(stage, image, case, config), flush=True)
    record = read_case(case)
    geometry = json.loads((case / "geometry.json").read_text())
    return {"case": case, "seconds_by_stage": {k: v["seconds"] for k, v in record["stages"].items()},
            "stenosis": {k: geometry["stenosis"].get(k) for k in ("nascet", "area_reduction")}}


def fresh_copy(case: Path, folder: Path) -> Path:
    """A run folder holding the case's mesh, centerlines and geometry only."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for name in ("mesh.vtu", "centerlines.vtp", "geometry.json"):
        shutil.copy(case / name, folder / name)
    return folder


def run_once(case: Path, folder: Path, rheology: str, outlets: str, cycles: float, dt: float | None) -> dict:
    """One ``simulate`` on a fresh copy of the case: its summary and the timings."""
    from carotid.flow.simulate import FlowParameters, simulate

    run_dir = fresh_copy(case, folder)
    stamps: list[float] = []
    params = FlowParameters(cycles=cycles, dt=dt, rheology=rheology, outlets=outlets, **SIM)
    load_before = os.getloadavg()
    start = time.perf_counter()
    summary = simulate(run_dir / "mesh.vtu", run_dir, params, progress=lambda info: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - start
    intervals = [b - a for a, b in zip(stamps, stamps[1:])]
    return {"summary": summary, "mesh": summary["mesh"], "wall_s": wall, "loop_s": summary["seconds"], "steps": summary["steps"],
            "s_per_step_mean": summary["seconds"] / summary["steps"],
            "s_per_step_median": statistics.median(intervals) if intervals else None,
            "load_average": {"start": load_before, "end": os.getloadavg()}}


def stats(values: list[float]) -> dict:
    return {"min": min(values), "median": statistics.median(values), "runs": values}


def timing(case: Path, work: Path, cycles: float, repeats: int, record) -> dict:
    """Warm-up, then the four variants round-robin ``repeats`` times; min / median and ratios to the reference."""
    runs: dict[str, list[dict]] = {f"{r}+{o}": [] for r, o in VARIANTS}
    for rheology, outlets in VARIANTS:  # numba compilation and first-touch costs, discarded
        run_once(case, work / "warmup", rheology, outlets, 0.002, FIXED_DT_S)
    for repeat in range(repeats):
        for rheology, outlets in VARIANTS:
            out = run_once(case, work / "timing", rheology, outlets, cycles, FIXED_DT_S)
            s = out.pop("summary")
            out.update(repeat=repeat, dt_s=s["dt_s"], cfl_max=s["cfl_max"], partial=s["partial"])
            runs[f"{rheology}+{outlets}"].append(out)
            print(f"timing {repeat} {rheology}+{outlets}: {out['steps']} steps, wall {out['wall_s']:.1f} s, "
                  f"loop {out['loop_s']:.1f} s, {1e3 * out['s_per_step_mean']:.2f} / "
                  f"{1e3 * out['s_per_step_median']:.2f} ms/step (mean/median), load {out['load_average']}", flush=True)
            record(runs)
    return summarise_timing(runs)


def summarise_timing(runs: dict) -> dict:
    ref_key = f"{REFERENCE[0]}+{REFERENCE[1]}"
    figures = {}
    for key, rows in runs.items():
        if not rows:
            continue
        figures[key] = {name: stats([r[name] for r in rows])
                        for name in ("wall_s", "loop_s", "s_per_step_mean", "s_per_step_median")}
        figures[key]["steps"] = sorted({r["steps"] for r in rows})
    if ref_key in figures:
        ref = figures[ref_key]
        for key, fig in figures.items():
            fig["ratio_to_reference"] = {name: {"min": fig[name]["min"] / ref[name]["min"],
                                                "median": fig[name]["median"] / ref[name]["median"]}
                                         for name in ("wall_s", "loop_s", "s_per_step_mean", "s_per_step_median")}
            fig["within_target"] = all(v["min"] <= TARGET_RATIO and v["median"] <= TARGET_RATIO
                                       for v in fig["ratio_to_reference"].values())
    return {"runs": runs, "figures": figures}


def region_figures(summary: dict) -> dict:
    stats_ = summary["regions"]["statistics"]
    out = {}
    for name in REGIONS:
        region = stats_.get(name)
        if region is None:
            continue
        out[name] = {"area_mm2": region["area_mm2"], "low_tawss_area_fraction": region["low_tawss_area_fraction"],
                     "tawss_mean_pa": region["TAWSS"]["mean"], "tawss_p5_pa": region["TAWSS"]["p5"],
                     "osi_mean": region["OSI"]["mean"], "high_osi_area_fraction": region["high_osi_area_fraction"]}
    return out


def cycle_comparison(case: Path, work: Path, cycles: float, record) -> dict:
    """Newtonian and Carreau under Murray's split over ``cycles`` cycles: per-region low-TAWSS and means."""
    result = {}
    for rheology in ("newtonian", "carreau"):
        out = run_once(case, work / f"cycle_{rheology}", rheology, "murray", cycles, None)
        s = out.pop("summary")
        result[rheology] = {**out, "partial": s["partial"], "indices_cycle_fraction": s["indices_cycle_fraction"],
                            "cycles": s["cycles"], "time_s": s["time_s"], "dt_s": s["dt_s"], "cfl_max": s["cfl_max"],
                            "periodicity": s["periodicity"], "regions": region_figures(s),
                            "regions_statistics": s["regions"]["statistics"],
                            "bulb_end_mm": s["regions"].get("bulb_end_mm"),
                            "stenosis_extent_mm": s["regions"].get("stenosis_extent_mm")}
        print(f"cycle {rheology}: {s['steps']} steps, {out['wall_s']:.0f} s, partial {s['partial']}, bulb "
              f"{result[rheology]['regions'].get('bulb')}", flush=True)
        record(result)
    newt, carr = result["newtonian"]["regions"], result["carreau"]["regions"]
    change = {}
    for name in newt:
        if name not in carr:
            continue
        a, b = newt[name], carr[name]
        change[name] = {
            "low_tawss_points": 100.0 * (b["low_tawss_area_fraction"] - a["low_tawss_area_fraction"]),
            "low_tawss_relative": (b["low_tawss_area_fraction"] / a["low_tawss_area_fraction"] - 1.0
                                   if a["low_tawss_area_fraction"] > 0 else None),
            "tawss_mean_relative": b["tawss_mean_pa"] / a["tawss_mean_pa"] - 1.0,
            "osi_mean_change": b["osi_mean"] - a["osi_mean"]}
    result["carreau_minus_newtonian"] = change
    n, c = result["newtonian"], result["carreau"]
    result["cost_ratio_carreau_to_newtonian"] = {  # adaptive step: the step counts differ
        "loop_s": c["loop_s"] / n["loop_s"], "wall_s": c["wall_s"] / n["wall_s"], "steps": c["steps"] / n["steps"],
        "s_per_step_mean": c["s_per_step_mean"] / n["s_per_step_mean"]}
    return result


def step_profile(case: Path, work: Path, cycles: float) -> dict:
    """Where a step's time goes, Newtonian vs Carreau under Murray's split (the timing protocol's interval and
    step, one run each): seconds in the viscosity evaluation, the re-assembly of the viscous matrix, the three
    viscous CG solves (and their iterations), the pressure solve, the outputs, and the rest of the step."""
    import scipy.sparse.linalg as spla

    from carotid.flow import cbs, simulate as sim

    clock: dict[str, float] = {}
    counts = {"cg_calls": 0, "cg_iterations": 0}

    def timed_method(owner, name, key):
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                clock[key] = clock.get(key, 0.0) + time.perf_counter() - start
        setattr(owner, name, wrapper)
        return original

    original_cg = spla.cg

    def counting_cg(*args, **kwargs):
        counts["cg_calls"] += 1
        user = kwargs.pop("callback", None)

        def callback(xk):
            counts["cg_iterations"] += 1
            if user is not None:
                user(xk)
        return original_cg(*args, callback=callback, **kwargs)

    saved = [(cbs.CBSSolver, "step", timed_method(cbs.CBSSolver, "step", "step_total")),
             (cbs.CBSSolver, "molecular_viscosity", timed_method(cbs.CBSSolver, "molecular_viscosity", "viscosity_eval")),
             (cbs.CBSSolver, "_viscous_matrices", timed_method(cbs.CBSSolver, "_viscous_matrices", "viscous_reassembly")),
             (cbs.CBSSolver, "_viscous_solve", timed_method(cbs.CBSSolver, "_viscous_solve", "viscous_cg")),
             (cbs.PressureSolver, "solve", timed_method(cbs.PressureSolver, "solve", "pressure_solve")),
             (sim, "_output", timed_method(sim, "_output", "outputs"))]
    spla.cg = counting_cg
    result = {}
    try:
        for rheology in ("newtonian", "carreau"):
            clock.clear()
            counts.update(cg_calls=0, cg_iterations=0)
            out = run_once(case, work / "profile", rheology, "murray", cycles, FIXED_DT_S)
            out.pop("summary")
            steps = out["steps"]
            row = {"steps": steps, "loop_s": out["loop_s"], "load_average": out["load_average"],
                   "ms_per_step": {k: 1e3 * v / steps for k, v in clock.items()},
                   "cg_iterations_per_solve": counts["cg_iterations"] / max(counts["cg_calls"], 1)}
            inner = sum(v for k, v in clock.items() if k not in ("step_total", "outputs"))
            row["ms_per_step"]["step_rest"] = 1e3 * (clock.get("step_total", 0.0) - inner) / steps
            result[rheology] = row
            print(f"profile {rheology}: {json.dumps(row)}", flush=True)
    finally:
        spla.cg = original_cg
        for owner, name, original in saved:
            setattr(owner, name, original)
    return result


def profile_main(quick: bool) -> None:
    """``--profile``: :func:`step_profile` on a freshly built case, added to the existing results file as
    ``step_profile`` with its own timestamp, commit and load average."""
    from datetime import datetime, timezone

    from _common import RESULTS_DIR, _jsonable
    from carotid.io import write_json

    path = RESULTS_DIR / f"physiology{'_quick' if quick else ''}.json"
    document = json.loads(path.read_text())
    load_start, stamp = os.getloadavg(), datetime.now(timezone.utc).isoformat(timespec="seconds")
    git = git_state()
    with tempfile.TemporaryDirectory() as folder:
        built = build_case(Path(folder))
        profile = step_profile(built["case"], Path(folder), 0.01 if quick else TIMING_CYCLES)
    document["step_profile"] = {"timestamp": stamp, "git": git, "command": "bench_physiology.py --profile",
                                "cycles_from_rest": 0.01 if quick else TIMING_CYCLES, "fixed_dt_s": FIXED_DT_S,
                                "note": "a separate run after the timing runs, with timers around the solver's "
                                        "methods (their overhead is included)",
                                "load_average": {"start": load_start, "end": os.getloadavg()}, **profile}
    write_json(_jsonable(document), path)
    print(f"wrote {path}")


def main() -> None:
    if "--profile" in sys.argv:
        sys.argv.remove("--profile")
        args = parse_args(__doc__.splitlines()[0])
        profile_main(args.quick)
        return
    args = parse_args(__doc__.splitlines()[0])
    timing_cycles, repeats, cycles = (0.01, 1, 0.05) if args.quick else (TIMING_CYCLES, REPEATS, CYCLES)
    git, load_start = git_state(), os.getloadavg()
    threads = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    protocol = {
        "case": "make_phantom(stenosis=0.7, noise=20, seed=0) through segment, centerlines, surface, mesh with "
                "carotid.cli.DEMO_CONFIG (0.8 mm surface, 2 wall layers); every run on that same mesh.vtu",
        "timing": {"variants": [f"{r}+{o}" for r, o in VARIANTS], "reference": f"{REFERENCE[0]}+{REFERENCE[1]}",
                   "cycles_from_rest": timing_cycles, "fixed_dt_s": FIXED_DT_S, "repeats": repeats,
                   "order": "warm-up of each variant (0.002 cycle, discarded), then round-robin over the variants",
                   "target_ratio": TARGET_RATIO, **SIM},
        "cycle": {"cycles_from_rest": cycles, "dt": "adaptive (default, safety 0.8)", "outlets": "murray",
                  "rheologies": ["newtonian", "carreau"], "low_tawss_threshold_pa": LOW_TAWSS_PA,
                  "indices": "summary.json regions.statistics, over the last whole cycle"},
        "rheology": "carreau = Carreau-Yasuda, Cho & Kensey 1991 (mu_0 0.056, mu_inf 0.00345 Pa s, lambda 3.313 s, "
                    "n 0.3568); newtonian mu 3.5e-3 Pa s",
        "rcr": "calibrated for Murray's split as the mean share, 93 mmHg mean, 40 mmHg pulse, R_p = 0.09 (R_p + R_d)",
        "threads": threads, "one simulation at a time": True}
    figures: dict = {"git": git, "protocol": protocol, "partial_run": True}

    def save() -> None:
        figures["load_average"] = {"start": load_start, "end": os.getloadavg()}
        write_results("physiology", figures, args.quick)

    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        built = build_case(work)
        case = built.pop("case")
        figures["case"] = built

        def record_timing(runs):
            figures["timing"] = summarise_timing(runs)
            save()

        figures["timing"] = timing(case, work, timing_cycles, repeats, record_timing)
        save()

        def record_cycle(result):
            figures["cycle"] = result
            save()

        figures["cycle"] = cycle_comparison(case, work, cycles, record_cycle)
        save()
        figures["step_profile"] = {"cycles_from_rest": timing_cycles, "fixed_dt_s": FIXED_DT_S,
                                   "note": "one run each after the timing and cycle runs, with timers around the "
                                           "solver's methods (their overhead is included)",
                                   **step_profile(case, work, timing_cycles)}
    figures["partial_run"] = False
    save()
    print(json.dumps({k: {"ratio": v.get("ratio_to_reference")} for k, v in figures["timing"]["figures"].items()},
                     indent=1))
    print(json.dumps(figures["cycle"]["carreau_minus_newtonian"], indent=1))


if __name__ == "__main__":
    main()
