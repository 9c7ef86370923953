"""Benchmark: a short, tight throat in overlapping slices, segmented with and without the slice thickness.

CT angiograms are reconstructed in slices thicker than their spacing (1 mm every 0.5 mm): each slice
integrates the vessel over its thickness, and a short throat is filled from the wider lumen on either
side.  The refinement's blur model (``deblur.axis_blur``) adds each slice's extent along the slice axis;
this benchmark runs ``segment`` (defaults, one seed at each end) on the same images twice:

* ``spacing``: the image records no thickness, and the model takes the slice spacing for it (what every
  NIfTI without a sidecar gets, and what a tool that ignores the slice profile assumes);
* ``thickness``: the image records its thickness (``Volume.slice_thickness``, as DICOM SliceThickness or a
  dcm2niix sidecar give it).

The cases: a straight tube of radius 2.5 mm along the slices, narrowed to ``r0`` at z = 0 by a Gaussian
notch of axial standard deviation ``length`` (0.8, 1.5 mm; the family phantom's sub-voxel throats bend
on 0.35-1 mm), ``r0`` 0.9 or 1.3 mm; 0.4 mm pixels and a 0.5 mm Gaussian scanner blur on a 0.1 mm
grid along z and 0.2 mm in plane, then a boxcar of the slice thickness (0.5, 1.0, 1.5, 2.0 mm) along z,
sampled every 0.5 mm, each pixel the mean of its 2 x 2 sub-pixels; lumen 350 HU on 40 HU, correlated
noise of 15 HU, two noise draws per geometry.  Figure: the error (mm) of the throat's radius, the mean
of the wall on 36 rays in the slice through z = 0 (``section_radii``), against ``r0``.  No peer models the slice
profile; ``spacing`` is the baseline.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_slice_thickness.py [--quick]
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
from scipy import ndimage

from _common import git_state, parse_args, timed, write_results
from carotid.centerline.axes import section_radii
from carotid.io import Volume
from carotid.segment import segment

PIXEL_MM, SPACING_MM, BLUR_MM = 0.4, 0.5, 0.5
FINE_Z_MM, FINE_XY = 0.1, 2  # fine grid: 0.1 mm along z, PIXEL_MM / 2 in plane
RADIUS_MM, LUMEN, TISSUE, NOISE = 2.5, 350.0, 40.0, 15.0
HALF_LENGTH_MM, HALF_WIDTH_MM = 12.0, 8.0


def throat_case(r0: float, length: float, thickness: float, draw: int) -> Volume:
    """The scan of a notched tube (module docstring), its throat in the slice through z = 0.

    Returns
    -------
    Volume
        Float32 HU, spacing (PIXEL_MM, PIXEL_MM, SPACING_MM), no slice thickness recorded.
    """
    step = int(round(SPACING_MM / FINE_Z_MM))
    box = max(int(round(thickness / FINE_Z_MM)), 1)
    slices = 2 * int(HALF_LENGTH_MM / SPACING_MM) + 1
    planes = (slices - 1) * step + 1 + 2 * box
    z = (np.arange(planes) - (planes - 1) / 2) * FINE_Z_MM
    fine_xy = PIXEL_MM / FINE_XY
    n = FINE_XY * int(2 * HALF_WIDTH_MM / PIXEL_MM)
    xy = (np.arange(n) - (n - 1) / 2) * fine_xy
    radius = RADIUS_MM - (RADIUS_MM - r0) * np.exp(-0.5 * (z / length) ** 2)
    rho = np.hypot(*np.meshgrid(xy, xy, indexing="ij"))
    fraction = np.clip(0.5 - (rho[None] - radius[:, None, None]) / fine_xy, 0, 1).astype(np.float32)
    fraction = ndimage.gaussian_filter(fraction, (BLUR_MM / FINE_Z_MM, BLUR_MM / fine_xy, BLUR_MM / fine_xy))
    fraction = ndimage.uniform_filter1d(fraction, box, axis=0)
    centre = (planes - 1) // 2
    fraction = fraction[centre - (slices - 1) // 2 * step:centre + (slices - 1) // 2 * step + 1:step]
    fraction = fraction.reshape(slices, n // FINE_XY, FINE_XY, n // FINE_XY, FINE_XY).mean(axis=(2, 4))
    rng = np.random.default_rng([draw, int(1000 * r0), int(1000 * length), int(1000 * thickness)])
    noise = ndimage.gaussian_filter(rng.standard_normal(fraction.shape).astype(np.float32), 0.6)
    image = TISSUE + (LUMEN - TISSUE) * fraction + NOISE * noise / noise.std()
    first = -(n // FINE_XY - 1) / 2 * PIXEL_MM
    origin = (first, first, -(slices - 1) / 2 * SPACING_MM)
    return Volume(image.astype(np.float32), (PIXEL_MM, PIXEL_MM, SPACING_MM), origin)


def throat_radius(levelset: Volume, z0: float = 0.0) -> float:
    """Mean radius (mm) of the lumen's wall on 36 rays from the tube's axis (x = y = 0) in the section at
    z = ``z0`` (``centerline.axes.section_radii``, as the grading reads its sections)."""
    axis = np.array([[0.0, 0.0, z0 - SPACING_MM], [0.0, 0.0, z0], [0.0, 0.0, z0 + SPACING_MM]])
    return float(np.mean(section_radii(levelset, axis, np.full(3, RADIUS_MM), n_rays=36)[1]))


def run_case(r0: float, length: float, thickness: float, draw: int) -> dict:
    """``segment`` on one scan without (``spacing``) and with (``thickness``) its slice thickness recorded:
    the throat's radius error (mm), the seconds, and the blur the model used along z."""
    volume = throat_case(r0, length, thickness, draw)
    seeds = [[0.0, 0.0, -HALF_LENGTH_MM + 2.0], [0.0, 0.0, HALF_LENGTH_MM - 2.0]]
    record = {"r0_mm": r0, "length_mm": length, "thickness_mm": thickness, "draw": draw}
    for name, recorded in (("spacing", None), ("thickness", thickness)):
        result, seconds = timed(segment, replace(volume, slice_thickness=recorded), seeds_xyz=seeds)
        record[name] = {"error_mm": throat_radius(result.levelset) - r0, "seconds": seconds,
                        "model_blur_z_mm": result.report["intensity"]["model_blur_kji_mm"][0],
                        "measured_blur_mm": result.report["intensity"]["blur_mm"]}
    return record


