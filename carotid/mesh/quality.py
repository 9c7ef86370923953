"""Element quality of tetrahedra: dihedral angles (a numba kernel, the hot loop of smoothing) and radius ratio."""

from __future__ import annotations

import numba
import numpy as np

_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_OPPOSITE = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])  # faces opposite the other two vertices


def _face_normals(p: np.ndarray) -> np.ndarray:
    """Outward area vectors of the 4 faces (face k opposite vertex k), shape (t, 4, 3), for positive tets."""
    a, b, c, d = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    return 0.5 * np.stack([np.cross(c - b, d - b), np.cross(d - a, c - a),
                           np.cross(b - a, d - a), np.cross(c - a, b - a)], axis=1)


def dihedral_angles(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The six interior dihedral angles (degrees) of each tetrahedron, shape (t, 6).

    The angle at an edge is pi minus the angle between the outward normals of
    the two faces that meet there (the faces opposite the edge's other two
    vertices).
    """
    n = _face_normals(points[tets])
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-300)
    cos = -np.einsum("tij,tij->ti", n[:, _OPPOSITE[:, 0]], n[:, _OPPOSITE[:, 1]])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@numba.njit(cache=True, nogil=True)
def _extreme_dihedrals(points, tets, out_min, out_max):  # pragma: no cover - compiled
    n = np.empty((4, 3))
    for t in range(tets.shape[0]):
        for f in range(4):  # unit normal of the face opposite vertex f, pointing away from it
            a, b, c = tets[t, (f + 1) % 4], tets[t, (f + 2) % 4], tets[t, (f + 3) % 4]
            ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
            vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
            nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
            d = tets[t, f]
            side = nx * (points[d, 0] - points[a, 0]) + ny * (points[d, 1] - points[a, 1]) \
                + nz * (points[d, 2] - points[a, 2])
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if side > 0:
                norm = -norm
            if norm == 0.0:
                norm = 1e-300
            n[f, 0], n[f, 1], n[f, 2] = nx / norm, ny / norm, nz / norm
        lo, hi = 1.0, -1.0  # extreme cosines of the interior angles
        for f in range(3):
            for g in range(f + 1, 4):
                cosine = -(n[f, 0] * n[g, 0] + n[f, 1] * n[g, 1] + n[f, 2] * n[g, 2])
                lo = min(lo, cosine)
                hi = max(hi, cosine)
        out_min[t] = np.degrees(np.arccos(min(max(hi, -1.0), 1.0)))
        out_max[t] = np.degrees(np.arccos(min(max(lo, -1.0), 1.0)))


def extreme_dihedrals(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest interior dihedral angle (degrees) of each tetrahedron, two arrays of shape (t,).

    Orientation-independent (face normals are turned away from the opposite
    vertex); a flat tetrahedron has 0 and 180 degrees.
    """
    out_min, out_max = np.empty(len(tets)), np.empty(len(tets))
    _extreme_dihedrals(np.ascontiguousarray(points, dtype=np.float64),
                       np.ascontiguousarray(tets, dtype=np.int64), out_min, out_max)
    return out_min, out_max


def min_dihedral(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Smallest dihedral angle (degrees) of each tetrahedron, shape (t,)."""
    return extreme_dihedrals(points, tets)[0]


def radius_ratio(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Normalised radius ratio 3 r_in / R_circ of each tetrahedron, 1 for the regular one, shape (t,)."""
    p = points[tets]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])) / 6.0
    area = np.linalg.norm(_face_normals(p), axis=2).sum(axis=1)
    r_in = 3.0 * vol / np.maximum(area, 1e-300)
    length = np.linalg.norm(p[:, _EDGES[:, 1]] - p[:, _EDGES[:, 0]], axis=2)
    # products of opposite edge lengths: (01, 23), (02, 13), (03, 12)
    a, b, c = length[:, 0] * length[:, 5], length[:, 1] * length[:, 4], length[:, 2] * length[:, 3]
    s = np.clip((a + b + c) * (-a + b + c) * (a - b + c) * (a + b - c), 0.0, None)
    r_circ = np.sqrt(s) / np.maximum(24.0 * vol, 1e-300)
    return 3.0 * r_in / np.maximum(r_circ, 1e-300)


def angle_summary(min_angles: np.ndarray) -> dict:
    """Minimum, percentiles and fractions above 10 / 20 degrees of per-element minimum dihedral angles."""
    if min_angles.size == 0:
        return {"count": 0}
    return {"count": int(min_angles.size), "min_deg": float(min_angles.min()),
            "p1_deg": float(np.percentile(min_angles, 1)), "median_deg": float(np.median(min_angles)),
            "fraction_ge_10deg": float(np.mean(min_angles >= 10.0)),
            "fraction_ge_20deg": float(np.mean(min_angles >= 20.0))}


def distribution(values: np.ndarray) -> dict:
    """Minimum, 1st percentile, median, 99th percentile and maximum of ``values`` as a JSON-ready dict."""
    if values.size == 0:
        return {}
    q = np.percentile(values, [0.0, 1.0, 50.0, 99.0, 100.0])
    return dict(zip(("min", "p1", "median", "p99", "max"), q.astype(float).tolist()))


