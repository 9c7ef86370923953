"""carotid's segmentation at the corners of the phantom family's ranges and beyond them.

``bench_segmentation`` and ``rescan`` draw every parameter of a case uniformly and
independently (``sample_family``), so the corners of the ranges, where two hard
settings meet, are rarely drawn: a vein 0.3-0.5 mm from the artery at 80-90 % of
its enhancement, for example, comes up in about 2 % of the cases.  Here each
variant takes the anatomy and the other draws of a family case and sets one or two
parameters to a corner of the family's range or past it:

* ``vein 0.3 mm at 70/80/90 %``: the jugular vein at the smallest gap of the range,
  with its enhancement at 70, 80 and 90 % of the artery's (the issue's range is
  0.3-2 mm at 40-90 %); each once more with a stop point in the vein, as a VMTK
  user would place a stopper (``segment(stops_xyz=...)``, ``carotid segment --stop``);
* ``blur 1.0 mm``: the scanner blur's standard deviation past the range's 0.8 mm;
* ``noise x 1.6``: past the range's 40 HU in CT;
* ``voxels 0.6 x 0.6 x 1.25 mm``: coarser than the range's 0.5 x 0.5 x 1.0;
* ``CT 250 HU, fade 0.3, noise 40 HU``: the range's lowest contrast-to-noise ratio, its weakest bolus
  fading most under its strongest noise (inside the range: 250-600 HU, fade 0-0.3, noise 10-40 HU);
* ``CT 180 HU, fade 0.45``: a weak, fading bolus, past the range's 250 HU and 0.3;
* ``calcium 2500 HU``: a large plaque of dense calcium, past the range's 1500 HU.

carotid segments each with the defaults and one seed per branch, scored as in
``bench_segmentation`` (``run_carotid``, ``score``).  The CT-only variants skip the
MR cases.

Usage (from the repository root)::

    .venv/bin/python benchmarks/stress_segmentation.py [--seeds 0,1,2,3,4,5,18,26] [--jobs 2]
        [--variant NAME=VALUE[,NAME=VALUE...]] [--name NAME]

Writes ``results/stress_segmentation.json`` (about 21 minutes with ``--jobs 2``); ``--variant`` runs carotid with
those ``SegmentParameters`` overrides, ``--name`` names another file.
"""

from __future__ import annotations

import argparse
from multiprocessing import Pool

import numpy as np
from scipy import ndimage

from _common import git_state, write_results
from bench_segmentation import (CRITERIA, branch_seeds, grade, log, meets, meets_all, non_negative, parse_variant,
                                run_carotid, score)
from carotid.phantom import make_phantom
from carotid.phantom.family import sample_family
from carotid.segment import SegmentParameters


def _set(**values):
    return lambda kw: {**kw, **values}


VARIANTS = {
    "vein 0.3 mm at 70 %": _set(vein_gap_mm=0.3, venous_fraction=0.7),
    "vein 0.3 mm at 80 %": _set(vein_gap_mm=0.3, venous_fraction=0.8),
    "vein 0.3 mm at 90 %": _set(vein_gap_mm=0.3, venous_fraction=0.9),
    "blur 1.0 mm": _set(blur_sigma_mm=1.0),
    "noise x 1.6": lambda kw: {**kw, "noise": 1.6 * kw["noise"]},
    "voxels 0.6 x 0.6 x 1.25 mm": _set(spacing=[0.6, 0.6, 1.25]),
    "CT 250 HU, fade 0.3, noise 40 HU": _set(arterial_hu=250.0, bolus_fade=0.3, noise=40.0),
    "CT 180 HU, fade 0.45": _set(arterial_hu=180.0, bolus_fade=0.45),
    "calcium 2500 HU": _set(calcium_hu=2500.0, plaque_size=1.5),
}
CT_ONLY = ("CT 250 HU, fade 0.3, noise 40 HU", "CT 180 HU, fade 0.45", "calcium 2500 HU")
WITH_STOP = ("vein 0.3 mm at 70 %", "vein 0.3 mm at 80 %", "vein 0.3 mm at 90 %")


