"""Screening variants of the partial-volume refinement on captured inputs: one evolution per scan, many variants.

The refinement (``segment.deblur.refine``, called by ``segmentation.deblur``) runs after the evolution, and
the ``SegmentParameters`` fields it alone reads (``deblur_*``) change nothing before it.
So ``segment`` need not run again for each variant of them: this script runs ``segment`` once per scan with
the defaults, keeps the arguments its refinement was called with (``refine_budget.captured_segment``) in a
cache, and reruns only the refinement and the lumen clean-up for each variant (``refine_budget.rerun``).  Each
result is scored as in ``bench_segmentation`` (``score``): NASCET against the true lumen graded the same way,
the minimal diameter against the phantom's analytic one.

Scans are family case SEED under noise draw DRAW, as ``rescan.py`` makes them (draw 0 is the family's own
image, the one ``bench_segmentation`` scores): ``--scans 0-29:0 13:1`` (a seed or a range of seeds, and the
draw, 0 when left out), and with ``--misses RESULT.json`` every scan of a ``rescan.py`` result that misses
the NASCET or the minimal-diameter limit there.  The cache (``--cache``) holds per scan the captured
arguments, the phantom and the true grade, in a folder named by the hash of carotid's sources
(``_common.git_state``): code that changes anything recaptures.

A screen tells which variant deserves the rescans (``rescan.py``); it is neither the acceptance figure
(``bench_segmentation``) nor the test-retest one, and a screen built from the scans that miss is not a
sample of the family.

Usage (from the repository root)::

    .venv/bin/python benchmarks/refine_screen.py [--scans SEEDS[:DRAW] ...] [--misses RESCAN.json ...]
        --variant NAME=VALUE[,NAME=VALUE...] [--variant ...] [--jobs J] [--cache DIR] [--name NAME]

Writes ``results/refine_screen.json`` (or ``--name``).  Capturing takes 10-25 s a scan on 2 cores and each
variant 3-8 s a scan; the cache takes about 20 MB a scan.
"""

from __future__ import annotations

import argparse
import os
import pickle
from dataclasses import fields
from multiprocessing import Pool
from pathlib import Path

import numpy as np

from _common import git_state, write_results
from bench_segmentation import CRITERIA, branch_seeds, grade, log, meets, meets_all, non_negative, parse_variant, score
from carotid.phantom import make_phantom
from carotid.phantom.family import sample_family
from carotid.segment import SegmentParameters
from refine_budget import captured_segment, rerun
from rescan import _fmt, rescan_cases

FIGURES = ("dice", "leak_fraction", "nascet_error_points", "min_diameter_error_mm")
REFINEMENT_FIELDS = frozenset(f.name for f in fields(SegmentParameters) if f.name.startswith("deblur_"))
DEFAULT_CACHE = "/tmp/carotid-refine-cache"


