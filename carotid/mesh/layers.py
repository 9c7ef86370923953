"""Boundary layer of prisms under the wall, each prism split into three tetrahedra (paper section 3).

The paper builds N sub-layers of prisms under every wall triangle, with the
height ratio f between neighbouring sub-layers, and splits every prism into
three tetrahedra.  No maintained library extrudes a layer from a labelled
surface with the three properties needed here (in-plane extrusion at the
caps, local thickness reduction until every tetrahedron is positive, and the
index-based prism split that makes the mesh conforming with the core mesher's
tetrahedra), so this module is written by hand; it is vectorised over
vertices, faces and prisms.

Construction
------------
* Inward directions: area-weighted vertex normals of the wall, smoothed by a
  few Laplacian iterations and kept within ``MAX_LEAN_DEG`` of the normal;
  at a cap rim they are projected onto the cap plane, so the layer
  continues inside the cap and the cap stays planar.  A direction must see
  every incident face (else that face's first prism is inverted at any
  thickness): it is pushed towards the faces it fails, and where that does
  not converge (a crease) it becomes the direction that sees them best, the
  axis of the smallest cone around their normals (``_most_visible``).
* Thickness per wall vertex: absolute, or ``thickness_ratio`` times the
  local radius, the radius of the largest inscribed ball touching the
  vertex (shrinking-ball medial-axis estimate on the wall vertices, along
  the wall normals: a ball centred along a leaning direction is not tangent
  to the wall and shrinks on the wall beside its vertex).  It is
  capped at ``max_fraction`` of that radius (with a warning when an absolute
  thickness had to be reduced), graded, and reduced locally until every
  tetrahedron of every prism column has a positive volume.
* Sub-layer k (0 at the wall) spans the fractions
  ``(f**k - 1) / (f**N - 1) .. (f**(k+1) - 1) / (f**N - 1)`` of the
  thickness, so heights grow by f away from the wall.
* Prism split: Dompierre et al. (1999), "How to subdivide pyramids, prisms
  and hexahedra into tetrahedra": every quadrilateral face is cut along the
  diagonal from its vertex with the smallest global index, which both prisms
  sharing the face see alike; the mesh is therefore conforming.
* The inner cap polygons (inside the innermost rim) keep the cap's
  triangulation; the cap's interior vertices follow the rim by a discrete
  harmonic extension of its displacement (checked not to fold).

Defaults: the paper fixes N = 10 but not f; f = 1.2 keeps the growth
between neighbouring elements at the usual <= 1.2-1.3, and a thickness of
0.3 x the local radius then gives a first layer of 0.3 r / 26 (~0.035 mm in
a 3 mm common carotid) and leaves a core of radius 0.7 r.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from carotid.errors import CarotidError
from carotid.mesh.boundary import WALL, Surface, cap_planes, edge_faces, triangulate_loop

# Dompierre et al. (1999), table 3: vertex permutations of a prism (0, 1, 2 bottom; i + 3 above i)
# that bring each vertex to position 0.
_PRISM_ROTATIONS = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                             [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])
_SPLIT_15 = np.array([[0, 1, 2, 5], [0, 1, 5, 4], [0, 4, 5, 3]])  # diagonal 1-5 on the face 1-2-5-4
_SPLIT_24 = np.array([[0, 1, 2, 4], [0, 4, 2, 5], [0, 4, 5, 3]])  # diagonal 2-4

MAX_LEAN_DEG = 30.0
"""Largest angle (deg) between an extrusion direction and its vertex's wall normal.  The paper asks for the
short edges of the layer's tetrahedra along the wall normal; a column leaning by 30 degrees still gains 87 %
of its length in depth.  Smoothing alone leans the columns beside a sharp flow divider by up to 40
degrees, where an edge walk from the wall no longer recognises them (``quality.walk_layers`` accepts 36.9)."""


@dataclass(frozen=True)
class BoundaryLayer:
    """The prism layer as tetrahedra and the surface it leaves for the core.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
        All vertices so far (mm): the input surface vertices (cap interior
        vertices moved onto the inner cap), then the sub-layer copies of the
        wall vertices, then the interior points of any re-triangulated
        inner cap (whose original interior vertices are then unused).
    tets : ndarray, shape (t, 4)
        Positively oriented layer tetrahedra.
    columns : ndarray, shape (N + 1, w)
        Vertex index of wall vertex j at depth level k (row 0: the wall).
    wall_vertices : ndarray, shape (w,)
        Input indices of the wall vertices (``columns[0]``).
    directions : ndarray, shape (w, 3)
        Unit inward extrusion directions.
    thickness : ndarray, shape (w,)
        Total layer thickness (mm) at each wall vertex after reductions.
    requested : ndarray, shape (w,)
        Thickness (mm) asked for at each wall vertex.
    fractions : ndarray, shape (N + 1,)
        Depth of each level as a fraction of the thickness.
    prisms : ndarray, shape (p, 6)
        The prisms before the split, sub-layer-major (``p = N m`` for m
        wall triangles): bottom triangle 0, 1, 2 (the outer level, towards
        the wall) and top 3, 4, 5, vertex i + 3 above i; ``tets[3 j: 3 j + 3]``
        split prism j.
    inner_triangles : ndarray, shape (s, 3)
        Closed, outward-oriented surface bounding the core: the innermost
        wall copy and the inner cap polygons.
    inner_labels : ndarray, shape (s,)
        Label of the input face each inner triangle comes from.
    local_radius : ndarray, shape (w,)
        Inscribed-ball radius (mm) at each wall vertex.
    """

    points: np.ndarray
    tets: np.ndarray
    prisms: np.ndarray
    columns: np.ndarray
    wall_vertices: np.ndarray
    directions: np.ndarray
    thickness: np.ndarray
    requested: np.ndarray
    fractions: np.ndarray
    inner_triangles: np.ndarray
    inner_labels: np.ndarray
    local_radius: np.ndarray


def level_fractions(layers: int, ratio: float) -> np.ndarray:
    """Depth of the N + 1 level surfaces as fractions of the total thickness, shape (N + 1,)."""
    k = np.arange(layers + 1, dtype=float)
    if abs(ratio - 1.0) < 1e-12:
        return k / layers
    return (ratio**k - 1.0) / (ratio**layers - 1.0)


def split_prisms(prisms: np.ndarray) -> np.ndarray:
    """Split prisms into three tetrahedra each by the smallest-global-index rule.

    Parameters
    ----------
    prisms : ndarray, shape (p, 6)
        Vertex indices: bottom triangle 0, 1, 2 and top 3, 4, 5 (i + 3 above i),
        oriented so that the tetrahedron (0, 1, 2, 3) is positive.

    Returns
    -------
    ndarray, shape (3p, 4)
        Tetrahedra, prism-major.  Every quadrilateral face is split along the
        diagonal from its smallest vertex index, whichever prism it is seen from.
    """
    rotated = np.take_along_axis(prisms, _PRISM_ROTATIONS[np.argmin(prisms, axis=1)], axis=1)
    use_15 = np.minimum(rotated[:, 1], rotated[:, 5]) < np.minimum(rotated[:, 2], rotated[:, 4])
    local = np.where(use_15[:, None, None], _SPLIT_15[None], _SPLIT_24[None])
    return np.take_along_axis(rotated[:, None, :], local, axis=2).reshape(-1, 4)


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (mm^3) of tetrahedra, positive for (a, b, c, d) with d above abc, shape (t,)."""
    a = points[tets[:, 0]]
    return np.einsum("ij,ij->i", np.cross(points[tets[:, 1]] - a, points[tets[:, 2]] - a),
                     points[tets[:, 3]] - a) / 6.0


