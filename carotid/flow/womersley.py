"""Womersley inlet profiles: the analytic solution in a circular pipe and its generalisation to any inlet face.

Analytic (Womersley 1957; formulas of validation.md): for a rigid pipe of radius R and the waveform's
harmonics Q_k, with Lambda_k = i^{3/2} alpha sqrt(k) and alpha = R sqrt(omega / nu), the axial velocity and
the wall shear stress are sums over harmonics of closed-form Bessel-function profiles.  The Bessel
functions of complex argument come from ``scipy.special.jve`` (exponentially scaled, so large alpha does not
overflow).

Generalised (Sazonov et al. 2011, Int J Numer Meth Biomed Eng 27:1167): on the actual inlet face, for each
harmonic k solve the 2D problem

    nu Lap(w_k) - i k omega w_k = -1   on the face,     w_k = 0 on its rim,

with P1 triangles, and scale w_k so that its flux is Q_k.  The face is projected onto the plane normal to
the inflow axis, so the flux of the axial velocity through the projected face is the flux through the
face.  P1 assembly is a few vectorised lines of scipy.sparse; the 2D systems are small and solved
directly (``scipy.sparse.linalg.spsolve``).  scikit-fem could assemble these forms too, but it is not a
dependency of the package and the two forms here do not justify one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from scipy.special import jve

from carotid.errors import CarotidError
from carotid.flow.waveform import Waveform, fourier_flow


def womersley_number(radius_m: float, period_s: float, nu: float) -> float:
    """alpha = R sqrt(omega / nu) with omega = 2 pi / T (R in m, T in s, nu in m^2/s)."""
    return radius_m * math.sqrt(2.0 * math.pi / period_s / nu)


def womersley_lambdas(alpha: float, n: int) -> np.ndarray:
    """Lambda_k = i^{3/2} alpha sqrt(k) for the harmonics k = 1..n, shape (n,)."""
    return np.exp(0.75j * math.pi) * alpha * np.sqrt(np.arange(1, n + 1))


def womersley_shape(xi: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Oscillatory profile per unit flow, ``u_k(xi) / (Q_k / (pi R^2))``, shape (len(lam),) + xi.shape.

    ``[J0(Lambda) - J0(Lambda xi)] / [J0(Lambda) - 2 J1(Lambda) / Lambda]`` written with the scaled Bessel
    functions: ``J0(Lambda xi) / J0(Lambda) = jve(0, Lambda xi) / jve(0, Lambda) exp(|Im Lambda| (xi - 1))``.

    Parameters
    ----------
    xi : ndarray
        r / R, in [0, 1].
    lam : ndarray, shape (n,)
        Lambda_k (non-zero).
    """
    lam = lam.reshape((-1,) + (1,) * np.ndim(xi))
    j0 = jve(0, lam)
    ratio = jve(0, lam * xi) / j0 * np.exp(np.abs(lam.imag) * (xi - 1.0))
    return (1.0 - ratio) / (1.0 - 2.0 * jve(1, lam) / (lam * j0))


def womersley_wall_factor(lam: np.ndarray) -> np.ndarray:
    """``tau_k / (4 mu Q_k / (pi R^3))`` = ``Lambda^2 J1 / (4 [2 J1 - Lambda J0])``, shape of ``lam``."""
    r1 = jve(1, lam) / jve(0, lam)
    return lam**2 * r1 / (4.0 * (2.0 * r1 - lam))


def _check_radius(radius_m: float) -> float:
    if not (math.isfinite(radius_m) and radius_m > 0):
        raise CarotidError(f"pipe radius must be positive, got {radius_m} m")
    return float(radius_m)


def womersley_velocity(r, t: float, R: float, waveform: Waveform, nu: float, n_harmonics: int = 10) -> np.ndarray:
    """Analytic Womersley axial velocity in a rigid circular pipe.

    Parameters
    ----------
    r : array_like
        Radial positions, m, in [0, R].
    t : float
        Time, s.
    R : float
        Pipe radius, m.
    waveform : Waveform
        Flow rate Q(t); its harmonics 0..n_harmonics are used.
    nu : float
        Kinematic viscosity, m^2/s.
    n_harmonics : int
        Number of oscillatory harmonics.

    Returns
    -------
    ndarray, shape of ``r``
        Axial velocity, m/s (positive along the flow).
    """
    R = _check_radius(R)
    xi = np.asarray(r, dtype=float) / R
    if np.any(xi < -1e-12) or np.any(xi > 1.0 + 1e-9):
        raise CarotidError("womersley_velocity: radial positions must lie in [0, R]")
    xi = np.clip(xi, 0.0, 1.0)
    q = waveform.harmonics(n_harmonics)
    u = 2.0 * q[0].real / (math.pi * R**2) * (1.0 - xi**2)
    if n_harmonics > 0:
        lam = womersley_lambdas(womersley_number(R, waveform.period_s, nu), n_harmonics)
        phase = q[1:] * np.exp(1j * np.arange(1, n_harmonics + 1) * waveform.omega * t) / (math.pi * R**2)
        u = u + np.real(np.tensordot(phase, womersley_shape(xi, lam), axes=(0, 0)))
    return u