def summary(records: list[dict], name: str) -> dict:
    """Median, median absolute and worst (which case) radius error of run ``name``, and the cases within
    0.125 mm (a quarter of a millimetre in diameter)."""
    errors = np.array([rec[name]["error_mm"] for rec in records])
    worst = int(np.argmax(np.abs(errors)))
    return {"median_error_mm": float(np.median(errors)), "median_abs_error_mm": float(np.median(np.abs(errors))),
            "worst_error_mm": float(errors[worst]),
            "worst_case": {k: records[worst][k] for k in ("r0_mm", "length_mm", "thickness_mm", "draw")},
            "within_0.125_mm": int(np.sum(np.abs(errors) <= 0.125)), "cases": len(errors)}


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    git = git_state()
    grid = list(itertools.product((0.9, 1.3), (0.8, 1.5), (1.5,) if args.quick else (0.5, 1.0, 1.5, 2.0),
                                  (0,) if args.quick else (0, 1)))
    records = []
    for r0, length, thickness, draw in grid:
        records.append(run_case(r0, length, thickness, draw))
        rec = records[-1]
        print(f"r0 {r0} mm, length {length} mm, thickness {thickness} mm, draw {draw}: throat radius error "
              f"spacing {rec['spacing']['error_mm']:+.3f} mm, thickness {rec['thickness']['error_mm']:+.3f} mm",
              flush=True)
    by_thickness = {str(t): {name: summary([r for r in records if r["thickness_mm"] == t], name)
                             for name in ("spacing", "thickness")}
                    for t in sorted({r["thickness_mm"] for r in records})}
    figures = {"git": git, "cases": records,
               "summary": {name: summary(records, name) for name in ("spacing", "thickness")},
               "by_thickness_mm": by_thickness}
    for name, s in figures["summary"].items():
        print(f"{name}: median error {s['median_error_mm']:+.3f} mm, worst {s['worst_error_mm']:+.3f} mm "
              f"({s['worst_case']}), within 0.125 mm {s['within_0.125_mm']}/{s['cases']}")
    write_results("slice_thickness", figures, args.quick)


if __name__ == "__main__":
    main()