def vein_stop(phantom) -> np.ndarray:
    """A stop point (mm, world), shape (1, 3): the point of the vein's axis within the image nearest the arterial
    lumen, where a user would click to keep the front out of the vein."""
    image = phantom.image
    kji = image.world_to_index(phantom.vein.points)
    inside = np.all((kji >= 0) & (kji <= np.asarray(image.array.shape) - 1), axis=1)
    lumen_sdf = ndimage.map_coordinates(np.asarray(phantom.sdf.array, np.float32), kji[inside].T, order=1)
    return phantom.vein.points[inside][[int(np.argmin(lumen_sdf))]]


def run(seed: int, variant: str, stop: bool, overrides: dict) -> dict:
    """carotid (``SegmentParameters(**overrides)``) on family case ``seed`` changed by ``variant`` (with a stop
    point in the vein)."""
    kwargs = VARIANTS[variant](sample_family(seed))
    record = {"seed": seed, "variant": variant, "stop_point": stop, "modality": kwargs["modality"]}
    if variant in CT_ONLY and kwargs["modality"] != "ct":
        return {**record, "status": "not applicable"}
    phantom = make_phantom(**kwargs)
    truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
    stops = vein_stop(phantom) if stop else None
    result = score(run_carotid(phantom.image, branch_seeds(phantom), SegmentParameters(**overrides), stops),
                   phantom, truth)
    record.update({k: v for k, v in result.items() if k in (
        "status", "error", "grading_error", "dice", "leak_fraction", "calcium_in_lumen", "nascet_error_points",
        "min_diameter_error_mm", "surface_mean_mm", "surface_max_mm", "seconds", "cavities_filled")})
    log(f"{variant}{' + stop' if stop else ''} seed {seed}: Dice {record.get('dice', float('nan')):.3f}, leak "
        f"{100 * record.get('leak_fraction', float('nan')):.1f} %")
    return record


def summarise(records: list[dict]) -> dict:
    """Per variant (and stop point): Dice median and worst, leak worst, and the cases meeting each criterion."""
    out = {}
    for variant in VARIANTS:
        for stop in (False, True):
            rows = [r for r in records if r["variant"] == variant and r["stop_point"] == stop
                    and r.get("status") == "ok"]
            if not rows:
                continue
            dice = np.array([r["dice"] for r in rows])
            worst = min(rows, key=lambda r: r["dice"])
            out[variant + (" + stop point" if stop else "")] = {
                "cases": len(rows), "dice_median": float(np.median(dice)),
                "dice_worst": {"value": float(worst["dice"]), "seed": worst["seed"]},
                "leak_worst": float(max(r["leak_fraction"] for r in rows)),
                "meeting": {**{key: int(sum(meets(key, r.get(key)) for r in rows)) for key in CRITERIA},
                            "all_four": int(sum(meets_all(r) for r in rows))}}
    return out


def main() -> None:
    """Run the variants and write ``results/stress_segmentation.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1,2,3,4,5,18,26", help="family seeds, comma-separated")
    parser.add_argument("--jobs", type=non_negative(int), default=1)
    parser.add_argument("--variant", type=parse_variant, default={}, metavar="NAME=VALUE[,NAME=VALUE...]",
                        help="SegmentParameters overrides in place of the defaults")
    parser.add_argument("--name", default="stress_segmentation", help="results file (default stress_segmentation)")
    options = parser.parse_args()
    try:
        seeds = [int(s) for s in options.seeds.split(",")]
    except ValueError:
        parser.error(f"--seeds {options.seeds!r} must be comma-separated integers")
    git = git_state()
    jobs = [(seed, variant, stop, options.variant) for variant in VARIANTS
            for stop in ((False, True) if variant in WITH_STOP else (False,)) for seed in seeds]
    with Pool(max(options.jobs, 1)) as pool:
        records = pool.starmap(run, jobs, chunksize=1)
    summary = summarise(records)
    for name, entry in summary.items():
        log(f"{name}: Dice median {entry['dice_median']:.3f}, worst {entry['dice_worst']['value']:.3f} "
            f"(#{entry['dice_worst']['seed']}), leak worst {100 * entry['leak_worst']:.1f} %, all four "
            f"{entry['meeting']['all_four']} of {entry['cases']}")
    write_results(options.name, {"git": git, "family_seeds": seeds, "variants": list(VARIANTS),
                                 "overrides": options.variant, "records": records, "summary": summary})


if __name__ == "__main__":
    main()