def womersley_pressure_gradient(t, R: float, waveform, nu: float, n_harmonics: int = 10):
    """Analytic Womersley axial pressure gradient in a rigid circular pipe, ``-(1/rho) dp/dz``, m/s^2.

    ``-(1/rho) dp/dz = Re sum_k A_k e^{i k omega t}`` with ``A_0 = 8 nu Q_0 / (pi R^4)`` and, for k >= 1,
    ``A_k = (8 nu Q_k / (pi R^4)) (i k alpha^2 / 8) / (1 - 2 J1(Lambda_k) / (Lambda_k J0(Lambda_k)))``: the
    momentum equation for ``u = Re u_k(r) e^{i k omega t}`` gives
    ``u_k = (A_k / (i k omega)) (1 - J0(Lambda_k r/R) / J0(Lambda_k))``, whose flux is
    ``(A_k / (i k omega)) pi R^2 (1 - 2 J1 / (Lambda_k J0))`` = Q_k (Womersley 1955; validation.md notation).

    Parameters
    ----------
    t : float or ndarray
        Time(s), s.
    R : float
        Pipe radius, m.
    waveform : Waveform
        Flow rate Q(t).
    nu : float
        Kinematic viscosity, m^2/s.
    n_harmonics : int

    Returns
    -------
    float or ndarray
        Shape of ``t``; positive when the pressure falls along the flow.
    """
    alpha = womersley_number(R, waveform.period_s, nu)
    factors = np.ones(n_harmonics + 1, dtype=complex)
    if n_harmonics > 0:
        lam = womersley_lambdas(alpha, n_harmonics)
        k = np.arange(1, n_harmonics + 1)
        factors[1:] = (1j * k * alpha**2 / 8.0) / (1.0 - 2.0 * jve(1, lam) / (lam * jve(0, lam)))
    return 8.0 * nu / (np.pi * R**4) * fourier_flow(waveform.harmonics(n_harmonics) * factors, waveform.omega, t)


def womersley_wss(t: float, R: float, waveform: Waveform, mu: float, nu: float, n_harmonics: int = 10) -> float:
    """Analytic Womersley wall shear stress in a rigid circular pipe, Pa, positive along the flow.

    ``tau_w = 4 mu Q_0 / (pi R^3) + Re sum_k (mu Q_k / (pi R^3)) Lambda_k^2 J1 / (2 J1 - Lambda_k J0) e^{i k w t}``.

    Parameters
    ----------
    t : float or ndarray
        Time(s), s.
    R : float
        Pipe radius, m.
    waveform : Waveform
        Flow rate Q(t).
    mu, nu : float
        Dynamic (Pa s) and kinematic (m^2/s) viscosity.
    n_harmonics : int
        Number of oscillatory harmonics.

    Returns
    -------
    float or ndarray
        Shape of ``t``.
    """
    R = _check_radius(R)
    q = waveform.harmonics(n_harmonics)
    factors = np.ones(n_harmonics + 1, dtype=complex)
    if n_harmonics > 0:
        factors[1:] = womersley_wall_factor(womersley_lambdas(womersley_number(R, waveform.period_s, nu), n_harmonics))
    tau = 4.0 * mu / (math.pi * R**3) * fourier_flow(q * factors, waveform.omega, t)
    return float(tau) if np.ndim(tau) == 0 else tau


