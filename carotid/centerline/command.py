"""``carotid centerlines CASE_DIR``: centerlines, branch names and stenosis grading of a segmented case."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from carotid.centerline.extract import compute_centerlines
from carotid.centerline.io import write_centerlines
from carotid.centerline.model import Centerlines
from carotid.centerline.plaque import annotate, calcified
from carotid.errors import CarotidError


def run_centerlines(case_dir: str | Path, prune: float = 2.0, smoothing: float = 1.0) -> tuple[Centerlines, Path]:
    """Read ``CASE_DIR/segmentation``, compute the centerlines and write them to the case folder.

    Each stenosis grading gets ``calcium_mm`` (``plaque.calcium_distance``) when the segmentation wrote its
    hyperdense structures (``calcium_mask.nii.gz``).

    Returns
    -------
    (Centerlines, Path)
        The centerlines and the VTP written.

    Raises
    ------
    CarotidError
        If the segmentation is missing, empty or fragmented.
    """
    from carotid.io import read_image

    seg = Path(case_dir) / "segmentation"
    levelset_path, mask_path = seg / "levelset.nii.gz", seg / "mask.nii.gz"
    if not levelset_path.exists() or not mask_path.exists():
        raise CarotidError(f"{seg}: no segmentation (levelset.nii.gz, mask.nii.gz); "
                           "run `carotid segment IMAGE -o CASE_DIR` first")
    levelset = read_image(levelset_path)
    mask = read_image(mask_path, dtype=np.uint8)
    cl = compute_centerlines(levelset, mask, prune=prune, smoothing=smoothing)
    calcium_path = seg / "calcium_mask.nii.gz"
    if calcium_path.exists():
        calcium = read_image(calcium_path, dtype=np.uint8)
        if not calcium.same_grid(levelset):
            raise CarotidError(f"{calcium_path}: not on the grid of {levelset_path}; segment the case again")
        annotate(cl.info, levelset, calcium)
    vtp, _ = write_centerlines(cl, case_dir)
    return cl, vtp


def summary(cl: Centerlines) -> str:
    """One paragraph: branches with lengths and radii, the bifurcation and the stenosis grading."""
    parts = [f"{b['name']} {b['length_mm']:.1f} mm long, mean radius {b['mean_radius_mm']:.2f} mm"
             for b in cl.info["branches"]]
    text = f"{len(parts)} branches: " + "; ".join(parts) + ". "
    if np.all(np.isfinite(cl.bifurcation)):
        text += f"Bifurcation at {np.round(cl.bifurcation, 1).tolist()} mm. "
    else:
        text += "No bifurcation found. "
    st = cl.info.get("stenosis")
    if st:
        text += (f"Narrowest {st['branch']} section {st['arclength_from_bifurcation_mm']:.1f} mm from the "
                 f"bifurcation: diameter {st['min_diameter_mm']:.2f} mm, NASCET {100 * st['nascet']:.0f}%, "
                 f"ECST {100 * st['ecst']:.0f}%, area reduction {100 * st['area_reduction']:.0f}%.")
        if calcified(st):
            text += f" Calcified: calcium {st['calcium_mm']:.1f} mm from the lumen at the stenosis."
    return text


def cmd_centerlines(args) -> int:
    """Run the stage from parsed arguments; prints the summary."""
    from carotid.stages import CenterlineStageParameters

    CenterlineStageParameters(prune=args.prune, smoothing=args.smoothing).validate()
    if not args.prune > 0:
        raise CarotidError("--prune must be positive")
    cl, vtp = run_centerlines(args.case_dir, prune=args.prune, smoothing=args.smoothing)
    print(f"centerlines written to {vtp} (features in {vtp.parent / 'geometry.json'}). {summary(cl)}")
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``centerlines`` subcommand to an argparse subparsers object."""
    p = subparsers.add_parser("centerlines", help="centerlines, branch names and stenosis grading of a segmented case")
    p.add_argument("case_dir", type=Path, metavar="CASE_DIR",
                   help="case folder holding segmentation/ (written by carotid segment)")
    p.add_argument("--prune", type=float, default=2.0,
                   help="remove end branches shorter than this many radii of their parent (default 2)")
    p.add_argument("--smoothing", type=float, default=1.0, metavar="MM",
                   help="Gaussian smoothing of each axis along its arc length, mm (default 1)")
    p.set_defaults(func=cmd_centerlines)
    return p
