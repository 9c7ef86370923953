"""Repair of a finished lumen surface from another tool before volume meshing.

Surfaces exported by other tools can be closed and labelled yet unusable for
a boundary layer: needle triangles with angles near 0 degrees (the inner
layer surface copies them into flat tetrahedra) and a few self-intersecting
triangles (prisms on them invert at any thickness).  Such a surface is
remeshed in place: its wall is given to gmsh as one discrete surface,
reparametrised (``classifySurfaces`` + ``createGeometry``) and meshed again
with the Frontal-Delaunay algorithm, so every new vertex lies on the old
wall and the rims are resampled along the old rim polylines (in the cap
planes); each rim is then closed by a new planar cap
(:func:`carotid.mesh.boundary.cap_open_ends`) that keeps the label of the
old cap in its plane.  The extent is kept; the volume changes only by the
chords of the new triangles across the old ones (reported).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError
from carotid.mesh.boundary import LABELS, WALL, Surface, cap_open_ends, cap_planes
from carotid.mesh.core import gmsh_session
from carotid.mesh.layers import triangle_min_angles
from carotid.surface.quality import self_intersections


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


def remesh_wall(surface: Surface, size: float) -> pv.PolyData:
    """Remesh the wall of a labelled surface with gmsh and close it with new planar caps.

    Parameters
    ----------
    surface : Surface
        Checked, labelled surface (mm).
    size : float
        Target edge length of the new triangles (mm).

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
    used, local = np.unique(wall, return_inverse=True)
    with gmsh_session() as gmsh:
        gmsh.model.add("wall")
        entity = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, entity, np.arange(1, used.size + 1), surface.points[used].ravel())
        gmsh.model.mesh.addElementsByType(entity, 2, [], local.ravel() + 1)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        try:
            # no split by angle (pi): only the cuts that make every piece a parametrisable disc
            gmsh.model.mesh.classifySurfaces(np.pi, True, True, np.pi)
            gmsh.model.mesh.createGeometry()
            gmsh.model.mesh.generate(2)
        except Exception as exc:  # gmsh raises a bare Exception with its log line
            raise CarotidError(f"gmsh could not remesh the surface's wall ({exc})") from None
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, nodes = gmsh.model.mesh.getElementsByType(2)
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    new_wall = pv.PolyData.from_regular_faces(coords.reshape(-1, 3), index[nodes.astype(np.int64)].reshape(-1, 3))
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
    return capped
