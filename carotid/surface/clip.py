"""Automatic clipping of the inlet and outlets with flat caps (paper section 3, step 3).

Every open end of the centerline tree gets a plane orthogonal to the smoothed axis, a few radii inside
the end (and, when the image is given, far enough from its border that the cut crosses the vessel, not
the padding of the marching cubes).  The part of the surface beyond the plane and within two local radii
of the axis is cut away (vtkClipPolyData on a scalar that equals the plane distance there, so the cut
follows the plane exactly), the component that holds the bifurcation is kept, and each rim is closed by a
planar fan from its centroid.  Optional flow extensions extrude the rim along the axis, as VMTK does.

Cells are labelled ``CellEntityIds``: wall 1, CCA inlet 2, outlets 3, 4, ... in the order of
``Centerlines.ends()``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv

from carotid.centerline.features import end_skips
from carotid.centerline.model import Centerlines
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.surface.mesh import (WALL, boundary_loops, face_areas, face_normals, from_polydata,
                                  largest_component, to_polydata)


RIM_TOLERANCE = 0.02
"""Largest distance of a cut rim from its plane, in radii: the clip's edge interpolation leaves a few rim points
a hundredth of a millimetre off it, which are moved onto it; a rim further off was cut by the reach, not the
plane."""


@dataclass(frozen=True)
class ClipPlane:
    """One open end: the cut plane and the branch it belongs to.

    Attributes
    ----------
    label : int
        ``CellEntityIds`` of its cap (2 for the inlet, 3, 4, ... for the outlets).
    name : str
        Branch name.
    centre : ndarray, shape (3,)
        Axis point on the plane, mm.
    normal : ndarray, shape (3,)
        Unit normal pointing out of the vessel (along the axis, away from the bifurcation).
    radius : float
        Inscribed radius of the axis at the plane, mm.
    """

    label: int
    name: str
    centre: np.ndarray
    normal: np.ndarray
    radius: float


def _outward_axis(centerlines: Centerlines, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Axis points and radii of a branch ordered from the bifurcation to its open end."""
    b = centerlines.branch(name)
    if name == "CCA":
        return b.points[::-1], b.radii[::-1]
    return b.points, b.radii


def _inside_image(domain: Volume, centre: np.ndarray, normal: np.ndarray, radius: float) -> bool:
    """Whether the disc of ``1.5 radius`` on the plane lies at least one voxel inside the image."""
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    a = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    disc = centre + 1.5 * radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v)
    kji = domain.world_to_index(disc)
    return bool(np.all((kji >= 1.0) & (kji <= np.asarray(domain.array.shape) - 2.0)))


def clip_planes(centerlines: Centerlines, inset_radii: float = 1.5, domain: Volume | None = None) -> list[ClipPlane]:
    """One plane per open end, ``inset_radii`` end radii inside the end along the axis.

    The end radius is at least the branch's median radius (``end_skips``): where the image border cuts a
    vessel, the axis continued to it reads a radius near zero over its last millimetres, and a plane that
    close to the border would cut the tapering marching-cubes closure, not the vessel.

    Parameters
    ----------
    centerlines : Centerlines
        The branch tree; ``ends()`` gives the order (inlet first).
    inset_radii : float
        Distance of the plane from the end of the axis, in end radii (at least the median radius).
    domain : Volume, optional
        The image grid: planes are moved further in until they are clear of its border.

    Returns
    -------
    list of ClipPlane
    """
    planes = []
    for label, (name, _, _, _) in enumerate(centerlines.ends(), start=2):  # loop over branches
        pts, radii = _outward_axis(centerlines, name)
        r_end = end_skips(radii)[1]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        from_end = s[-1] - s
        ok = False
        for depth in inset_radii * r_end + r_end * 0.25 * np.arange(40):  # candidate depths
            if depth >= s[-1] - r_end:
                break
            centre = np.array([np.interp(-depth, -from_end, pts[:, i]) for i in range(3)])
            r = float(np.interp(-depth, -from_end, radii))
            ahead = np.array([np.interp(-(depth - r), -from_end, pts[:, i]) for i in range(3)])
            behind = np.array([np.interp(-(depth + r), -from_end, pts[:, i]) for i in range(3)])
            normal = (ahead - behind) / np.linalg.norm(ahead - behind)
            ok = domain is None or _inside_image(domain, centre, normal, r)
            if ok:
                break
        if not ok:
            raise CarotidError(f"the {name} branch is too short to be clipped {inset_radii} radii inside its end "
                               "and clear of the image border")
        planes.append(ClipPlane(label, name, centre, normal, r))
    return planes


