"""P1 element geometry, the pressure stiffness matrix and the element-by-element explicit CBS terms.

The explicit terms of the characteristic-based split are assembled element by element: each tetrahedron
computes its own contribution from its four nodal values and scatters it to its nodes (numba kernels, one
pass over the elements, serial: the scatter is memory-bound and ``prange`` does not pay on 2 cores, see
dependencies.md).  This is the locally conservative Galerkin (LCG) form of Nithiarasu (2004) and Thomas &
Nithiarasu (2008) with the interface fluxes taken from the averaged nodal solution of the previous step:
the element-wise balances then sum, node by node, to the standard Galerkin residual with a lumped mass,
which is what the kernels compute (no global matrix for the explicit steps).  No library offers these
CBS element kernels, hence hand-written numba; the global Laplacian is assembled with scipy.sparse.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import scipy.sparse as sp


def element_geometry(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Volumes and P1 shape-function gradients of every tetrahedron.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Node coordinates, m.
    tets : ndarray, shape (m, 4)
        Positively oriented tetrahedra.

    Returns
    -------
    volumes : ndarray, shape (m,)
        m^3.
    grads : ndarray, shape (m, 4, 3)
        ``grads[e, i]`` is the (constant) gradient of the hat function of local node ``i``, 1/m.
    """
    p = points[tets]
    d = p[:, 1:] - p[:, :1]  # rows: x1-x0, x2-x0, x3-x0
    volumes = np.linalg.det(d) / 6.0
    g = np.empty((len(tets), 4, 3))
    g[:, 1:] = np.linalg.inv(d).transpose(0, 2, 1)  # grad lambda_i = row i of inv(D)^T
    g[:, 0] = -g[:, 1:].sum(axis=1)
    return volumes, g


def element_size(grads: np.ndarray) -> np.ndarray:
    """Length scale per element from its largest local stiffness eigenvalue, m, shape (m,).

    ``h_e = 2 / sqrt(lambda_max(M_e^-1 K_e))`` with the lumped element mass, so that the explicit diffusion
    limit ``h_e^2 / (2 nu)`` equals ``2 / (nu lambda_max)``: the forward-Euler bound of the assembled
    lumped-mass system (its largest eigenvalue is at most the largest element one).  For a right-angled
    slab element of thickness delta, h_e is about delta.
    """
    lam = 4.0 * np.linalg.eigvalsh(np.einsum("eib,eic->ebc", grads, grads))[:, -1]
    return 2.0 / np.sqrt(lam)


def lumped_mass(volumes: np.ndarray, tets: np.ndarray, n: int) -> np.ndarray:
    """Row-sum lumped P1 mass, m^3, shape (n,)."""
    return np.bincount(tets.ravel(), np.repeat(volumes / 4.0, 4), minlength=n)


