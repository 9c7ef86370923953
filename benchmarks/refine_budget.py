"""Where the graded throat's error comes from: the refinement rerun with its estimates replaced by the truth.

``bench_segmentation`` grades carotid's stenoses on the phantom family; the
cases that miss the NASCET limit are tight throats graded too wide, and the
mild, calcified ones that come closest to the minimal-diameter limit are
graded too narrow.  The partial-volume refinement (``segment.deblur.refine``)
decides where the throat's wall ends up, and it rests on five things that
can each be wrong: the lumen level ``A`` it follows along the vessel
(``lumen_level``), the tissue level ``B`` around the wall
(``normal_background``), the blur within the slices (``intensity.edge_blur``),
the blur along the slice axis (``axis_blur``, from the slice thickness
measured on the image, ``intensity.through_plane_variance``), and its
regularisation (the wall's speed smoothed by ``deblur_smooth_mm`` and
stopped after ``deblur_iterations`` steps).  This script runs ``segment``
once per family case, keeps the front the evolution converged to, and
reruns only the refinement with one estimate at a time replaced by the
phantom's truth:

* ``defaults``: ``segment``'s own result;
* ``true_z_blur``: the through-plane blur given as the slice thickness that
  reproduces it (``bench_segmentation.recorded_thickness``);
* ``true_blur``: that, and the phantom's in-plane blur (its Gaussian and its
  one-voxel partial-volume ramp in quadrature, what ``edge_blur`` measures) in
  place of the measured one;
* ``true_levels``: ``A`` and ``B`` from the phantom, the lumen's level with
  its bolus fade (and the MR bias field), the tissue, fat and vein levels of
  the label map outside it;
* ``true_model``: the true levels and both true blurs;
* ``true_model_converged``: both, the speed unsmoothed and the descent run
  to convergence (100 steps of three times the step length);
* ``from_truth``: the defaults started from the true wall instead of the
  evolution's front (what the start alone decides);
* ``mean_level``: the lumen level followed by a local mean instead of the
  default local linear fit (``deblur_linear_level``); the mean lags a
  fading bolus and reads the throat's lumen too bright;
* ``uniform_smoothing``: the wall's speed smoothed by ``deblur_smooth_mm``
  everywhere instead of at most half the lumen's radius
  (``deblur_smooth_radius``);

and the same on the case with its noise scaled by 0.02
(``noise_free_defaults``, ``noise_free_true_model``,
``noise_free_true_model_converged``, and
``noise_free_true_model_from_truth``: converged from the true wall), with
two more that separate the model's estimates from its regularisation:
``noise_free_converged`` (carotid's own estimates, converged) and
``noise_free_true_z_blur_converged`` (only the through-plane blur from the
truth, converged).  Each
result goes through the same lumen clean-up as ``segment``
(``segmentation.lumen_levelset``) and is scored by
``bench_segmentation.score``: NASCET error against the true lumen graded the
same way, minimal-diameter error against the analytic one.

The oracles are injected by replacing ``deblur``'s estimators for the
duration of one call; the levels are the phantom's nominal ones (its tissue
texture and the fat's partial occupancy are not modelled).

Usage (from the repository root)::

    .venv/bin/python benchmarks/refine_budget.py [--first-seed F] [--cases N] [--jobs J]

Writes ``results/refine_budget.json`` (about 45 minutes for 30 cases on one core).
"""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import replace
from multiprocessing import Pool

import numpy as np

import carotid.segment.deblur as deblur_module
import carotid.segment.segmentation as segmentation
from _common import git_state, write_results
from bench_segmentation import branch_seeds, grade, log, meets, non_negative, recorded_thickness, score
from carotid.phantom import make_phantom
from carotid.phantom.ct import bolus_level
from carotid.phantom.family import sample_family
from carotid.phantom.geometry import bias_field
from carotid.segment import SegmentParameters, segment

LABEL_LEVEL = {5: "fat", 2: "venous", 3: "cortical_bone"}
CONVERGED = {"deblur_smooth_mm": 0.0, "deblur_iterations": 100, "deblur_gain": 6.0}
NOISE_FREE = 0.02
TIGHT_MM = 3.0


