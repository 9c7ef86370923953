"""Semi-implicit characteristic-based split (CBS) for incompressible Newtonian flow on P1 tetrahedra.

One time step (Zienkiewicz & Codina 1995; Nithiarasu et al. 2006; validation.md, theta1 = theta2 = 1):

1. intermediate momentum, explicit, no pressure, lumped mass::

       M dU* / dt = -C(u) u - nu K u - (dt/2) S(u) u

   with the characteristic-Galerkin term ``S`` (:func:`carotid.flow.assembly.momentum_residual`);
2. pressure Poisson (kinematic pressure p / rho)::

       K_tau p = int grad N . (u^n + dU*) - int_Gamma N g.n + sum_e (tau_e - dt) int grad N . P(grad p^n)

   with ``K_tau = sum_e tau_e K_e`` assembled once, Dirichlet on the outlets, natural on walls and inlet
   (the inlet flux ``int_Gamma N g.n`` is the consistent boundary integral, like the weak divergence it
   balances); factorised once by a sparse Cholesky (CHOLMOD, from the self-contained cholespy wheel) up
   to ``PressureSolver.CHOLESKY_LIMIT`` unknowns, above that solved by conjugate gradients preconditioned
   with pyamg smoothed aggregation (hierarchy built once, warm start from the previous step);
3. correction ``u^{n+1} = u* - dt M^-1 int N grad p``, then the velocity Dirichlet conditions.

Equal-order P1 velocity and pressure are stable because the split leaves a pressure Laplacian in the
continuity equation: with ``tau_e = dt`` this is the textbook scheme (``dt K p = ...``) and the residual
``dt (K - D M^-1 G) p`` stabilises.  That O(dt) stabilisation vanishes when the global step is set by a
thin wall layer (dt ~ 3e-5 s against ~1e-3 s for the core elements) and the pressure then wiggles, so the
stabilisation uses each element's own local time step ``tau_e = 1 / (U/h_e + 2 nu/h_e^2)`` (the CBS local
time step, U the inlet velocity scale), and the extra ``(tau_e - dt)`` part is made consistent with the
lumped projection ``P(grad p^n)`` of the previous pressure gradient: the discrete continuity equation
then reads ``int grad N . u^{n+1} - int_Gamma N g.n = sum_e tau_e int grad N . (grad p^{n+1} - P grad p^n)``
(the velocity-Dirichlet nodes, where the correction is not applied, get their ``dt P grad p^n`` added back
to the right-hand side so that this holds there too), which
vanishes for a linear pressure: an orthogonal-projection stabilisation in the sense of Codina (2000),
and the discrete fully developed (Poiseuille) profile of the section is an exact steady state.

Implicit viscosity (``viscous="implicit"``, not in the paper; the default of :func:`carotid.flow.simulate`).
With explicit viscosity the global step is bounded by ``h^2 / (2 nu)`` of the thinnest wall layer: 1e-7 to
1e-6 s on a patient mesh with ten layers, millions of steps per cardiac cycle.  The implicit option treats
the molecular viscous term of step 1 by backward Euler::

       (M / dt + nu K) dU* = -C(u) u - nu_e K u - (dt/2) S(u) u + nu K (dt M^-1 P grad p^n)

``nu_e`` includes the turbulent viscosity, which stays explicit; the last, lagged term makes a steady state
independent of dt (:meth:`CBSSolver._implicit_momentum`).  The step is then bounded by the convective
limit measured along the flow (:meth:`CBSSolver.time_step`).  The Spalart-Allmaras equation stays explicit,
molecular diffusion included, so with ``turbulence`` the step is bounded as before: the gain is for laminar
runs.  Where the step can exceed ``tau_e`` the pressure stabilisation uses ``max(tau_e, dt_max)``, with
``dt_max`` the longest step the scheme takes (:meth:`CBSSolver._stabilisation_times`), so the pressure
matrix is the same for the whole run and factorised once.  The three velocity components share one
symmetric positive definite matrix ``M/dt + nu K``; it is dominated by the mass matrix and solved by
Jacobi-preconditioned conjugate gradients (about 20 iterations on a 10-layer mesh, nothing to set up, so the
adaptive step can change at every step).

Boundary conditions: rigid no-slip walls (label 1); inlet (label 2) velocity = the inlet profile's axial
speed times the inward normal; outlets (labels 3, ...) are traction-free (Laplacian-form viscous term)
with a uniform pressure per outlet.  For verification against an exact solution (``exact``), the velocity
is instead that solution's on every boundary node (walls, inlet and outlets), the outlet nodes take its
pressure, and no flow split is imposed; the boundary flux of the continuity equation is then taken over every
non-outlet face.

Lumped outlets (``outlets``, :mod:`carotid.flow.outlets`): instead of a prescribed split, each outlet's
pressure follows a resistance or RCR law of its consistent flux.  The fluxes are affine in the outlet
pressures, ``q = q0 + F c``, and the backward-Euler law is affine in the flux, ``P = R_eff q + b``, so the
step solves ``(I - R_eff F) c = R_eff q0 + b`` (implicit coupling) and then advances the Windkessel states
with the flux it gives.  Where blood re-enters through an outlet (diastole, vortices leaving a branch), the
convective energy flux ``-(rho/2) |u|^2 u.n`` feeds the domain without bound; the directional backflow
stabilisation of Esmaily-Moghadam et al. (2011, Comput Mech 48:277) adds the outlet traction
``beta rho min(u.n, 0) u`` (``backflow`` = beta, 0.2 in SimVascular; 0.5 cancels that flux), lumped at the
outlet nodes.

Mass balance and flow split.  The volume flow through an outlet is measured by the consistent flux: the
residual of the discrete continuity equation at the outlet nodes (pressure-Dirichlet rows, whose equations
are not solved), shared between outlets by boundary area where two meet (Hughes et al. 2000, "The
continuous Galerkin method is locally conservative").  The residuals of all rows sum to the inflow, so the
total consistent outflow equals the inflow up to the pressure solver's tolerance.  The outlet pressures
impose the split in that same measure every step: ``p = p0 + sum_j c_j phi_j``, where ``p0`` has zero
outlet pressure and ``phi_j`` is the discrete ``K_tau``-harmonic lifting equal to 1 on outlet j and 0 on the
others (computed once); the consistent outlet fluxes are affine in ``c`` (``-K_tau phi_j`` at the outlet
rows), so a small (outlets x outlets) system gives the ``c`` for which every outlet carries its share and
the area-weighted mean outlet pressure is zero.  ``int u.n`` of the P1 velocity over each outlet is reported
too; it differs from the consistent flux by the stabilisation flux through the outlet's element layer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse.linalg as spla

from carotid.errors import CarotidError
from carotid.flow import assembly as asm
from carotid.flow.mesh import INLET, WALL, FlowMesh
from carotid.flow.rheology import shear_rate


def murray_split(mesh: FlowMesh) -> np.ndarray:
    """Murray's law flow fractions of the outlets, ``Q_i ~ A_i^{3/2}`` (i.e. ~ D^3), shape (outlets,)."""
    a = np.array([mesh.face_area(lab) for lab in mesh.outlet_labels]) ** 1.5
    return a / a.sum()


