"""Lumen surfaces made by other tools (STL, VTP, VTK, OBJ, PLY), closed or open-ended, and their level set.

The surface is cleaned (duplicate points merged), reduced to its main piece (specks dropped with a warning,
comparable pieces refused: ``main_piece``) and checked for 2-manifoldness; open ends (boundary loops, as
left by tools that do not cap) are closed by planar caps so that inside and outside are defined.  ``levelset_from_surface`` samples the signed distance on a
regular grid: the sign from VTK's scan conversion (vtkPolyDataToImageStencil through pyvista), the
distance exact (to the nearest triangle, ``carotid.surface.project``) near the surface and from
scipy's Euclidean distance transform further away, which the centerline stage then
treats like a segmentation's level set.  ``label_caps`` labels the surface's own flat caps
(``carotid.mesh.boundary.label_flat_caps``) by the vessel ends of its centerlines, so that the surface
stage can keep them instead of clipping the ends again.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from carotid.centerline.model import Centerlines
from carotid.centerline.skeleton import FRAGMENT_FRACTION
from carotid.errors import CarotidError, CarotidWarning
from carotid.io import Volume
from carotid.io.vtkfile import read_vtk
from carotid.mesh.boundary import INLET, label_flat_caps
from carotid.surface.clip import planar_cap
from carotid.surface.mesh import (WALL, boundary_loops, compact, face_areas, face_components, from_polydata,
                                  signed_volume, to_polydata)
from carotid.surface.project import TriangleProjector
from carotid.surface.quality import manifold_report, self_intersections

SUFFIXES = (".stl", ".vtp", ".vtk", ".obj", ".ply")
METRES_EXTENT = 0.5  # a carotid bifurcation spans several cm: below 0.5 units it is in metres
MICROMETRES_EXTENT = 1000.0
"""Largest span of a lumen surface, mm.  A neck CT or MR angiogram covers at most the aortic arch to the skull
base, some 300 mm, so a surface spanning over 1 m is not in mm: micrometres (or a scaling slip) give 1000 times
the size, and meshing it at the default edge lengths would not end."""
FLAT_RATIO = 1e-3
"""Smallest thickness of a lumen surface (its span across its thinnest principal direction) as a fraction of its
largest span.  A 1 mm vessel 100 mm long is 1e-2; below 1e-3 the surface is flat (a squashed or 2-D export)
and encloses no volume to mesh."""


def check_extent(points: np.ndarray, where: str = "") -> None:
    """Raise CarotidError unless the points span a lumen's size in mm, in all three directions.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Surface vertices, in the units the caller will mesh in (mm).
    where : str
        Prefix of the messages (the file, ``"path: "``), or empty.

    Raises
    ------
    CarotidError
        A span below ``METRES_EXTENT`` (metres: ``--scale 1000``) or above ``MICROMETRES_EXTENT``
        (micrometres: ``--scale 0.001``), or a thickness below ``FLAT_RATIO`` of the span (flat).
    """
    extent = float(np.ptp(points, axis=0).max())
    if extent < METRES_EXTENT:
        raise CarotidError(f"{where}the surface spans {extent:.3g} mm: looks like metres, pass --scale 1000")
    if extent > MICROMETRES_EXTENT:
        raise CarotidError(f"{where}the surface spans {extent:.3g} mm, more than a neck angiogram covers: looks "
                           "like micrometres, pass --scale 0.001")
    centred = points - points.mean(axis=0)
    thickness = float(np.ptp(centred @ np.linalg.svd(centred, full_matrices=False)[2][2]))
    if thickness < FLAT_RATIO * extent:
        raise CarotidError(f"{where}the surface is flat ({thickness:.3g} mm thick across its thinnest direction, "
                           f"{extent:.3g} mm long): a lumen surface encloses a volume; export it in 3-D")


def read_surface(path: Path) -> pv.PolyData:
    """A triangle surface file (``SUFFIXES``; a volume mesh gives its boundary), in its own units.

    Raises
    ------
    CarotidError
        If the file is missing, unreadable or not a surface file (:func:`carotid.io.vtkfile.read_vtk`), or has
        no faces.
    """
    data = read_vtk(path, "surface", SUFFIXES)
    if not isinstance(data, pv.PolyData):
        data = data.extract_surface(algorithm="dataset_surface")
    data = data.triangulate()
    if not data.faces.size:
        raise CarotidError(f"{path}: the surface has no faces ({data.n_points} points, no triangles or polygons)")
    return data


def main_piece(points: np.ndarray, faces: np.ndarray, where: str = "") -> np.ndarray:
    """The faces of the piece of a surface with the largest area; the other pieces may only be debris.

    Exports from segmentation tools often carry specks beside the lumen.  Pieces holding together more than
    ``FRAGMENT_FRACTION`` of the whole area (the segmentation's fragment rule,
    :func:`carotid.centerline.skeleton.largest_component`) are another vessel or a lumen cut in two, which no
    choice here would get right.  Only ratios of areas are compared, so the units do not matter.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    faces : ndarray of int, shape (m, 3)
    where : str
        Prefix of the messages (the file, ``"path: "``), or empty.

    Returns
    -------
    ndarray of bool, shape (m,)
        The faces of the largest piece.

    Raises
    ------
    CarotidError
        When the other pieces hold more than ``FRAGMENT_FRACTION`` of the area.

    Warns
    -----
    CarotidWarning
        When smaller pieces are dropped: how many and their share of the area.
    """
    comp = face_components(len(points), faces)
    areas = np.bincount(comp, weights=face_areas(points, faces))
    largest = int(np.argmax(areas))
    others, dropped = len(areas) - 1, 1.0 - areas[largest] / areas.sum()
    if dropped > FRAGMENT_FRACTION:
        shares = np.sort(areas)[::-1] / areas[largest]
        raise CarotidError(f"{where}the surface has {len(areas)} separate pieces, the next largest "
                           f"{', '.join(f'{100 * a:.0f}' for a in shares[1:4])}{', ...' if others > 3 else ''} % of "
                           "the largest one's area; a lumen is one: keep the lumen's piece only")
    if others:
        warnings.warn(f"{where}{others} small separate piece{'s' if others > 1 else ''} dropped "
                      f"({100 * dropped:.2g} % of the surface's area)", CarotidWarning, stacklevel=2)
    return comp == largest


def _close_loops(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Close every boundary loop with a cap in its best-fit plane; returns (points, faces, loops closed).

    Raises CarotidError when a loop is not simple (pinched) or when a cap crosses the surface or another
    cap (a badly non-planar or folded rim).
    """
    loops = boundary_loops(faces)
    n_boundary = int(manifold_report(len(points), faces)["boundary_edges"])
    if sum(len(lp) for lp in loops) != n_boundary:
        raise CarotidError("the surface's open ends are not simple loops (pinched boundary): it cannot be closed")
    n_faces = len(faces)
    for loop in loops:  # loop over open ends
        rim = points[loop]
        centred = rim - rim.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][2]
        # the cap runs the rim against the wall, so its normal is opposite to the rim's winding
        winding = np.cross(centred, np.roll(centred, -1, axis=0)).sum(axis=0)
        normal = normal if winding @ normal < 0 else -normal
        interior, cap = planar_cap(points, loop, normal)
        points = np.vstack([points, interior])
        faces = np.vstack([faces, cap])
    crossing = self_intersections(points, faces, among=np.arange(len(faces)) >= n_faces)
    if len(crossing):
        raise CarotidError(f"{len(loops)} open end(s) cannot be closed by flat caps: a rim is badly non-planar or "
                           "folds over itself, so its cap crosses the surface; cut the ends flat first")
    return points, faces, len(loops)


