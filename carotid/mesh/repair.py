"""Repair of a finished lumen surface from another tool before volume meshing.

Surfaces exported by other tools can be closed and labelled yet unusable for
a boundary layer: needle triangles with angles near 0 degrees (the inner
layer surface copies them into flat tetrahedra) and a few self-intersecting
triangles (prisms on them invert at any thickness).  Such a surface is
remeshed in place: its wall is given to gmsh as one discrete surface,
reparametrised (``classifySurfaces`` + ``createGeometry``, with the sharp
edges of a machined part such as a nozzle's sudden expansion kept as
curves when gmsh can parametrise the pieces, else none) and meshed again
with the Frontal-Delaunay algorithm, so every new vertex lies on the old
wall and the rims are resampled along the old rim polylines (in the cap
planes); each rim is then closed by a new planar cap
(:func:`carotid.mesh.boundary.cap_open_ends`) that keeps the label of the
old cap in its plane.  Frontal-Delaunay leaves a few needles where the
pieces of the reparametrisation meet (fluid.stl: 15 wall triangles under
10 degrees, the smallest 2.4); their prisms split into flat tetrahedra
whose convective rate set the step of the whole flow run (5e-6 s from
the start of the cycle on fluid.stl).  So the result is
given ``POLISH_ROUNDS`` rounds of the isotropic remesher
(:func:`carotid.surface.remesh.remesh`) at the edge lengths gmsh reached,
projected onto gmsh's surface (the nearest-triangle projection onto the
old one is unreliable among its needles), and a round more at a time, up
to ``POLISH_MAX_ROUNDS``, while an angle stays under ``POLISH_TARGET_DEG``:
fluid.stl then has no angle under 20 degrees.  Each remeshing cuts its
chords across the surface it projects onto, so the polish runs only where
gmsh left an angle under ``POLISH_BELOW_DEG``.  The extent is kept; the
volume changes only by the chords of the new triangles across the old ones
(reported).

The new edge length follows the local radius (:func:`wall_sizes`): a CAD
export triangulates a cylinder as a ring of long strips, so the median edge
of the input says nothing about the size its narrowest part needs (remeshed
at its 10 mm median edge, the 32-segment STL of the stenotic nozzle kept 12
triangles in all and its volume grew by 26 %).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from carotid.errors import CarotidError
from carotid.mesh.boundary import LABELS, WALL, Surface, cap_open_ends, cap_planes
from carotid.mesh.core import gmsh_session
from carotid.mesh.layers import inscribed_radius, triangle_min_angles
from carotid.surface.quality import self_intersections
from carotid.surface.remesh import local_edge_length, remesh


def surface_defects(surface: Surface, min_angle_deg: float = 5.0) -> dict:
    """Counts of the defects that make a surface unfit for a boundary layer.

    Returns
    -------
    dict
        ``self_intersections`` (pairs of crossing triangles) and ``needles``
        (triangles with an angle below ``min_angle_deg`` degrees).
    """
    return {"self_intersections": int(len(self_intersections(surface.points, surface.triangles))),
            "needles": int(np.sum(triangle_min_angles(surface.points, surface.triangles) < min_angle_deg))}


CIRCUMFERENCE_ELEMENTS = 24
"""Edges around a circular section of the local radius at least (the size field of :func:`wall_sizes`).
24 chords cut 1.1 % off a circle's area; the remeshed walls of the tests (fluid.stl, the CAD-style nozzle
STLs, new vertices on the old wall) lose 0.3-0.45 % of their volume."""

POLISH_ROUNDS = 2
"""Rounds of :func:`carotid.surface.remesh.remesh` after gmsh at first (one leaves fluid.stl 4 triangles under
20 degrees, two none or one, at 14 degrees, depending on the machine's floating point)."""

POLISH_TARGET_DEG = 20.0
"""Smallest angle (degrees) the polish must reach: short of it, the polish is run again from gmsh's result
with one round more, up to ``POLISH_MAX_ROUNDS``."""

POLISH_MAX_ROUNDS = 5
"""Most rounds of the polish (fluid.stl: 20.5 degrees after three, 23 after four or five; each round cuts
0.01-0.02 % more off the volume)."""

POLISH_BELOW_DEG = 15.0
"""gmsh's result is polished when one of its triangles has an angle below this (degrees)."""

FEATURE_DEG = 40.0
"""Dihedral angle (degrees) between neighbouring triangles above which the remeshing keeps their
common edge as a sharp edge, when gmsh can parametrise the pieces it cuts (a noisy organic surface
falls back to no sharp edges)."""


def wall_sizes(surface: Surface, size: float) -> np.ndarray:
    """Target edge length (mm) at every vertex: ``2 pi r / CIRCUMFERENCE_ELEMENTS`` of the local radius r.

    r is the inscribed-ball radius at the vertex along its area-weighted
    normal (:func:`carotid.mesh.layers.inscribed_radius`); on a cap rim it is
    the cap's equivalent radius ``sqrt(area / pi)`` instead (the radius at a
    rim corner is small, and an unevenly sampled rim gives the new cap
    slivers).  Lengths are clipped to [half the median shortest edge of the
    wall triangles, ``size``]: no finer than the input's own resolution.

    Parameters
    ----------
    surface : Surface
        Checked, labelled surface (mm).
    size : float
        Largest edge length (mm).

    Returns
    -------
    ndarray, shape (n,)
        Lengths in mm, one per point of ``surface`` (unused points included).
    """
    points, triangles = surface.points, surface.triangles
    corner = points[triangles]
    area = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # twice the area, outward
    normals = np.stack([np.bincount(triangles.ravel(), weights=np.repeat(area[:, k], 3), minlength=len(points))
                        for k in range(3)], axis=1)
    inward = -normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    radius = inscribed_radius(points, inward)
    wall = triangles[surface.labels == WALL]
    on_wall = np.zeros(len(points), dtype=bool)
    on_wall[wall] = True
    for label in np.unique(surface.labels[surface.labels != WALL]):
        cap = surface.labels == label
        rim = np.unique(triangles[cap])
        radius[rim[on_wall[rim]]] = np.sqrt(0.5 * np.linalg.norm(area[cap], axis=1).sum() / np.pi)
    shortest = np.linalg.norm(points[wall] - points[np.roll(wall, 1, axis=1)], axis=2).min(axis=1)
    return np.clip(2.0 * np.pi / CIRCUMFERENCE_ELEMENTS * radius, 0.5 * np.median(shortest), size)


def _remesh_with_gmsh(points: np.ndarray, wall: np.ndarray, lengths: np.ndarray, size: float,
                      feature_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Remesh the open wall ``wall`` (k, 3) on ``points`` with gmsh, edge lengths interpolated from
    ``lengths`` (one per point, mm) on the old triangles; new points (p, 3) and triangles (q, 3)."""
    used, local = np.unique(wall, return_inverse=True)
    with gmsh_session() as gmsh:
        gmsh.model.add("wall")
        entity = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, entity, np.arange(1, used.size + 1), points[used].ravel())
        gmsh.model.mesh.addElementsByType(entity, 2, [], local.ravel() + 1)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.MeshSizeMin", float(lengths[used].min()))
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.LcIntegrationPrecision", 1e-3)  # gmsh's 1e-9: seconds on the curves
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        # the old triangles with the lengths at their corners, as the background size field
        view = gmsh.view.add("size")
        corners = points[wall].transpose(0, 2, 1).reshape(len(wall), 9)  # x1 x2 x3 y1 y2 y3 z1 z2 z3
        gmsh.view.addListData(view, "ST", len(wall), np.hstack([corners, lengths[wall]]).ravel())
        field = gmsh.model.mesh.field.add("PostView")
        gmsh.model.mesh.field.setNumber(field, "ViewTag", view)
        gmsh.model.mesh.field.setAsBackgroundMesh(field)
        try:
            # no split by curve angle (pi): only the cuts that make every piece a parametrisable disc
            gmsh.model.mesh.classifySurfaces(np.radians(feature_deg), True, True, np.pi)
            gmsh.model.mesh.createGeometry()
            gmsh.model.mesh.generate(2)
        except Exception as exc:  # gmsh raises a bare Exception with its log line
            raise CarotidError(f"gmsh could not remesh the surface's wall ({exc})") from None
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, nodes = gmsh.model.mesh.getElementsByType(2)
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    return coords.reshape(-1, 3), index[nodes.astype(np.int64)].reshape(-1, 3)


def remesh_wall(surface: Surface, size: float) -> pv.PolyData:
    """Remesh the wall of a labelled surface with gmsh and close it with new planar caps.

    Sharp edges (``FEATURE_DEG``) are kept when gmsh can parametrise the
    pieces between them; otherwise the wall is remeshed without.  The
    result is polished by ``POLISH_ROUNDS`` rounds of the isotropic
    remesher when gmsh leaves an angle under ``POLISH_BELOW_DEG``, by more
    (up to ``POLISH_MAX_ROUNDS``) while an angle stays under
    ``POLISH_TARGET_DEG``.

    Parameters
    ----------
    surface : Surface
        Checked, labelled surface (mm).
    size : float
        Largest edge length of the new triangles (mm); narrower parts get
        shorter edges (:func:`wall_sizes`).

    Returns
    -------
    pyvista.PolyData
        Closed surface with ``CellEntityIds``: the new wall 1 and every cap
        with its old label.

    Raises
    ------
    CarotidError
        If gmsh cannot reparametrise or mesh the wall.
    """
    wall = surface.triangles[surface.labels == WALL]
    lengths = wall_sizes(surface, size)
    try:
        coords, triangles = _remesh_with_gmsh(surface.points, wall, lengths, size, FEATURE_DEG)
    except CarotidError:
        coords, triangles = _remesh_with_gmsh(surface.points, wall, lengths, size, 180.0)
    new_wall = pv.PolyData.from_regular_faces(coords, triangles)
    capped = cap_open_ends(new_wall.clean(tolerance=0.0))
    # cap_open_ends numbers the caps by perimeter: give each the label of the old cap nearest its centre
    labels = np.asarray(capped.cell_data[LABELS])
    planes = cap_planes(surface)
    old = np.array(list(planes))
    centres = np.array([centre for centre, _ in planes.values()])
    triangles, points = capped.regular_faces, np.asarray(capped.points)
    relabel = np.zeros(labels.max() + 1, dtype=np.int32)
    relabel[WALL] = WALL
    for label in np.unique(labels[labels != WALL]):
        centre = points[np.unique(triangles[labels == label])].mean(axis=0)
        relabel[label] = old[np.argmin(np.linalg.norm(centres - centre, axis=1))]
    if len(np.unique(relabel[labels])) != len(planes) + 1:
        raise CarotidError("remeshing the wall changed its open ends: the caps could not be matched")
    capped.cell_data[LABELS] = relabel[labels]
    if triangle_min_angles(points, triangles).min() >= POLISH_BELOW_DEG:
        return capped
    # the polish keeps the sizes gmsh reached: the mean length of the edges at the nearest new vertex
    mean = local_edge_length(points, triangles, neighbours=False)
    nearest = cKDTree(points)

    def reached(x):
        return mean[nearest.query(x)[1]]

    for rounds in range(POLISH_ROUNDS, POLISH_MAX_ROUNDS + 1):
        polished = remesh(capped, reached, iterations=rounds)
        if triangle_min_angles(np.asarray(polished.points), polished.regular_faces).min() >= POLISH_TARGET_DEG:
            break
    return polished
