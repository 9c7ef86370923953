"""Rescans: carotid's grade of the same anatomy under independent noise draws (test-retest).

``bench_segmentation`` scans each family case once, with one draw of the
noise, so a grade within the limits there may be luck and a grade outside them
may be the noise.  Here each case's anatomy is scanned ``--draws`` times:
its own draw (``noise_seed`` None, the image of ``bench_segmentation``) and
independent ones (``make_phantom(noise_seed=n)``: the same anatomy, levels,
texture and bias field, the noise alone redrawn).  carotid segments each with
the defaults and one seed per branch, and each result is graded and scored as
in ``bench_segmentation`` (``run_carotid``, ``score``) against the true lumen,
which the draws share and which is graded once.

Per case the errors of the NASCET grade and of the minimal diameter are split
into their mean over the draws, the bias that a better method can remove, and
their standard deviation, the spread the noise leaves (a test-retest figure
of the kind clinical studies quote for NASCET on CTA), with the fraction of
draws that meet each criterion.  No peer runs here: the peers' figures on the
same anatomy are ``bench_segmentation``'s; this splits carotid's own error.

Usage (from the repository root)::

    .venv/bin/python benchmarks/rescan.py [--first-seed F] [--cases N] [--draws K] [--jobs J]
        [--variant NAME=VALUE[,NAME=VALUE...]] [--modality ct|mr|tof] [--name NAME]

Writes ``results/rescan.json`` (19 minutes for 30 cases of 6 draws with ``--jobs 2``), or with
``--variant`` (carotid with those ``SegmentParameters`` overrides) ``results/rescan_variant.json``;
``--name`` names another.  ``--modality`` scans every case's anatomy in one modality
(``sample_family(seed, modality)``; ``tof``, time-of-flight MRA, is never drawn otherwise).
"""

from __future__ import annotations

import argparse
import json
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from scipy import stats

from _common import git_state, write_results
from bench_segmentation import (CRITERIA, branch_seeds, grade, log, meets, meets_all, non_negative, parse_variant,
                                run_carotid, score)
from carotid.phantom import make_phantom
from carotid.phantom.ct import MODALITIES
from carotid.phantom.family import sample_family
from carotid.segment import SegmentParameters

FIGURES = ("nascet_error_points", "min_diameter_error_mm")
RECORDED = ("dice", "leak_fraction", "calcium_in_lumen", *FIGURES)


def run_case(seed: int, draws: int, overrides: dict, modality: str | None = None) -> dict:
    """carotid (``SegmentParameters(**overrides)``) on ``draws`` scans of family case ``seed`` (in ``modality``,
    None: the drawn one): its own noise, then noise seeds 1, 2, ..."""
    kwargs = sample_family(seed, modality)
    case = {"seed": seed, "modality": kwargs["modality"], "noise": kwargs["noise"], "draws": []}
    truth = None
    for draw in range(draws):
        phantom = make_phantom(**kwargs, noise_seed=draw or None)
        if truth is None:
            truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
            case.update(truth=phantom.info["stenosis"], truth_graded=truth)
        run = run_carotid(phantom.image, branch_seeds(phantom), SegmentParameters(**overrides))
        scored = score(run, phantom, truth)
        case["draws"].append({"noise_seed": draw or None, "cavities_filled": run["cavities_filled"],
                              **{k: scored.get(k) for k in RECORDED}})
        log(f"case {seed:2d} draw {draw}: NASCET {_fmt(scored.get(FIGURES[0]), '+.1f')} points, "
            f"minimal diameter {_fmt(scored.get(FIGURES[1]), '+.2f')} mm, Dice {scored['dice']:.3f}")
    case.update(split(case["draws"]))
    return case


def _fmt(value, spec: str) -> str:
    """``value`` formatted by ``spec``, or "-" for a figure that could not be graded."""
    return "-" if value is None else format(value, spec)


def split(draws: list[dict]) -> dict:
    """Per figure: the mean error over the draws (bias), its standard deviation (spread, ``ddof=1``), and the
    fraction of draws within the figure's limit (a draw without a graded ICA counts as missing it); and the
    fraction meeting all four of ``CRITERIA`` (Dice and leak too)."""
    out = {}
    for key in FIGURES:
        values = np.array([d[key] for d in draws if d[key] is not None], float)
        out[key] = {"bias": float(values.mean()) if values.size else None,
                    "spread": float(values.std(ddof=1)) if values.size > 1 else None,
                    "meeting_fraction": float(np.mean([meets(key, d[key]) for d in draws]))}
    out["all_meeting_fraction"] = float(np.mean([meets_all(d) for d in draws]))
    return out


def expected_without_bias(cases: list[dict], key: str) -> float:
    """The count of cases expected within ``key``'s limit if each case's bias were removed and its spread kept.

    Each case's error is taken as normal with mean zero and the standard deviation of its draws; the count is
    the sum over the cases of the probability of falling within the limit.  With few draws a case's spread is
    a rough estimate (two draws: one degree of freedom), and a heavy-tailed error (a wall that locks onto the
    noise in one draw and not in the other) is not normal, so the figure says how far a method as repeatable
    as this one can get by removing biases alone, not a count to expect exactly.

    Parameters
    ----------
    cases : list of dict
        ``run_case`` results.
    key : str
        One of ``FIGURES``.

    Returns
    -------
    float
        Expected count, between 0 and the number of cases with a spread.
    """
    limit = CRITERIA[key][1]
    spreads = np.array([c[key]["spread"] for c in cases if c[key]["spread"] is not None], float)
    return float(np.sum(2.0 * stats.norm.cdf(limit / np.maximum(spreads, 1e-12)) - 1.0))


