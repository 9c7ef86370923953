"""Labelled, capped test surfaces: straight, stenosed or bent tubes, a stenotic nozzle, a Y bifurcation and a
tube with a thin side branch; and the nozzle as a CAD tool exports it.

The surfaces are made with gmsh's OpenCASCADE kernel (a loft of circles or a
union of cylinders) and meshed by gmsh's Frontal-Delaunay surface mesher, so
the triangles are nearly equilateral, like the remeshed lumen surface of the
pipeline.  Every surface is closed, oriented outward, in mm, and carries the
VMTK face labels in the cell array ``CellEntityIds``: wall 1, inlet cap 2,
outlet caps 3, 4, ...  Caps are exactly planar.  The exception,
:func:`faceted_nozzle`, is an unlabelled STL-like triangulation of long
needles, as surfaces from other tools come.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from carotid.mesh.boundary import orient_outward
from carotid.mesh.core import gmsh_session


def stenosis_profile(z: np.ndarray, radius: float, length: float, stenosis: float, width: float) -> np.ndarray:
    """Radius (mm) along a tube with a cosine-shaped stenosis in its middle.

    Parameters
    ----------
    z : ndarray, shape (n,)
        Axial positions in mm, 0 at the inlet.
    radius, length : float
        Normal radius and tube length (mm).
    stenosis : float
        Diameter reduction at the throat, 0 <= stenosis < 1 (0.8: 80 %).
    width : float
        Axial length (mm) of the narrowing.

    Returns
    -------
    ndarray, shape (n,)
    """
    s = np.clip((z - 0.5 * length) / (0.5 * width), -1.0, 1.0)
    return radius * (1.0 - 0.5 * stenosis * (1.0 + np.cos(np.pi * s)))


def _mesh_labelled(gmsh, volume_tag: int, size: float, inlet_axis: np.ndarray) -> pv.PolyData:
    """Mesh the boundary of an OCC volume and return it as a labelled PolyData.

    Planar faces bounded by a single curve are caps (a planar annulus is
    wall); the one whose centre is lowest along ``inlet_axis`` is the inlet
    (2); the other caps are numbered 3, 4, ... by increasing x of their centres.
    """
    gmsh.option.setNumber("Mesh.MeshSizeMax", size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.25 * size)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 16)
    gmsh.option.setNumber("Mesh.Algorithm", 6)
    gmsh.model.mesh.generate(2)
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.zeros(int(node_tags.max()) + 1, dtype=np.int64)
    index[node_tags.astype(np.int64)] = np.arange(node_tags.size)
    points = coords.reshape(-1, 3)
    boundary = gmsh.model.getBoundary([(3, volume_tag)], oriented=False)
    caps = []
    for _, signed in boundary:
        tag = abs(signed)
        if gmsh.model.getType(2, tag) == "Plane" and len(gmsh.model.getBoundary([(2, tag)])) == 1:
            box = np.array(gmsh.model.getBoundingBox(2, tag))
            caps.append((tag, 0.5 * (box[:3] + box[3:])))
    inlet = min(caps, key=lambda cap: float(cap[1] @ inlet_axis))
    outlets = sorted((c for c in caps if c[0] != inlet[0]), key=lambda cap: cap[1][0])
    label_of = {inlet[0]: 2, **{tag: 3 + k for k, (tag, _) in enumerate(outlets)}}
    faces, labels = [], []
    for _, signed in boundary:
        tag = abs(signed)
        _, elem_nodes = gmsh.model.mesh.getElementsByType(2, tag)
        tri = index[elem_nodes.astype(np.int64)].reshape(-1, 3)
        faces.append(tri)
        labels.append(np.full(len(tri), label_of.get(tag, 1)))
    return labelled_surface(points, np.vstack(faces), np.concatenate(labels))


def labelled_surface(points: np.ndarray, triangles: np.ndarray, labels: np.ndarray) -> pv.PolyData:
    """PolyData of ``triangles`` (k, 3) on ``points`` (n, 3) with ``CellEntityIds`` ``labels`` (k,).

    Unused points are dropped and the orientation is made outward (positive
    enclosed volume).
    """
    used, inverse = np.unique(triangles, return_inverse=True)
    pts = np.asarray(points, dtype=float)[used]
    tri = orient_outward(pts, inverse.reshape(-1, 3))
    surface = pv.PolyData.from_regular_faces(pts, tri)
    surface.cell_data["CellEntityIds"] = np.asarray(labels, dtype=np.int32)
    return surface


def labelled_tube(radius: float = 3.0, length: float = 20.0, size: float = 0.5, stenosis: float = 0.0,
                  stenosis_width: float | None = None, bend_deg: float = 0.0, sections: int = 21) -> pv.PolyData:
    """A capped, labelled tube along +z from the origin: straight, stenosed and/or bent.

    Parameters
    ----------
    radius : float
        Radius away from the stenosis (mm).
    length : float
        Length of the axis (mm).
    size : float
        Target triangle edge length (mm); gmsh refines where the curvature is high.
    stenosis : float
        Diameter reduction at mid-length (0.8: 80 %), 0 for none.
    stenosis_width : float, optional
        Axial extent of the narrowing (mm); default ``2 * radius``.
    bend_deg : float
        Total turning angle of the axis (a circular arc in the x-z plane, see
        :func:`bend_z_axis`), 0 for straight.
    sections : int
        Number of circular sections across the stenosis (joined by ruled, conical bands).

    Returns
    -------
    pyvista.PolyData
        Closed, outward-oriented triangles with ``CellEntityIds``: wall 1, inlet 2 (z = 0), outlet 3.
    """
    width = 2.0 * radius if stenosis_width is None else stenosis_width
    z = np.array([0.0, length])
    if stenosis > 0:
        z = np.r_[0.0, np.linspace(0.5 * (length - width), 0.5 * (length + width), sections), length]
    radii = stenosis_profile(z, radius, length, stenosis, width)
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        wires = [occ.addCurveLoop([occ.addCircle(0.0, 0.0, zk, rk)]) for zk, rk in zip(z, radii)]
        dimtags = occ.addThruSections(wires, makeSolid=True, makeRuled=True)
        occ.synchronize()
        volume = [tag for dim, tag in dimtags if dim == 3][0]
        surface = _mesh_labelled(gmsh, volume, size, np.array([0.0, 0.0, 1.0]))
    if bend_deg > 0:
        surface.points = bend_z_axis(np.asarray(surface.points), length / np.radians(bend_deg))
    return surface


def stenotic_nozzle(radius: float = 6.0, throat_radius: float = 2.0, cone_deg: float = 20.0,
                    throat_length: float = 40.0, inlet_length: float = 10.0, outlet_length: float = 30.0,
                    size: float = 1.0) -> pv.PolyData:
    """The stenotic nozzle (FDA benchmark shape): pipe, conical contraction, throat, sudden expansion, pipe.

    Along +z from the inlet at z = 0: a pipe of ``radius`` and ``inlet_length``,
    a cone of included angle ``cone_deg`` down to ``throat_radius`` (length
    ``(radius - throat_radius) / tan(cone_deg / 2)``, 22.7 mm by default), the
    throat of ``throat_length``, then a sudden expansion (a flat annulus, labelled
    wall) back to ``radius`` for ``outlet_length``.  Lengths in mm.

    Returns
    -------
    pyvista.PolyData
        Closed, outward-oriented triangles with ``CellEntityIds``: wall 1 (with
        the annulus), inlet 2 (z = 0), outlet 3.
    """
    cone = (radius - throat_radius) / np.tan(np.radians(0.5 * cone_deg))
    z = np.cumsum([0.0, inlet_length, cone, throat_length])
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        parts = [occ.addCylinder(0, 0, z[0], 0, 0, inlet_length, radius),
                 occ.addCone(0, 0, z[1], 0, 0, cone, radius, throat_radius),
                 occ.addCylinder(0, 0, z[2], 0, 0, throat_length, throat_radius),
                 occ.addCylinder(0, 0, z[3], 0, 0, outlet_length, radius)]
        fused, _ = occ.fuse([(3, parts[0])], [(3, tag) for tag in parts[1:]])
        occ.synchronize()
        volume = [tag for dim, tag in fused if dim == 3][0]
        return _mesh_labelled(gmsh, volume, size, np.array([0.0, 0.0, 1.0]))


def side_branch(radius: float = 3.0, outlet_radius: float = 2.7, length: float = 20.0, branch_radius: float = 0.6,
                branch_length: float = 8.0, angle_deg: float = 70.0, size: float = 0.6) -> pv.PolyData:
    """A slightly tapered tube along +z from the origin with a thin side branch leaving its middle.

    The parent is a cone from ``radius`` at z = 0 to ``outlet_radius`` at
    z = ``length`` (so the three caps differ in area, as the flat-cap
    labelling ranks them); the branch cylinder starts on the parent's axis
    at mid-length, leaves at ``angle_deg`` from +z towards +x and ends
    ``branch_length`` beyond the parent's wall along its axis.  Lengths in mm.

    Returns
    -------
    pyvista.PolyData
        Closed, outward-oriented triangles with ``CellEntityIds``: wall 1, inlet 2 (z = 0), outlet 3
        (the parent's end, z = ``length``), outlet 4 (the branch's end).
    """
    a = np.radians(angle_deg)
    reach = 0.5 * (radius + outlet_radius) / np.sin(a) + branch_length  # axis to the branch's end
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        parent = occ.addCone(0, 0, 0, 0, 0, length, radius, outlet_radius)
        branch = occ.addCylinder(0, 0, 0.5 * length, reach * np.sin(a), 0.0, reach * np.cos(a), branch_radius)
        fused, _ = occ.fuse([(3, parent)], [(3, branch)])
        occ.synchronize()
        volume = [tag for dim, tag in fused if dim == 3][0]
        return _mesh_labelled(gmsh, volume, size, np.array([0.0, 0.0, 1.0]))


def faceted_nozzle(segments: int = 32, radius: float = 6.0, throat_radius: float = 2.0, cone_deg: float = 20.0,
                   throat_length: float = 40.0, inlet_length: float = 10.0, outlet_length: float = 30.0
                   ) -> pv.PolyData:
    """The stenotic nozzle of :func:`stenotic_nozzle` triangulated the way CAD tools export an STL.

    A ring of ``segments`` vertices sits at every corner of the profile only
    (the inlet, the start and end of the cone, the two rims of the sudden
    expansion's annulus, the outlet); the band between two rings is cut into
    ``2 segments`` long triangles (the throat is one band of 40 mm needles)
    and each end cap is a fan around its centre.  No labels.

    Returns
    -------
    pyvista.PolyData
        Closed, outward-oriented triangles (mm), along +z from the inlet at z = 0.
    """
    cone = (radius - throat_radius) / np.tan(np.radians(0.5 * cone_deg))
    step = inlet_length + cone + throat_length
    ring_z = np.array([0.0, inlet_length, inlet_length + cone, step, step, step + outlet_length])
    ring_r = np.array([radius, radius, throat_radius, throat_radius, radius, radius])
    theta = 2.0 * np.pi * np.arange(segments) / segments
    rings = np.stack([ring_r[:, None] * np.cos(theta), ring_r[:, None] * np.sin(theta),
                      np.repeat(ring_z[:, None], segments, axis=1)], axis=2).reshape(-1, 3)
    points = np.vstack([rings, [[0.0, 0.0, 0.0], [0.0, 0.0, ring_z[-1]]]])
    j = np.arange(segments)
    a = (np.arange(len(ring_z) - 1)[:, None] * segments + j).ravel()  # vertex j of every ring but the last
    nxt = a - a % segments + (a + 1) % segments
    bands = np.vstack([np.c_[a, nxt, nxt + segments], np.c_[a, nxt + segments, a + segments]])
    last = (len(ring_z) - 1) * segments
    caps = np.vstack([np.c_[j, (j + 1) % segments, np.full(segments, len(points) - 2)],
                      np.c_[last + j, last + (j + 1) % segments, np.full(segments, len(points) - 1)]])
    triangles = np.vstack([bands, caps])
    return pv.PolyData.from_regular_faces(points, orient_outward(points, triangles))


def bend_z_axis(points: np.ndarray, bend_radius: float) -> np.ndarray:
    """Bend the z axis into a circular arc of radius ``bend_radius`` (mm) in the x-z plane.

    A point at height z and offset (x, y) from the axis goes to
    ``c(z) + x n(z) + y e_y`` with ``c`` the arc through the origin tangent to
    +z, turning towards +x, and ``n`` its unit normal pointing away from the
    centre of curvature; planes z = const stay planar.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    bend_radius : float

    Returns
    -------
    ndarray, shape (n, 3)
    """
    theta = points[:, 2] / bend_radius
    centre = np.c_[bend_radius * (1.0 - np.cos(theta)), np.zeros_like(theta), bend_radius * np.sin(theta)]
    normal = np.c_[-np.cos(theta), np.zeros_like(theta), np.sin(theta)]
    return centre - points[:, :1] * normal + points[:, 1:2] * np.array([0.0, 1.0, 0.0])


def labelled_bifurcation(radius: float = 3.0, branch_radii: tuple[float, float] = (2.2, 1.7),
                         lengths: tuple[float, float, float] = (15.0, 15.0, 12.0),
                         angles_deg: tuple[float, float] = (25.0, 30.0), size: float = 0.5,
                         stenosis: float = 0.0, sections: int = 21) -> pv.PolyData:
    """A capped, labelled Y bifurcation: a common trunk along +z ending at the origin and two branches.

    The trunk (radius ``radius``, from z = -lengths[0]) and a sphere of the same
    radius at the origin are united with two cylinders leaving the origin at
    ``angles_deg`` from +z towards +x (first branch) and -x (second branch).
    With ``stenosis`` (an area reduction, 0.7: 70 %) the first branch narrows at
    mid-length with the cosine profile of :func:`stenosis_profile` over two
    diameters (a smooth loft through ``sections`` circles).

    Returns
    -------
    pyvista.PolyData
        Closed, outward-oriented triangles with ``CellEntityIds``: wall 1, inlet 2 (trunk),
        outlet 3 (branch towards +x), outlet 4 (towards -x).
    """
    with gmsh_session() as gmsh:
        occ = gmsh.model.occ
        trunk = occ.addCylinder(0, 0, -lengths[0], 0, 0, lengths[0], radius)
        ball = occ.addSphere(0, 0, 0, radius)
        branches = []
        for r, length, angle, side in zip(branch_radii, lengths[1:], angles_deg, (1.0, -1.0)):
            a = np.radians(angle)
            axis = np.array([side * np.sin(a), 0.0, np.cos(a)])
            if side > 0 and stenosis > 0:
                width = 4.0 * r
                s = np.r_[0.0, np.linspace(0.5 * (length - width), 0.5 * (length + width), sections), length]
                radii = stenosis_profile(s, r, length, 1.0 - np.sqrt(1.0 - stenosis), width)
                wires = [occ.addCurveLoop([occ.addCircle(0.0, 0.0, sk, rk)]) for sk, rk in zip(s, radii)]
                loft = [(dim, tag) for dim, tag in occ.addThruSections(wires, makeSolid=True, makeRuled=False)
                        if dim == 3]
                occ.rotate(loft, 0, 0, 0, 0, 1, 0, a)  # +z onto the branch axis (towards +x)
                branches.append(loft[0][1])
            else:
                branches.append(occ.addCylinder(0, 0, 0, *(length * axis), r))
        fused, _ = occ.fuse([(3, trunk)], [(3, ball)] + [(3, b) for b in branches])
        occ.synchronize()
        volume = [tag for dim, tag in fused if dim == 3][0]
        return _mesh_labelled(gmsh, volume, size, np.array([0.0, 0.0, 1.0]))
