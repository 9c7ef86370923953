"""Benchmark: the calcium's blur subtraction alone, against the same scan without the calcium.

``calcium.hyperdense_edge`` replaces each calcification and its blur by the background before the
evolution, so that the lumen beside it keeps only its own intensity.  Whether it does is hidden in the
segmentation's figures, which mix it with the front and the refinement.  Here each calcified CT case is
scanned twice with the same noise: as drawn, and with its calcium at the plaque's level (the family's
``calcium_hu`` 1 HU above the tissue, the second generator's at its muscle level), which is the image the
subtraction should produce.  carotid segments the first scan with its defaults and one seed per branch, and
``hyperdense_edge`` then runs on it again with the intensity model that run reported (window top, lumen,
background, blur), once per configuration of ``CONFIGS``:

* ``defaults``;
* ``balls``, ``depth_cap``, ``tissue_level``: the options ``calcium_balls``, ``calcium_depth_cap`` and
  ``calcium_tissue_level`` (all off by default).

Both images are smoothed by 0.4 mm, as the front sees them, and compared within 2 mm of the true calcium and
1.5 mm of the true lumen's wall:

* ``lumen_lost_mm3``: the calcium-free image is at or above the lumen's half level and the corrected one below
  it (the lumen the front will not enter: a calcified throat graded too tight);
* ``calcium_left_mm3``: the reverse (calcium or its blur the front will take for lumen: too mild a grade);
* ``bias``: the mean of corrected minus calcium-free over the band, in units of the contrast.

With them, the calcium's smoothed peak above the lumen level and the window's top, in units of the contrast:
a calcification whose blurred peak stays below the top is never found.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_calcium_subtraction.py [--cases N] [--first-seed F] [--jobs J]

Writes ``results/calcium_subtraction.json`` (about 10 minutes for the family's first 60 seeds and the second
generator's 48 cases with ``--jobs 2``).
"""

from __future__ import annotations

import argparse
from multiprocessing import Pool

import numpy as np
from scipy import ndimage

from _common import git_state, write_results
from bench_segmentation import branch_seeds, log, non_negative
from carotid.phantom import make_phantom
from carotid.phantom.ct import LABELS, TISSUE_HU
from carotid.phantom.family import sample_family
from carotid.segment import SegmentParameters, segment
from carotid.segment.calcium import decision_smoothing, hyperdense_edge
from carotid.segment.preprocess import gaussian_filter
from second_generator import draw, make_second_phantom

CONFIGS = {"defaults": {}, "balls": {"balls": True}, "depth_cap": {"depth_cap": True},
           "tissue_level": {"tissue_offset": True}}
NEAR_CALCIUM_MM = 2.0
NEAR_WALL_MM = 1.5
SMOOTH_MM = 0.4
FIGURES = ("lumen_lost_mm3", "calcium_left_mm3", "bias")


def twins(source: str, seed: int):
    """The phantom of case ``seed`` of ``source`` ("family" or "second") and its image with the calcium at the
    plaque's level, same noise; None where the case is not CT or has no calcium."""
    if source == "family":
        kwargs = sample_family(seed)
        if kwargs["modality"] != "ct" or kwargs.get("calcium_hu") is None:
            return None
        phantom = make_phantom(**kwargs)
        plain = make_phantom(**{**kwargs, "calcium_hu": TISSUE_HU + 1.0}).image.array
        return phantom, branch_seeds(phantom), plain
    p = draw(seed)
    if p["modality"] != "ct" or not p["calcium"]:
        return None
    phantom = make_second_phantom(seed)
    plain = make_second_phantom(seed, calcium_hu=p["muscle"]).image.array
    seeds = np.array([phantom.info["seeds_mm"][b] for b in ("CCA", "ICA", "ECA")], float)
    return phantom, seeds, plain


def compare(corrected: np.ndarray, plain: np.ndarray, band: np.ndarray, half: float, contrast: float,
            spacing) -> dict:
    """``FIGURES`` of a corrected image against the calcium-free one within ``band`` (bool)."""
    sigma = SMOOTH_MM / np.asarray(spacing, float)
    seen, truth = gaussian_filter(corrected, sigma), gaussian_filter(plain, sigma)
    voxel = float(np.prod(spacing))
    lost = band & (truth >= half) & (seen < half)
    left = band & (truth < half) & (seen >= half)
    return {"lumen_lost_mm3": float(np.count_nonzero(lost) * voxel),
            "calcium_left_mm3": float(np.count_nonzero(left) * voxel),
            "bias": float(np.mean((corrected - plain)[band]) / contrast) if band.any() else 0.0}


