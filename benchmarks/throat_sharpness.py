"""How sharp each family case's true throat is, beside how carotid graded it.

``bench_segmentation`` scores carotid's stenosis grade on the phantom family; the
cases that miss the NASCET and minimal-diameter limits are mostly tight throats
graded too wide.  This script asks whether those throats are resolved by the
image at all.  For every family case in ``results/segmentation.json`` (carotid,
one seed per branch) and ``results/segmentation_variants.json`` (the defaults on
the held-out seeds) it grades the phantom's true lumen with carotid's
centerlines, as the benchmark does, and measures the throat's bend along the
ICA: the rise of the ICA's narrow radius (half the narrowest diameter,
``section_profile``) from the narrowest section to one voxel (the largest voxel
size ``h``) on either side, and the radius of curvature of that profile,
``h^2 / (2 rise)``.  A throat whose profile bends on a radius shorter than ``h``
changes its width within one voxel: the narrowest section is a feature of the
object smaller than the voxel.  The cases are then split into throats the voxel
resolves (bend radius >= h) and sub-voxel throats, with carotid's pass counts
(all four criteria of ``bench_segmentation``) in each.

Usage (from the repository root)::

    .venv/bin/python benchmarks/throat_sharpness.py

Writes ``results/throat_sharpness.json`` (about 6 minutes for 100 cases on one core).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from _common import git_state, write_results
from bench_segmentation import log, meets_all
from carotid.centerline import compute_centerlines
from carotid.centerline.axes import arclength
from carotid.phantom import make_phantom
from carotid.phantom.family import sample_family

RESULTS = Path(__file__).resolve().parent / "results"
SOURCES = (("segmentation.json", "carotid"), ("segmentation_variants.json", "defaults"))


def throat_bend(phantom) -> dict:
    """The bend of the true ICA's narrow-radius profile at its narrowest section.

    Parameters
    ----------
    phantom : Phantom
        A family phantom (its ``sdf`` and ``mask`` are the true lumen).

    Returns
    -------
    dict
        ``narrow_radius_mm`` (half the narrowest diameter), ``voxel_mm`` (largest voxel size h),
        ``rise_mm`` (mean narrow radius one voxel either side, minus the narrowest; interpolated along the
        axis), ``bend_radius_mm`` (``h^2 / (2 rise)``; None where the profile does not rise), ``resolved``
        (bend radius >= h).
    """
    grid = phantom.image
    cl = compute_centerlines(grid.with_array(np.asarray(phantom.sdf.array, np.float32)),
                             grid.with_array(np.asarray(phantom.mask.array > 0, np.uint8)))
    ica = cl.branch("ICA")
    s, narrow = arclength(ica.points), np.asarray(ica.narrow_radii, float)
    k = int(np.argmin(narrow[1:-1])) + 1  # the end samples read the junction and the image's face
    h = float(max(grid.spacing_kji))
    rise = 0.5 * (np.interp(s[k] - h, s, narrow) + np.interp(s[k] + h, s, narrow)) - narrow[k]
    bend = h * h / (2.0 * rise) if rise > 0 else None  # None: no bend (the profile does not rise)
    return {"narrow_radius_mm": float(narrow[k]), "voxel_mm": h, "rise_mm": float(rise), "bend_radius_mm": bend,
            "resolved": bend is None or bend >= h}


def split(rows: list[dict]) -> dict:
    """Pass counts and failing seeds among resolved and among sub-voxel throats."""
    out = {}
    for name, keep in (("resolved", True), ("sub_voxel", False)):
        group = [r for r in rows if r["resolved"] is keep]
        out[name] = {"cases": len(group), "all_four": sum(r["all_four"] for r in group),
                     "failing_seeds": [r["seed"] for r in group if not r["all_four"]]}
    return out


def main() -> None:
    """Measure every case of the two result files and write ``results/throat_sharpness.json``."""
    missing = [name for name, _ in SOURCES if not (RESULTS / name).is_file()]
    if missing:
        print(f"throat_sharpness: results/{missing[0]} is missing: run bench_segmentation.py first", file=sys.stderr)
        sys.exit(2)
    git = git_state()
    sets = {}
    for filename, method in SOURCES:
        data = json.loads((RESULTS / filename).read_text())
        rows = []
        for case in data["cases"]:
            seed, record = case["seed"], case["methods"][method]
            phantom = make_phantom(**sample_family(seed))
            row = {"seed": seed, "modality": phantom.info["modality"],
                   "area_reduction": case["truth"]["area_reduction"], **throat_bend(phantom),
                   "nascet_error_points": record.get("nascet_error_points"),
                   "min_diameter_error_mm": record.get("min_diameter_error_mm"), "all_four": meets_all(record)}
            rows.append(row)
            log(f"case {seed:2d}: rise {row['rise_mm']:.3f} mm within {row['voxel_mm']:.2f} mm, bend radius "
                f"{row['bend_radius_mm'] or float('inf'):.2f} mm ({'resolved' if row['resolved'] else 'sub-voxel'}), "
                f"{'passes' if row['all_four'] else 'fails'}")
        sets[filename] = {"method": method, "results_commit": data["git"]["commit"], "cases": rows,
                          "summary": split(rows)}
    every = [row for s in sets.values() for row in s["cases"]]
    write_results("throat_sharpness", {"git": git, "sets": sets, "summary": split(every)})


if __name__ == "__main__":
    main()