def prism_measures(points: np.ndarray, prisms: np.ndarray, requested_height: np.ndarray) -> dict:
    """Shape measures of (anisotropic) boundary-layer prisms, each an array of shape (p,).

    A thin prism is a good element when its triangles are good and its
    side edges stand on them, whatever its aspect ratio; its split
    tetrahedra are then flat by construction, so the prism is judged
    instead.  With n the unit normal of the bottom triangle (towards the
    top) and e_i = x_{i+3} - x_i its side edges:

    * ``base_min_angle_deg`` / ``base_max_angle_deg``: smallest and largest
      angle (degrees) of the bottom and top triangles together;
    * ``skew_deg``: angle (degrees) between the mean side edge and n, 0 for
      a right prism (the extrusion leans from the base normal by this much);
    * ``height_mm``: mean of e_i . n;
    * ``height_ratio``: ``height_mm`` over ``requested_height``, 1 where the
      sub-layer has its requested height, near 0 where the layer was thinned
      to almost nothing.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Vertex coordinates (mm).
    prisms : ndarray, shape (p, 6)
        Bottom triangle 0, 1, 2 (counter-clockwise seen from the top), top
        3, 4, 5 with i + 3 above i.
    requested_height : ndarray, shape (p,)
        Requested height (mm) of each prism.

    Returns
    -------
    dict of ndarray
    """
    x = points[prisms]
    tri = np.concatenate([x[:, :3], x[:, 3:]], axis=1).reshape(-1, 3, 3)  # bottom, top of each prism
    e = np.roll(tri, -1, axis=1) - tri
    length = np.linalg.norm(e, axis=2)
    cos = -np.einsum("mij,mij->mi", e, np.roll(e, 1, axis=1)) / np.maximum(length * np.roll(length, 1, axis=1),
                                                                          1e-300)
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).reshape(len(prisms), 6)
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    side = (x[:, 3:] - x[:, :3]).mean(axis=1)
    height = np.einsum("ij,ij->i", side, normal)
    skew = np.degrees(np.arccos(np.clip(height / np.maximum(np.linalg.norm(side, axis=1), 1e-300), -1.0, 1.0)))
    return {"base_min_angle_deg": angles.min(axis=1), "base_max_angle_deg": angles.max(axis=1),
            "skew_deg": skew, "height_mm": height, "height_ratio": height / requested_height}


def histogram(values: np.ndarray, bins: np.ndarray) -> dict:
    """Counts of ``values`` in ``bins`` as a JSON-ready dict."""
    counts, edges = np.histogram(values, bins=bins)
    return {"edges": edges.round(6).tolist(), "counts": counts.tolist()}


def walk_layers(points: np.ndarray, tets: np.ndarray, wall_triangles: np.ndarray, max_depth: float,
                steps: int, min_alignment: float = 0.8) -> np.ndarray:
    """Depths of the nodes met walking inward from every wall node along mesh edges, shape (steps + 1, w).

    An independent read-back of a prismatic layer from any tetrahedral mesh
    (ours or another mesher's): from each wall vertex, follow the mesh edge
    best aligned with the wall's inward normal (area-weighted vertex normal
    of ``wall_triangles``, outward-oriented), then at every node the edge
    best aligned with the previous step, so the walk stays on a straight
    prism column even where the column leans from the normal.  Depths are
    measured along the normal.  A walk stops (NaN from then on) when no edge
    is within ``arccos(min_alignment)`` of its reference direction or the
    depth exceeds ``max_depth``.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    tets : ndarray, shape (t, 4)
    wall_triangles : ndarray, shape (m, 3)
        Outward-oriented wall faces of the mesh boundary.
    max_depth : float
        Deepest depth (mm) of interest.
    steps : int
        Edges to follow.

    Returns
    -------
    ndarray, shape (steps + 1, w)
        Depth (mm, along the normal) of the node reached after k steps; row 0
        is 0 (the wall nodes, in ``np.unique(wall_triangles)`` order).
    """
    from scipy import sparse

    n = len(points)
    edges = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    adj = sparse.coo_matrix((np.ones(2 * len(edges), dtype=np.int8),
                             (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                            shape=(n, n)).tocsr()
    adj.sum_duplicates()
    a = points[wall_triangles[:, 0]]
    area = np.cross(points[wall_triangles[:, 1]] - a, points[wall_triangles[:, 2]] - a)
    normal = np.zeros((n, 3))
    for k in range(3):
        np.add.at(normal, wall_triangles[:, k], area)
    wall = np.unique(wall_triangles)
    inward = -normal[wall] / np.linalg.norm(normal[wall], axis=1, keepdims=True)
    depth = np.full((steps + 1, wall.size), np.nan)
    depth[0] = 0.0
    current, alive, heading = wall.copy(), np.ones(wall.size, dtype=bool), inward.copy()
    for k in range(1, steps + 1):
        starts, ends = adj.indptr[current], adj.indptr[current + 1]
        counts = ends - starts
        owner = np.repeat(np.arange(wall.size), counts)
        first = np.cumsum(counts) - counts  # where each wall node's neighbours start in the flat list
        nbr = adj.indices[np.arange(owner.size) - np.repeat(first - starts, counts)]
        step = points[nbr] - points[current[owner]]
        align = np.einsum("ij,ij->i", step, heading[owner]) / np.maximum(np.linalg.norm(step, axis=1), 1e-300)
        best = np.full(wall.size, -np.inf)
        np.maximum.at(best, owner, align)
        pick = np.flatnonzero(align == best[owner])
        choice = np.empty(wall.size, dtype=np.int64)
        choice[owner[pick]] = nbr[pick]
        alive &= best >= min_alignment
        previous = current
        current = np.where(alive, choice, current)
        moved = points[current] - points[previous]
        heading = np.where(alive[:, None], moved / np.maximum(np.linalg.norm(moved, axis=1, keepdims=True), 1e-300),
                           heading)
        depth[k] = np.where(alive, np.einsum("ij,ij->i", points[current] - points[wall], inward), np.nan)
        alive &= depth[k] <= max_depth
        depth[k][~alive] = np.nan
    return depth