def _adjacency(triangles: np.ndarray, n: int) -> sparse.csr_matrix:
    """Symmetric 0/1 vertex adjacency (n, n) of a triangle mesh."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    adj = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = ((adj + adj.T) > 0).astype(float)
    return adj.tocsr()


def _face_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area vectors (twice the area times the unit normal), shape (m, 3)."""
    a = points[triangles[:, 0]]
    return np.cross(points[triangles[:, 1]] - a, points[triangles[:, 2]] - a)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def inscribed_radius(points: np.ndarray, inward: np.ndarray, iterations: int = 40,
                     min_angle_deg: float = 30.0) -> np.ndarray:
    """Radius of the largest ball inside the surface that touches each point (shrinking-ball method).

    Ma, Bae & Marchetti (2012), "3D medial axis point approximation using
    nearest neighbors and the normal field": a ball tangent at p with centre
    p + r n, first as large as the surface, is shrunk to pass through the
    nearest sample q inside it until none is.  A q on the same side as p
    (its inward normal within 90 degrees of p's) that the shrunk ball would
    see within ``min_angle_deg`` of p from its centre is a neighbour of p
    (the ball only pokes out because the normal is slightly off), not the
    opposite wall, and stops the shrinking (the paper's denoising rule).
    The normal test matters while the ball is still large: a sample of the
    opposite wall far along the axis is then also seen at a small angle
    (in a 4 mm throat 30 mm before a sudden expansion, the first ball of a
    160 mm nozzle met the expansion's rim at 29 degrees, and the radius
    stayed 160 mm).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Surface samples (mm).
    inward : ndarray, shape (n, 3)
        Unit inward normals.
    iterations : int
        Maximum number of shrinking steps.
    min_angle_deg : float
        Separation angle below which a same-side sample does not shrink the ball.

    Returns
    -------
    ndarray, shape (n,)
        Radii in mm.
    """
    tree = cKDTree(points)
    radius = np.full(len(points), float(np.ptp(points, axis=0).max()))
    active = np.arange(len(points))
    cos_min = np.cos(np.radians(min_angle_deg))
    for _ in range(iterations):
        p, d, r = points[active], inward[active], radius[active]
        dist, nearest = tree.query(p + r[:, None] * d)
        q = points[nearest]
        along = np.einsum("ij,ij->i", q - p, d)
        new_r = np.einsum("ij,ij->i", p - q, p - q) / (2.0 * np.maximum(along, 1e-300))
        centre = p + new_r[:, None] * d
        cos_sep = np.einsum("ij,ij->i", _unit(p - centre), _unit(q - centre))
        neighbour = (cos_sep >= cos_min) & (np.einsum("ij,ij->i", inward[nearest], d) > 0.0)
        shrink = (dist < r * (1.0 - 1e-9)) & (along > 1e-12) & (new_r < r * (1.0 - 1e-9)) & ~neighbour
        radius[active[shrink]] = new_r[shrink]
        active = active[shrink]
        if active.size == 0:
            break
    return radius


