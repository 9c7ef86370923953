"""Spalart-Allmaras one-equation turbulence model and the exact distance to the wall triangles.

The model (Spalart & Allmaras 1992/1994, constants in validation.md, without the trip terms) transports
``nut_hat`` explicitly with the same element-by-element Galerkin residual and characteristic-Galerkin
(dt/2) stabilisation as the momentum step; production and destruction are evaluated at the nodes with the
recovered (volume-averaged) vorticity and the exact wall distance, with the usual ``S_hat >= 0.3 Omega``
limiter.  ``nut_hat`` is 0 on the wall and ``inflow_ratio * nu`` at the inlet; ``nu_t = nut_hat f_v1`` is
added to the viscosity of the momentum step.

The wall distance is exact to the triangulated wall: candidate triangles come from a k-d tree of triangle
centroids (scipy), and a candidate set is accepted only when it provably contains the nearest triangle
(no triangle whose centroid lies farther than the k-th candidate, minus the largest centroid-to-vertex
radius, can be closer); the remaining points are checked against every triangle within that bound.
The point-triangle distance is Ericson's closest-point algorithm (Real-Time Collision Detection, 5.1.5)
in a numba kernel: no library offers a vectorised exact point-to-triangle distance.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from carotid.flow import assembly as asm
from carotid.flow.mesh import INLET, WALL, FlowMesh

CB1, CB2, SIGMA, KAPPA = 0.1355, 0.622, 2.0 / 3.0, 0.41
CW1 = CB1 / KAPPA**2 + (1.0 + CB2) / SIGMA
CW2, CW3, CV1 = 0.3, 2.0, 7.1


@nb.njit(cache=True, inline="always")
def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


@nb.njit(cache=True)
def _closest_sq(p, a, b, c):
    """Squared distance from point p to triangle abc (Ericson 2005, closest point on triangle)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = _dot(ab, ap)
    d2 = _dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        q = a
    else:
        bp = p - b
        d3 = _dot(ab, bp)
        d4 = _dot(ac, bp)
        cp = p - c
        d5 = _dot(ab, cp)
        d6 = _dot(ac, cp)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            q = b
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            q = a + (d1 / (d1 - d3)) * ab
        elif d6 >= 0.0 and d5 <= d6:
            q = c
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            q = a + (d2 / (d2 - d6)) * ac
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            q = b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
        else:
            den = 1.0 / (va + vb + vc)
            q = a + ab * (vb * den) + ac * (vc * den)
    d = p - q
    return _dot(d, d)


@nb.njit(cache=True)
def _pair_distances(points, tri_pts, pidx, tidx, out):
    """``out[k] = |points[pidx[k]] - triangle tidx[k]|^2`` for candidate pairs."""
    for k in range(len(pidx)):
        t = tidx[k]
        out[k] = _closest_sq(points[pidx[k]], tri_pts[t, 0], tri_pts[t, 1], tri_pts[t, 2])