@dataclass(frozen=True, eq=False)
class InletProfile:
    """Axial velocity on an inlet face, a sum of harmonic modes carrying the prescribed flow exactly.

    Attributes
    ----------
    nodes : ndarray, shape (p, 3)
        Face node coordinates as given, m.
    triangles : ndarray, shape (t, 3)
        Face triangles (indices into ``nodes``).
    normal : ndarray, shape (3,)
        Unit axis of the inlet; the face was projected onto the plane normal to it.
    mass : ndarray, shape (p,)
        Nodal area weights, m^2: the row sums of the P1 mass matrix of the projected face (identical for
        the consistent and the lumped mass, and zero at nodes used by no triangle).  For any nodal field
        v, ``mass @ v`` is the exact P1 integral over the face, hence the flux of the axial velocity.
        A solver imposing nodal velocities should use these weights (its lumped boundary mass) to
        measure the inflow; with them ``mass @ velocity(t) == flow(t)`` to rounding.  The weights are
        those of the face projected on the plane normal to ``normal``: the flux of an axial velocity
        through the face.  A solver measuring the flux with its own 3D face areas must weight them by
        the cosine between the face normal and ``normal`` (equal for a flat face normal to it).
    rim : ndarray of bool, shape (p,)
        Nodes on the face boundary (on edges used by one triangle), where the velocity is 0.
    modes : ndarray of complex, shape (n + 1, p)
        W_k, m/s: ``velocity(t) = Re sum_k W_k exp(i k omega t)``.  ``modes[0]`` is real (steady,
        Poiseuille-like).
    flow_harmonics : ndarray of complex, shape (n + 1,)
        Q_k of the waveform, m^3/s; ``mass @ modes[k] == flow_harmonics[k]``.
    omega : float
        2 pi / T, rad/s.
    """

    nodes: np.ndarray
    triangles: np.ndarray
    normal: np.ndarray
    mass: np.ndarray
    rim: np.ndarray
    modes: np.ndarray
    flow_harmonics: np.ndarray
    omega: float

    def velocity(self, t) -> np.ndarray:
        """Axial speed at the face nodes at time(s) t, m/s, shape ``np.shape(t) + (p,)``; 0 on the rim."""
        t = np.asarray(t, dtype=float)
        phase = np.exp(1j * self.omega * t[..., None] * np.arange(len(self.modes)))
        return np.real(phase @ self.modes)

    def flux(self, t):
        """Flux of ``velocity(t)`` through the face, ``velocity(t) @ mass``, m^3/s."""
        out = self.velocity(t) @ self.mass
        return float(out) if np.ndim(out) == 0 else out

    def flow(self, t):
        """Prescribed flow, the waveform truncated to the harmonics used, m^3/s (equals ``flux(t)``)."""
        out = fourier_flow(self.flow_harmonics, self.omega, t)
        return float(out) if np.ndim(out) == 0 else out