def _inward_normals(points, wall_tris, local_wall, n_wall):
    """Unit inward wall normals at the wall vertices (area-weighted means of the incident face normals)."""
    area = _face_normals(points, wall_tris)
    normals = np.zeros((n_wall, 3))
    for k in range(3):
        np.add.at(normals, local_wall[:, k], area)
    return -_unit(normals)


def _directions(points, wall_tris, inward, local_wall, rim_cap_normal, adjacency, smoothing,
                max_lean_deg=MAX_LEAN_DEG, visibility_deg=5.0, repairs=100):
    """Unit inward directions at the wall vertices: smoothed, near the normal, in-plane at cap rims, valid.

    The wall normals are smoothed by ``smoothing`` Laplacian iterations, so
    that neighbouring columns stay nearly parallel where the wall curves;
    a smoothed direction that leans more than ``max_lean_deg`` from its own
    vertex's normal is turned back onto that cone.  A direction must then
    point into every incident wall face's inner side by at least
    ``visibility_deg`` (else the first prism of that face is inverted at any
    thickness); offending directions are pushed along the inward normals of
    the faces they fail, a few vectorised rounds.
    """
    unit_face = _unit(_face_normals(points, wall_tris))

    def project(d):
        return _unit(d - np.einsum("ij,ij->i", d, rim_cap_normal)[:, None] * rim_cap_normal)

    normal = project(inward)
    directions = normal
    for _ in range(smoothing):
        directions = project(directions + adjacency @ directions)
    directions = project(_within_cone(directions, normal, max_lean_deg))
    margin = np.sin(np.radians(visibility_deg))
    for _ in range(repairs):
        dots = np.einsum("fki,fi->fk", directions[local_wall], unit_face)  # d . outward face normal
        bad = dots > -margin
        if not bad.any():
            return directions
        face = np.broadcast_to(np.arange(len(wall_tris))[:, None], bad.shape)[bad]
        push = np.stack([np.bincount(local_wall[bad], weights=-unit_face[face, k], minlength=len(inward))
                         for k in range(3)], axis=1)
        directions = project(directions + 0.5 * push)
    # Where the pushes did not converge, the direction that sees its incident faces best (at a crease, one
    # that sees them all may exist only within a few degrees).
    dots = np.einsum("fki,fi->fk", directions[local_wall], unit_face)
    stuck = np.unique(local_wall[dots > -margin])
    if stuck.size:
        incident = _incident_faces(local_wall, len(inward), stuck)
        best, seen = _most_visible(-unit_face[incident], rim_cap_normal[stuck])
        now = np.einsum("vmi,vi->vm", -unit_face[incident], directions[stuck]).min(axis=1)
        better = seen > now
        directions[stuck[better]] = best[better]
    return directions