def check_split(split, n_outlets: int) -> np.ndarray:
    """Validate user flow fractions: one per outlet, positive, summing to 1 (to 1e-6)."""
    s = np.asarray(split, dtype=float).ravel()
    if len(s) != n_outlets:
        raise CarotidError(f"the flow split has {len(s)} ratios but the mesh has {n_outlets} outlets")
    if np.any(~np.isfinite(s)) or np.any(s <= 0):
        raise CarotidError("flow split ratios must be positive numbers")
    if abs(s.sum() - 1.0) > 1e-6:
        raise CarotidError(f"flow split ratios must sum to 1 (they sum to {s.sum():.6g})")
    return s


def jacobi_preconditioner(diagonal: np.ndarray) -> spla.LinearOperator:
    """Multiplication by the inverse of ``diagonal`` (k,): the Jacobi preconditioner of a matrix with that diagonal."""
    inverse = 1.0 / diagonal
    return spla.LinearOperator((len(inverse), len(inverse)), matvec=lambda x: inverse * x, dtype=float)


class PressureSolver:
    """Repeated solves with one SPD matrix: sparse Cholesky, pyamg SA-preconditioned CG, LU, or Jacobi-CG.

    Parameters
    ----------
    matrix : scipy.sparse matrix, shape (k, k)
        Symmetric positive definite.
    method : {"auto", "cholesky", "amg", "lu", "jacobi"}
        "auto": CHOLMOD's Cholesky factorisation (cholespy) up to ``CHOLESKY_LIMIT`` unknowns, pyamg above.
        One factorisation, then each solve is two triangular sweeps: on a 10-layer tube of 490k tetrahedra
        (84k unknowns) 0.06 s per solve against 0.55 s for AMG-CG, after a 31 s factorisation (cholespy
        bundles the reference BLAS) and with 0.25 GB more memory; on a 1.09M-tetrahedron carotid mesh (190k
        unknowns) 49 s and 0.7 GB more for the set-up.  Fill-in grows faster than ``k`` in 3D, hence the
        limit.  "lu" (SuperLU) and "jacobi" are kept for comparison (benchmarks/bench_flow.py).
    rtol : float
        Relative residual ``|b - A x| / |b|`` at which the iterative methods stop.
    """

    METHODS = ("auto", "cholesky", "amg", "lu", "jacobi")
    CHOLESKY_LIMIT = 300_000

    def __init__(self, matrix, method: str = "auto", rtol: float = 1e-8):
        self.matrix = matrix.tocsr()
        if method == "auto":
            method = "cholesky" if matrix.shape[0] <= self.CHOLESKY_LIMIT else "amg"
        self.method, self.rtol = method, rtol
        self.iterations = 0
        if method == "cholesky":
            from cholespy import CholeskySolverD, MatrixType

            a = self.matrix
            try:
                self._chol = CholeskySolverD(a.shape[0], a.indptr.astype(np.int32), a.indices.astype(np.int32),
                                             a.data.astype(float), MatrixType.CSR)
            except ValueError as error:  # CHOLMOD: "Matrix is not positive definite!"
                raise CarotidError("the pressure matrix is not positive definite: part of the mesh is degenerate "
                                   "or not connected to an outlet") from error
        elif method == "amg":
            import pyamg

            self._ml = pyamg.smoothed_aggregation_solver(self.matrix, symmetry="symmetric")
        elif method == "lu":
            self._lu = spla.splu(self.matrix.tocsc())
        elif method == "jacobi":
            self._jacobi = jacobi_preconditioner(self.matrix.diagonal())
        else:
            raise CarotidError(f"unknown pressure solver {method!r} ({', '.join(self.METHODS)})")

    def solve(self, b: np.ndarray, x0: np.ndarray | None = None) -> np.ndarray:
        """Solve ``A x = b`` from the initial guess ``x0``; sets ``.iterations``."""
        if self.method == "cholesky":
            self.iterations = 1
            x = np.empty(len(b))
            self._chol.solve(np.ascontiguousarray(b, dtype=float), x)
            return x
        if self.method == "lu":
            self.iterations = 1
            return self._lu.solve(b)
        if not np.any(b):
            self.iterations = 0
            return np.zeros_like(b)
        count = [0]

        def callback(*_):
            count[0] += 1

        if self.method == "amg":
            residuals: list = []
            x = self._ml.solve(b, x0=x0, tol=self.rtol, accel="cg", maxiter=500, residuals=residuals)
            self.iterations = max(len(residuals) - 1, 0)
            return x
        x, _ = spla.cg(self.matrix, b, x0=x0, rtol=self.rtol, maxiter=20000, M=self._jacobi, callback=callback)
        self.iterations = count[0]
        return x