def run_case(job: tuple[str, int]) -> dict | None:
    """Every configuration's subtraction on case ``job = (source, seed)``, scored; None if not calcified CT."""
    source, seed = job
    made = twins(source, seed)
    if made is None:
        return None
    phantom, seeds, plain = made
    volume = phantom.image
    spacing = np.asarray(volume.spacing_kji, float)
    model = segment(volume, seeds_xyz=seeds, params=SegmentParameters()).report["intensity"]
    lumen, background, blur, top = model["lumen"], model["background"], model["blur_mm"], model["window"][1]
    calcium = phantom.labels.array == LABELS["calcium"]
    band = ((ndimage.distance_transform_edt(~calcium, sampling=spacing) < NEAR_CALCIUM_MM)
            & (phantom.sdf.array < NEAR_WALL_MM))
    contrast = lumen - background
    smooth = gaussian_filter(np.asarray(volume.array, np.float32), decision_smoothing(spacing) / spacing)
    case = {"source": source, "seed": seed, "calcium_mm3": float(np.count_nonzero(calcium) * np.prod(spacing)),
            "calcium_peak_over_lumen": float((smooth[calcium].max() - lumen) / contrast),
            "top_over_lumen": float((top - lumen) / contrast), "configs": {}}
    for name, options in CONFIGS.items():
        corrected, _, info = hyperdense_edge(volume.array, top, lumen, background, spacing, blur, **options)
        case["configs"][name] = {**compare(corrected, plain, band, 0.5 * (lumen + background), contrast, spacing),
                                 "structures": info["structures"]}
    d = case["configs"]["defaults"]
    log(f"{source} {seed:2d}: calcium {case['calcium_mm3']:.1f} mm^3, peak {case['calcium_peak_over_lumen']:+.2f} "
        f"(top {case['top_over_lumen']:+.2f}); defaults lose {d['lumen_lost_mm3']:.1f} mm^3 of lumen, leave "
        f"{d['calcium_left_mm3']:.1f} mm^3 of calcium")
    return case


def summarise(cases: list[dict]) -> dict:
    """Per configuration and source: the median and worst of each figure, and the cases over 1 mm^3."""
    out = {}
    for name in CONFIGS:
        for source in ("family", "second"):
            rows = [c for c in cases if c["source"] == source]
            if not rows:
                continue
            entry = {"cases": len(rows)}
            for key in FIGURES:
                values = np.array([c["configs"][name][key] for c in rows])
                worst = int(np.argmax(np.abs(values)))
                entry[key] = {"median": float(np.median(values)), "worst": float(values[worst]),
                              "worst_case": rows[worst]["seed"]}
                if key != "bias":
                    entry[key]["cases_over_1mm3"] = int(np.count_nonzero(values > 1.0))
            out[f"{name}/{source}"] = entry
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=non_negative(int), default=60, help="family seeds (default 60)")
    parser.add_argument("--first-seed", type=non_negative(int), default=0)
    parser.add_argument("--second", type=non_negative(int), default=48, help="second-generator cases (default 48)")
    parser.add_argument("--jobs", type=non_negative(int), default=1)
    args = parser.parse_args()
    git = git_state()
    jobs = ([("family", s) for s in range(args.first_seed, args.first_seed + args.cases)]
            + [("second", s) for s in range(args.second)])
    with Pool(max(args.jobs, 1)) as pool:
        cases = [c for c in pool.imap(run_case, jobs) if c is not None]
    summary = summarise(cases)
    for key, entry in summary.items():
        log(f"{key}: " + ", ".join(f"{f} median {entry[f]['median']:.2f} worst {entry[f]['worst']:.2f} "
                                   f"(#{entry[f]['worst_case']})" for f in FIGURES))
    write_results("calcium_subtraction", {"git": git, "configs": CONFIGS, "near_calcium_mm": NEAR_CALCIUM_MM,
                                          "near_wall_mm": NEAR_WALL_MM, "smooth_mm": SMOOTH_MM, "cases": cases,
                                          "summary": summary})


if __name__ == "__main__":
    main()