def section_reach(surface: pv.PolyData, plane: ClipPlane, margin: float = 1.25) -> float:
    """How far from the axis the cut of an end reaches (mm): past the vessel's own section in the plane.

    The inscribed radius is a section's smallest half-width; where a vessel leaves the image obliquely or its
    section is elliptic, its rim reaches further.  The plane's intersection with the surface is split into
    closed curves, the one nearest the axis point is the vessel's own, and the reach is ``margin`` times its
    largest distance from the axis, at least two inscribed radii.

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed lumen surface, mm.
    plane : ClipPlane
    margin : float

    Returns
    -------
    float
    """
    section = surface.slice(normal=plane.normal, origin=plane.centre)
    if section.n_points == 0:
        return 2.0 * plane.radius
    pieces = section.connectivity()
    offset = pieces.points - plane.centre
    radial = np.linalg.norm(offset - (offset @ plane.normal)[:, None] * plane.normal, axis=1)
    region = np.asarray(pieces.point_data["RegionId"])
    own = radial[region == region[np.argmin(radial)]]
    return max(2.0 * plane.radius, margin * float(own.max()))


def _cut_scalar(points: np.ndarray, planes: list[ClipPlane], reaches: list[float]) -> np.ndarray:
    """Scalar (n,) that is positive where a point is cut away: beyond a plane and within its reach (mm) of
    its axis."""
    f = np.full(len(points), -np.inf)
    for p, reach in zip(planes, reaches):  # loop over ends
        d = (points - p.centre) @ p.normal
        radial = np.linalg.norm((points - p.centre) - d[:, None] * p.normal, axis=1)
        f = np.maximum(f, np.minimum(d, reach - radial))
    return f


def _zip(ring_a: np.ndarray, par_a: np.ndarray, ring_b: np.ndarray, par_b: np.ndarray) -> np.ndarray:
    """Triangles (len(a) + len(b), 3) between two closed loops of point ids with increasing parameters in
    [0, 1); both loops run the same way round.  Each triangle advances one loop by one point, in the
    order of the parameters (a merge of the two sorted sequences)."""
    na, nb = len(ring_a), len(ring_b)
    when = np.concatenate([np.append(par_a[1:], 1.0 + par_a[0]), np.append(par_b[1:], 1.0 + par_b[0])])
    from_a = np.arange(na + nb) < na
    order = np.argsort(when, kind="stable")
    step_a = from_a[order]
    i = np.cumsum(step_a) - step_a
    k = np.cumsum(~step_a) - ~step_a
    tri_a = np.stack([ring_a[i % na], ring_b[k % nb], ring_a[(i + 1) % na]], axis=1)
    tri_b = np.stack([ring_a[i % na], ring_b[k % nb], ring_b[(k + 1) % nb]], axis=1)
    return np.where(step_a[:, None], tri_a, tri_b)