@dataclass
class StepInfo:
    """Diagnostics of one time step.

    Attributes
    ----------
    dt : float
        s.
    cfl : float
    inflow : float
        Volume flow in through the inlet, m^3/s.
    outflow : ndarray, shape (outlets,)
        Consistent volume flow out of each outlet (the discrete continuity residual at its nodes), m^3/s.
    outflow_p1 : ndarray, shape (outlets,)
        ``int u.n dS`` of the P1 velocity over each outlet, m^3/s (differs from ``outflow`` by the pressure
        stabilisation flux through the outlet's element layer).
    pressure_iterations : int
    """

    dt: float
    cfl: float
    inflow: float
    outflow: np.ndarray
    outflow_p1: np.ndarray
    pressure_iterations: int

    @property
    def imbalance(self) -> float:
        """(inflow - total consistent outflow) / inflow."""
        return float((self.inflow - self.outflow.sum()) / self.inflow) if self.inflow else 0.0

    @property
    def imbalance_p1(self) -> float:
        """(inflow - total P1 outflow) / inflow."""
        return float((self.inflow - self.outflow_p1.sum()) / self.inflow) if self.inflow else 0.0


class CBSSolver:
    """CBS time stepping on a :class:`FlowMesh`.

    Parameters
    ----------
    mesh : FlowMesh
    inlet_speed : callable
        ``inlet_speed(t) -> (k,)`` axial speed (m/s, positive inward) at ``mesh.face_patch(2)[0]`` nodes.
    nu : float
        Kinematic viscosity, m^2/s.
    split : array_like, optional
        Outflow fraction of each outlet (ascending label); default Murray's law.
    dt : float, optional
        Fixed time step, s; default: adaptive, ``safety * min_e 1 / (|u_e|/h_e + 2 nu_e/h_e^2)``.
    safety : float
        Safety factor of the adaptive step.
    velocity_scale : float, optional
        Velocity U of the stabilisation time scale, m/s; default: twice the largest inlet mean speed
        among ``inlet_speed(0)``.
    turbulence : object, optional
        A :class:`carotid.flow.turbulence.SpalartAllmaras`; None for laminar flow.
    pressure : {"auto", "cholesky", "amg", "lu", "jacobi"}
        See :class:`PressureSolver`.
    pressure_rtol : float
    viscous : {"explicit", "implicit"}
        Molecular viscous term of the momentum step: explicit (the paper's CBS) or backward Euler (module
        docstring).
    outlets : OutletModel, optional
        Resistance or RCR outlets (:mod:`carotid.flow.outlets`) instead of the prescribed ``split``.
    rho : float
        Density, kg/m^3: converts the outlet model's pressures (Pa) to the solver's kinematic pressure.
    backflow : float
        Coefficient beta of the outlet backflow stabilisation (0: none).
    rheology : Rheology, optional
        A shear-rate dependent viscosity (:mod:`carotid.flow.rheology`), evaluated per element from the previous
        step's velocity; ``nu`` then only sets the stabilisation time scale.
    exact : object, optional
        An exact solution for verification, with methods ``velocity(x, t) -> (k, 3)`` (m/s) and
        ``pressure(x, t) -> (k,)`` (kinematic, m^2/s^2) at points ``x`` (k, 3) in m: its velocity is imposed on
        the whole boundary and its pressure on the outlet nodes (``inlet_speed`` and ``split`` are then not
        used; give ``velocity_scale``).

    Attributes
    ----------
    passed : ndarray, shape (1 + outlets,)
        Volume that has entered through the inlet and left through each outlet (``int u.n`` of the P1
        velocity) since t = 0, m^3: the flows at the end of each step times its length, so a window's flow
        shares are ratios of volumes, not means of instantaneous ratios.
    """

    VISCOUS = ("explicit", "implicit")

    def __init__(self, mesh: FlowMesh, inlet_speed: Callable[[float], np.ndarray], nu: float, split=None,
                 dt: float | None = None, safety: float = 0.5, velocity_scale: float | None = None,
                 turbulence=None, pressure: str = "auto", pressure_rtol: float = 1e-8, viscous: str = "explicit",
                 outlets=None, rho: float = 1060.0, backflow: float = 0.0, rheology=None, exact=None):
        if dt is not None and not dt > 0:
            raise CarotidError(f"the time step must be positive (got {dt})")
        if viscous not in self.VISCOUS:
            raise CarotidError(f"the viscous term must be 'explicit' or 'implicit' (got {viscous!r})")
        self.viscous, self._pressure_method, self._rtol = viscous, pressure, pressure_rtol
        self.mesh, self.inlet_speed, self.nu = mesh, inlet_speed, float(nu)
        self.fixed_dt, self.safety, self.turbulence, self.exact = dt, float(safety), turbulence, exact
        self.lumped, self.rho, self.backflow = outlets, float(rho), float(backflow)
        self.rheology = None if rheology is None or rheology.newtonian else rheology
        if outlets is not None:
            if outlets.n_outlets != len(mesh.outlet_labels):
                raise CarotidError(f"the outlet model has {outlets.n_outlets} outlets but the mesh has "
                                   f"{len(mesh.outlet_labels)}")
            self._pc0 = outlets.pc.copy()  # the Windkessel state at t = 0
        n = mesh.n_points
        self.volumes, self.grads = asm.element_geometry(mesh.points, mesh.tets)
        self.h = asm.element_size(self.grads)
        self.mass = asm.lumped_mass(self.volumes, mesh.tets, n)
        self.outlets = mesh.outlet_labels
        self.split = murray_split(mesh) if split is None else check_split(split, len(self.outlets))
        self._setup_boundaries()
        if velocity_scale is None:
            if exact is not None:
                raise CarotidError("a solver with an exact solution needs its velocity_scale")
            velocity_scale = 2.0 * float(np.abs(inlet_speed(0.0)).mean())
        self.velocity_scale = float(velocity_scale)
        self.tau = 1.0 / (velocity_scale / self.h + 2.0 * self.nu / self.h**2)
        if viscous == "implicit":
            self._setup_implicit_viscosity()
        self._setup_pressure(self._stabilisation_times())
        self._resid = np.zeros((n, 3))
        self._div = np.zeros(n)
        self._proj = np.zeros(n)
        self._gp = np.zeros((n, 3))
        self._rate = np.zeros(len(mesh.tets))
        self._node_rate = np.zeros(mesh.n_points)
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _setup_boundaries(self) -> None:
        mesh, n = self.mesh, self.mesh.n_points
        wall = mesh.face_nodes(WALL)
        self.inlet_nodes = mesh.face_patch(INLET)[0]
        self.inlet_dir = -mesh.face_normal(INLET)  # inward unit normal
        nodes, weights = mesh.flux_weights(INLET)
        self._in_nodes, self._in_w = nodes, weights
        self.u_dirichlet = np.zeros(n, bool)
        self.u_dirichlet[wall] = True
        self.u_dirichlet[self.inlet_nodes] = True
        self._inlet_free = ~np.isin(self.inlet_nodes, wall)  # inlet nodes not on the rim
        # faces whose prescribed velocity enters the continuity equation: the inlet, or every non-outlet face
        flux_faces = mesh.labels == INLET if self.exact is None else mesh.labels <= INLET
        if self.exact is not None:
            self.u_dirichlet[np.unique(mesh.faces)] = True
            self.exact_nodes = np.flatnonzero(self.u_dirichlet)
        self._bc_nodes = np.unique(mesh.faces[flux_faces])
        self._bc_tri = np.searchsorted(self._bc_nodes, mesh.faces[flux_faces])
        self._bc_an = mesh.face_area_normals()[flux_faces]
        owner = np.full(n, -1)
        for j, lab in reversed(list(enumerate(self.outlets))):
            owner[mesh.face_nodes(lab)] = j
        self.p_dirichlet = np.flatnonzero(owner >= 0)
        self.p_owner = owner[self.p_dirichlet]
        self.free = np.flatnonzero(owner < 0)
        self.out_flux = [mesh.flux_weights(lab) for lab in self.outlets]
        self._out_nodes = np.concatenate([nodes for nodes, _ in self.out_flux])
        self._out_w = np.concatenate([w for _, w in self.out_flux])
        self.out_share = self._outlet_shares()
        self.outlet_areas = np.array([mesh.face_area(lab) for lab in self.outlets])

    def _outlet_shares(self) -> np.ndarray:
        """Share of each outlet node's continuity residual given to each outlet, shape (outlets, k).

        ``share[j, i] = int_{outlet j} N_i dS / int_{all outlets} N_i dS`` for the pressure-Dirichlet nodes
        ``p_dirichlet``: 1 for a node on one outlet only, split by area on a line where two outlets meet.
        """
        mesh, n = self.mesh, self.mesh.n_points
        area = np.zeros((len(self.outlets), n))
        for j, lab in enumerate(self.outlets):
            f = mesh.faces[mesh.labels == lab]
            a = np.linalg.norm(mesh.face_area_normals(lab), axis=1)
            area[j] = np.bincount(f.ravel(), np.repeat(a / 3.0, 3), minlength=n)
        area = area[:, self.p_dirichlet]
        return area / area.sum(axis=0)[None]

    def _stabilisation_times(self) -> np.ndarray:
        """Stabilisation time of each element for the whole run, s, shape (m,).

        ``tau_e`` for explicit viscosity, whose step never exceeds it.  With implicit viscosity the step can
        exceed ``tau_e`` in the wall layers, and the lagged part ``dt D M^-1 G (p^n - p^{n+1})`` of the
        continuity equation (module docstring) would then grow from step to step; ``max(tau_e, dt_max)``,
        with ``dt_max`` the fixed step or the step of a fluid at rest (the longest :meth:`time_step` takes),
        keeps it a damping for every step of the run with one pressure matrix.
        """
        if self.viscous == "explicit":
            return self.tau
        dt_max = self.fixed_dt if self.fixed_dt is not None else self.safety * self._h_rest / self.velocity_scale
        return np.maximum(self.tau, dt_max)

    def _setup_pressure(self, tau: np.ndarray) -> None:
        """The pressure equation for the stabilisation times ``tau`` (m,), s: matrix ``K_tau`` and its solver
        ``pressure``, outlet rows ``_k_out``, outlet liftings ``phi`` (outlets, n), velocity corrections per unit
        outlet pressure ``s`` (outlets, n, 3; before the dt factor, 1/m) and ``flux_response`` (outlets,
        outlets), the consistent outlet fluxes per unit outlet pressure, m^3/s per (m^2/s^2)."""
        n, m = self.mesh.n_points, len(self.outlets)
        self.tau_stab = tau
        k = asm.stiffness_matrix(self.volumes * tau, self.grads, self.mesh.tets, n)
        k_fd = self._k_fd = k[self.free][:, self.p_dirichlet]
        self._k_out = k[self.p_dirichlet]  # outlet rows of the pressure matrix: the consistent outlet fluxes
        self.pressure = PressureSolver(k[self.free][:, self.free], self._pressure_method, self._rtol)
        self.phi = np.zeros((m, n))
        self.s = np.zeros((m, n, 3))
        for j in range(m):
            pd = (self.p_owner == j).astype(float)
            self.phi[j, self.p_dirichlet] = pd
            # with one outlet the lifting is the constant 1 (the rows of K_tau sum to zero)
            self.phi[j, self.free] = self.pressure.solve(-(k_fd @ pd)) if m > 1 else 1.0
            grad = np.zeros((n, 3))
            asm.lumped_gradient(self.mesh.tets, self.grads, self.volumes, self.phi[j], grad)
            self.s[j] = -grad / self.mass[:, None]
            self.s[j, self.u_dirichlet] = 0.0
        # consistent outlet flux per unit outlet pressure: -sum_i share[i] (K_tau phi_j)_i, [outlet i, lifting j]
        self.flux_response = -self.out_share @ np.column_stack([self._k_out @ self.phi[j] for j in range(m)])

    def _setup_implicit_viscosity(self) -> None:
        """The molecular viscous matrix split into free/Dirichlet velocity columns, and the size ``h_rest`` of
        the step for a fluid at rest (:meth:`time_step`).  With a ``rheology`` its blocks are kept to be
        re-assembled with each step's element viscosity (:meth:`_viscous_matrices`)."""
        mesh = self.mesh
        self._u_free = np.flatnonzero(~self.u_dirichlet)
        blocks = [asm.StiffnessBlock(self.volumes, self.grads, mesh.tets, mesh.n_points, self._u_free, cols)
                  for cols in (self._u_free, np.flatnonzero(self.u_dirichlet))]
        self._viscous_matrices(np.full(len(mesh.tets), self.nu), blocks)
        self._kv_blocks = blocks if self.rheology is not None else None
        self._du_free = np.zeros((len(self._u_free), 3))
        self._h_rest = float(np.median(np.cbrt(6.0 * np.sqrt(2.0) * self.volumes)))

    def _viscous_matrices(self, nu: np.ndarray, blocks=None) -> None:
        """Set the free/free and free/Dirichlet blocks of the viscous matrix for the element viscosity ``nu``
        (m,), m^2/s, and the diagonal of the first."""
        ff, fd = blocks or self._kv_blocks
        self._kv_ff, self._kv_fd = ff.update(nu), fd.update(nu)
        self._kv_diag = self._kv_ff.diagonal()

    def _viscous_solve(self, dt: float, rhs: np.ndarray) -> None:
        """Solve ``(M/dt + nu K) dU = rhs`` on the free velocity nodes into ``_du_free`` (warm start from the
        previous step's increment), one Jacobi-preconditioned CG per component; ``rhs`` shape (k, 3)."""
        shift = self.mass[self._u_free] / dt
        kv = self._kv_ff
        a = spla.LinearOperator(kv.shape, matvec=lambda x: kv @ x + shift * x, dtype=float)
        jacobi = jacobi_preconditioner(self._kv_diag + shift)
        for c in range(3):
            self._du_free[:, c], info = spla.cg(a, rhs[:, c], x0=self._du_free[:, c], rtol=self._rtol,
                                                maxiter=5000, M=jacobi)
            if info:
                raise CarotidError(f"the implicit viscous solve did not converge at t = {self.t:.6g} s "
                                   f"(dt = {dt:.3g} s): the mesh may be degenerate")

    def _implicit_momentum(self, dt: float, t1: float) -> np.ndarray:
        """``u*`` of step 1 with backward-Euler molecular viscosity (Dirichlet values at ``t1`` included).

        The right-hand side carries ``nu K (dt M^-1 P grad p^n)`` as well: the pressure correction of step 3
        is not viscous-implicit, and without this lagged term a steady state would satisfy the momentum
        equation only up to ``nu K dt M^-1 grad p`` (an O(dt) error: +1.4 % mean WSS in a Poiseuille pipe).
        Needs ``self._gp``, the lumped gradient of ``p^n``.
        """
        ustar = self.u.copy()
        self._apply_velocity_bc(ustar, t1)
        d, free = self.u_dirichlet, self._u_free
        rhs = (self._resid[free] - self._kv_fd @ (ustar[d] - self.u[d])
               + self._kv_ff @ ((dt / self.mass[free])[:, None] * self._gp[free]))
        self._viscous_solve(dt, rhs)
        ustar[self._u_free] += self._du_free
        return ustar

    def _flux(self, u: np.ndarray, j: int) -> float:
        nodes, w = self.out_flux[j]
        return float(np.einsum("ij,ij->", w, u[nodes]))

    def _boundary_nodal_flux(self, u: np.ndarray) -> np.ndarray:
        """Consistent boundary flux ``int_Gamma N_i u.n dS`` over the inlet (with ``exact``: every non-outlet face)
        at its nodes ``_bc_nodes``, m^3/s, shape (k,).

        It must be the consistent (not lumped) boundary integral: the weak divergence ``int grad N_i . u``
        it balances in the continuity equation is consistent, and a lumped flux leaves a node-by-node source
        at the inlet that the pressure equation turns into a spurious inlet pressure layer.
        """
        tri, an = self._bc_tri, self._bc_an
        un = np.einsum("tkc,tc->tk", u[self._bc_nodes][tri], an)  # u_j . (area n) per triangle corner
        return np.bincount(tri.ravel(), ((un.sum(axis=1)[:, None] + un) / 12.0).ravel(),
                           minlength=len(self._bc_nodes))

    def inflow(self, u: np.ndarray) -> float:
        """Volume flow into the domain through the inlet, m^3/s."""
        return -float(np.einsum("ij,ij->", self._in_w, u[self._in_nodes]))

    def outflows(self, u: np.ndarray) -> np.ndarray:
        """Volume flow out of each outlet, m^3/s, shape (outlets,)."""
        return np.array([self._flux(u, j) for j in range(len(self.outlets))])

    # ------------------------------------------------------------------ state
    def reset(self, u0: np.ndarray | None = None, t0: float = 0.0) -> None:
        """Start from rest (or from the velocity ``u0`` (n, 3)) at time ``t0``."""
        n = self.mesh.n_points
        self.t, self.step_count = float(t0), 0
        self.u = np.zeros((n, 3)) if u0 is None else np.array(u0, dtype=float)
        self.p = np.zeros(n)
        self._p0_free = np.zeros(len(self.free))
        self.passed = np.zeros(1 + len(self.outlets))
        if self.lumped is not None:
            self.lumped.pc = self._pc0.copy()
        self.nut_hat = None if self.turbulence is None else self.turbulence.initial(n)
        if self.viscous == "implicit":
            self._du_free[:] = 0.0
        self._apply_velocity_bc(self.u, self.t)
        if self.turbulence is not None:
            self.turbulence.apply_bc(self.nut_hat)

    def state(self) -> dict:
        """Every array and scalar needed to continue the run bit for bit (for checkpoints)."""
        st = {"u": self.u, "p": self.p, "p0_free": self._p0_free, "t": self.t, "step": self.step_count,
              "passed": self.passed.copy()}
        if self.lumped is not None:
            st["outlet_pc"] = self.lumped.pc.copy()
        if self.nut_hat is not None:
            st["nut_hat"] = self.nut_hat
        if self.viscous == "implicit":
            st["du_free"] = self._du_free
        return st

    def load_state(self, st: dict) -> None:
        """Restore a :meth:`state` (shapes are checked)."""
        if np.shape(st["u"]) != self.u.shape or np.shape(st["p0_free"]) != self._p0_free.shape:
            raise CarotidError("the checkpoint does not belong to this mesh: delete it or run without --resume")
        self.u = np.array(st["u"], dtype=float)
        self.p = np.array(st["p"], dtype=float)
        self._p0_free = np.array(st["p0_free"], dtype=float)
        self.t, self.step_count = float(st["t"]), int(st["step"])
        self.passed = np.array(st["passed"], dtype=float)
        if self.lumped is not None:
            self.lumped.pc = np.array(st["outlet_pc"], dtype=float)
        if self.turbulence is not None:
            self.nut_hat = np.array(st["nut_hat"], dtype=float)
        if self.viscous == "implicit":
            self._du_free = np.array(st["du_free"], dtype=float)

    # ------------------------------------------------------------------ stepping
    def _apply_velocity_bc(self, u: np.ndarray, t: float) -> None:
        if self.exact is not None:
            u[self.exact_nodes] = self.exact.velocity(self.mesh.points[self.exact_nodes], t)
            return
        u[self.u_dirichlet] = 0.0
        speed = np.asarray(self.inlet_speed(t), dtype=float)
        u[self.inlet_nodes[self._inlet_free]] = speed[self._inlet_free, None] * self.inlet_dir

    def molecular_viscosity(self) -> np.ndarray:
        """Kinematic viscosity of the fluid per element, m^2/s, shape (m,): ``nu``, or the ``rheology``'s at the
        element's shear rate."""
        if self.rheology is None:
            return np.full(len(self.mesh.tets), self.nu)
        return self.rheology.viscosity(shear_rate(self.velocity_gradients())) / self.rho

    def element_viscosity(self, molecular: np.ndarray | None = None) -> np.ndarray:
        """Effective kinematic viscosity per element (molecular plus turbulent), m^2/s, shape (m,)."""
        nu = self.molecular_viscosity() if molecular is None else molecular
        if self.turbulence is None:
            return nu
        return nu + self.turbulence.nu_t(self.nut_hat)[self.mesh.tets].mean(axis=1)

    def time_step(self, nu_e: np.ndarray) -> tuple[float, float]:
        """``(dt, CFL)`` for the current velocity: adaptive or fixed, and the CFL number ``rate * dt``.

        The adaptive step is ``safety / max_e(c_e + 2 nu_e/h_e^2)`` with the explicit diffusivity (the
        viscosity, and with Spalart-Allmaras at least that of its own explicit equation) and the convective
        rate ``c_e = |u_e| / h_e``; the CFL is ``max_e c_e dt``.

        With implicit viscosity and no turbulence model there is no explicit diffusivity.  ``c_e`` is then the
        directional rate of :func:`carotid.flow.assembly.element_convective_rate` (a thin wall-layer element
        crossed tangentially does not set the step), and the step is bounded per node, not per element: by
        the lumped-mass root mean square of the rates of the node's elements
        (:func:`carotid.flow.assembly.nodal_rate`), at least ``velocity_scale / h_rest`` (a step for a fluid
        still at rest; ``h_rest`` is the median edge of the regular tetrahedron of each element's volume).
        The explicit update of a node is ``M_ii^-1`` times element sums, so its Gershgorin bound is set by
        the volume-weighted means of ``c_e`` (convection) and ``c_e^2`` (the characteristic term) over the
        node's elements, which the root mean square bounds both: on a uniform mesh the rule is the
        element-wise one, and a few flat elements among normal ones no longer hold the whole mesh to their
        step (on the fluid.stl carotids their directional rate reaches 2.1-2.7 times the nodal bound, where
        the layer is thinned at the flow divider and the flow crosses it).  The CFL is then the nodal one.
        """
        laminar_implicit = self.viscous == "implicit" and self.turbulence is None
        if self.viscous == "implicit":
            asm.element_convective_rate(self.mesh.tets, self.grads, self.u, self._rate)
        else:
            asm.element_speed(self.mesh.tets, self.u, self._rate)
            self._rate /= self.h
        if laminar_implicit:
            asm.nodal_rate(self.mesh.tets, self.volumes, self._rate, self.mass, self._node_rate)
            rate = float(self._node_rate.max())
            cfl_rate = rate
        else:
            nu_dt = nu_e if self.turbulence is None else np.maximum(nu_e, self.turbulence.diffusivity_bound(
                self.nut_hat, self.mesh.tets))  # (the Spalart-Allmaras equation keeps its explicit diffusion)
            rate = float(np.max(self._rate + 2.0 * nu_dt / self.h**2))
            cfl_rate = float(np.max(self._rate))
        if self.fixed_dt is not None:
            dt = self.fixed_dt
        elif self.viscous == "implicit":
            dt = self.safety / max(rate, self.velocity_scale / self._h_rest)
        else:
            dt = self.safety / rate
        return dt, cfl_rate * dt

    def step(self, max_dt: float | None = None) -> StepInfo:
        """Advance one time step (at most ``max_dt`` s long); returns its diagnostics."""
        mesh, tets = self.mesh, self.mesh.tets
        molecular = self.molecular_viscosity()
        nu_e = self.element_viscosity(molecular)
        if self.rheology is not None and self.viscous == "implicit":
            self._viscous_matrices(molecular)
        dt, cfl = self.time_step(nu_e)
        if max_dt is not None and max_dt < dt:
            dt, cfl = max_dt, cfl * max_dt / dt
        t1 = self.t + dt
        # 1. intermediate momentum
        asm.momentum_residual(tets, self.grads, self.volumes, self.u, nu_e, 0.5 * dt, self._resid)
        if self.backflow > 0:
            self._backflow_traction(self._resid)
        asm.lumped_gradient(tets, self.grads, self.volumes, self.p, self._gp)
        if self.viscous == "implicit":
            ustar = self._implicit_momentum(dt, t1)
        else:
            ustar = self.u + (dt / self.mass)[:, None] * self._resid
            self._apply_velocity_bc(ustar, t1)
        # 2. pressure with zero outlet pressure
        asm.weak_divergence(tets, self.grads, self.volumes, ustar, self._div)
        self._div[self._bc_nodes] -= self._boundary_nodal_flux(ustar)
        projected = self._gp / self.mass[:, None]
        asm.weak_divergence(tets, self.grads, self.volumes * (self.tau_stab - dt), projected, self._proj)
        rhs = self._div + self._proj
        # the correction skips velocity-Dirichlet nodes: put their dt P(grad p^n) back into the balance
        projected[~self.u_dirichlet] = 0.0
        asm.weak_divergence(tets, self.grads, self.volumes * dt, projected, self._proj)
        rhs += self._proj
        p = np.zeros(mesh.n_points)
        if self.exact is not None:
            p[self.p_dirichlet] = self.exact.pressure(mesh.points[self.p_dirichlet], t1)
        self._p0_free = self.pressure.solve(rhs[self.free] - self._k_fd @ p[self.p_dirichlet], x0=self._p0_free)
        p[self.free] = self._p0_free
        # consistent outlet fluxes: the residual of the discrete continuity equation at the outlet nodes
        q0 = self.out_share @ (rhs[self.p_dirichlet] - self._k_out @ p)
        # 3. correction, then outlet pressures that impose the split
        asm.lumped_gradient(tets, self.grads, self.volumes, p, self._gp)
        u = ustar - (dt / self.mass)[:, None] * self._gp
        u[self.u_dirichlet] = ustar[self.u_dirichlet]
        if self.exact is not None:
            c = np.zeros(len(self.outlets))
        elif self.lumped is not None:
            c = self._lumped_pressures(q0, dt)
        else:
            c = self._outlet_pressures(q0)
        u += dt * np.tensordot(c, self.s, axes=1)
        p += c @ self.phi
        if self.turbulence is not None:
            self.nut_hat = self.turbulence.step(self.nut_hat, u, dt, nu_e)
        self.u, self.p, self.t = u, p, t1
        self.step_count += 1
        outflow = q0 + self.flux_response @ c
        if self.lumped is not None:
            self.lumped.advance(outflow, dt)
        info = StepInfo(dt, cfl, self.inflow(u), outflow, self.outflows(u), self.pressure.iterations)
        self.passed += dt * np.r_[info.inflow, info.outflow_p1]
        return info

    def _backflow_traction(self, resid: np.ndarray) -> None:
        """Add ``int_outlets N_i beta min(u.n, 0) u dS`` (lumped) to the momentum residual ``resid`` (n, 3)."""
        u = self.u[self._out_nodes]
        flux = np.minimum(np.einsum("ij,ij->i", u, self._out_w), 0.0)  # min(u.n, 0) times the node's area
        np.add.at(resid, self._out_nodes, self.backflow * flux[:, None] * u)

    def _lumped_pressures(self, q0: np.ndarray, dt: float) -> np.ndarray:
        """Kinematic outlet pressures c (outlets,) that satisfy the lumped outlet laws with the consistent
        fluxes ``q0 + flux_response @ c`` at the end of the step (module docstring)."""
        r_eff, b = self.lumped.affine(dt)
        r_eff, b = r_eff / self.rho, b / self.rho
        return np.linalg.solve(np.eye(len(r_eff)) - r_eff[:, None] * self.flux_response, r_eff * q0 + b)

    def _outlet_pressures(self, q0: np.ndarray) -> np.ndarray:
        """Outlet pressures c (outlets,) for which outlets 0..N-2 carry ``split`` of the total consistent outflow
        ``q0 + flux_response @ c`` and ``sum(A c) = 0``."""
        m = len(self.outlets)
        r = self.flux_response
        a = np.zeros((m, m))
        b = np.zeros(m)
        a[: m - 1] = r[: m - 1] - self.split[: m - 1, None] * r.sum(axis=0)[None]
        b[: m - 1] = self.split[: m - 1] * q0.sum() - q0[: m - 1]
        a[m - 1] = self.outlet_areas
        return np.linalg.solve(a, b)

    # ------------------------------------------------------------------ diagnostics
    def check_finite(self, max_speed: float) -> tuple[bool, int]:
        """``(ok, node)``: whether the velocity is finite and below ``max_speed`` m/s, and the worst node."""
        speed = np.einsum("ij,ij->i", self.u, self.u)
        bad = ~np.isfinite(speed)
        if bad.any():
            return False, int(np.flatnonzero(bad)[0])
        node = int(np.argmax(speed))
        return bool(speed[node] <= max_speed**2), node

    def pressure_pa(self, rho: float) -> np.ndarray:
        """Pressure in Pa (the solver works with p / rho), shape (n,)."""
        return rho * self.p

    def velocity_gradients(self, u: np.ndarray | None = None) -> np.ndarray:
        """Element velocity gradients ``G[e, r, c] = d u_r / d x_c``, 1/s, shape (m, 3, 3)."""
        out = np.empty((len(self.mesh.tets), 3, 3))
        asm.velocity_gradients(self.mesh.tets, self.grads, self.u if u is None else u, out)
        return out