def summarise(cases: list[dict]) -> dict:
    """Over the cases: median and worst bias and spread per figure; how many cases meet the limit (``all``: all
    four of ``CRITERIA``) on every draw, on some, on none; the count meeting it on the first draw
    (``bench_segmentation``'s image) and the count expected over rescans (the sum of the cases' meeting
    fractions), and per figure the count expected without the cases' biases (``expected_without_bias``)."""
    out = {}
    for key in (*FIGURES, "all"):
        fractions = np.array([c["all_meeting_fraction"] if key == "all" else c[key]["meeting_fraction"]
                              for c in cases])
        first = [meets_all(c["draws"][0]) if key == "all" else meets(key, c["draws"][0][key]) for c in cases]
        entry = {"every_draw": int(np.sum(fractions == 1.0)),
                 "some_draws": int(np.sum((fractions > 0) & (fractions < 1))),
                 "no_draw": int(np.sum(fractions == 0.0)), "first_draw": int(sum(first)),
                 "expected": float(fractions.sum()), "cases": len(cases)}
        if key != "all":
            bias = np.array([c[key]["bias"] for c in cases if c[key]["bias"] is not None])
            spread = np.array([c[key]["spread"] for c in cases if c[key]["spread"] is not None])
            worst = max((c for c in cases if c[key]["bias"] is not None), key=lambda c: abs(c[key]["bias"]))
            entry.update(limit=CRITERIA[key][1], bias_median=float(np.median(bias)),
                         bias_abs_worst={"seed": worst["seed"], "bias": worst[key]["bias"]},
                         spread_median=float(np.median(spread)), spread_max=float(spread.max()),
                         expected_without_bias=expected_without_bias(cases, key),
                         beyond_limit_by_bias=sorted(c["seed"] for c in cases
                                                     if c[key]["bias"] is not None
                                                     and not meets(key, c[key]["bias"])))
        out[key] = entry
    return out


def rescan_cases(path: str) -> list[dict]:
    """The ``cases`` of a ``rescan.py`` result file (an argparse ``type``).

    Raises
    ------
    argparse.ArgumentTypeError
        When the file cannot be read as such a result, so that argparse prints one line and exits with 2.
    """
    try:
        cases = json.loads(Path(path).read_text())["cases"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise argparse.ArgumentTypeError(f"{path}: not a rescan.py result ({error})") from None
    if not isinstance(cases, list):
        raise argparse.ArgumentTypeError(f"{path}: not a rescan.py result (its cases are not a list)")
    return cases


def log_summary(summary: dict) -> None:
    """One line per figure of ``summarise``'s counts."""
    for key, entry in summary.items():
        unbiased = (f", {entry['expected_without_bias']:.1f} without the biases"
                    if "expected_without_bias" in entry else "")
        log(f"summary {key}: every draw {entry['every_draw']}, some {entry['some_draws']}, none {entry['no_draw']}; "
            f"first draw {entry['first_draw']}, expected {entry['expected']:.1f}{unbiased} of {entry['cases']}")


def main() -> None:
    """Run the cases and write ``results/rescan.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first-seed", type=non_negative(int), default=0)
    parser.add_argument("--cases", type=non_negative(int), default=30)
    parser.add_argument("--draws", type=non_negative(int), default=6, help="scans per case, at least 2 (default 6)")
    parser.add_argument("--jobs", type=non_negative(int), default=1)
    parser.add_argument("--variant", type=parse_variant, default={}, metavar="NAME=VALUE[,NAME=VALUE...]",
                        help="SegmentParameters overrides in place of the defaults")
    parser.add_argument("--modality", choices=MODALITIES, default=None,
                        help="scan every case in this modality (default: the family's draw)")
    parser.add_argument("--name", default=None,
                        help="results file (default rescan, with --variant rescan_variant)")
    parser.add_argument("--summary-of", type=rescan_cases, default=None, metavar="RESCAN.json",
                        help="scan nothing: print the summary of an earlier result's cases")
    options = parser.parse_args()
    if options.summary_of is not None:
        log_summary(summarise(options.summary_of))
        return
    if options.draws < 2:
        parser.error("--draws must be at least 2: the spread needs two scans")
    git = git_state()
    seeds = range(options.first_seed, options.first_seed + options.cases)
    with Pool(max(options.jobs, 1)) as pool:
        cases = pool.starmap(run_case, [(seed, options.draws, options.variant, options.modality) for seed in seeds],
                             chunksize=1)
    summary = summarise(cases)
    log_summary(summary)
    name = options.name or ("rescan_variant" if options.variant else "rescan")
    write_results(name, {
        "git": git, "family_seeds": f"range({seeds.start}, {seeds.stop})", "draws": options.draws,
        "overrides": options.variant, "modality": options.modality, "cases": cases, "summary": summary})


if __name__ == "__main__":
    main()
