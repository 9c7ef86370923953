"""Benchmark: the segmentation on carotid angiograms from a second, independent phantom generator.

``bench_segmentation.py`` measures ``segment`` on the family of ``carotid phantom``, which was built beside
the segmentation.  ``second_generator.py`` builds the same anatomy class another way (sphere sweeps, an
eccentric two-sided Gaussian stenosis, a calcified crescent that fills the plaque, the image formed on a
three times finer grid, integrated over each slice's thickness and pixel; see its docstring).  Every case
runs, from the same three seeds (CCA, distal ICA, distal ECA):

* carotid with its defaults;
* VMTK 1.5.2 (colliding fronts and geodesic level set, ``bench_segmentation.run_vmtk``), when its venv is
  there;
* SimpleITK's geodesic active contour and the threshold baseline of ``bench_segmentation``.

Each is scored as in ``bench_segmentation.score``: Dice, surface distances, leak (lumen more than 1 mm
outside the truth), calcium inside the lumen, and the NASCET error against the true lumen graded the same
way.  The minimal-diameter error is taken against that grading of the true lumen too
(``min_diameter_error_mm``), because the lesion here need not be the ICA's narrowest section (a mild
stenosis in the bulb leaves the distal ICA narrower); the error against the ICA's analytic narrowest
diameter is kept as ``min_diameter_error_analytic_mm``.  Where the grading of the true lumen itself misses
the drawn lesion (its narrowest section more than ``AT_LESION_MM`` from the lesion's throat: a mild lesion
beside the ICA's end cut by the image, or one the centerlines put in the common trunk above a high
bifurcation), both errors compare two gradings of something else; ``summary_graded_at_lesion`` leaves
those cases out.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_second_generator.py [--quick] [--cases N] [--jobs J]
        [--variant NAME=VALUE[,NAME=VALUE...]] [--name NAME]

Writes ``results/second_generator.json``.  ``--variant`` runs carotid alone, with those ``SegmentParameters``
overrides, into ``results/second_generator_variant.json`` (``--name`` names another), to set an option against
the defaults' figures of ``second_generator.json`` case for case.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from _common import git_state, write_results
from bench_segmentation import (brief, grade, guarded, meets, parse_variant, run_carotid, run_gac_from_seeds,
                                run_threshold, run_vmtk, score, summarise, threshold_rule)
from carotid.centerline.plaque import CALCIFIED_MM, calcified
from carotid.segment import SegmentParameters
from second_generator import draw, make_second_phantom

METHODS = ("carotid", "vmtk", "gac", "threshold")
# The true lumen's grading found the drawn lesion when its narrowest section lies this close to the lesion's
# throat; elsewhere it graded the end of the ICA cut by the image or a lesion it took for part of the CCA.
AT_LESION_MM = 5.0
BRANCHES = ("CCA", "ICA", "ECA")


def run_case(seed: int, overrides: dict | None = None) -> tuple[dict, list[str]]:
    """One case: every method from the same seeds, scored against the truth; (record, log lines).  With
    ``overrides`` (``SegmentParameters`` fields), carotid alone, so parameterised."""
    lines = []
    t0 = time.perf_counter()
    phantom = make_second_phantom(seed)
    generation = time.perf_counter() - t0
    p = phantom.info["parameters"]
    volume = phantom.image
    seeds = np.array([phantom.info["seeds_mm"][b] for b in BRANCHES], float)
    try:
        truth = grade(phantom.sdf.array, phantom.mask.array > 0, volume)
    except Exception as error:  # noqa: BLE001 - a grading failure of the truth is a result
        truth = {"nascet": None, "error": f"{type(error).__name__}: {error}"}
    lesion = phantom.info["lesion"]
    truth["graded_at_lesion"] = bool(truth.get("location_mm") is not None and np.linalg.norm(
        np.subtract(truth["location_mm"], lesion["throat_mm"])) <= AT_LESION_MM)
    rule = threshold_rule(volume, seeds)
    tag = (f"{seed:2d} ({p['modality']}, area {p['stenosis_area']:.2f}, vein gap "
           f"{phantom.info['vein_gap_measured_mm']:.2f} mm, calcium {'%.0f' % p['calcium_hu'] if p['calcium'] else '-'})")
    lines.append(f"case {tag}: {volume.array.shape} in {generation:.1f} s; true lumen graded NASCET "
                 f"{truth.get('nascet')}, min diameter {truth.get('min_diameter_mm')} mm")
    runners = {"carotid": (run_carotid, volume, seeds, SegmentParameters(**(overrides or {}))),
               "vmtk": (run_vmtk, volume, seeds, rule["lower_threshold"]),
               "gac": (run_gac_from_seeds, volume, seeds),
               "threshold": (run_threshold, volume, seeds, rule["lower_threshold"])}
    if overrides is not None:
        runners = {"carotid": runners["carotid"]}
    methods = {}
    for name, (func, *args) in runners.items():
        record, run = guarded(name, tag, func, *args)
        if run is not None:
            try:
                record = score(run, phantom, truth)
                analytic = record.get("min_diameter_error_mm")
                record["min_diameter_error_analytic_mm"] = analytic
                record["min_diameter_error_mm"] = (
                    None if analytic is None or truth.get("min_diameter_mm") is None or truth["graded_branch"] != "ICA"
                    else record["min_diameter_mm"] - truth["min_diameter_mm"])
            except Exception as error:  # noqa: BLE001
                record = {"status": "failed", "error": f"scoring: {type(error).__name__}: {error}"}
            lines.append(f"case {tag} {name}: {brief(record)}")
        methods[name] = record
    case = {"seed": seed, "parameters": p, "vein_gap_measured_mm": phantom.info["vein_gap_measured_mm"],
            "lesion": lesion,
            "shape_kji": list(volume.array.shape), "generation_seconds": generation, "seeds_mm": seeds,
            "truth_graded": truth, "threshold_rule": rule, "methods": methods}
    return case, lines


def calcified_split(cases: list[dict]) -> dict:
    """carotid's NASCET and minimal-diameter counts (``CRITERIA``) over the cases graded at the lesion, apart
    for the stenoses its grading calls calcified (``plaque.calcified``: calcium it found within
    ``CALCIFIED_MM`` of the throat's wall, the report's note) and the others, with the drawn calcium's
    presence beside each."""
    out = {"calcified_mm": CALCIFIED_MM}
    for name, flagged in (("calcified", True), ("not_calcified", False)):
        rows = [(c["seed"], c["parameters"]["calcium"], c["methods"]["carotid"]) for c in cases
                if c["truth_graded"]["graded_at_lesion"] and c["methods"]["carotid"].get("status") == "ok"
                and calcified(c["methods"]["carotid"]) == flagged]
        out[name] = {"cases": [seed for seed, _, _ in rows],
                     "with_drawn_calcium": sum(bool(drawn) for _, drawn, _ in rows),
                     **{f"meeting_{key}": [seed for seed, _, r in rows if meets(key, r.get(key))]
                        for key in ("nascet_error_points", "min_diameter_error_mm")}}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="four cases")
    parser.add_argument("--cases", type=int, default=48, help="cases 0 .. N-1 (default 48)")
    parser.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    parser.add_argument("--variant", type=parse_variant, help="carotid alone, with these SegmentParameters "
                        "overrides: NAME=VALUE[,NAME=VALUE...]")
    parser.add_argument("--name", help="results file name (default second_generator, or second_generator_variant "
                        "with --variant)")
    args = parser.parse_args()
    seeds = list(range(4 if args.quick else args.cases))
    methods = METHODS if args.variant is None else ("carotid",)
    git = git_state()
    start = time.perf_counter()
    cases = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for case, lines in pool.map(run_case, seeds, [args.variant] * len(seeds)):
            print("\n".join(lines), flush=True)
            cases.append(case)
    summary = summarise(cases, methods)
    at_lesion = summarise([c for c in cases if c["truth_graded"]["graded_at_lesion"]], methods)
    for name, s in (("all cases", summary), ("true lumen graded at the lesion", at_lesion)):
        for method, m in s["methods"].items():
            print(f"{name}, {method}: ok {m['ok']}, meeting {m['meeting']}, median {m['median']}", flush=True)
    calcified_cases = calcified_split(cases)
    for name in ("calcified", "not_calcified"):
        split = calcified_cases[name]
        print(f"carotid, {name.replace('_', ' ')} at the lesion: {len(split['cases'])} cases "
              f"({split['with_drawn_calcium']} with calcium drawn), NASCET within 5 points on "
              f"{len(split['meeting_nascet_error_points'])}, minimal diameter within 0.25 mm on "
              f"{len(split['meeting_min_diameter_error_mm'])}", flush=True)
    name = args.name or ("second_generator" if args.variant is None else "second_generator_variant")
    write_results(name, {
        "benchmark": "segmentation on a second phantom generator", "git": git, "jobs": args.jobs,
        "overrides": args.variant or {},
        "draw": {"seeds": seeds, "parameters_of_seed_0": draw(0)}, "cases": cases, "summary": summary,
        "summary_graded_at_lesion": at_lesion, "at_lesion_mm": AT_LESION_MM, "calcified": calcified_cases,
        "total_seconds": time.perf_counter() - start}, quick=args.quick)


if __name__ == "__main__":
    main()
