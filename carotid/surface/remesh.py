"""Isotropic remeshing of the capped lumen surface (paper section 3, step 4; Botsch & Kobbelt 2004).

Each iteration: split edges longer than ``4/3 h`` at their midpoint, collapse edges shorter than
``4/5 h`` (never flipping a triangle, never creating a non-manifold configuration or an edge longer
than ``4/3 h``), flip edges when that brings the valences of the four vertices involved towards 6,
move every vertex towards the area-weighted centroid of its triangles in its tangent plane, and project
it back onto the input surface.  A last round of flips widens the smallest angles (an edge of a triangle
with an angle below 30 degrees is flipped when that enlarges the smaller of the two triangles' smallest
angles) without moving any vertex.  ``h`` is a global length or a function of position, e.g. ``k r`` from the
centerline radius (``radius_size_field``) or a multiple of the surface's own local edge length
(``coarsened_surface``).

Caps and labels are preserved: a vertex is *wall*, *cap* (interior of a cap) or *rim* (on both).  Wall
vertices are projected onto the input wall, cap vertices onto their cap's plane and rim vertices onto
the input rim polyline; a rim edge is only split or collapsed along the rim, an edge between two faces of
different labels is never flipped, and no triangle (wall or cap) may end with its three vertices on a rim
(it would lie along the rim: a sliver once the rim vertices are relaxed along it, and a wall sliver folds
across the cap).  So the caps stay planar and labelled and their rims stay on the original cut.

Why hand-written: no maintained BSD-compatible library does capped, label-preserving isotropic
remeshing (pymeshlab is GPL-3 and MMG/mmgpy LGPL; they are the peers in ``benchmarks/bench_surface.py``,
not dependencies; VTK and pyvista have no remesher of this kind).

Every topological operation is applied to a batch of edges at once, chosen so that their
neighbourhoods do not overlap (a maximal set of locally best edges, Luby-style), with numpy; the
batches repeat until no edge qualifies.  There is no Python loop over edges or vertices.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pyvista as pv
from scipy import sparse
from scipy.spatial import cKDTree

from carotid.centerline.model import Centerlines
from carotid.surface.mesh import WALL, adjacency, compact, edges_of, face_normals, from_polydata, to_polydata
from carotid.surface.project import PolylineProjector, TriangleProjector
from carotid.surface.quality import triangle_angles

KIND_WALL, KIND_CAP, KIND_RIM = 0, 1, 2
SPLIT_BATCHES, COLLAPSE_BATCHES, FLIP_BATCHES = 12, 8, 4

SizeField = float | Callable[[np.ndarray], np.ndarray]


class _Mesh:
    """Mutable labelled triangle mesh with the topology of its current state."""

    def __init__(self, points, faces, labels):
        self.v = np.asarray(points, float).copy()
        self.f = np.asarray(faces, np.int64).copy()
        self.lab = np.asarray(labels, np.int32).copy()
        self.update()

    def update(self):
        """Recompute edges, half-edge pairs, vertex kinds, cap ids and valences."""
        f, n = self.f, len(self.v)
        src = f.ravel()
        dst = np.roll(f, -1, axis=1).ravel()
        key = np.minimum(src, dst) * n + np.maximum(src, dst)
        order = np.argsort(key)  # introsort: deterministic, and 4x faster than a stable sort here
        key = key[order]
        if len(key) % 2 or not np.array_equal(key[0::2], key[1::2]) or (
                len(key) > 2 and np.any(key[2::2] == key[1:-1:2])):
            raise RuntimeError("remeshing lost the closed 2-manifold structure")
        self.h0, self.h1 = order[0::2], order[1::2]
        self.a, self.b = src[self.h0], dst[self.h0]
        fr = f.ravel()
        self.c = fr[3 * (self.h0 // 3) + (self.h0 % 3 + 2) % 3]
        self.d = fr[3 * (self.h1 // 3) + (self.h1 % 3 + 2) % 3]
        self.f0, self.f1 = self.h0 // 3, self.h1 // 3
        wall_face = self.lab == WALL
        on_wall = np.zeros(n, bool)
        on_cap = np.zeros(n, bool)
        on_wall[f[wall_face].ravel()] = True
        on_cap[f[~wall_face].ravel()] = True
        self.kind = np.where(on_wall & on_cap, KIND_RIM, np.where(on_cap, KIND_CAP, KIND_WALL))
        self.cap = np.zeros(n, np.int32)
        self.cap[f[~wall_face].ravel()] = np.repeat(self.lab[~wall_face], 3)
        self.valence = np.bincount(np.concatenate([self.a, self.b]), minlength=n)
        self.feature = self.lab[self.f0] != self.lab[self.f1]

    def adjacency(self) -> sparse.csr_matrix:
        n = len(self.v)
        a = sparse.coo_matrix((np.ones(len(self.a)), (self.a, self.b)), shape=(n, n))
        return (a + a.T).tocsr()

    def lengths(self) -> np.ndarray:
        return np.linalg.norm(self.v[self.a] - self.v[self.b], axis=1)


def _jitter(n: int, rng: np.random.Generator) -> np.ndarray:
    """Tiny distinct offsets that make batch priorities unique."""
    return rng.permutation(n) * 1e-9


def _split_batch(m: _Mesh, h: np.ndarray, rng) -> int:
    """Split a face-disjoint set of the longest edges longer than 4/3 h; returns how many."""
    target = 0.5 * (h[m.a] + h[m.b])
    ratio = m.lengths() / target
    cand = ratio > 4.0 / 3.0
    if not cand.any():
        return 0
    prio = np.where(cand, ratio + _jitter(len(ratio), rng), -1.0)
    he_edge = np.empty(3 * len(m.f), np.int64)
    he_edge[m.h0] = np.arange(len(m.a))
    he_edge[m.h1] = np.arange(len(m.a))
    face_max = prio[he_edge].reshape(-1, 3).max(axis=1)
    sel = np.flatnonzero(cand & (prio >= face_max[m.f0]) & (prio >= face_max[m.f1]))
    k, n = len(sel), len(m.v)
    new_v = n + np.arange(k)
    h0, h1, f0, f1 = m.h0[sel], m.h1[sel], m.f0[sel], m.f1[sel]
    i0, i1 = h0 % 3, h1 % 3
    add0, add1 = m.f[f0].copy(), m.f[f1].copy()
    add0[np.arange(k), i0] = new_v
    add1[np.arange(k), i1] = new_v
    m.f[f0, (i0 + 1) % 3] = new_v
    m.f[f1, (i1 + 1) % 3] = new_v
    m.v = np.vstack([m.v, 0.5 * (m.v[m.a[sel]] + m.v[m.b[sel]])])
    m.f = np.vstack([m.f, add0, add1])
    m.lab = np.concatenate([m.lab, m.lab[f0], m.lab[f1]])
    m.update()
    return k


def _independent(m: _Mesh, cand: np.ndarray, prio: np.ndarray, hops: int) -> np.ndarray:
    """Candidate edges whose priority is the largest of all candidates with an endpoint within ``hops``
    edges of either of their endpoints (so the selected edges' neighbourhoods are disjoint)."""
    n = len(m.v)
    p = np.full(n, -np.inf)
    np.maximum.at(p, m.a[cand], prio[cand])
    np.maximum.at(p, m.b[cand], prio[cand])
    for _ in range(hops):  # a few graph hops
        q = p.copy()
        np.maximum.at(q, m.a, p[m.b])
        np.maximum.at(q, m.b, p[m.a])
        p = q
    sel = cand & (prio >= p[m.a]) & (prio >= p[m.b])
    return np.flatnonzero(sel)


def _collapse_batch(m: _Mesh, h: np.ndarray, rng, rejected: np.ndarray) -> tuple[np.ndarray, bool]:
    """Collapse an independent set of edges shorter than 4/5 h.

    Vertex indices do not change (dropped vertices stay, unreferenced, until ``compact``), so that
    ``rejected``, the keys ``lo * n + hi`` of edges whose collapse was refused, stays valid.

    Returns
    -------
    rejected : ndarray
        Updated keys of refused edges.
    more : bool
        Whether candidates remain that were neither collapsed nor refused.
    """
    n = len(m.v)
    target = 0.5 * (h[m.a] + h[m.b])
    length = m.lengths()
    ka, kb = m.kind[m.a], m.kind[m.b]
    rim_a, rim_b = ka == KIND_RIM, kb == KIND_RIM
    allowed = np.where(rim_a & rim_b, m.feature & (m.cap[m.a] == m.cap[m.b]), ~m.feature)
    key = np.minimum(m.a, m.b) * n + np.maximum(m.a, m.b)
    cand = (length < 0.8 * target) & allowed & ~np.isin(key, rejected)
    if not cand.any():
        return rejected, False
    prio = np.where(cand, -length / target + _jitter(len(length), rng), -np.inf)
    sel = _independent(m, cand, prio, hops=2)
    # keep: the rim vertex when only one endpoint is on a rim
    swap = rim_b[sel] & ~rim_a[sel]
    keep = np.where(swap, m.b[sel], m.a[sel])
    drop = np.where(swap, m.a[sel], m.b[sel])
    one_rim = rim_a[sel] ^ rim_b[sel]
    pos = np.where(one_rim[:, None], m.v[keep], 0.5 * (m.v[keep] + m.v[drop]))
    bad = np.zeros(len(sel), bool)
    # topology: link condition and valences
    adj = m.adjacency()
    common = np.asarray(adj[keep].multiply(adj[drop]).sum(axis=1)).ravel()
    bad |= common != 2
    bad |= (m.valence[m.c[sel]] <= 3) | (m.valence[m.d[sel]] <= 3) | (m.valence[keep] + m.valence[drop] - 4 < 3)
    # geometry of the faces around keep/drop (not the two removed)
    owner = np.full(n, -1, np.int64)
    owner[keep] = np.arange(len(sel))
    owner[drop] = np.arange(len(sel))
    new_v = m.v.copy()
    new_v[keep] = pos
    new_v[drop] = pos
    new_kind = m.kind.copy()
    new_kind[keep] = np.maximum(m.kind[keep], m.kind[drop])
    new_kind[drop] = new_kind[keep]
    fo = owner[m.f]
    face_owner = fo.max(axis=1)
    gone = np.zeros(len(m.f), bool)
    gone[m.f0[sel]] = True
    gone[m.f1[sel]] = True
    touched = (face_owner >= 0) & ~gone
    tf = np.flatnonzero(touched)
    n_old = face_normals(m.v, m.f[tf])
    n_new = face_normals(new_v, m.f[tf], unit=False)
    area_new = np.linalg.norm(n_new, axis=1)
    flipped = (np.einsum("ij,ij->i", n_old, n_new) <= 0.2 * area_new) | (area_new < 1e-12)
    all_rim = np.all(new_kind[m.f[tf]] == KIND_RIM, axis=1)
    np.logical_or.at(bad, face_owner[tf], flipped | all_rim)
    # no resulting edge longer than 4/3 h
    for u, w in ((m.a, m.b), (m.b, m.a)):
        o = owner[u]
        ext = (o >= 0) & (owner[w] != o)
        too_long = np.linalg.norm(pos[o[ext]] - m.v[w[ext]], axis=1) > (4.0 / 3.0) * target[ext]
        np.logical_or.at(bad, o[ext], too_long)
    rejected = np.concatenate([rejected, key[sel[bad]]])
    more = int(cand.sum()) > len(sel)
    ok = ~bad
    if not ok.any():
        return rejected, more
    keep, drop, pos = keep[ok], drop[ok], pos[ok]
    m.v[keep] = pos
    remap = np.arange(n)
    remap[drop] = keep
    f = remap[m.f]
    alive = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    m.f = f[alive]
    m.lab = m.lab[alive]
    m.update()
    return rejected, True


def _valence_gain(m: _Mesh) -> np.ndarray:
    """Decrease (ne,) of the summed distance of the four valences to 6 if each edge were flipped."""
    a, b, c, d, val = m.a, m.b, m.c, m.d, m.valence
    before = np.abs(val[a] - 6) + np.abs(val[b] - 6) + np.abs(val[c] - 6) + np.abs(val[d] - 6)
    after = np.abs(val[a] - 7) + np.abs(val[b] - 7) + np.abs(val[c] - 5) + np.abs(val[d] - 5)
    return before - after


def _angle_gain(m: _Mesh) -> np.ndarray:
    """Increase (ne,) of the smallest angle (degrees) of the two triangles of each edge if it were flipped,
    for the edges of triangles with an angle below 30 degrees (zero elsewhere)."""
    old = triangle_angles(m.v, m.f).min(axis=1)
    worst = np.minimum(old[m.f0], old[m.f1])
    gain = np.zeros(len(m.a))
    low = np.flatnonzero(worst < 30.0)
    a, b, c, d = m.a[low], m.b[low], m.c[low], m.d[low]
    new = np.minimum(triangle_angles(m.v, np.stack([a, d, c], 1)).min(axis=1),
                     triangle_angles(m.v, np.stack([d, b, c], 1)).min(axis=1))
    gain[low] = new - worst[low]
    return gain


def _flip_batch(m: _Mesh, rng, gain_of: Callable[[_Mesh], np.ndarray] = _valence_gain) -> int:
    """Flip a vertex-disjoint set of edges with a positive ``gain_of`` (by default: that bring valences
    towards 6); returns how many."""
    a, b, c, d = m.a, m.b, m.c, m.d
    val = m.valence
    gain = gain_of(m)
    cand = (gain > 0) & ~m.feature & ~((m.kind[c] == KIND_RIM) & (m.kind[d] == KIND_RIM)) & (c != d)
    cand &= (val[a] > 3) & (val[b] > 3)
    idx = np.flatnonzero(cand)
    if len(idx) == 0:
        return 0
    a, b, c, d = a[idx], b[idx], c[idx], d[idx]
    ok = np.asarray(m.adjacency()[c, d]).ravel() == 0
    # geometry: the two new triangles (a, d, c) and (d, b, c) must not fold
    p = m.v
    n1 = np.cross(p[d] - p[a], p[c] - p[a])
    n2 = np.cross(p[b] - p[d], p[c] - p[d])
    fn = face_normals(p, m.f)
    old = fn[m.f0[idx]] + fn[m.f1[idx]]
    l1, l2 = np.linalg.norm(n1, axis=1), np.linalg.norm(n2, axis=1)
    cos12 = np.einsum("ij,ij->i", n1, n2) / np.maximum(l1 * l2, 1e-300)
    ok &= (cos12 > 0.7) & (np.einsum("ij,ij->i", n1, old) > 0) & (np.einsum("ij,ij->i", n2, old) > 0)
    ok &= (l1 > 1e-12) & (l2 > 1e-12)
    a, b, c, d, idx = a[ok], b[ok], c[ok], d[ok], idx[ok]
    if len(idx) == 0:
        return 0
    prio = gain[idx] + _jitter(len(idx), rng)
    vmax = np.full(len(m.v), -np.inf)
    for v in (a, b, c, d):
        np.maximum.at(vmax, v, prio)
    sel = (prio >= vmax[a]) & (prio >= vmax[b]) & (prio >= vmax[c]) & (prio >= vmax[d])
    a, b, c, d, idx = a[sel], b[sel], c[sel], d[sel], idx[sel]
    m.f[m.f0[idx]] = np.stack([a, d, c], axis=1)
    m.f[m.f1[idx]] = np.stack([d, b, c], axis=1)
    m.update()
    return len(idx)


class _Reference:
    """The input surface that vertices are projected back onto: wall triangles, cap planes and rims."""

    def __init__(self, points, faces, labels):
        wall = labels == WALL
        self.wall = TriangleProjector(points, faces[wall])
        self.planes = {}
        for lab in np.unique(labels[~wall]):  # loop over caps
            sel = faces[labels == lab]
            nrm = face_normals(points, sel, unit=False).sum(axis=0)
            self.planes[int(lab)] = (points[np.unique(sel)].mean(axis=0), nrm / np.linalg.norm(nrm))
        m = _Mesh(points, faces, labels)
        rim = m.feature
        self.rim = PolylineProjector(np.stack([points[m.a[rim]], points[m.b[rim]]], axis=1))

    def project(self, m: _Mesh) -> None:
        wall = m.kind == KIND_WALL
        m.v[wall] = self.wall(m.v[wall])[0]
        rim = m.kind == KIND_RIM
        m.v[rim] = self.rim(m.v[rim])
        for lab, (centre, normal) in self.planes.items():  # loop over caps
            sel = (m.kind == KIND_CAP) & (m.cap == lab)
            m.v[sel] -= ((m.v[sel] - centre) @ normal)[:, None] * normal


def _relax(m: _Mesh, weight: float = 1.0) -> None:
    """Tangential relaxation: towards the area-weighted centroid of the incident triangles in the tangent
    plane (wall and cap vertices), towards the midpoint of the two rim neighbours along the rim."""
    n = len(m.v)
    fn = face_normals(m.v, m.f, unit=False)
    area = 0.5 * np.linalg.norm(fn, axis=1)
    cen = m.v[m.f].mean(axis=1)
    corner = m.f.ravel()
    wsum = np.bincount(corner, np.repeat(area, 3), minlength=n)
    target = np.stack([np.bincount(corner, np.repeat(area * cen[:, i], 3), minlength=n) for i in range(3)], 1)
    target /= np.maximum(wsum, 1e-300)[:, None]
    normal = np.stack([np.bincount(corner, np.repeat(fn[:, i], 3), minlength=n) for i in range(3)], 1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    move = target - m.v
    move -= np.einsum("ij,ij->i", move, normal)[:, None] * normal
    rim_e = m.feature
    ra, rb = m.a[rim_e], m.b[rim_e]
    mid = np.zeros_like(m.v)
    np.add.at(mid, ra, m.v[rb])
    np.add.at(mid, rb, m.v[ra])
    cnt = np.bincount(np.concatenate([ra, rb]), minlength=n)
    rim = (m.kind == KIND_RIM) & (cnt == 2)
    move[m.kind == KIND_RIM] = 0.0
    move[rim] = mid[rim] / 2.0 - m.v[rim]
    m.v += weight * move


def radius_size_field(centerlines: Centerlines, ratio: float, hmin: float, hmax: float
                      ) -> Callable[[np.ndarray], np.ndarray]:
    """Target edge length ``h = ratio * r`` from the inscribed radius at the nearest axis point, in [hmin, hmax] mm.

    Returns
    -------
    callable
        Points (n, 3) mm -> target lengths (n,) mm.
    """
    pts = np.vstack([b.points for b in centerlines.branches])
    radii = np.concatenate([b.radii for b in centerlines.branches])
    tree = cKDTree(pts)

    def size(points: np.ndarray) -> np.ndarray:
        return np.clip(ratio * radii[tree.query(points)[1]], hmin, hmax)

    return size


def local_edge_length(points: np.ndarray, faces: np.ndarray, neighbours: bool = True) -> np.ndarray:
    """Edge length at each vertex of a triangle surface: the mean length of its edges, averaged once more with
    its neighbours' (so that one long or short edge does not set it).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Vertices, mm.
    faces : ndarray, shape (m, 3)
        Triangles.
    neighbours : bool
        Average with the neighbours'; if False, the mean length of each vertex's own edges.

    Returns
    -------
    ndarray, shape (n,)
        mm (0 at unreferenced vertices).
    """
    edges, _, _ = edges_of(faces)
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    degree = np.bincount(edges.ravel(), minlength=len(points))
    own = np.bincount(edges.ravel(), np.repeat(length, 2), minlength=len(points)) / np.maximum(degree, 1)
    if not neighbours:
        return own
    return (adjacency(len(points), faces) @ own + own) / (degree + 1)


def remesh(surface: pv.PolyData, target: SizeField, *, iterations: int = 10, seed: int = 0) -> pv.PolyData:
    """Isotropic remeshing of a closed, labelled triangle surface to a prescribed edge length.

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed, consistently oriented 2-manifold in mm, with ``CellEntityIds`` (wall 1, caps 2, 3, ...).
    target : float or callable
        Target edge length in mm, or a function points (n, 3) -> lengths (n,) (see ``radius_size_field``).
    iterations : int
        Split / collapse / flip / relax / project rounds.
    seed : int
        Seed of the tie-breaking among equally good edges (the result is deterministic for a seed).

    Returns
    -------
    pyvista.PolyData
        Remeshed surface, same labels, caps planar, rims on the input rims.
    """
    points, faces, labels = from_polydata(surface)
    ref = _Reference(points, faces, labels)
    m = _Mesh(points, faces, labels)
    rng = np.random.default_rng(seed)

    def sizes() -> np.ndarray:
        return np.full(len(m.v), float(target)) if not callable(target) else np.asarray(target(m.v), float)

    for _ in range(iterations):  # remeshing rounds
        for _ in range(SPLIT_BATCHES):
            if _split_batch(m, sizes(), rng) == 0:
                break
        rejected, more = np.zeros(0, np.int64), True
        for _ in range(COLLAPSE_BATCHES):
            rejected, more = _collapse_batch(m, sizes(), rng, rejected)
            if not more:
                break
        m.v, m.f = compact(m.v, m.f)
        m.update()
        for _ in range(FLIP_BATCHES):
            if _flip_batch(m, rng) == 0:
                break
        _relax(m)
        ref.project(m)
    for _ in range(FLIP_BATCHES):  # a last clean-up: flips that widen the smallest angles (Delaunay-like)
        if _flip_batch(m, rng, _angle_gain) == 0:
            break
    return to_polydata(m.v, m.f, m.lab)


def coarsened_surface(surface: pv.PolyData, factor: float, iterations: int = 12) -> pv.PolyData:
    """The surface remeshed with edges ``factor`` times as long as its own (``factor`` < 1: shorter).

    The target edge length at a point is ``factor`` times :func:`local_edge_length` at the nearest vertex of
    ``surface``, so a surface graded by the local radius stays graded.  :func:`remesh` (as many rounds as the
    surface stage gives an external surface) projects the new vertices back onto ``surface``: the wall is the
    same piecewise-linear lumen, sampled more coarsely, and the caps stay planar, labelled and on their rims.

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed labelled surface (``surface.vtp``: ``CellEntityIds`` wall 1, caps 2, 3, ...), mm.
    factor : float
        Edge-length factor, > 0.
    iterations : int
        Remeshing rounds.

    Returns
    -------
    pyvista.PolyData
        The remeshed surface, same labels.
    """
    points, faces, _ = from_polydata(surface)
    target = factor * local_edge_length(points, faces)
    tree = cKDTree(points)
    return remesh(surface, lambda query: target[tree.query(query)[1]], iterations=iterations)