def load_external_surface(path: str | Path, scale: float | None = None) -> tuple[pv.PolyData, int]:
    """Read, clean and close a lumen surface from another tool.

    Parameters
    ----------
    path : str or Path
        STL, VTP, VTK, OBJ or PLY file, in mm (or scaled to mm by ``scale``).
    scale : float, optional
        Factor applied to the coordinates (e.g. 1000 for a surface in metres).

    Returns
    -------
    surface : pyvista.PolyData
        Closed, consistently oriented (outward) triangle surface in mm.
    open_ends : int
        Number of boundary loops that were closed by planar caps.

    Raises
    ------
    CarotidError
        Unreadable file, no triangles, non-finite coordinates, coordinates that look like metres or micrometres, a
        flat surface, a non-manifold surface, open ends whose flat caps would cross the surface (badly non-planar
        or folded rims), or open ends that are not simple loops.
    """
    path = Path(path)
    mesh = read_surface(path).clean(tolerance=1e-9, absolute=False)
    points, faces, _ = from_polydata(pv.PolyData(mesh.points, mesh.faces))
    if scale is not None:
        if not scale > 0:
            raise CarotidError(f"--scale {scale} must be positive")
        points = points * float(scale)
    points, faces = compact(points, faces[main_piece(points, faces, f"{path}: ")])
    check_extent(points, f"{path}: ")
    report = manifold_report(len(points), faces)
    if report["nonmanifold_edges"] or report["nonmanifold_vertices"]:
        raise CarotidError(f"{path}: the surface is not a 2-manifold ({report['nonmanifold_edges']} edges in more "
                           f"than two triangles, {report['nonmanifold_vertices']} pinched vertices); repair it first")
    if not report["consistently_oriented"]:
        oriented = to_polydata(points, faces).compute_normals(consistent_normals=True, auto_orient_normals=False,
                                                              split_vertices=False, point_normals=False)
        points, faces, _ = from_polydata(pv.PolyData(oriented.points, oriented.faces))
    points, faces, open_ends = _close_loops(points, faces)
    if not manifold_report(len(points), faces)["watertight"]:
        raise CarotidError(f"{path}: the surface could not be closed into a watertight surface")
    if signed_volume(points, faces) < 0:
        faces = faces[:, ::-1].copy()
    return to_polydata(points, faces, np.ones(len(faces), np.int32)), open_ends


