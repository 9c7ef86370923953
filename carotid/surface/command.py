"""``carotid surface``: the clipped, smoothed, remeshed lumen surface of a case, or of an external surface."""

from __future__ import annotations

import argparse
from pathlib import Path

from carotid.errors import CarotidError
from carotid.stages import SurfaceStageParameters


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``surface`` subcommand to an argparse subparsers object."""
    p = subparsers.add_parser(
        "surface", help="clipped, remeshed lumen surface (CASE_DIR/surface.vtp)",
        description="Marching cubes on the level set, automatic clipping with flat labelled caps, Taubin "
                    "smoothing and isotropic remeshing. Reads CASE_DIR/segmentation/levelset.nii.gz and "
                    "CASE_DIR/centerlines.vtp, or an external surface with --from-surface, whose own flat "
                    "caps are kept (only its wall is remeshed) unless --reclip cuts its ends again.")
    p.add_argument("case_dir", type=Path, nargs="?", metavar="CASE_DIR", help="case folder")
    p.add_argument("--from-surface", type=Path, metavar="FILE",
                   help="closed or open-ended STL/VTP/VTK/OBJ/PLY lumen surface in mm (needs -o)")
    p.add_argument("-o", "--output", type=Path, metavar="CASE_DIR", help="case folder for --from-surface")
    p.add_argument("--reclip", action="store_true",
                   help="with --from-surface: cut the ends orthogonal to the axis and cap them again, instead of "
                        "keeping the surface's own flat caps")
    p.add_argument("--scale", type=float, help="factor to mm for --from-surface (1000 for metres)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--target-edge", type=float, default=0.3, metavar="MM", help="target edge length (0.3 mm)")
    size.add_argument("--edge-radius-ratio", type=float, metavar="K",
                      help="target edge length K times the local radius, within [0.15, 1] mm")
    p.add_argument("--flow-extensions", type=float, default=0.0, metavar="N",
                   help="flow extensions of N radii at every end (default none)")
    p.add_argument("--stl", action="store_true", help="also write CASE_DIR/surface.stl")
    p.set_defaults(func=run)
    return p


def _external(args):
    """The closed external surface, its level set and centerlines, and the case folder to write."""
    from carotid.centerline import compute_centerlines
    from carotid.surface.external import levelset_from_surface, load_external_surface

    if args.output is None:
        raise CarotidError("--from-surface needs -o CASE_DIR")
    closed, _ = load_external_surface(args.from_surface, scale=args.scale)
    levelset = levelset_from_surface(closed)
    return args.output, closed, levelset, compute_centerlines(levelset)


def run(args) -> int:
    """Build and write the surface of a case; raises CarotidError on bad input."""
    from carotid.surface.pipeline import (build_surface, build_surface_keeping_caps, read_levelset_and_centerlines,
                                          write_surface)

    SurfaceStageParameters(target_edge_mm=args.target_edge, flow_extension_radii=args.flow_extensions,
                           edge_radius_ratio=0.0 if args.edge_radius_ratio is None else args.edge_radius_ratio
                           ).validate()  # the [surface] ranges; a ratio of 0 is refused by build_surface
    if args.from_surface is not None:
        case_dir, closed, levelset, centerlines = _external(args)
    elif args.case_dir is None:
        raise CarotidError("give CASE_DIR, or --from-surface FILE -o CASE_DIR")
    else:
        if args.scale is not None or args.reclip:
            raise CarotidError("--scale and --reclip apply to --from-surface only")
        case_dir = args.case_dir
        levelset, centerlines = read_levelset_and_centerlines(case_dir)
    size = {"target_edge_mm": args.target_edge, "edge_radius_ratio": args.edge_radius_ratio,
            "flow_extension_radii": args.flow_extensions}
    if args.from_surface is not None and not args.reclip:
        surface, caps, quality = build_surface_keeping_caps(closed, centerlines, **size)
    else:
        surface, caps, quality = build_surface(levelset, centerlines, **size)
    if args.from_surface is not None:
        from carotid.centerline import write_centerlines
        from carotid.io import write_image

        write_image(levelset, Path(case_dir) / "segmentation" / "levelset.nii.gz")
        write_centerlines(centerlines, case_dir)
    path = write_surface(surface, case_dir, stl=args.stl, quality=quality, caps=caps)
    print(f"wrote {path}: {quality['triangles']} triangles, caps "
          + ", ".join(f"{c['id']}={c['name']}" for c in caps)
          + f", min angle >= 30 deg: {100 * quality['min_angle_deg']['fraction_ge_30']:.1f}%")
    return 0
