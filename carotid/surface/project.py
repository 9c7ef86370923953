"""Closest points on a triangle soup or a polyline, vectorised: a k-d tree proposes candidate elements,
a numba kernel computes the exact closest point on each (Ericson, Real-Time Collision Detection, 5.1.5).

VTK's cell locators answer one point per Python call; this answers all points in one call.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree


@numba.njit(cache=True)
def _closest_triangles(points, tri, cand):
    """Closest point on the candidate triangles of each point (scalar arithmetic: no temporaries)."""
    out = np.empty_like(points)
    best_face = np.empty(len(points), np.int64)
    for i in range(len(points)):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        for j in range(cand.shape[1]):
            f = cand[i, j]
            ax, ay, az = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
            abx, aby, abz = tri[f, 1, 0] - ax, tri[f, 1, 1] - ay, tri[f, 1, 2] - az
            acx, acy, acz = tri[f, 2, 0] - ax, tri[f, 2, 1] - ay, tri[f, 2, 2] - az
            apx, apy, apz = px - ax, py - ay, pz - az
            d1 = abx * apx + aby * apy + abz * apz
            d2 = acx * apx + acy * apy + acz * apz
            bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
            d3 = abx * bpx + aby * bpy + abz * bpz
            d4 = acx * bpx + acy * bpy + acz * bpz
            cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
            d5 = abx * cpx + aby * cpy + abz * cpz
            d6 = acx * cpx + acy * cpy + acz * cpz
            vc = d1 * d4 - d3 * d2
            vb = d5 * d2 - d1 * d6
            va = d3 * d6 - d5 * d4
            if d1 <= 0.0 and d2 <= 0.0:
                s, t = 0.0, 0.0
            elif d3 >= 0.0 and d4 <= d3:
                s, t = 1.0, 0.0
            elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                s, t = d1 / (d1 - d3), 0.0
            elif d6 >= 0.0 and d5 <= d6:
                s, t = 0.0, 1.0
            elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                s, t = 0.0, d2 / (d2 - d6)
            elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                s, t = 1.0 - w, w
            else:
                denom = 1.0 / (va + vb + vc)
                s, t = vb * denom, vc * denom
            qx, qy, qz = ax + s * abx + t * acx, ay + s * aby + t * acy, az + s * abz + t * acz
            d = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
            if d < best:
                best = d
                out[i, 0], out[i, 1], out[i, 2] = qx, qy, qz
                best_face[i] = f
    return out, best_face


@numba.njit(cache=True)
def _closest_segments(points, seg, cand):
    out = np.empty_like(points)
    for i in range(len(points)):
        best = np.inf
        for j in range(cand.shape[1]):
            k = cand[i, j]
            ax, ay, az = seg[k, 0, 0], seg[k, 0, 1], seg[k, 0, 2]
            bx, by, bz = seg[k, 1, 0] - ax, seg[k, 1, 1] - ay, seg[k, 1, 2] - az
            t = ((points[i, 0] - ax) * bx + (points[i, 1] - ay) * by + (points[i, 2] - az) * bz)
            t = min(max(t / max(bx * bx + by * by + bz * bz, 1e-300), 0.0), 1.0)
            qx, qy, qz = ax + t * bx, ay + t * by, az + t * bz
            d = (qx - points[i, 0]) ** 2 + (qy - points[i, 1]) ** 2 + (qz - points[i, 2]) ** 2
            if d < best:
                best = d
                out[i, 0], out[i, 1], out[i, 2] = qx, qy, qz
    return out


class TriangleProjector:
    """Closest points on a fixed triangle surface.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    faces : ndarray, shape (m, 3)
    candidates : int
        Number of nearest triangle centroids examined per query point.
    """

    def __init__(self, points: np.ndarray, faces: np.ndarray, candidates: int = 12):
        self.tri = np.ascontiguousarray(points[faces], dtype=np.float64)
        self.tree = cKDTree(self.tri.mean(axis=1))
        self.k = min(candidates, len(faces))

    def __call__(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest points (q, 3) and the index (q,) of the triangle each lies on."""
        if len(query) == 0:
            return query.copy(), np.zeros(0, np.int64)
        _, cand = self.tree.query(query, k=self.k)
        cand = np.asarray(cand, np.int64).reshape(len(query), -1)
        return _closest_triangles(np.ascontiguousarray(query, dtype=np.float64), self.tri, cand)


class PolylineProjector:
    """Closest points on a fixed set of segments (s, 2, 3)."""

    def __init__(self, segments: np.ndarray, candidates: int = 6):
        self.seg = np.ascontiguousarray(segments, dtype=np.float64)
        self.tree = cKDTree(self.seg.mean(axis=1))
        self.k = min(candidates, len(segments))

    def __call__(self, query: np.ndarray) -> np.ndarray:
        """Closest points (q, 3)."""
        if len(query) == 0:
            return query.copy()
        _, cand = self.tree.query(query, k=self.k)
        cand = np.asarray(cand, np.int64).reshape(len(query), -1)
        return _closest_segments(np.ascontiguousarray(query, dtype=np.float64), self.seg, cand)
