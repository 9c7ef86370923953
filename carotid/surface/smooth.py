"""Taubin smoothing of the lumen surface, with cap rims held (paper section 3, step 4 i).

Taubin's lambda|mu filter (Taubin 1995) alternates a shrinking Laplacian step (``lambda > 0``) with an
inflating one (``mu < -lambda``): a low-pass filter with pass-band ``k_PB = 1/lambda + 1/mu`` that
removes the marching-cubes staircase without the shrinkage of plain Laplacian smoothing.  The umbrella
operator is a sparse matrix product, so every iteration is two sparse mat-vecs.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy import sparse

from carotid.surface.mesh import WALL, adjacency, from_polydata, to_polydata


def _umbrella(n: int, faces: np.ndarray) -> sparse.csr_matrix:
    """Uniform umbrella operator ``L = D^-1 A - I`` (n, n) of the vertex graph."""
    a = adjacency(n, faces)
    deg = np.asarray(a.sum(axis=1)).ravel()
    return sparse.diags(1.0 / np.maximum(deg, 1.0)) @ a - sparse.identity(n, format="csr")


def held_vertices(surface: pv.PolyData) -> np.ndarray:
    """Boolean (n,) mask of the vertices of any cap face (cap interiors and their rims)."""
    points, faces, labels = from_polydata(surface)
    held = np.zeros(len(points), bool)
    held[faces[labels != WALL].ravel()] = True
    return held


def _filter(surface: pv.PolyData, factors: list[float], iterations: int, fixed: np.ndarray | None) -> pv.PolyData:
    points, faces, labels = from_polydata(surface)
    lap = _umbrella(len(points), faces)
    move = ~(held_vertices(surface) if fixed is None else np.asarray(fixed, bool))
    p = points.copy()
    for _ in range(iterations):
        for f in factors:
            p[move] += f * (lap @ p)[move]
    return to_polydata(p, faces, labels)


def taubin_smooth(surface: pv.PolyData, iterations: int = 30, lam: float = 0.5, pass_band: float = 0.1,
                  fixed: np.ndarray | None = None) -> pv.PolyData:
    """Taubin lambda|mu smoothing.

    Parameters
    ----------
    surface : pyvista.PolyData
        Triangle surface in mm; ``CellEntityIds`` is kept.
    iterations : int
        Number of lambda|mu pairs.
    lam : float
        Shrinking factor lambda (0 < lam < 1).
    pass_band : float
        Pass-band frequency ``k_PB``; ``mu = 1 / (k_PB - 1 / lam)``.
    fixed : ndarray of bool, shape (n,), optional
        Vertices that do not move; default the caps and their rims (``held_vertices``).

    Returns
    -------
    pyvista.PolyData
        Same connectivity and labels, smoothed points.
    """
    mu = 1.0 / (pass_band - 1.0 / lam)
    return _filter(surface, [lam, mu], iterations, fixed)


def laplacian_smooth(surface: pv.PolyData, iterations: int = 30, lam: float = 0.5,
                     fixed: np.ndarray | None = None) -> pv.PolyData:
    """Plain Laplacian (umbrella) smoothing, ``p += lam L p`` per iteration: it shrinks the surface.

    Parameters are those of ``taubin_smooth``; kept for comparison with it.
    """
    return _filter(surface, [lam], iterations, fixed)