def point_triangle_distance(points: np.ndarray, triangles: np.ndarray, k: int = 8) -> np.ndarray:
    """Exact Euclidean distance from each point to the nearest triangle.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    triangles : ndarray, shape (t, 3, 3)
        Triangle vertex coordinates.
    k : int
        Candidate triangles tried first per point.

    Returns
    -------
    ndarray, shape (n,)
        Distances, same unit as the input.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    tri = np.ascontiguousarray(triangles, dtype=np.float64)
    centroids = tri.mean(axis=1)
    radius = float(np.linalg.norm(tri - centroids[:, None], axis=2).max())
    tree = cKDTree(centroids)
    k = min(k, len(tri))
    dist_c, cand = tree.query(points, k=k)
    dist_c, cand = dist_c.reshape(len(points), k), cand.reshape(len(points), k)
    sq = np.empty(cand.size)
    _pair_distances(points, tri, np.repeat(np.arange(len(points)), k), cand.ravel(), sq)
    best = np.sqrt(sq.reshape(-1, k).min(axis=1))
    unsure = np.flatnonzero(best > dist_c[:, -1] - radius) if k < len(tri) else np.zeros(0, np.int64)
    if len(unsure):
        lists = tree.query_ball_point(points[unsure], best[unsure] + radius)
        lengths = np.array([len(c) for c in lists])
        pidx = np.repeat(unsure, lengths)
        tidx = np.concatenate(lists).astype(np.int64)
        sq = np.empty(len(pidx))
        _pair_distances(points, tri, pidx, tidx, sq)
        low = np.full(len(points), np.inf)
        np.minimum.at(low, pidx, sq)
        best[unsure] = np.minimum(best[unsure], np.sqrt(low[unsure]))
    return best


def wall_distance(mesh: FlowMesh) -> np.ndarray:
    """Exact distance of every mesh node to the wall triangles (label 1), m, shape (n,); 0 on the wall."""
    d = point_triangle_distance(mesh.points, mesh.points[mesh.faces[mesh.labels == WALL]])
    d[mesh.face_nodes(WALL)] = 0.0
    return d


@nb.njit(cache=True)
def _transport_residual(tets, grads, volumes, u, phi, diff_e, half_dt, out):
    """``out_i = -int N_i u.grad phi - int D_e grad N_i.grad phi - (dt/2) int (u.grad N_i)(u.grad phi)
    + int N_i (c_b2/sigma) |grad phi|^2`` for a P1 scalar ``phi`` (n,); overwrites ``out``."""
    out[:] = 0.0
    for e in range(tets.shape[0]):
        v = volumes[e]
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        ub0 = 0.0
        ub1 = 0.0
        ub2 = 0.0
        for k in range(4):
            nk = tets[e, k]
            g0 += phi[nk] * grads[e, k, 0]
            g1 += phi[nk] * grads[e, k, 1]
            g2 += phi[nk] * grads[e, k, 2]
            ub0 += 0.25 * u[nk, 0]
            ub1 += 0.25 * u[nk, 1]
            ub2 += 0.25 * u[nk, 2]
        a = np.empty(4)
        sa = 0.0
        for k in range(4):
            nk = tets[e, k]
            a[k] = u[nk, 0] * g0 + u[nk, 1] * g1 + u[nk, 2] * g2
            sa += a[k]
        cb = ub0 * g0 + ub1 * g1 + ub2 * g2
        src = 0.25 * v * (CB2 / SIGMA) * (g0 * g0 + g1 * g1 + g2 * g2)
        for i in range(4):
            gi0 = grads[e, i, 0]
            gi1 = grads[e, i, 1]
            gi2 = grads[e, i, 2]
            ug = (ub0 * gi0 + ub1 * gi1 + ub2 * gi2) * half_dt * v
            out[tets[e, i]] += src - v / 20.0 * (sa + a[i]) - diff_e[e] * v * (gi0 * g0 + gi1 * g1 + gi2 * g2) \
                - ug * cb


class SpalartAllmaras:
    """Explicit Spalart-Allmaras transport on a :class:`FlowMesh`.

    Parameters
    ----------
    mesh : FlowMesh
    nu : float
        Molecular kinematic viscosity, m^2/s.
    inflow_ratio : float
        ``nut_hat / nu`` prescribed at the inlet (and the initial value in the fluid).
    """

    def __init__(self, mesh: FlowMesh, nu: float, inflow_ratio: float = 3.0):
        self.mesh, self.nu, self.inflow_ratio = mesh, float(nu), float(inflow_ratio)
        self.volumes, self.grads = asm.element_geometry(mesh.points, mesh.tets)
        self.mass = asm.lumped_mass(self.volumes, mesh.tets, mesh.n_points)
        self.d = wall_distance(mesh)
        self.wall = mesh.face_nodes(WALL)
        self.inlet = np.setdiff1d(mesh.face_nodes(INLET), self.wall)
        self._res = np.zeros(mesh.n_points)
        self._grad = np.empty((len(mesh.tets), 3, 3))

    def initial(self, n: int) -> np.ndarray:
        """Initial ``nut_hat`` (n,), m^2/s."""
        return np.full(n, self.inflow_ratio * self.nu)

    def apply_bc(self, nut_hat: np.ndarray) -> None:
        nut_hat[self.wall] = 0.0
        nut_hat[self.inlet] = self.inflow_ratio * self.nu

    def fv1(self, nut_hat: np.ndarray) -> np.ndarray:
        chi3 = (nut_hat / self.nu) ** 3
        return chi3 / (chi3 + CV1**3)

    def nu_t(self, nut_hat: np.ndarray) -> np.ndarray:
        """Eddy viscosity ``nut_hat f_v1`` (n,), m^2/s."""
        return nut_hat * self.fv1(nut_hat)

    def diffusivity_bound(self, nut_hat: np.ndarray, tets: np.ndarray) -> np.ndarray:
        """Largest diffusivity of the ``nut_hat`` equation per element, ``(nu + nut_hat) / sigma``, m^2/s."""
        return (self.nu + nut_hat[tets].max(axis=1)) / SIGMA

    def sources(self, nut_hat: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Production minus destruction at the nodes, m^2/s^2, shape (n,)."""
        asm.velocity_gradients(self.mesh.tets, self.grads, u, self._grad)
        g = self._grad
        w = np.stack([g[:, 2, 1] - g[:, 1, 2], g[:, 0, 2] - g[:, 2, 0], g[:, 1, 0] - g[:, 0, 1]], 1)
        omega = asm.nodal_average(np.linalg.norm(w, axis=1), self.volumes, self.mesh.tets, self.mesh.n_points)
        d2 = np.maximum(self.d, 1e-12) ** 2
        chi = nut_hat / self.nu
        fv2 = 1.0 - chi / (1.0 + chi * self.fv1(nut_hat))
        s_hat = np.maximum(omega + nut_hat * fv2 / (KAPPA**2 * d2), 0.3 * omega)
        r = np.minimum(nut_hat / np.maximum(s_hat * KAPPA**2 * d2, 1e-300), 10.0)
        gg = r + CW2 * (r**6 - r)
        fw = gg * ((1.0 + CW3**6) / (gg**6 + CW3**6)) ** (1.0 / 6.0)
        return CB1 * s_hat * nut_hat - CW1 * fw * nut_hat**2 / d2

    def step(self, nut_hat: np.ndarray, u: np.ndarray, dt: float, nu_e=None) -> np.ndarray:
        """Advance ``nut_hat`` (n,) by ``dt`` in the velocity ``u`` (n, 3); returns the new array."""
        diff_e = (self.nu + nut_hat[self.mesh.tets].mean(axis=1)) / SIGMA
        _transport_residual(self.mesh.tets, self.grads, self.volumes, u, nut_hat, diff_e, 0.5 * dt, self._res)
        new = nut_hat + dt * (self._res / self.mass + self.sources(nut_hat, u))
        np.maximum(new, 0.0, out=new)
        self.apply_bc(new)
        return new