def _incident_faces(triangles: np.ndarray, n: int, vertices: np.ndarray) -> np.ndarray:
    """Faces around each of ``vertices`` (v, m): indices into ``triangles``, rows padded with their first face."""
    faces = np.repeat(np.arange(len(triangles)), 3)
    incidence = sparse.csr_matrix((np.ones(triangles.size), (triangles.ravel(), faces)), shape=(n, len(triangles)))
    start, count = incidence.indptr[vertices], np.diff(incidence.indptr)[vertices]
    slot = np.arange(count.max())[None]
    return incidence.indices[np.where(slot < count[:, None], start[:, None] + slot, start[:, None])]


def _most_visible(inward: np.ndarray, plane_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unit direction that maximises its smallest dot product with a few unit vectors, and that product.

    On the sphere the maximin direction is the axis of the smallest cone around the vectors, fixed by one,
    two or three of them: a vector, the bisector of two, or the direction equidistant from three (the normal
    of the plane through their tips).  Every such candidate is scored and the best kept; exact, and
    vectorised over the vertices (a vertex has some ten faces: a few hundred candidates).

    Parameters
    ----------
    inward : ndarray, shape (v, m, 3)
        Unit inward normals of the faces around each vertex.
    plane_normal : ndarray, shape (v, 3)
        Unit normal of the plane the direction must lie in (a cap's, at its rim), or zero.

    Returns
    -------
    direction : ndarray, shape (v, 3)
    visibility : ndarray, shape (v,)
        Smallest dot product of the direction with the vectors (> 0: it sees every face).
    """
    p = inward - np.einsum("vmi,vi->vm", inward, plane_normal)[..., None] * plane_normal[:, None]
    m = p.shape[1]
    i, j = np.triu_indices(m, 1)
    a, b, c = np.array([t for t in combinations(range(m), 3)] or [(0, 0, 0)]).T
    across = np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a])
    across *= np.sign(np.einsum("vti,vti->vt", across, p[:, a]))[..., None]
    candidates = np.concatenate([p, p[:, i] + p[:, j], across], axis=1)
    candidates -= np.einsum("vci,vi->vc", candidates, plane_normal)[..., None] * plane_normal[:, None]
    length = np.linalg.norm(candidates, axis=2)
    candidates = candidates / np.maximum(length, 1e-300)[..., None]
    seen = np.where(length > 1e-9, np.einsum("vci,vmi->vcm", candidates, p).min(axis=2), -np.inf)
    best = np.argmax(seen, axis=1)
    rows = np.arange(len(p))
    return candidates[rows, best], seen[rows, best]


def _within_cone(directions, axes, max_angle_deg):
    """Unit ``directions`` (n, 3) turned towards their unit ``axes`` (n, 3) where they lean further than
    ``max_angle_deg``, onto the cone of that half-angle in the plane of the two."""
    cos_lean = np.einsum("ij,ij->i", directions, axes)
    limit = np.radians(max_angle_deg)
    across = _unit(directions - cos_lean[:, None] * axes)
    onto = np.cos(limit) * axes + np.sin(limit) * across
    return np.where((cos_lean < np.cos(limit))[:, None], onto, directions)


def _cap_follow(points, surface, wall_index, moved_wall):
    """Points with the cap interior vertices moved by the harmonic extension of the rim displacement.

    ``moved_wall`` (w, 3) are the new positions of the wall vertices; only the
    rim ones are used.
    """
    cap = surface.labels != WALL
    cap_vertices = np.unique(surface.triangles[cap])
    interior = cap_vertices[wall_index[cap_vertices] < 0]
    if interior.size == 0:
        return points
    n = len(points)
    adj = _adjacency(surface.triangles[cap], n)
    degree = np.asarray(adj.sum(axis=1)).ravel()
    lap = sparse.diags(degree) - adj
    rim = cap_vertices[wall_index[cap_vertices] >= 0]
    shift = np.zeros((n, 3))
    shift[rim] = moved_wall[wall_index[rim]] - points[rim]
    rhs = -(lap[interior][:, rim] @ shift[rim])
    shift_interior = spsolve(lap[interior][:, interior].tocsc(), rhs)
    out = points.copy()
    out[interior] += np.asarray(shift_interior).reshape(-1, 3)
    return out


def triangle_min_angles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Smallest angle (degrees) of each triangle, shape (m,)."""
    p = points[triangles]
    e = np.roll(p, -1, axis=1) - p  # edge i: vertex i -> i + 1
    lengths = np.linalg.norm(e, axis=2)
    cos = -np.einsum("mij,mij->mi", e, np.roll(e, 1, axis=1)) / np.maximum(lengths * np.roll(lengths, 1, axis=1),
                                                                          1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).min(axis=1)


def _inner_caps(points, surface, wall_index, innermost, min_angle=15.0):
    """Triangles of the inner cap polygons, with new points where a cap had to be re-triangulated.

    Each cap keeps its own triangles on the moved vertices (rim vertices
    replaced by their innermost copies) unless one of them folds (the
    harmonic extension is not guaranteed to be injective) or gets an angle
    below ``min_angle`` degrees (a flat cap triangle makes a flat core
    tetrahedron on it); that cap's inner rim is then triangulated afresh
    (:func:`carotid.mesh.boundary.triangulate_loop`, Delaunay, so no flat
    ears) and its original interior vertices are left unused.

    Returns
    -------
    points : ndarray, shape (n', 3)
    triangles : ndarray, shape (c, 3)
        Oriented like the input caps (outward).
    labels : ndarray, shape (c,)
    """
    tris, labels = surface.triangles, surface.labels
    out_tris, out_labels = [], []
    for label, (_, normal) in cap_planes(surface).items():
        cap = tris[labels == label]
        rim = wall_index[cap] >= 0
        inner = np.where(rim, innermost[np.maximum(wall_index[cap], 0)], cap)
        if np.any(_face_normals(points, inner) @ normal <= 0) or triangle_min_angles(points, inner).min() < min_angle:
            edges, key, counts = edge_faces(inner)
            new_points, inner = triangulate_loop(points, edges[counts[key] == 1])
            points = np.vstack([points, new_points])
            flip = _face_normals(points, inner) @ normal < 0
            inner = np.where(flip[:, None], inner[:, ::-1], inner)
            if np.any(np.abs(_face_normals(points, inner) @ normal) <= 0):
                raise CarotidError(f"cannot mesh the inner part of cap {label}: use a thinner layer")
        out_tris.append(inner)
        out_labels.append(np.full(len(inner), label, dtype=np.int32))
    if not out_tris:
        return points, np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int32)
    return points, np.vstack(out_tris), np.concatenate(out_labels)


def build_layers(surface: Surface, *, layers: int = 10, ratio: float = 1.2, thickness: float | None = None,
                 thickness_ratio: float | None = 0.3, max_fraction: float = 0.5, smoothing: int = 10,
                 grading: int = 3, max_reductions: int = 40, scale: np.ndarray | None = None) -> BoundaryLayer:
    """Extrude N sub-layers of prisms inward from the wall and split them into tetrahedra.

    Parameters
    ----------
    surface : Surface
        Checked, outward-oriented labelled surface (see :func:`carotid.mesh.boundary.check_surface`).
    layers : int
        Number of sub-layers N.
    ratio : float
        Height ratio f between a sub-layer and the next one outward (>= 1:
        the thinnest at the wall).
    thickness : float, optional
        Total thickness in mm (overrides ``thickness_ratio``).
    thickness_ratio : float, optional
        Total thickness as a fraction of the local radius (inscribed ball).
    max_fraction : float
        The thickness never exceeds this fraction of the local radius, so
        layers from facing walls cannot meet.
    smoothing : int
        Laplacian smoothing iterations of the extrusion directions.
    grading : int
        Iterations of ``t = min(t, neighbourhood mean of t)`` that spread a
        local reduction over a few rings of neighbours.
    max_reductions : int
        Rounds of local thickness reduction before giving up.
    scale : ndarray, shape (w,), optional
        Factor (<= 1) on the thickness of each wall vertex (in
        ``np.unique`` order of the wall vertices), applied before grading;
        the mesher thins the layer where the core it leaves is too thin.

    Returns
    -------
    BoundaryLayer

    Raises
    ------
    CarotidError
        Bad parameters, or no valid layer even after local reductions.
    """
    if layers < 1 or ratio < 1.0 or (thickness is None and thickness_ratio is None):
        raise CarotidError("need layers >= 1, ratio >= 1 and a thickness or a thickness ratio")
    if thickness is not None and thickness <= 0 or thickness_ratio is not None and thickness_ratio <= 0:
        raise CarotidError("the layer thickness must be positive")
    points, tris, labels = surface.points, surface.triangles, surface.labels
    n = len(points)
    wall_tris = tris[labels == WALL]
    wall = np.unique(wall_tris)
    wall_index = np.full(n, -1)
    wall_index[wall] = np.arange(wall.size)
    # rim vertices: the cap normal they must stay perpendicular to (zero elsewhere)
    rim_normal = np.zeros((wall.size, 3))
    for label, (_, normal) in cap_planes(surface).items():
        cap_vertices = np.unique(tris[labels == label])
        on_rim = wall_index[cap_vertices]
        rim_normal[on_rim[on_rim >= 0]] = normal
    local_wall = wall_index[wall_tris]
    adjacency = _adjacency(local_wall, wall.size)
    inward = _inward_normals(points, wall_tris, local_wall, wall.size)
    directions = _directions(points, wall_tris, inward, local_wall, rim_normal, adjacency, smoothing)
    radius = inscribed_radius(points[wall], inward)
    requested = np.full(wall.size, thickness) if thickness is not None else thickness_ratio * radius
    limit = max_fraction * radius
    if thickness is not None and np.any(requested > limit):
        warnings.warn(f"boundary layer reduced where it is thicker than {max_fraction:g} x the local radius "
                      f"({int(np.sum(requested > limit))} of {wall.size} wall vertices, down to "
                      f"{limit.min():.3g} mm)", stacklevel=2)
    total = np.minimum(requested, limit) * (1.0 if scale is None else scale)
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    for _ in range(grading):  # no vertex much thicker than its neighbourhood
        total = np.minimum(total, (total + adjacency @ total) / (1.0 + degree))
    fractions = level_fractions(layers, ratio)
    columns = np.vstack([wall, n + np.arange(layers * wall.size).reshape(layers, wall.size)])
    # prisms: reversed wall triangle (so the top lies above) at level k, its copy at level k + 1
    bottom = local_wall[:, ::-1]
    for _ in range(max_reductions):
        depth = fractions[1:, None, None] * total[None, :, None] * directions[None]
        all_points = np.vstack([points, (points[wall][None] + depth).reshape(-1, 3)])
        prisms = np.concatenate([np.hstack([columns[k][bottom], columns[k + 1][bottom]]) for k in range(layers)])
        tets = split_prisms(prisms)
        bad_prisms = np.unique(np.flatnonzero(tet_volumes(all_points, tets) <= 0) // 3)
        if bad_prisms.size == 0:
            break
        bad_vertices = np.unique(bottom[bad_prisms % len(bottom)])
        total[bad_vertices] *= 0.7
    else:
        raise CarotidError(f"could not build a valid boundary layer ({bad_prisms.size} prisms stay inverted even "
                           "when thin): the surface has folded or self-intersecting triangles; remesh it "
                           "(`carotid surface`) or use a thinner layer")
    all_points[:n] = _cap_follow(points, surface, wall_index, all_points[columns[-1]])
    all_points, inner_caps, inner_cap_labels = _inner_caps(all_points, surface, wall_index, columns[-1])
    inner = np.vstack([columns[-1][local_wall], inner_caps])
    return BoundaryLayer(points=all_points, tets=tets, prisms=prisms, columns=columns, wall_vertices=wall, directions=directions,
                         thickness=total, requested=requested, fractions=fractions, inner_triangles=inner,
                         inner_labels=np.concatenate([labels[labels == WALL], inner_cap_labels]),
                         local_radius=radius)
