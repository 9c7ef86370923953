"""Seedless start: the forking structure against the brightest one, and the seeds placed in it.

``carotid run`` and ``carotid batch`` start the segmentation without seeds unless a config gives them.  The
start is the core of one bright structure, and picking it by brightness alone (``fork_fit`` above 1, the
rule before) takes bone or a jugular vein on some scans; the default prefers the structures that fork
(``init.fork_score``) and, when the pick forks, places a seed in its trunk and near the end of each branch
(``init.fork_seeds``), from which the seeded segmentation runs.  For every case of the phantom family
(``sample_family``) and of the second generator (``second_generator.py``), on the image ``segment`` starts
from (provisional window, capture stage's speed), both rules pick a region and the script records what it
lies in: the true lumen (the fraction of its voxels in the truth mask), else the truth label most of it
holds.  With ``--segment N`` and ``--segment-second N`` the first N cases of each generator are also
segmented without seeds by the defaults: Dice, leak (the result's voxels more than 1 mm outside the true
wall, as ``bench_segmentation``), how many derived seeds lie in the true lumen, seconds.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_autoinit.py [--family N] [--second N] [--segment N] [--segment-second N]

Writes ``results/autoinit.json`` (about 20 minutes for 60 + 48 picks and 30 + 48 segmentations on one core).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _common import git_state, write_results
from bench_segmentation import LEAK_MM
from carotid.phantom import LABELS, make_phantom, sample_family
from carotid.segment import SegmentParameters, segment
from carotid.segment.init import automatic_region
from carotid.segment.metrics import dice
from carotid.segment.segmentation import automatic_inputs
from second_generator import make_second_phantom

RULES = {"brightest": 1.01, "forking": 0.75}  # fork_fit: above 1 no candidate counts as a fork
NAMES = {value: name for name, value in LABELS.items()}


def pick(phantom) -> dict:
    """What each rule's start lies in, and how long the default one took (s)."""
    image, spacing = phantom.image.array, np.asarray(phantom.image.spacing_kji, float)
    image01, ghat, excluded = automatic_inputs(image, image, spacing, SegmentParameters().validate())
    out = {}
    for rule, fit in RULES.items():
        start = time.perf_counter()
        region = automatic_region(image01, ghat, spacing, excluded=excluded, fork_fit=fit)
        inside = float(np.mean(phantom.mask.array[region] > 0))
        values, counts = np.unique(phantom.labels.array[region & ~(phantom.mask.array > 0)], return_counts=True)
        out[rule] = {"in_lumen_fraction": inside, "lumen": inside > 0.5,
                     "else_mostly": None if inside > 0.5 or not len(values) else
                     NAMES.get(int(values[np.argmax(counts)]), int(values[np.argmax(counts)])),
                     "seconds": time.perf_counter() - start}
    return out


def segmented(phantom) -> dict:
    """The default seedless segmentation scored against the truth, and where its derived seeds lie."""
    start = time.perf_counter()
    result = segment(phantom.image, params=SegmentParameters())
    seconds = time.perf_counter() - start
    seg, truth = result.mask.array > 0, phantom.mask.array > 0
    leak = np.count_nonzero(seg & (phantom.sdf.array > LEAK_MM)) / max(np.count_nonzero(seg), 1)
    seeds = result.report["seeds_mm"]
    in_lumen = None
    if seeds is not None:
        kji = np.clip(np.round(phantom.image.world_to_index(np.asarray(seeds))).astype(int), 0,
                      np.asarray(truth.shape) - 1)
        in_lumen = int(np.count_nonzero(truth[tuple(kji.T)]))
    return {"dice": dice(seg, truth), "leak_fraction": leak, "derived_seeds": None if seeds is None else len(seeds),
            "derived_seeds_in_lumen": in_lumen, "seconds": seconds}


def summarise(cases: list) -> dict:
    """Starts in the lumen per rule, and the cases each rule gets wrong."""
    return {rule: {"in_lumen": sum(c[rule]["lumen"] for c in cases), "cases": len(cases),
                   "wrong": {str(c["seed"]): c[rule]["else_mostly"] for c in cases if not c[rule]["lumen"]}}
            for rule in RULES}


def summarise_segmentation(scored: list) -> dict:
    """Median and worst Dice and leak of the seedless segmentations, the cases below Dice 0.92, the seeds."""
    dices = np.array([c["dice"] for c in scored])
    leaks = np.array([c["leak_fraction"] for c in scored])
    seeded = [c for c in scored if c["derived_seeds"]]
    return {"cases": len(scored), "dice_median": float(np.median(dices)), "dice_worst": float(dices.min()),
            "dice_worst_seed": int(scored[int(np.argmin(dices))]["seed"]),
            "below_dice_0.92": {str(c["seed"]): round(c["dice"], 3) for c in scored if c["dice"] < 0.92},
            "leak_median": float(np.median(leaks)), "leak_worst": float(leaks.max()),
            "leak_worst_seed": int(scored[int(np.argmax(leaks))]["seed"]),
            "with_derived_seeds": len(seeded),
            "derived_seeds_outside_lumen": sum(c["derived_seeds"] - c["derived_seeds_in_lumen"] for c in seeded),
            "seconds_median": float(np.median([c["seconds"] for c in scored])),
            "seconds_worst": float(max(c["seconds"] for c in scored))}


def main() -> None:
    """Run both generators and write ``results/autoinit.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", type=int, default=60, help="family cases, seeds 0..N-1")
    parser.add_argument("--second", type=int, default=48, help="second-generator cases, seeds 0..N-1")
    parser.add_argument("--segment", type=int, default=30, help="family cases also segmented without seeds")
    parser.add_argument("--segment-second", type=int, default=48,
                        help="second-generator cases also segmented without seeds")
    options = parser.parse_args()
    git = git_state()
    family, second, scored, scored_second = [], [], [], []
    for seed in range(options.family):
        kwargs = sample_family(seed)
        phantom = make_phantom(**kwargs)
        family.append({"seed": seed, "modality": kwargs.get("modality", "ct"), **pick(phantom)})
        if seed < options.segment:
            scored.append({"seed": seed, **segmented(phantom)})
        print("family", seed, {rule: family[-1][rule]["lumen"] for rule in RULES}, flush=True)
    for seed in range(options.second):
        phantom = make_second_phantom(seed)
        second.append({"seed": seed, "modality": phantom.info["parameters"]["modality"], **pick(phantom)})
        if seed < options.segment_second:
            scored_second.append({"seed": seed, **segmented(phantom)})
        print("second", seed, {rule: second[-1][rule]["lumen"] for rule in RULES}, flush=True)
    summary = {"family": summarise(family), "second_generator": summarise(second)}
    if scored:
        summary["seedless_segmentation"] = summarise_segmentation(scored)
    if scored_second:
        summary["seedless_segmentation_second_generator"] = summarise_segmentation(scored_second)
    print(summary, flush=True)
    write_results("autoinit", {"git": git, "rules_fork_fit": RULES, "family": family, "second_generator": second,
                               "seedless_segmentation": scored, "seedless_segmentation_second_generator": scored_second,
                               "summary": summary})


if __name__ == "__main__":
    main()
