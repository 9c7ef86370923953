"""The ``carotid mesh`` subcommand.

``carotid mesh CASE_DIR`` meshes ``CASE_DIR/surface.vtp`` (the labelled
output of ``carotid surface``); ``carotid mesh --from-surface FILE -o
CASE_DIR`` meshes any surface file pyvista reads (VTP, VTK, STL, PLY, OBJ):
a labelled closed surface is used as is, an open one gets a planar cap per
boundary loop, an unlabelled closed one gets its flat end caps detected.
The file must be in mm (``--scale 1000`` for metres, ``--scale 0.001`` for
micrometres: a surface spanning less than 0.5 or more than 1000 units is
refused, and so is a flat one or one of several pieces of comparable size;
specks beside the lumen are dropped with a warning).  A surface with
self-intersecting or needle triangles has its wall remeshed in place first
(``carotid.mesh.repair``).
With ``--from-surface`` the case folder also gets the surface that was meshed
(``surface.vtp``) and its centerlines (``centerlines.vtp``, from the surface's
signed distance), so that ``carotid simulate`` (its Doppler gates and
``--convergence``, whose coarser levels are remeshed from ``surface.vtp``) and
``carotid report`` take it like a case made by ``carotid surface``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError
from carotid.mesh.boundary import LABELS, cap_open_ends, check_surface, edge_faces, label_flat_caps
from carotid.mesh.core import CORES
from carotid.mesh.io import write_mesh
from carotid.mesh.mesher import build_mesh, median_edge
from carotid.mesh.repair import remesh_wall, surface_defects
from carotid.stages import MeshStageParameters
from carotid.surface.external import check_extent, main_piece, read_surface
from carotid.surface.mesh import compact, signed_volume


def external_surface(poly: pv.PolyData, scale: float | None = None) -> pv.PolyData:
    """A labelled closed surface in mm from any triangle surface (see the module docstring).

    Parameters
    ----------
    poly : pyvista.PolyData
        Triangle surface, in mm or in units that ``scale`` turns into mm.
    scale : float, optional
        Factor to mm (1000 for metres).

    Raises
    ------
    CarotidError
        Non-positive scale, a surface spanning less than 0.5 mm (metres given
        as mm) or more than 1000 mm (micrometres), a flat surface, one of
        several comparable pieces (``carotid.surface.external.main_piece``), or one with holes that flat caps
        do not close.
    """
    poly = poly.triangulate().clean()
    if scale is not None:
        if not scale > 0:
            raise CarotidError(f"--scale {scale} must be positive")
        poly.points = np.asarray(poly.points) * float(scale)
    keep = main_piece(np.asarray(poly.points, float), poly.regular_faces)
    if not keep.all():
        points, faces = compact(np.asarray(poly.points, float), poly.regular_faces[keep])
        labels = {LABELS: np.asarray(poly.cell_data[LABELS])[keep]} if LABELS in poly.cell_data else {}
        poly = pv.PolyData(points, np.c_[np.full(len(faces), 3), faces].ravel())
        poly.cell_data.update(labels)
    check_extent(np.asarray(poly.points, float))
    _, _, counts = edge_faces(poly.regular_faces)
    if (counts == 1).any():
        capped = cap_open_ends(poly)
        _, _, counts = edge_faces(capped.regular_faces)
        if (counts == 1).any():
            raise CarotidError(f"the surface stays open after capping its open ends ({int(np.sum(counts == 1))} "
                               "boundary edges left: holes in the wall, or ends that are not simple loops); "
                               "close the holes first")
        return capped
    if LABELS in poly.cell_data:
        return poly
    return label_flat_caps(poly)


def repaired_surface(poly: pv.PolyData) -> pv.PolyData:
    """The labelled surface, with its wall remeshed in place if it has defects (see :mod:`carotid.mesh.repair`).

    Prints one line with the defects found and the volume change when it remeshes.
    """
    surface = check_surface(poly)
    defects = surface_defects(surface)
    if not any(defects.values()):
        return poly
    repaired = remesh_wall(surface, median_edge(surface))
    after = check_surface(repaired)
    before = signed_volume(surface.points, surface.triangles)
    change = signed_volume(after.points, after.triangles) / before - 1.0
    print(f"surface remeshed in place ({defects['self_intersections']} self-intersecting triangle pairs, "
          f"{defects['needles']} needle triangles): {len(after.triangles)} triangles, volume change {change:+.2%}")
    return repaired


def mesh_case(surface: pv.PolyData, case_dir: Path, **params) -> dict:
    """Build the mesh of ``surface`` and write it into ``case_dir``; return the quality report."""
    mesh, quality = build_mesh(surface, **params)
    write_mesh(mesh, case_dir, quality)
    return quality


def write_case_geometry(surface: pv.PolyData, case_dir: Path) -> str:
    """Write ``surface.vtp`` and ``centerlines.vtp`` of a case meshed from an external surface.

    Parameters
    ----------
    surface : pyvista.PolyData
        The labelled closed surface that was meshed, mm.
    case_dir : Path
        The case folder.

    Returns
    -------
    str
        What was written, for the command's output.  Centerlines that cannot be traced (a surface that is
        not a vessel tree) are reported there and skipped: the mesh stands without them.
    """
    from carotid.centerline import compute_centerlines, write_centerlines
    from carotid.surface.external import levelset_from_surface
    from carotid.surface.pipeline import write_surface

    write_surface(surface, case_dir)
    try:
        centerlines = compute_centerlines(levelset_from_surface(surface))
    except CarotidError as error:
        return f"surface.vtp written; no centerlines.vtp ({error})"
    write_centerlines(centerlines, case_dir)
    return f"surface.vtp and centerlines.vtp ({', '.join(b.name for b in centerlines.branches)}) written"


def cmd_mesh(args: argparse.Namespace) -> int:
    """Run ``carotid mesh`` (see :func:`register`)."""
    p = MeshStageParameters(layers=args.layers, ratio=args.ratio, thickness_mm=args.thickness or 0.0,
                            thickness_ratio=0.3 if args.thickness_ratio is None else args.thickness_ratio,
                            size_mm=args.size or 0.0, core=args.core, lloyd_iterations=args.lloyd).validate()
    if args.from_surface is not None:
        if args.output is None:
            raise CarotidError("--from-surface needs -o CASE_DIR")
        surface = repaired_surface(external_surface(read_surface(args.from_surface), args.scale))
        case_dir = args.output
    else:
        if args.scale is not None:
            raise CarotidError("--scale applies to --from-surface only")
        if args.case_dir is None:
            raise CarotidError("give CASE_DIR, or --from-surface FILE -o CASE_DIR")
        path = args.case_dir / "surface.vtp"
        if not path.is_file():
            raise CarotidError(f"no surface.vtp in {args.case_dir}: run `carotid surface` first")
        surface = read_surface(path)
        case_dir = args.output or args.case_dir
    quality = mesh_case(surface, case_dir, layers=p.layers, ratio=p.ratio, thickness=p.thickness_mm or None,
                        thickness_ratio=None if p.thickness_mm else p.thickness_ratio, size=p.size_mm or None,
                        core=p.core, lloyd_iterations=p.lloyd_iterations)
    elements, floor = quality["elements"], quality["mesh"]["core"]
    slivers = (f" ({floor['below_floor']} core tetrahedra below the {floor['floor_deg']:g} deg floor, not fixed)"
               if floor["below_floor"] else "")
    prisms = quality.get("layer_prisms")
    layer = (f", layer prisms: smallest base angle {prisms['base_min_angle_deg']['min']:.1f} deg, largest skew "
             f"{prisms['skew_deg']['max']:.1f} deg, {prisms['degenerate']['count']} degenerate" if prisms else "")
    print(f"mesh written to {case_dir}: {elements['tetrahedra']} tetrahedra ({elements['layer']} in "
          f"{args.layers} layers, {elements['core']} core), core min dihedral {floor['worst_deg']:.1f} deg"
          f"{slivers}{layer}, volume error {quality['volume']['relative_error']:.1e}, "
          f"{quality['seconds']['total']:.1f} s")
    if args.from_surface is not None:
        print(write_case_geometry(surface, case_dir))
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``mesh`` subcommand to an argparse subparsers object."""
    p = subparsers.add_parser("mesh", help="boundary-layer tetrahedral volume mesh of the lumen surface",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("case_dir", nargs="?", type=Path, metavar="CASE_DIR",
                   help="case folder holding surface.vtp; the mesh files are written there")
    p.add_argument("--from-surface", type=Path, metavar="FILE", help="mesh this surface file instead")
    p.add_argument("--scale", type=float, help="factor to mm for --from-surface (1000 for metres)")
    p.add_argument("-o", "--output", type=Path, metavar="CASE_DIR", help="output folder (with --from-surface)")
    p.add_argument("--layers", type=int, default=10, help="boundary sub-layers N (default 10; 0: none)")
    p.add_argument("--ratio", type=float, default=1.2, help="height ratio f between sub-layers (default 1.2)")
    thick = p.add_mutually_exclusive_group()
    thick.add_argument("--thickness", type=float, metavar="MM", help="total layer thickness in mm")
    thick.add_argument("--thickness-ratio", type=float, metavar="R",
                       help="total layer thickness as a fraction of the local radius (default 0.3)")
    p.add_argument("--size", type=float, metavar="MM", help="core element size (default: surface edge)")
    p.add_argument("--core", choices=CORES, default="gmsh", help="core mesher (default gmsh HXT)")
    p.add_argument("--lloyd", type=int, default=5, metavar="N", help="Lloyd smoothing iterations (default 5)")
    p.set_defaults(func=cmd_mesh)
    return p