def parse_scans(text: str) -> list[tuple[int, int]]:
    """``"SEED[:DRAW]"`` or ``"FIRST-LAST[:DRAW]"`` -> ``[(seed, draw), ...]`` (the ``type`` of ``--scans``).

    Raises
    ------
    argparse.ArgumentTypeError
        On anything else, so that argparse prints one line and exits with status 2.
    """
    seeds, _, draw = text.partition(":")
    first, _, last = seeds.partition("-")
    try:
        first, last, draw = int(first), int(last or first), int(draw or 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not SEED[:DRAW] or FIRST-LAST[:DRAW]") from None
    if min(first, last, draw) < 0 or last < first:
        raise argparse.ArgumentTypeError(f"{text!r}: seeds and draw must be >= 0, the range increasing")
    return [(seed, draw) for seed in range(first, last + 1)]


def refinement_variant(text: str) -> dict:
    """``parse_variant``, refusing fields the refinement does not read (their variants would need ``segment``
    itself, ``rescan.py --variant``)."""
    overrides = parse_variant(text)
    others = sorted(set(overrides) - REFINEMENT_FIELDS)
    if others:
        raise argparse.ArgumentTypeError(f"{', '.join(others)}: not read by the refinement alone; the fields "
                                         f"this screen can vary are {', '.join(sorted(REFINEMENT_FIELDS))}")
    return overrides


def missed_scans(path: Path) -> list[tuple[int, int]]:
    """The (seed, draw) of every scan of a ``rescan.py`` result missing the NASCET or minimal-diameter limit.

    Raises
    ------
    argparse.ArgumentTypeError
        When the file cannot be read as such a result.
    """
    cases = rescan_cases(path)
    try:
        return [(case["seed"], draw) for case in cases for draw, record in enumerate(case["draws"])
                if not (meets("nascet_error_points", record["nascet_error_points"])
                        and meets("min_diameter_error_mm", record["min_diameter_error_mm"]))]
    except (KeyError, TypeError) as error:
        raise argparse.ArgumentTypeError(f"{path}: not a rescan.py result ({error})") from None


def captured(seed: int, draw: int, cache: Path) -> dict:
    """The scan's captured refinement arguments, phantom, true grade and default figures, from ``cache`` or
    made (and written there atomically)."""
    path = cache / f"{seed}_{draw}.pkl"
    if path.exists():
        with path.open("rb") as handle:
            return pickle.load(handle)
    phantom = make_phantom(**sample_family(seed), noise_seed=draw or None)
    seeds_xyz = branch_seeds(phantom)
    truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
    result, args = captured_segment(phantom, seeds_xyz)
    defaults = score({"levelset": np.asarray(result.levelset.array, np.float32), "mask": result.mask.array > 0},
                     phantom, truth)
    entry = {"args": args, "phantom": phantom, "truth": truth, "seeds_kji": phantom.image.world_to_index(seeds_xyz),
             "defaults": {key: defaults.get(key) for key in FIGURES}}
    partial = path.with_suffix(f".{os.getpid()}.tmp")
    with partial.open("wb") as handle:
        pickle.dump(entry, handle, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(partial, path)
    return entry


def run_scan(seed: int, draw: int, variants: dict, cache: Path) -> dict:
    """The defaults' and every variant's figures on one scan."""
    entry = captured(seed, draw, cache)
    scan = {"seed": seed, "draw": draw, "true_nascet": entry["truth"].get("nascet"),
            "true_min_diameter_mm": entry["truth"].get("min_diameter_mm"), "results": {"defaults": entry["defaults"]}}
    for name, overrides in variants.items():
        scored = score(rerun(entry["args"], entry["seeds_kji"], **overrides), entry["phantom"], entry["truth"])
        scan["results"][name] = {key: scored.get(key) for key in FIGURES}
    log(f"scan {seed}:{draw} minimal diameter error (mm): " + ", ".join(
        f"{name} {_fmt(r['min_diameter_error_mm'], '+.3f')}" for name, r in scan["results"].items()))
    return scan


def summarise(scans: list[dict]) -> dict:
    """Per variant: the scans meeting each limit and all four, the minimal diameter's median and worst error,
    the worst Dice, and the scans that cross the NASCET or minimal-diameter limit against the defaults."""
    out = {}
    for name in scans[0]["results"]:
        rows = [(f"{s['seed']}:{s['draw']}", s["results"][name], s["results"]["defaults"]) for s in scans]
        errors = [(label, r["min_diameter_error_mm"]) for label, r, _ in rows if r["min_diameter_error_mm"] is not None]
        worst = max(errors, key=lambda e: abs(e[1])) if errors else (None, None)
        entry = {key: sum(meets(key, r[key]) for _, r, _ in rows) for key in CRITERIA}
        entry.update(all=sum(meets_all(r) for _, r, _ in rows), scans=len(rows),
                     min_diameter_error_median_mm=float(np.median([e for _, e in errors])) if errors else None,
                     min_diameter_error_worst={"scan": worst[0], "mm": worst[1]},
                     dice_worst=min(r["dice"] for _, r, _ in rows))
        for key in ("nascet_error_points", "min_diameter_error_mm"):
            entry[f"{key}_gained"] = [label for label, r, d in rows if meets(key, r[key]) and not meets(key, d[key])]
            entry[f"{key}_lost"] = [label for label, r, d in rows if meets(key, d[key]) and not meets(key, r[key])]
        out[name] = entry
    return out


def main() -> None:
    """Capture what is not cached, rerun the refinement for each variant, write ``results/refine_screen.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=parse_scans, nargs="+", default=[], metavar="SEEDS[:DRAW]")
    parser.add_argument("--misses", type=missed_scans, action="append", default=[], metavar="RESCAN.json",
                        help="add the scans of a rescan.py result that miss the NASCET or minimal-diameter limit")
    parser.add_argument("--variant", type=refinement_variant, action="append", required=True,
                        metavar="NAME=VALUE[,NAME=VALUE...]", help="refinement overrides (repeatable)")
    parser.add_argument("--jobs", type=non_negative(int), default=1)
    parser.add_argument("--cache", type=Path, default=Path(DEFAULT_CACHE))
    parser.add_argument("--name", default="refine_screen")
    options = parser.parse_args()
    scans = list(dict.fromkeys([s for group in options.scans for s in group]
                               + [s for group in options.misses for s in group]))
    if not scans:
        parser.error("no scans: give --scans or --misses")
    variants = {",".join(f"{k}={v}" for k, v in overrides.items()): overrides for overrides in options.variant}
    git = git_state()
    cache = options.cache / git["carotid_sources_sha1"][:12]
    cache.mkdir(parents=True, exist_ok=True)
    log(f"{len(scans)} scans, {len(variants)} variants; cache {cache}")
    with Pool(max(options.jobs, 1)) as pool:
        results = pool.starmap(run_scan, [(seed, draw, variants, cache) for seed, draw in scans], chunksize=1)
    summary = summarise(results)
    for name, entry in summary.items():
        worst = entry["min_diameter_error_worst"]
        log(f"{name}: NASCET {entry['nascet_error_points']}, minimal diameter {entry['min_diameter_error_mm']}, "
            f"all four {entry['all']} of {entry['scans']}; median error "
            f"{_fmt(entry['min_diameter_error_median_mm'], '+.3f')} mm, "
            f"worst {worst['scan']} {_fmt(worst['mm'], '+.3f')}")
    write_results(options.name, {"git": git, "scans": [f"{s}:{d}" for s, d in scans], "variants": variants,
                                 "results": results, "summary": summary})


if __name__ == "__main__":
    main()
