"""The blur along the slice axis measured on the image, against the phantom's truth and the slice-spacing model.

``segment``'s refinement blurs its lumen model along the slice axis by the
in-plane blur ``edge_blur`` measures plus the boxcar of the slice thickness
(``deblur.axis_blur``; the scan's record, else the slice spacing).  The
phantom family, like a CT scanner's slice sensitivity profile, blurs along z
more than that: 1.25 times the in-plane Gaussian, plus the slice's boxcar.
``measure_slice_blur`` measures the difference on the image instead
(``intensity.through_plane_variance``: the width of the fat/muscle edges
against their tilt out of the slices).  For each family case this script
builds the intensity model ``segment`` builds from one seed per branch and
compares, as the model's blur along k (mm):

* ``oracle``: the measured in-plane blur plus the phantom's true extra
  variance along z, ``sqrt(blur^2 + sigma_z^2 - sigma^2)`` (what
  ``bench_segmentation.recorded_thickness`` gives the model);
* ``slices``: the default, ``sqrt(blur^2 + (h_k^2 - h_min^2) / 12)``;
* ``measured``: ``sqrt(blur^2 + through_plane_variance)``, or no estimate.

It also compares the in-plane blur ``edge_blur`` reads (``edge_blur_mm``)
with the phantom's: its Gaussian and its partial-volume ramp (one mean voxel
size wide) in quadrature, ``sqrt(sigma^2 + w^2 / 12)``; and the same for two
earlier forms of ``edge_blur``: every profile centred on the isosurface and
read as sampled (``isosurface_edge_blur_mm``, ``own_levels=False``), and
besides that with edges located on the image smoothed by half a voxel, every
tilt and linear interpolation (``previous_edge_blur_mm``).

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_slice_blur.py [--first-seed F] [--cases N] [--repeat R]

Writes ``results/slice_blur.json`` (about 4 minutes for 60 cases on one core).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _common import git_state, write_results
from bench_segmentation import branch_seeds, log, non_negative
from carotid.phantom import make_phantom
from carotid.phantom.family import sample_family
from carotid.segment.intensity import edge_blur, estimate_from_sample, through_plane_variance
from carotid.segment.segmentation import SegmentParameters, seed_start


def intensity_model(phantom):
    """The intensity model ``segment`` estimates from the phantom's CCA, ICA and ECA seeds."""
    volume = phantom.image
    _, _, sample = seed_start(volume, branch_seeds(phantom), SegmentParameters().seed_radius_mm)
    return estimate_from_sample(volume.array, sample, volume.spacing_kji, "seeds")


def run_case(seed: int, repeat: int) -> dict:
    """One family case: the three blurs along k (mm), their relative errors, and the measurement's time."""
    phantom = make_phantom(**sample_family(seed))
    model = intensity_model(phantom)
    spacing = np.asarray(phantom.image.spacing_kji, float)
    blur = phantom.info["blur_sigma_mm"]
    seconds, variance = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        variance = through_plane_variance(phantom.image.array, model.box, model.half_level, spacing)
        seconds.append(time.perf_counter() - start)
    oracle = float(np.sqrt(model.blur ** 2 + blur["z"] ** 2 - blur["in_plane"] ** 2))
    slices = float(np.sqrt(model.blur ** 2 + (spacing[0] ** 2 - spacing.min() ** 2) / 12.0))
    measured = None if variance is None else float(np.sqrt(model.blur ** 2 + variance))
    in_plane = float(np.hypot(blur["in_plane"], spacing.mean() / np.sqrt(12.0)))
    previous = edge_blur(phantom.image.array, model.box, model.bright, model.half_level, spacing, locate_mm=None,
                         max_tilt=1.0, order=1, own_levels=False)
    isosurface = edge_blur(phantom.image.array, model.box, model.bright, model.half_level, spacing,
                           own_levels=False)
    case = {"seed": seed, "modality": phantom.info["modality"], "spacing_kji_mm": spacing.tolist(),
            "true_blur_mm": blur, "edge_blur_mm": model.blur, "isosurface_edge_blur_mm": isosurface,
            "previous_edge_blur_mm": previous, "true_in_plane_mm": in_plane,
            "in_plane_relative_error": {name: None if value is None else value / in_plane - 1.0
                                        for name, value in (("edge_blur", model.blur), ("isosurface", isosurface),
                                                            ("previous", previous))},
            "true_extra_variance_mm2": blur["z"] ** 2 - blur["in_plane"] ** 2, "measured_extra_variance_mm2": variance,
            "z_blur_mm": {"oracle": oracle, "slices": slices, "measured": measured},
            "relative_error": {"slices": slices / oracle - 1.0,
                               "measured": None if measured is None else measured / oracle - 1.0},
            "seconds": {"min": min(seconds), "median": float(np.median(seconds))}}
    errors = {k: "-" if v is None else f"{v:+.1%}" for k, v in case["in_plane_relative_error"].items()}
    log(f"case {seed:2d} ({case['modality']}): in plane {in_plane:.3f} mm, edge_blur {errors['edge_blur']}, "
        f"isosurface {errors['isosurface']}, previous {errors['previous']}; along k oracle {oracle:.3f} mm, "
        f"slices {slices:.3f} ({case['relative_error']['slices']:+.1%}), measured "
        + ("-" if measured is None else f"{measured:.3f} ({case['relative_error']['measured']:+.1%})"))
    return case