def true_levels(phantom, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The phantom's lumen level ``A`` and tissue level ``B`` (float32 arrays of the image's shape).

    ``A`` falls from the proximal arterial level along z by the bolus fade (``phantom.ct.bolus_level``);
    ``B`` is the level of each voxel's label (tissue, fat, vein, bone; the lumen and calcium, which the
    refinement's image no longer holds, take the tissue's).  In MR mode both carry the bias field.
    """
    info, image = phantom.info, phantom.image
    levels, shape = info["levels"], image.array.shape
    z = image.origin[2] + np.arange(shape[0]) * image.spacing_kji[0]
    tissue = levels["tissue"]
    lumen = bolus_level(z, tissue, levels["arterial_proximal"], levels["bolus_fade"],
                        float(info["parameters"]["extent"][2]))
    lumen = np.broadcast_to(lumen[:, None, None], shape)
    labels = np.asarray(phantom.labels.array)
    background = np.full(shape, tissue, np.float32)
    for label, name in LABEL_LEVEL.items():
        if levels.get(name) is not None:
            background[labels == label] = levels[name]
    if info.get("bias_field"):
        bias = bias_field(shape, np.random.default_rng([seed, 5]), info["bias_field"]["amplitude"])
        return lumen * bias, background * bias
    return np.array(lumen), background


@contextlib.contextmanager
def oracle_levels(lumen: np.ndarray, background: np.ndarray):
    """``deblur.refine`` with ``lumen_level`` and ``normal_background`` returning the given fields (cropped to
    the box ``refine`` works in)."""
    saved = deblur_module.region_box, deblur_module.lumen_level, deblur_module.normal_background
    box = {}

    def region_box(*args, **kwargs):
        box["crop"] = saved[0](*args, **kwargs)
        return box["crop"]

    deblur_module.region_box = region_box
    deblur_module.lumen_level = lambda *args, **kwargs: np.ascontiguousarray(lumen[box["crop"]])
    deblur_module.normal_background = lambda *args, **kwargs: np.array(background[box["crop"]])
    try:
        yield
    finally:
        deblur_module.region_box, deblur_module.lumen_level, deblur_module.normal_background = saved


def captured_segment(phantom, seeds_xyz) -> tuple[object, tuple]:
    """``segment`` with the defaults, and the arguments its refinement (``segmentation.deblur``) was called with."""
    original, captured = segmentation.deblur, {}

    def capture(*args):
        captured["args"] = args
        return original(*args)

    segmentation.deblur = capture
    try:
        result = segment(phantom.image, seeds_xyz=seeds_xyz, params=SegmentParameters())
    finally:
        segmentation.deblur = original
    return result, captured["args"]


def rerun(args: tuple, seeds_kji, thickness=None, levels=None, start=None, blur=None, **overrides) -> dict:
    """The refinement rerun on captured arguments (``thickness``, the ``levels`` pair, the ``start`` level set
    and the in-plane ``blur`` replaced when given), then ``segment``'s lumen clean-up: a scorable run.

    Without ``thickness`` the rerun keeps the slice thickness ``segment`` gave its refinement (measured on the
    image by default, ``measure_slice_blur``), so that a variant differs from the defaults only in what it
    replaces."""
    image, phi, spacing, model, params, stopped, dense, captured_thickness = args
    thickness = captured_thickness if thickness is None else thickness
    params = replace(params, **overrides)
    model = model if blur is None else replace(model, blur=blur)
    phi = phi if start is None else start
    with oracle_levels(*levels) if levels is not None else contextlib.nullcontext():
        refined, _ = segmentation.deblur(image, phi, spacing, model, params, stopped, dense, thickness)
    levelset, mask, _, _ = segmentation.lumen_levelset(refined, stopped, seeds_kji, spacing, params)
    return {"levelset": levelset, "mask": mask > 0}


def run_case(seed: int) -> dict:
    """Every variant on one family case (and on the same case nearly without noise, whose true lumen is the
    same)."""
    case = {"seed": seed, "variants": {}}
    truth = None
    for noise_scale, prefix in ((1.0, ""), (NOISE_FREE, "noise_free_")):
        kwargs = sample_family(seed)
        kwargs["noise"] = kwargs["noise"] * noise_scale
        phantom = make_phantom(**kwargs)
        seeds_xyz = branch_seeds(phantom)
        seeds_kji = phantom.image.world_to_index(seeds_xyz)
        if truth is None:
            truth = grade(phantom.sdf.array, phantom.mask.array > 0, phantom.image)
        result, args = captured_segment(phantom, seeds_xyz)
        thickness = recorded_thickness(phantom)
        levels = true_levels(phantom, seed)
        # The in-plane blur as the image holds it (edge_blur's measurand): the phantom's Gaussian and its
        # partial-volume ramp one mean voxel wide, in quadrature.
        blur = float(np.hypot(phantom.info["blur_sigma_mm"]["in_plane"],
                              np.mean(phantom.image.spacing_kji) / np.sqrt(12.0)))
        if not prefix:
            case.update(modality=phantom.info["modality"], truth=phantom.info["stenosis"], truth_graded=truth,
                        recorded_thickness_mm=thickness,
                        blur_mm={"measured": args[3].blur, "in_plane": phantom.info["blur_sigma_mm"]["in_plane"],
                                 "in_plane_with_ramp": blur, "z": phantom.info["blur_sigma_mm"]["z"]})
        sdf = np.asarray(phantom.sdf.array, np.float32)
        runs = {"defaults": lambda: {"levelset": result.levelset.array, "mask": result.mask.array > 0}}
        if not prefix:
            runs["true_z_blur"] = lambda: rerun(args, seeds_kji, thickness)
            runs["true_blur"] = lambda: rerun(args, seeds_kji, thickness, blur=blur)
            runs["true_levels"] = lambda: rerun(args, seeds_kji, levels=levels)
            runs["from_truth"] = lambda: rerun(args, seeds_kji, start=sdf)
            runs["mean_level"] = lambda: rerun(args, seeds_kji, deblur_linear_level=False)
            runs["uniform_smoothing"] = lambda: rerun(args, seeds_kji, deblur_smooth_radius=0.0)
        else:
            runs["converged"] = lambda: rerun(args, seeds_kji, **CONVERGED)
            runs["true_z_blur_converged"] = lambda: rerun(args, seeds_kji, thickness, **CONVERGED)
        runs["true_model"] = lambda: rerun(args, seeds_kji, thickness, levels, blur=blur)
        runs["true_model_converged"] = lambda: rerun(args, seeds_kji, thickness, levels, blur=blur, **CONVERGED)
        if prefix:
            runs["true_model_from_truth"] = lambda: rerun(args, seeds_kji, thickness, levels, sdf, blur,
                                                          **CONVERGED)
        for name, run in runs.items():
            scored = score(run(), phantom, truth)
            case["variants"][prefix + name] = {k: scored.get(k) for k in (
                "dice", "surface_mean_mm", "nascet_error_points", "min_diameter_error_mm")}
        log(f"case {seed:2d}: " + ", ".join(f"{name} {v['min_diameter_error_mm']:+.2f}" if v[
            "min_diameter_error_mm"] is not None else f"{name} -" for name, v in case["variants"].items()))
    return case


def summarise(cases: list[dict]) -> dict:
    """Per variant: the pass counts, and the minimal-diameter error's median and range over all cases and over
    the tight throats (true minimal diameter below ``TIGHT_MM``)."""
    out = {}
    for name in cases[0]["variants"]:
        rows = [(c["truth_graded"]["min_diameter_mm"], c["variants"][name]) for c in cases]
        errors = np.array([v["min_diameter_error_mm"] for _, v in rows if v["min_diameter_error_mm"] is not None])
        tight = np.array([v["min_diameter_error_mm"] for d, v in rows
                          if v["min_diameter_error_mm"] is not None and d is not None and d < TIGHT_MM])
        out[name] = {
            "nascet_within_5": sum(meets("nascet_error_points", v["nascet_error_points"]) for _, v in rows),
            "min_diameter_within_0_25": sum(meets("min_diameter_error_mm", v["min_diameter_error_mm"])
                                            for _, v in rows),
            "min_diameter_error_median_mm": float(np.median(errors)),
            "min_diameter_error_range_mm": [float(errors.min()), float(errors.max())],
            "tight_cases": int(tight.size),
            "tight_min_diameter_error_median_mm": float(np.median(tight)) if tight.size else None,
            "dice_min": float(min(v["dice"] for _, v in rows)),
            "cases": len(rows)}
    return out


def main() -> None:
    """Run the cases and write ``results/refine_budget.json``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--first-seed", type=non_negative(int), default=0)
    parser.add_argument("--cases", type=non_negative(int), default=30)
    parser.add_argument("--jobs", type=non_negative(int), default=1)
    options = parser.parse_args()
    git = git_state()
    seeds = range(options.first_seed, options.first_seed + options.cases)
    with Pool(max(options.jobs, 1)) as pool:
        cases = pool.map(run_case, seeds, chunksize=1)
    write_results("refine_budget", {"git": git, "family_seeds": f"range({seeds.start}, {seeds.stop})",
                                    "converged": CONVERGED, "noise_free_scale": NOISE_FREE,
                                    "tight_below_mm": TIGHT_MM, "cases": cases, "summary": summarise(cases)})


if __name__ == "__main__":
    main()