def _plane_coordinates(points: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal and the 2D coordinates (p, 2) of ``points`` in the plane normal to it (origin: centroid)."""
    n = normal / np.linalg.norm(normal)
    helper = np.eye(3)[np.argmin(np.abs(n))]
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    rel = points - points.mean(axis=0)
    return n, np.column_stack([rel @ e1, rel @ e2])


def p1_matrices(xy: np.ndarray, triangles: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix, np.ndarray]:
    """P1 stiffness and consistent mass matrices of a planar triangulation.

    Parameters
    ----------
    xy : ndarray, shape (p, 2)
        Node coordinates, m.
    triangles : ndarray, shape (t, 3)
        Triangles, any orientation.

    Returns
    -------
    stiffness, mass : csr_matrix, shape (p, p)
        ``int grad(phi_i) . grad(phi_j)`` and ``int phi_i phi_j`` (m^2).
    signed_area : ndarray, shape (t,)
        Signed triangle areas, m^2.
    """
    p = xy[triangles]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    area = 0.5 * np.abs(det)
    g1 = np.column_stack([d2[:, 1], -d2[:, 0]]) / det[:, None]
    g2 = np.column_stack([-d1[:, 1], d1[:, 0]]) / det[:, None]
    grads = np.stack([-g1 - g2, g1, g2], axis=1)  # (t, 3, 2)
    k_local = area[:, None, None] * np.einsum("tid,tjd->tij", grads, grads)
    m_local = area[:, None, None] * (np.ones((3, 3)) + np.eye(3)) / 12.0
    rows = np.repeat(triangles, 3, axis=1).ravel()
    cols = np.tile(triangles, (1, 3)).ravel()
    shape = (len(xy), len(xy))
    stiffness = sp.csr_matrix((k_local.ravel(), (rows, cols)), shape=shape)
    mass = sp.csr_matrix((m_local.ravel(), (rows, cols)), shape=shape)
    return stiffness, mass, 0.5 * det


def rim_nodes(triangles: np.ndarray, n_points: int) -> np.ndarray:
    """Boolean mask (n_points,) of nodes on edges used by exactly one triangle."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    mask = np.zeros(n_points, dtype=bool)
    mask[unique[counts == 1].ravel()] = True
    return mask


def _check_face(points, triangles, normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles)
    normal = np.asarray(normal, dtype=float).ravel()
    if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
        raise CarotidError(f"inlet face points must be a finite (p, 3) array, got shape {points.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0 \
            or not np.issubdtype(triangles.dtype, np.integer):
        raise CarotidError(f"inlet face triangles must be a non-empty (t, 3) integer array, got {triangles.shape}")
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise CarotidError("inlet face triangles refer to points that do not exist")
    if normal.shape != (3,) or not np.all(np.isfinite(normal)) or np.linalg.norm(normal) == 0:
        raise CarotidError(f"inlet normal must be a non-zero 3-vector, got {normal}")
    return points, triangles.astype(np.int64), normal


def inlet_profile(points, triangles, normal, waveform: Waveform, nu: float, n_harmonics: int = 10) -> InletProfile:
    """Generalised Womersley inlet profile on a triangulated inlet face.

    For each harmonic k = 0..n of the waveform solve, with P1 elements on the face projected onto the
    plane normal to ``normal``,

        nu Lap(w_k) - i k omega w_k = -1,   w_k = 0 on the rim,

    i.e. ``(nu K + i k omega M) w_k = M 1`` on the interior nodes, and scale ``W_k = w_k Q_k / (m . w_k)``
    so that the P1 flux ``m . W_k`` (``m`` the nodal area weights) equals Q_k exactly.  On a circle this is
    the discrete Womersley profile; k = 0 is the steady Poiseuille-like profile of the section.

    Parameters
    ----------
    points : array_like, shape (p, 3)
        Face node coordinates, m.  Nodes used by no triangle get zero velocity and zero weight.
    triangles : array_like of int, shape (t, 3)
        Face triangles.
    normal : array_like, shape (3,)
        Axis of the inlet (any length, either sign); the velocity is along it.
    waveform : Waveform
        Inlet flow rate.
    nu : float
        Kinematic viscosity, m^2/s.
    n_harmonics : int
        Number of oscillatory harmonics (the flux is the waveform truncated to them).

    Returns
    -------
    InletProfile

    Raises
    ------
    CarotidError
        Malformed arrays, degenerate triangles, a face that folds over when projected (its normal is far
        from ``normal``; detected as projected triangles of both orientations, so the triangles must be
        consistently wound), a face without a rim or without interior nodes.
    """
    points, triangles, normal = _check_face(points, triangles, normal)
    if not (math.isfinite(nu) and nu > 0):
        raise CarotidError(f"kinematic viscosity must be positive, got {nu} m^2/s")
    unit, xy = _plane_coordinates(points, normal)
    stiffness, mass, signed = p1_matrices(xy, triangles)
    scale = np.ptp(xy, axis=0).prod()
    if np.any(np.abs(signed) <= 1e-12 * scale):
        raise CarotidError("the inlet face has degenerate triangles (zero area in the plane of the inlet normal)")
    if np.any(signed > 0) and np.any(signed < 0):
        raise CarotidError("the inlet face folds over when projected on the plane of the inlet normal: "
                           "the normal is not the axis of this face, the face is not planar, or its triangles "
                           "are not consistently oriented")
    rim = rim_nodes(triangles, len(points))
    used = np.zeros(len(points), dtype=bool)
    used[triangles.ravel()] = True
    if not rim.any():
        raise CarotidError("the inlet face has no boundary (it is a closed surface)")
    free = np.flatnonzero(used & ~rim)
    if free.size == 0:
        raise CarotidError("the inlet face has no interior nodes: refine its triangulation")
    weights = np.asarray(mass.sum(axis=1)).ravel()
    q = waveform.harmonics(n_harmonics)
    k_ff = stiffness[free][:, free].tocsc()
    m_ff = mass[free][:, free].tocsc()
    modes = np.zeros((n_harmonics + 1, len(points)), dtype=complex)
    for k in range(n_harmonics + 1):
        system = nu * k_ff + (1j * k * waveform.omega) * m_ff
        w = np.atleast_1d(spsolve(system, weights[free].astype(complex), permc_spec="MMD_AT_PLUS_A"))
        modes[k, free] = w * (q[k] / (weights[free] @ w))
    modes[0] = modes[0].real
    return InletProfile(nodes=points, triangles=triangles, normal=unit, mass=weights, rim=rim, modes=modes,
                        flow_harmonics=q, omega=waveform.omega)
