"""Benchmark: the segmentation from one seed alone, in the CCA, the ICA or the ECA.

``bench_segmentation`` seeds every branch (the issue's protocol) and the CCA alone (``carotid_one_seed``).  A
user who clicks once may click anywhere, and a distal seed sees the bolus from its faded end: the window is
estimated from the lumen at the seed, so the proximal lumen, up to 1 / 0.7 as bright above the tissue in the
family (``bolus_fade`` up to 0.3), lies above the window's top.  Each family case
(``make_phantom(**sample_family(seed))``) runs from each seed alone, with each configuration of ``CONFIGS``:

* ``defaults``;
* ``top_over_fade``: the window's top margin (``window_margins[1]``, a fraction of the contrast above the
  lumen level) raised from 0.25 to 0.5, over a proximal lumen 1 / 0.7 as bright as the seed's (0.43 above
  it) with the noise's margin.  Not a default: the lead this benchmark measures.

Each run is scored as in ``bench_segmentation.score`` against the true lumen, graded the same way.  Per
configuration and seed branch: Dice median and worst, leak worst, and the counts meeting each of ``CRITERIA``.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_one_seed.py [--cases N] [--first-seed F] [--jobs J]

Writes ``results/one_seed.json`` (about 25 minutes for 30 cases with ``--jobs 2``).
"""

from __future__ import annotations

import argparse
from multiprocessing import Pool

import numpy as np

from _common import git_state, write_results
from bench_segmentation import CRITERIA, grade, guarded, log, meets, non_negative, run_carotid, score
from carotid.phantom import make_phantom
from carotid.phantom.family import sample_family
from carotid.segment import SegmentParameters

BRANCHES = ("CCA", "ICA", "ECA")
CONFIGS = {"defaults": {}, "top_over_fade": {"window_margins": [0.1, 0.5]}}
RECORDED = ("status", "error", "dice", "leak_fraction", "nascet_error_points", "min_diameter_error_mm", "seconds")


def run_case(seed: int) -> dict:
    """Family case ``seed`` from each branch's seed alone, with each configuration: scored records."""
    kwargs = sample_family(seed)
    phantom = make_phantom(**kwargs)
    truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
    case = {"seed": seed, "modality": kwargs["modality"], "bolus_fade": kwargs.get("bolus_fade"), "runs": {}}
    for name, overrides in CONFIGS.items():
        for branch in BRANCHES:
            tag = f"case {seed:2d} {name} {branch}"
            record, run = guarded("carotid", tag, run_carotid, phantom.image,
                                  [phantom.info["seeds_mm"][branch]], SegmentParameters(**overrides))
            if run is not None:
                record = score(run, phantom, truth)
            case["runs"][f"{name}/{branch}"] = {k: record.get(k) for k in RECORDED}
            log(f"{tag}: Dice {record.get('dice', float('nan')):.3f}")
    return case


def summarise(cases: list[dict]) -> dict:
    """Per configuration and seed branch: Dice median and worst (with the case), leak worst, failures, and
    the cases meeting each of ``CRITERIA``."""
    out = {}
    for key in cases[0]["runs"]:
        rows = [(c["seed"], c["runs"][key]) for c in cases]
        ok = [(seed, r) for seed, r in rows if r.get("dice") is not None]
        dice = np.array([r["dice"] for _, r in ok])
        worst = min(ok, key=lambda row: row[1]["dice"]) if ok else (None, {})
        out[key] = {"cases": len(rows), "failed": [seed for seed, r in rows if r.get("dice") is None],
                    "dice_median": float(np.median(dice)) if ok else None,
                    "dice_worst": {"seed": worst[0], "value": worst[1].get("dice")},
                    "leak_worst": float(max(r["leak_fraction"] for _, r in ok)) if ok else None,
                    "meeting": {k: int(sum(meets(k, r.get(k)) for _, r in rows)) for k in CRITERIA}}
    return out


def main() -> None:
    """Run the cases and write ``results/one_seed.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first-seed", type=non_negative(int), default=0)
    parser.add_argument("--cases", type=non_negative(int), default=30)
    parser.add_argument("--jobs", type=non_negative(int), default=2)
    options = parser.parse_args()
    git = git_state()
    seeds = range(options.first_seed, options.first_seed + options.cases)
    with Pool(max(options.jobs, 1)) as pool:
        cases = pool.map(run_case, seeds, chunksize=1)
    summary = summarise(cases)
    for key, entry in summary.items():
        log(f"summary {key}: Dice median {entry['dice_median']:.3f}, worst {entry['dice_worst']['value']:.3f} "
            f"(#{entry['dice_worst']['seed']}); meeting {entry['meeting']}")
    write_results("one_seed", {"git": git, "family_seeds": f"range({seeds.start}, {seeds.stop})",
                               "configs": CONFIGS, "cases": cases, "summary": summary})


if __name__ == "__main__":
    main()
