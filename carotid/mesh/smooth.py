"""3D Lloyd smoothing of the free (interior core) vertices of a tetrahedral mesh (paper section 3, [3]).

Lloyd's iteration moves every generator to the centroid of its cell (Du &
Wang 2003).  On a given tetrahedral mesh the cell of vertex i is taken as
its barycentric (median) dual cell: the points of its star whose
barycentric coordinate of i is the largest.  Inside one tetrahedron that
region has volume V/4 and centroid ``(52 x_i + 92 g) / 144`` (g the
tetrahedron's centroid; exact, from the expected largest of four uniform
spacings, 25/48), so the cell centroid of i is

    c_i = (52 x_i + 92 sum_T V_T g_T / sum_T V_T) / 144,

computed for all vertices at once with ``np.bincount``.  Unlike the Voronoi
cell, this cell always lies in the star of i, so it exists for any mesh
(Voronoi centroids of obtuse stars can leave the star).  No library offers
this on a fixed-connectivity mesh with fixed boundary and layer vertices,
hence this module.

A move is kept only if no incident tetrahedron inverts or has its smallest
dihedral angle drop below ``min(its old angle, min_angle_deg)``; rejected
vertices retry with half the step (vectorised backtracking), then stay.
"""

from __future__ import annotations

import numpy as np

from carotid.mesh.layers import tet_volumes
from carotid.mesh.quality import min_dihedral

_OWN, _CENTROID = 52.0 / 144.0, 92.0 / 144.0


def dual_cell_centroids(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Centroid of the barycentric dual cell of every vertex, shape (n, 3) (unused vertices: unchanged)."""
    vol = np.abs(tet_volumes(points, tets))
    g = points[tets].mean(axis=1)
    flat = tets.ravel()
    weight = np.repeat(vol, 4)
    total = np.bincount(flat, weights=weight, minlength=len(points))
    mean = np.stack([np.bincount(flat, weights=weight * np.repeat(g[:, k], 4), minlength=len(points))
                     for k in range(3)], axis=1)
    used = total > 0
    out = points.copy()
    out[used] = _OWN * points[used] + _CENTROID * mean[used] / total[used, None]
    return out


def lloyd_smooth(points: np.ndarray, tets: np.ndarray, free: np.ndarray, iterations: int = 5,
                 min_angle_deg: float = 30.0, backtracks: int = 3) -> tuple[np.ndarray, dict]:
    """Lloyd iterations on the free vertices; elements never invert or degrade past the bound.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Vertex coordinates (mm).
    tets : ndarray, shape (t, 4)
        Positively oriented tetrahedra.  Only the tetrahedra touching a free
        vertex matter; passing just those is faster.
    free : ndarray of bool, shape (n,)
        Vertices allowed to move.
    iterations : int
        Lloyd iterations.
    min_angle_deg : float
        Quality floor of the acceptance test (degrees): an element may not
        end below ``min(its old smallest dihedral angle, min_angle_deg)``.
        30 keeps the tail of the distribution (at 20, more elements fall
        into the 0.3-0.4 radius-ratio range; at 40, few vertices move).
    backtracks : int
        Step halvings tried for a rejected vertex within one iteration.

    Returns
    -------
    points : ndarray, shape (n, 3)
        Smoothed coordinates (fixed vertices unchanged).
    info : dict
        ``moved`` (vertex moves accepted per iteration) and ``mean_step_mm``.
    """
    points = points.copy()
    moving = free[tets].any(axis=1)
    local = tets[moving]
    info = {"moved": [], "mean_step_mm": []}
    if local.size == 0:
        return points, info
    for _ in range(iterations):
        old_angle = min_dihedral(points, local)
        floor = np.minimum(old_angle, min_angle_deg)
        step = dual_cell_centroids(points, local) - points
        step[~free] = 0.0
        scale = np.ones(len(points))
        for attempt in range(backtracks + 1):
            trial = points + scale[:, None] * step
            bad = (tet_volumes(trial, local) <= 0) | (min_dihedral(trial, local) < floor)
            if not bad.any():
                break
            culprits = np.unique(local[bad])
            scale[culprits] = 0.0 if attempt == backtracks else 0.5 * scale[culprits]
        # reverting vertices can only restore old elements, so a last pass settles every conflict
        while True:
            trial = points + scale[:, None] * step
            bad = (tet_volumes(trial, local) <= 0) | (min_dihedral(trial, local) < floor)
            if not bad.any():
                break
            scale[np.unique(local[bad])] = 0.0
        accepted = free & (scale > 0)
        info["moved"].append(int(accepted.sum()))
        info["mean_step_mm"].append(float(np.linalg.norm(scale[accepted, None] * step[accepted], axis=1).mean())
                                    if accepted.any() else 0.0)
        points = trial
    return points, info