def levelset_from_surface(surface: pv.PolyData, spacing: float = 0.25, margin: float = 2.0,
                          band_mm: float = 1.0) -> Volume:
    """Signed distance to a closed surface on a regular grid (mm, negative inside).

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed, outward-oriented triangle surface in mm.
    spacing : float
        Isotropic voxel size in mm.
    margin : float
        Space around the surface's bounding box, mm.
    band_mm : float
        Inside and within this distance outside the surface the distance is exact (to the nearest
        triangle); further out, the Euclidean distance transform of the voxelised inside (within a voxel).

    Returns
    -------
    Volume
        float32 signed distance, clipped to +-10 mm, identity direction.
    """
    lo = np.asarray(surface.points.min(axis=0)) - margin
    hi = np.asarray(surface.points.max(axis=0)) + margin
    dims = np.ceil((hi - lo) / spacing).astype(int) + 1
    grid = pv.ImageData(dimensions=tuple(int(d) for d in dims), spacing=(spacing,) * 3, origin=tuple(lo))
    inside = surface.voxelize_binary_mask(reference_volume=grid)
    inside = np.asarray(inside.point_data[inside.point_data.keys()[0]]).reshape(dims[::-1]) > 0  # (k, j, i)
    spacing_kji = np.full(3, spacing)
    phi = np.where(inside, -ndimage.distance_transform_edt(inside, spacing_kji),
                   ndimage.distance_transform_edt(~inside, spacing_kji)) - np.where(inside, -0.5, 0.5) * spacing
    band = inside | (phi < band_mm)
    points, faces, _ = from_polydata(surface)
    near = np.asarray(grid.points).reshape(*dims[::-1], 3)[band]
    dist = np.linalg.norm(TriangleProjector(points, faces)(near)[0] - near, axis=1)
    phi[band] = np.where(inside[band], -dist, dist)
    return Volume(np.clip(phi, -10.0, 10.0).astype(np.float32), (spacing,) * 3, tuple(float(x) for x in lo))


def label_caps(surface: pv.PolyData, centerlines: Centerlines) -> pv.PolyData:
    """Label the flat end caps of a closed surface by the vessel end each one closes.

    The caps are found by ``carotid.mesh.boundary.label_flat_caps`` and matched one to one to the ends
    of the centerlines (least total distance from cap centroids to end points), so that the cap of
    ``centerlines.ends()[i]`` gets ``CellEntityIds`` ``2 + i``: the CCA inlet 2, the outlets 3, 4, ...

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed, outward-oriented triangle surface in mm (e.g. from ``load_external_surface``).
    centerlines : Centerlines
        Centerlines of the same lumen.

    Returns
    -------
    pyvista.PolyData
        The surface with ``CellEntityIds`` (wall 1, caps 2, 3, ...).

    Raises
    ------
    CarotidError
        When the surface has no flat end caps, or not one per vessel end.
    """
    try:
        labelled = label_flat_caps(surface)
    except CarotidError:
        raise CarotidError("the surface has no flat end caps to keep: pass --reclip to cut its ends") from None
    points, faces, labels = from_polydata(labelled)
    ends = centerlines.ends()
    caps = np.unique(labels[labels != WALL])
    if len(caps) != len(ends):
        raise CarotidError(f"the surface has {len(caps)} flat end caps for {len(ends)} vessel ends "
                           f"({', '.join(e[0] for e in ends)}): pass --reclip to cut its ends")
    centroids = np.array([points[np.unique(faces[labels == cap])].mean(axis=0) for cap in caps])
    tips = np.array([point for _, point, _, _ in ends])
    rows, cols = linear_sum_assignment(np.linalg.norm(centroids[:, None] - tips[None], axis=2))
    relabel = np.full(labels.max() + 1, WALL, np.int32)
    relabel[caps[rows]] = INLET + cols
    return to_polydata(points, faces, relabel[labels])