def planar_cap(points: np.ndarray, loop: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interior points (q, 3) and faces (k, 3) of a planar cap closing a rim; new points are numbered from
    ``len(points)``.

    Concentric loops, scaled copies of the rim towards its centroid at about one rim edge length apart,
    each with ``2 pi`` times its ring number of points, zipped together: near-equilateral triangles and
    valence-6 vertices, for any rim that is star-shaped about its centroid (a vessel cross-section).
    The cap runs the rim against the wall's direction, so the closed surface stays consistently oriented.
    """
    rim = points[loop]
    seg = np.linalg.norm(np.roll(rim, -1, axis=0) - rim, axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    par_rim = s[:-1] / s[-1]
    centre = ((rim + np.roll(rim, -1, axis=0)) * seg[:, None]).sum(0) / (2.0 * s[-1])
    radius = float(np.linalg.norm(rim - centre, axis=1).mean())
    rings = max(1, int(round(radius / seg.mean())))
    closed = np.vstack([rim, rim[:1]])
    new_pts, faces = [centre[None]], []
    n0 = len(points)
    prev_ids, prev_par = np.array([n0]), np.array([0.0])
    next_id = n0 + 1
    for j in range(1, rings + 1):  # loop over rings, a handful
        if j == rings:
            ids, par = loop, par_rim
        else:
            count = max(3, int(round(len(loop) * j / rings)))
            par = (np.arange(count) + 0.5 * (j % 2)) / count
            on_rim = np.stack([np.interp(par * s[-1], s, closed[:, d]) for d in range(3)], axis=1)
            new_pts.append(centre + (j / rings) * (on_rim - centre))
            ids = next_id + np.arange(count)
            next_id += count
        faces.append(_zip(prev_ids, prev_par, ids, par))
        prev_ids, prev_par = ids, par
    faces = np.concatenate(faces)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    allp = np.vstack([points, *new_pts])
    area = np.cross(allp[faces[:, 1]] - allp[faces[:, 0]], allp[faces[:, 2]] - allp[faces[:, 0]]).sum(axis=0)
    if area @ normal < 0:
        faces = faces[:, ::-1]
    return np.vstack(new_pts), faces


def extrude_rim(points: np.ndarray, loop: np.ndarray, normal: np.ndarray, length: float):
    """Extrude a rim along ``normal`` by ``length`` mm; returns ``(points, wall faces, new loop)``."""
    a, b = loop, np.roll(loop, -1)
    edge = float(np.linalg.norm(points[b] - points[a], axis=1).mean())
    layers = max(1, int(round(length / edge)))
    n, k = len(points), len(loop)
    rings = points[loop][None] + (length * np.arange(1, layers + 1) / layers)[:, None, None] * normal
    ids = np.vstack([loop[None], n + np.arange(layers * k).reshape(layers, k)])
    a0, b0 = ids[:-1], np.roll(ids[:-1], -1, axis=1)
    a1, b1 = ids[1:], np.roll(ids[1:], -1, axis=1)
    faces = np.concatenate([np.stack([b0, a0, a1], -1).reshape(-1, 3), np.stack([b0, a1, b1], -1).reshape(-1, 3)])
    return np.vstack([points, rings.reshape(-1, 3)]), faces, ids[-1]


def clip_surface(surface: pv.PolyData, centerlines: Centerlines, *, inset_radii: float = 1.5,
                 flow_extension_radii: float = 0.0, domain: Volume | None = None
                 ) -> tuple[pv.PolyData, list[dict]]:
    """Clip every open end by a plane orthogonal to the axis and close it with a flat, labelled cap.

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed lumen surface in mm (e.g. from ``extract_surface``).
    centerlines : Centerlines
        Its centerlines; the ends are clipped in the order of ``centerlines.ends()``.
    inset_radii : float
        Distance of each plane inside its end, in end radii.
    flow_extension_radii : float
        Length of the cylindrical flow extension at each end, in radii of its cap (0: none).
    domain : Volume, optional
        The image grid, to keep the planes clear of its border.

    Returns
    -------
    surface : pyvista.PolyData
        Closed surface with ``CellEntityIds`` (wall 1, inlet 2, outlets 3, ...).
    caps : list of dict
        Per cap: ``id``, ``name``, ``centre``, ``normal``, ``area``, ``equivalent_radius`` (see ``cap_info``).

    Raises
    ------
    CarotidError
        When a plane does not cut its vessel in exactly one closed rim.
    """
    planes = clip_planes(centerlines, inset_radii, domain)
    points, faces, _ = from_polydata(surface)
    poly = to_polydata(points, faces)
    poly.point_data["cut"] = _cut_scalar(points, planes, [section_reach(poly, p) for p in planes])
    kept = poly.clip_scalar(scalars="cut", invert=True, value=0.0).triangulate().clean(tolerance=1e-9,
                                                                                      absolute=True)
    points, faces, _ = from_polydata(pv.PolyData(kept.points, kept.faces))
    if len(faces) == 0:
        raise CarotidError("clipping removed the whole surface: do the centerlines belong to this surface?")
    points, faces, _ = largest_component(points, faces)
    loops = boundary_loops(faces)
    centroids = np.array([points[lp].mean(0) for lp in loops]).reshape(-1, 3)
    labels = [WALL] * len(faces)
    all_faces = [faces]
    for p in planes:  # loop over ends
        mine = [i for i, c in enumerate(centroids) if np.linalg.norm(c - p.centre) < 1.5 * p.radius]
        if len(mine) != 1 or np.abs((points[loops[mine[0]]] - p.centre) @ p.normal).max() > RIM_TOLERANCE * p.radius:
            raise CarotidError(f"the clipping plane of the {p.name} end does not cut the vessel in one closed rim "
                               "(is the branch too short or bent near its end?)")
        loop = loops[mine[0]]
        points[loop] -= ((points[loop] - p.centre) @ p.normal)[:, None] * p.normal  # onto the plane exactly
        if flow_extension_radii > 0:
            points, ext, loop = extrude_rim(points, loop, p.normal, flow_extension_radii * p.radius)
            all_faces.append(ext)
            labels += [WALL] * len(ext)
        interior, cap = planar_cap(points, loop, p.normal)
        points = np.vstack([points, interior])
        all_faces.append(cap)
        labels += [p.label] * len(cap)
    if len(loops) != len(planes):
        raise CarotidError(f"the clipped surface has {len(loops)} open rims for {len(planes)} vessel ends: "
                           "the surface has holes or a branch the centerlines miss")
    faces = np.concatenate(all_faces)
    labels = np.asarray(labels, np.int32)
    return to_polydata(points, faces, labels), cap_info(to_polydata(points, faces, labels),
                                                         [p.name for p in planes])


def cap_info(surface: pv.PolyData, names: list[str]) -> list[dict]:
    """Geometry of each cap of a labelled surface.

    Parameters
    ----------
    surface : pyvista.PolyData
        Surface with ``CellEntityIds``; caps are labels 2, 3, ...
    names : list of str
        Branch name of cap ``2 + i``.

    Returns
    -------
    list of dict
        ``id``, ``name``, ``centre`` (mm), ``normal`` (unit, outward), ``area`` (mm^2),
        ``equivalent_radius`` (mm, ``sqrt(area / pi)``) and ``planarity`` (largest distance of a cap
        vertex from the cap's plane, mm).
    """
    points, faces, labels = from_polydata(surface)
    out = []
    for i, name in enumerate(names):  # loop over caps
        sel = faces[labels == i + 2]
        area = face_areas(points, sel)
        centre = (points[sel].mean(1) * area[:, None]).sum(0) / area.sum()
        normal = (face_normals(points, sel) * area[:, None]).sum(0)
        normal /= np.linalg.norm(normal)
        planarity = float(np.abs((points[np.unique(sel)] - centre) @ normal).max())
        out.append({"id": i + 2, "name": name, "centre": centre.tolist(), "normal": normal.tolist(),
                    "area": float(area.sum()), "equivalent_radius": float(np.sqrt(area.sum() / np.pi)),
                    "planarity": planarity})
    return out