def stiffness_matrix(volumes: np.ndarray, grads: np.ndarray, tets: np.ndarray, n: int) -> sp.csr_matrix:
    """P1 Laplacian ``K_ij = sum_e V_e grad N_i . grad N_j`` (symmetric positive semi-definite), m."""
    ke = volumes[:, None, None] * np.einsum("eic,ejc->eij", grads, grads)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    k = sp.coo_matrix((ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    k.sum_duplicates()
    return k


class StiffnessBlock:
    """A block of the weighted P1 Laplacian ``K(w)_ij = sum_e w_e V_e grad N_i . grad N_j``, re-assembled in
    place for new element weights without rebuilding its sparsity pattern (for an element viscosity that
    changes every step).

    Parameters
    ----------
    volumes : ndarray, shape (m,)
        Element volumes, m^3.
    grads : ndarray, shape (m, 4, 3)
        Shape-function gradients, 1/m.
    tets : ndarray, shape (m, 4)
    n : int
        Number of nodes.
    rows, cols : ndarray of int
        Global node indices of the block's rows and columns (in that order).
    """

    def __init__(self, volumes, grads, tets, n: int, rows: np.ndarray, cols: np.ndarray):
        local_rows, local_cols = np.full(n, -1), np.full(n, -1)
        local_rows[rows], local_cols[cols] = np.arange(len(rows)), np.arange(len(cols))
        er = local_rows[np.repeat(tets, 4, axis=1)].ravel()
        ec = local_cols[np.tile(tets, (1, 4))].ravel()
        keep = np.flatnonzero((er >= 0) & (ec >= 0))
        self._element = (keep // 16).astype(np.int32)
        self._values = (volumes[:, None, None] * np.einsum("eic,ejc->eij", grads, grads)).ravel()[keep]
        keys = er[keep].astype(np.int64) * len(cols) + ec[keep]
        unique, pos = np.unique(keys, return_inverse=True)
        self._pos = pos.astype(np.int32)
        indptr = np.r_[0, np.cumsum(np.bincount(unique // len(cols), minlength=len(rows)))]
        self.matrix = sp.csr_matrix((np.zeros(len(unique)), unique % len(cols), indptr), shape=(len(rows), len(cols)))

    def update(self, weights: np.ndarray) -> sp.csr_matrix:
        """The block for element weights ``weights`` (m,) (a viscosity in m^2/s: the viscous matrix), written
        into ``self.matrix``, which is returned."""
        _scatter_weighted(self._pos, self._values, self._element, np.ascontiguousarray(weights, dtype=float),
                          self.matrix.data)
        return self.matrix


@nb.njit(cache=True)
def _scatter_weighted(pos, values, element, weights, out):
    """``out[:] = 0; out[pos[i]] += values[i] * weights[element[i]]``."""
    out[:] = 0.0
    for i in range(len(pos)):
        out[pos[i]] += values[i] * weights[element[i]]


@nb.njit(cache=True, fastmath=False)
def momentum_residual(tets, grads, volumes, u, nu_e, half_dt, out):
    """Explicit CBS momentum residual, scattered to ``out`` (n, 3), which it overwrites.

    ``out_i = -int N_i (u.grad)u - int nu grad N_i : grad u - (dt/2) int (u.grad N_i)(u.grad u)``
    per unit density, m^4/s^2: Galerkin convection with the consistent element mass of the linear velocity,
    Laplacian-form viscous term (traction-free natural outflow), and the characteristic-Galerkin
    stabilisation with the element-mean convecting velocity.

    Parameters
    ----------
    tets (m, 4), grads (m, 4, 3), volumes (m,), u (n, 3) m/s, nu_e (m,) m^2/s, half_dt : float (s).
    """
    out[:] = 0.0
    g = np.empty((3, 3))
    a = np.empty((4, 3))
    for e in range(tets.shape[0]):
        v = volumes[e]
        ub0 = 0.0
        ub1 = 0.0
        ub2 = 0.0
        for r in range(3):
            for c in range(3):
                g[r, c] = 0.0
        for k in range(4):
            nk = tets[e, k]
            ub0 += 0.25 * u[nk, 0]
            ub1 += 0.25 * u[nk, 1]
            ub2 += 0.25 * u[nk, 2]
            for r in range(3):
                for c in range(3):
                    g[r, c] += u[nk, r] * grads[e, k, c]  # g[r, c] = d u_r / d x_c
        sa0 = 0.0
        sa1 = 0.0
        sa2 = 0.0
        for k in range(4):
            nk = tets[e, k]
            for r in range(3):
                a[k, r] = g[r, 0] * u[nk, 0] + g[r, 1] * u[nk, 1] + g[r, 2] * u[nk, 2]
            sa0 += a[k, 0]
            sa1 += a[k, 1]
            sa2 += a[k, 2]
        cb0 = g[0, 0] * ub0 + g[0, 1] * ub1 + g[0, 2] * ub2  # (u.grad)u with the element-mean u
        cb1 = g[1, 0] * ub0 + g[1, 1] * ub1 + g[1, 2] * ub2
        cb2 = g[2, 0] * ub0 + g[2, 1] * ub1 + g[2, 2] * ub2
        c20 = v / 20.0
        nv = nu_e[e] * v
        for i in range(4):
            ni = tets[e, i]
            gi0 = grads[e, i, 0]
            gi1 = grads[e, i, 1]
            gi2 = grads[e, i, 2]
            ug = (ub0 * gi0 + ub1 * gi1 + ub2 * gi2) * half_dt * v
            out[ni, 0] -= c20 * (sa0 + a[i, 0]) + nv * (g[0, 0] * gi0 + g[0, 1] * gi1 + g[0, 2] * gi2) + ug * cb0
            out[ni, 1] -= c20 * (sa1 + a[i, 1]) + nv * (g[1, 0] * gi0 + g[1, 1] * gi1 + g[1, 2] * gi2) + ug * cb1
            out[ni, 2] -= c20 * (sa2 + a[i, 2]) + nv * (g[2, 0] * gi0 + g[2, 1] * gi1 + g[2, 2] * gi2) + ug * cb2


@nb.njit(cache=True, inline="always")
def _vertex_sum(tets, u, e):
    """Sum of ``u`` (n, 3) over the four vertices of element ``e``, as three scalars."""
    a = 0.0
    b = 0.0
    c = 0.0
    for k in range(4):
        nk = tets[e, k]
        a += u[nk, 0]
        b += u[nk, 1]
        c += u[nk, 2]
    return a, b, c


@nb.njit(cache=True)
def weak_divergence(tets, grads, volumes, u, out):
    """``out_i = int grad N_i . u dV`` (n,), m^3/s, for a P1 velocity ``u`` (n, 3); overwrites ``out``."""
    out[:] = 0.0
    for e in range(tets.shape[0]):
        ub0, ub1, ub2 = _vertex_sum(tets, u, e)
        v = 0.25 * volumes[e]
        for i in range(4):
            out[tets[e, i]] += v * (grads[e, i, 0] * ub0 + grads[e, i, 1] * ub1 + grads[e, i, 2] * ub2)


@nb.njit(cache=True)
def lumped_gradient(tets, grads, volumes, p, out):
    """``out_i = int N_i grad p dV`` (n, 3) for a P1 scalar ``p`` (n,); overwrites ``out``."""
    out[:] = 0.0
    for e in range(tets.shape[0]):
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for k in range(4):
            pk = p[tets[e, k]]
            g0 += pk * grads[e, k, 0]
            g1 += pk * grads[e, k, 1]
            g2 += pk * grads[e, k, 2]
        v = 0.25 * volumes[e]
        for i in range(4):
            ni = tets[e, i]
            out[ni, 0] += v * g0
            out[ni, 1] += v * g1
            out[ni, 2] += v * g2


@nb.njit(cache=True)
def velocity_gradients(tets, grads, u, out):
    """Element velocity gradients ``out[e, r, c] = d u_r / d x_c`` (m, 3, 3), 1/s; overwrites ``out``."""
    for e in range(tets.shape[0]):
        for r in range(3):
            for c in range(3):
                s = 0.0
                for k in range(4):
                    s += u[tets[e, k], r] * grads[e, k, c]
                out[e, r, c] = s


@nb.njit(cache=True)
def element_speed(tets, u, out):
    """Magnitude of the element-mean velocity (m,), m/s; overwrites ``out``."""
    for e in range(tets.shape[0]):
        a, b, c = _vertex_sum(tets, u, e)
        out[e] = 0.25 * np.sqrt(a * a + b * b + c * c)


@nb.njit(cache=True)
def element_convective_rate(tets, grads, u, out):
    """Directional convective rate ``|u_e| / h_UGN = 0.5 sum_i |u_e . grad N_i|`` per element (m,), 1/s.

    ``h_UGN`` is the element length along its mean velocity (Tezduyar & Osawa 2000): a thin wall-layer
    element crossed tangentially is long in the flow direction, so its rate is not set by its thickness.
    Overwrites ``out``.
    """
    for e in range(tets.shape[0]):
        a, b, c = _vertex_sum(tets, u, e)
        rate = 0.0
        for i in range(4):
            rate += abs(a * grads[e, i, 0] + b * grads[e, i, 1] + c * grads[e, i, 2])
        out[e] = 0.125 * rate  # 0.5 * (1/4 of the nodal sum) * sum_i


@nb.njit(cache=True)
def nodal_rate(tets, volumes, rate, mass, out):
    """Lumped-mass root mean square of the element rates ``rate`` (m,) at each node, ``sqrt(sum_e (V_e / 4)
    r_e^2 / m_i)`` with ``m_i`` the lumped mass (:func:`lumped_mass`), shape (n,), the unit of ``rate``;
    overwrites ``out``.  It is ``sqrt(nodal_average(rate**2, volumes, tets, n))`` (:func:`nodal_average`)
    without its temporaries: it runs every time step (4 ms against 41 ms on 604k tetrahedra)."""
    out[:] = 0.0
    for e in range(tets.shape[0]):
        w = 0.25 * volumes[e] * rate[e] * rate[e]
        for k in range(4):
            out[tets[e, k]] += w
    for i in range(out.shape[0]):
        out[i] = np.sqrt(out[i] / mass[i])


def nodal_average(values: np.ndarray, weights: np.ndarray, cells: np.ndarray, n: int) -> np.ndarray:
    """Weighted average at the nodes of per-cell ``values`` (c, ...) over ``cells`` (c, k) with ``weights`` (c,).

    The recovered (volume- or area-weighted) nodal field; nodes touching no cell get 0.
    """
    k = cells.shape[1]
    flat = values.reshape(len(values), -1)
    idx = cells.ravel()
    w = np.repeat(weights, k)
    den = np.bincount(idx, w, minlength=n)
    out = np.stack([np.bincount(idx, np.repeat(flat[:, j], k) * w, minlength=n) for j in range(flat.shape[1])], 1)
    out /= np.where(den > 0, den, 1.0)[:, None]
    return out.reshape((n,) + values.shape[1:])