def error_summary(cases: list[dict], errors_of) -> dict:
    """Median, median absolute, worst and range of the relative errors ``errors_of(case)`` (None: no
    estimate) over ``cases``, the count within 5 %, and the cases without an estimate."""
    errors = np.array([errors_of(c) for c in cases if errors_of(c) is not None])
    if not errors.size:
        return {"median": None, "median_abs": None, "worst": None, "within_5_percent": 0, "range": None,
                "no_estimate": [c["seed"] for c in cases]}
    return {"median": float(np.median(errors)), "median_abs": float(np.median(np.abs(errors))),
            "worst": float(errors[np.argmax(np.abs(errors))]),
            "within_5_percent": int(np.count_nonzero(np.abs(errors) <= 0.05)),
            "range": [float(errors.min()), float(errors.max())],
            "no_estimate": [c["seed"] for c in cases if errors_of(c) is None]}


def summarise(cases: list[dict]) -> dict:
    """Per modality, the relative error of the blur along k of each estimate; over all cases, that of the
    in-plane blur (``edge_blur`` and the previous estimator); the measurement's time."""
    out = {}
    for modality in sorted({c["modality"] for c in cases}):
        mine = [c for c in cases if c["modality"] == modality]
        out[modality] = {"cases": len(mine)}
        for name in ("slices", "measured"):
            out[modality][name] = error_summary(mine, lambda c, name=name: c["relative_error"][name])
    for name in ("edge_blur", "isosurface", "previous"):
        def error(case, name=name):
            return case["in_plane_relative_error"][name]
        out[f"in_plane_{name}"] = error_summary(cases, error)
        for modality in sorted({c["modality"] for c in cases}):
            out[modality][f"in_plane_{name}"] = error_summary([c for c in cases if c["modality"] == modality], error)
    times = np.array([c["seconds"]["min"] for c in cases])
    out["seconds"] = {"min": float(times.min()), "median": float(np.median(times)), "max": float(times.max())}
    return out


def main() -> None:
    """Run the cases and write ``results/slice_blur.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first-seed", type=non_negative(int), default=0)
    parser.add_argument("--cases", type=non_negative(int), default=60)
    parser.add_argument("--repeat", type=non_negative(int), default=3, help="timed measurements per case")
    options = parser.parse_args()
    git = git_state()
    seeds = range(options.first_seed, options.first_seed + options.cases)
    cases = [run_case(seed, max(options.repeat, 1)) for seed in seeds]
    write_results("slice_blur", {"git": git, "family_seeds": f"range({seeds.start}, {seeds.stop})",
                                 "cases": cases, "summary": summarise(cases)})


if __name__ == "__main__":
    main()
