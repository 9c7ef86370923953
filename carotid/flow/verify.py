"""Analytic verification of the flow solver on the user's machine (``carotid verify``).

Every flow case starts from rest or, for the exact unsteady solution, from its field at t = 0 over a run
in which it decays by a fifth, so a scheme that does not move the flow cannot pass; every pass/fail
criterion comes from an analytic solution or a published correlation, never from this code's own output
(formulas in validation.md):

* convective: the Ethier-Steinman exact unsteady Navier-Stokes solution (:mod:`carotid.flow.exact`) in a
  tube meshed by the mesh stage with its boundary layers, the exact velocity on the whole boundary and the
  exact pressure on the outlet; errors of the nodal velocity, the element velocity gradients and the
  pressure, with the observed orders under refinement in space and in time (:func:`convective_cases`).
  In this Beltrami flow the convective term is balanced by the pressure, so convection is checked through
  the pressure and the velocity it drives;
* generalised inlet: the Womersley profile that :func:`carotid.flow.womersley.inlet_profile` solves on a
  triangulated face, on a circular face against the analytic Womersley profile over a cycle, and on an
  elliptic face against the elliptic-pipe Poiseuille profile ``u = 2U (1 - x^2/a^2 - y^2/b^2)``;
* Poiseuille: steady flow in a straight rigid pipe with the developed inlet profile; centreline velocity,
  wall shear stress (mean and worst point around the circumference) and the axial pressure gradient
  against ``u_max = 2Q/(pi R^2)``, ``tau_w = 4 mu Q/(pi R^3)``, ``dp/dz = -8 mu Q/(pi R^4)``, on two or three
  refinements of the tube mesh, with the observed order of the WSS error.  The velocity and the WSS of
  Poiseuille flow do not depend on the viscosity; the pressure gradient does;
* mass: the P1 flux ``int u.n`` through the outlet(s) against the inflow, in the straight pipe and in a pipe
  whose outlet is cut in two with a prescribed 70:30 split.  The solver imposes the split and the balance on
  its consistent (continuity-residual) fluxes; the P1 flux of the velocity field is not imposed;
* entrance: a uniform (plug) inlet profile at Re = 50 develops into Poiseuille flow downstream; the
  development length (centreline velocity at 99 % of its developed value) against the correlation of Durst
  et al. (2005).  Convection sets that length (0.6 D without it, 3 D with it at Re 50): the straight-pipe
  cases cannot see the convective and characteristic terms, which vanish there;
* power-law fluid: flow of a shear-thinning fluid (``mu = k gamma_dot^(n-1)``) developing from a parabolic
  inlet profile in a tube; centreline velocity, WSS and pressure gradient against the exact fully developed
  power-law solution (implicit viscosity only);
* RCR outlet: a three-element Windkessel outlet on a straight tube under a sinusoidal inflow; the outlet
  pressure's mean, amplitude and phase against the analytic 0D impedance (implicit viscosity only);
* Womersley: the built-in carotid waveform (alpha ~ 4.7) in a straight pipe five diameters long; velocity,
  WSS and axial pressure gradient over the section between two diameters from the inlet and two from the
  outlet against the analytic Womersley solution, relative to their peaks, after the start-up transient.

The pipe meshes are structured tetrahedral tubes built here (the mesh stage's boundary-layer mesher needs
a lumen surface; a tube is all these cases need): an O-grid ("butterfly") cross-section - a square core
block and a ring whose radial spacing is uniform in the core and geometrically graded in a wall layer -
triangulated and extruded along z into prisms, each prism cut into three tetrahedra by the lowest-index
rule (every vertical quad face is cut by the diagonal through its lowest-numbered corner, so neighbouring
prisms agree and the mesh is conforming; Dompierre et al. 1999).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from carotid.errors import CarotidError
from carotid.flow.mesh import WALL, FlowMesh
from carotid.flow.waveform import constant_waveform

RHO, MU = 1060.0, 3.5e-3  # validation.md: Newtonian blood
NU = MU / RHO


@dataclass(frozen=True)
class TubeSpec:
    """A structured tube: radius and length in mm, cells per core-square side, core radial intervals,
    wall layers with first thickness (mm) and growth ratio, axial intervals."""

    radius: float = 3.25
    length: float = 13.0
    n_square: int = 6
    n_core: int = 4
    n_layers: int = 6
    first_layer: float = 0.04
    growth: float = 1.3
    n_axial: int = 12

    def refined(self, factor: int) -> TubeSpec:
        """Every interval count times ``factor`` and the first layer divided by it (same grading span)."""
        return TubeSpec(self.radius, self.length, self.n_square * factor, self.n_core * factor,
                        self.n_layers * factor, self.first_layer / factor, self.growth ** (1.0 / factor),
                        self.n_axial * factor)


# Poiseuille base mesh (refined x2 for the pass/fail figures), split-outlet tube, Womersley tube (five
# diameters long, sampled from two diameters after the inlet to two before the outlet), entrance tube (six
# diameters, coarse: the developing flow at Re 50 has no thin boundary layer)
POISEUILLE = TubeSpec(n_square=8, n_core=4, n_layers=4, first_layer=0.06, growth=1.25, n_axial=2, length=2.0)
SPLIT = TubeSpec(n_square=8, n_core=4, n_layers=4, first_layer=0.06, growth=1.25, n_axial=6, length=6.5)
WOMERSLEY = TubeSpec(n_square=12, n_core=6, n_layers=5, first_layer=0.05, growth=1.25, n_axial=10, length=32.5)
ENTRANCE = TubeSpec(n_square=6, n_core=3, n_layers=3, first_layer=0.2, growth=1.3, n_axial=39, length=39.0)
# power-law tube: four diameters, about twice the development length of its flow
POWER_LAW = TubeSpec(n_square=8, n_core=4, n_layers=4, first_layer=0.06, growth=1.25, n_axial=26, length=26.0)
# Ethier-Steinman case: tube radius (mm; the solution's length scale), Reynolds number U L / nu, run length in
# convective times L / U
ES_RADIUS, ES_RE, ES_DURATION = 3.0, 20.0, 2.0


def disc_mesh(spec: TubeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """O-grid triangulation of the disc of radius ``spec.radius`` (mm).

    Returns
    -------
    points : ndarray, shape (k, 2)
    triangles : ndarray, shape (t, 3)
    rim : ndarray, shape (4N, 2)
        The boundary edges (node pairs) on the circle.
    """
    n, r = spec.n_square, spec.radius
    a = 0.35 * r
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    block = np.stack([-a + 2 * a * ii.ravel() / n, -a + 2 * a * jj.ravel() / n], 1)
    bid = lambda i, j: i * (n + 1) + j  # noqa: E731  (node id of block grid point i, j)
    k = np.arange(4 * n)
    side, q = k // n, k % n
    pi_ = np.select([side == 0, side == 1, side == 2, side == 3], [np.full_like(q, n), n - q, np.zeros_like(q), q])
    pj_ = np.select([side == 0, side == 1, side == 2, side == 3], [q, np.full_like(q, n), n - q, np.zeros_like(q)])
    perim = bid(pi_, pj_)
    phi = -np.pi / 4 + 2 * np.pi * k / (4 * n)
    circle = r * np.stack([np.cos(phi), np.sin(phi)], 1)
    span = np.linalg.norm(circle - block[perim], axis=1)  # square-to-circle distance per ray, mm
    # distances from the wall of the layer stations (0 at the wall), then uniform core stations
    d_layers = spec.first_layer * np.concatenate([[0.0], np.cumsum(spec.growth ** np.arange(spec.n_layers))])
    if d_layers[-1] >= 0.8 * span.min():
        raise ValueError("the wall layer is thicker than the ring of the O-grid")
    core = np.linspace(0.0, 1.0, spec.n_core + 1)[1:, None] * (span - d_layers[-1])[None, :]  # from square
    from_square = np.concatenate([core, span[None, :] - d_layers[::-1][1:, None]])  # (n_rad, 4n)
    s = from_square / span[None, :]
    ring = (1 - s)[..., None] * block[perim][None] + s[..., None] * circle[None]
    points = np.concatenate([block, ring.reshape(-1, 2)])
    n_rad = len(s)
    ring_id = np.vstack([perim[None], len(block) + np.arange(n_rad * 4 * n).reshape(n_rad, 4 * n)])
    quads = [np.stack([bid(ii[:-1, :-1], jj[:-1, :-1]), bid(ii[1:, :-1], jj[1:, :-1]),
                       bid(ii[1:, 1:], jj[1:, 1:]), bid(ii[:-1, 1:], jj[:-1, 1:])], -1).reshape(-1, 4)]
    k1 = np.roll(np.arange(4 * n), -1)
    quads.append(np.stack([ring_id[:-1, :], ring_id[:-1, k1], ring_id[1:, k1], ring_id[1:, :]], -1).reshape(-1, 4))
    quads = np.concatenate(quads)
    triangles = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    rim = np.stack([ring_id[-1], ring_id[-1, k1]], 1)
    return points, triangles, rim


def tube_mesh(spec: TubeSpec = TubeSpec(), split_outlet: bool = False) -> FlowMesh:
    """Structured tetrahedral tube along +z from z = 0 (inlet, label 2) to ``spec.length`` (outlet).

    Parameters
    ----------
    spec : TubeSpec
    split_outlet : bool
        Divide the second half of the tube by a wall (septum) in the plane x = 0 into two channels with
        their own outlets (x < 0: label 3, x > 0: label 4); see :func:`_septum_tube`.

    Returns
    -------
    FlowMesh
        Wall label 1; about ``6 N^2 + 8 N (n_core + n_layers)`` triangles per section times 3 per axial
        interval tetrahedra.
    """
    pts2, tri, rim = disc_mesh(spec)
    m2, nz = len(pts2), spec.n_axial
    z = np.linspace(0.0, spec.length, nz + 1)
    points = np.concatenate([np.column_stack([pts2, np.full(m2, zl)]) for zl in z])
    tri = np.sort(tri, axis=1)
    lay = (np.arange(nz) * m2)[:, None, None]
    a, b, c = (tri[None, :, i] + lay[..., 0] for i in range(3))
    a1, b1, c1 = a + m2, b + m2, c + m2
    tets = np.concatenate([np.stack([a, b, c, c1], -1), np.stack([a, b, c1, b1], -1),
                           np.stack([a, b1, c1, a1], -1)], axis=1).reshape(-1, 4)
    rim = np.sort(rim, axis=1)
    ra, rb = rim[None, :, 0] + lay[..., 0], rim[None, :, 1] + lay[..., 0]
    wall = np.concatenate([np.stack([ra, rb, rb + m2], -1), np.stack([ra, rb + m2, ra + m2], -1)], 1).reshape(-1, 3)
    if split_outlet:
        return _septum_tube(points, tets, spec)
    faces = np.concatenate([wall, tri, tri + nz * m2])
    labels = np.concatenate([np.ones(len(wall), int), np.full(len(tri), 2), np.full(len(tri), 3)])
    return FlowMesh.from_arrays(points, tets, faces, labels)


def _septum_tube(points: np.ndarray, tets: np.ndarray, spec: TubeSpec) -> FlowMesh:
    """Cut the tube by a zero-thickness wall in the plane x = 0 from mid-length to the outlet.

    The nodes on that plane beyond mid-length are duplicated and the tetrahedra on the x > 0 side take the
    copies, so the tube ends in two half-pipe channels (outlets 3: x < 0 and 4: x > 0), like the two
    branches of a bifurcation.  The plane is a union of mesh faces: it contains the middle grid line of the
    core square (``n_square`` even) and the two rays at 90 and 270 degrees.
    """
    if spec.n_square % 2:
        raise ValueError("a split tube needs an even n_square")
    tol = 1e-9 * spec.radius
    z_start = 0.5 * spec.length
    cut = np.flatnonzero((np.abs(points[:, 0]) < tol) & (points[:, 2] > z_start + tol))
    copy = np.arange(len(points))
    copy[cut] = len(points) + np.arange(len(cut))
    points = np.concatenate([points, points[cut]])
    right = points[tets].mean(axis=1)[:, 0] > 0
    tets = tets.copy()
    tets[right] = copy[tets[right]]
    faces = np.sort(tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    faces, counts = np.unique(faces, axis=0, return_counts=True)
    faces = faces[counts == 1]
    centre = points[faces].mean(axis=1)
    labels = np.full(len(faces), WALL)
    labels[centre[:, 2] < tol] = 2
    end = centre[:, 2] > spec.length - tol
    labels[end] = np.where(centre[end, 0] < 0, 3, 4)
    return FlowMesh.from_arrays(points, tets, faces, labels)


def developed_start(mesh: FlowMesh, profile) -> np.ndarray:
    """Initial velocity (n, 3), m/s: the inlet profile at t = 0 carried along the tube axis (+z)."""
    from scipy.spatial import cKDTree

    nodes, pts, _ = mesh.face_patch(2)
    idx = cKDTree(pts[:, :2]).query(mesh.points[:, :2])[1]
    u = np.zeros((mesh.n_points, 3))
    u[:, 2] = profile.velocity(0.0)[idx]
    return u


def section_profile(mesh: FlowMesh, waveform, n_harmonics: int):
    """The generalised Womersley profile (:func:`carotid.flow.womersley.inlet_profile`) on the inlet face."""
    from carotid.flow.womersley import inlet_profile

    nodes, pts, tris = mesh.face_patch(2)
    return inlet_profile(pts, tris, mesh.face_normal(2), waveform, NU, n_harmonics)


def axial_gradient(z: np.ndarray, p: np.ndarray) -> float:
    """Least-squares slope ``dp/dz`` of nodal values ``p`` against the axial positions ``z`` (m)."""
    zc = z - z.mean()
    return float(zc @ (p - p.mean()) / (zc @ zc))


def _mid_wall(mesh: FlowMesh, wall, spec: TubeSpec) -> np.ndarray:
    z = mesh.points[wall.nodes, 2] / 1e-3
    return (z > 0.3 * spec.length) & (z < 0.7 * spec.length)


def _run_to_steady(solver, max_steps: int, tol: float):
    """Step until the relative velocity change rate ``max|du| / (dt max|u|)`` is below ``tol`` (1/s) or for
    ``max_steps``; returns the last rate and the last :class:`carotid.flow.cbs.StepInfo`."""
    residual, info = np.inf, None
    for _ in range(max_steps):
        before = solver.u.copy()
        info = solver.step()
        residual = float(np.abs(solver.u - before).max() / (info.dt * np.abs(solver.u).max()))
        if not residual >= tol:  # (a NaN stops the run too)
            break
    return residual, info


def poiseuille(spec: TubeSpec = POISEUILLE, q: float = 6e-6, max_steps: int = 6000, tol: float = 1e-3,
               split_outlet: bool = False, split=None, viscous: str = "explicit") -> dict:
    """Steady Poiseuille flow in a tube started from rest; errors of centreline velocity, WSS (mid-length
    third) and axial pressure gradient (whole tube).

    The inlet carries the section's developed profile (the generalised inlet at zero frequency); the run
    stops when the relative velocity change rate ``max|du|/(dt max|u|)`` drops below ``tol`` 1/s or after
    ``max_steps``.

    Returns
    -------
    dict
        ``centreline_error``, ``wss_mean_error``, ``pressure_gradient_error`` (relative, signed),
        ``wss_max_error`` (relative, absolute; these four not for a split tube), ``imbalance_p1``
        ((inflow - P1 outflow ``int u.n``) / inflow) and ``split_error_p1`` (max |Q_i / Q_in - s_i| with the P1
        outlet fluxes), the same with the solver's consistent fluxes (``imbalance``, ``split_error``: imposed
        by the scheme, reported, not checked), ``steps``, ``residual``, mesh sizes.
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.wss import WallShear

    mesh = tube_mesh(spec, split_outlet=split_outlet)
    r = spec.radius * 1e-3
    profile = section_profile(mesh, constant_waveform(q), 0)
    solver = CBSSolver(mesh, profile.velocity, NU, split=split, safety=0.8, viscous=viscous)
    solver.reset()
    residual, info = _run_to_steady(solver, max_steps, tol)
    res = {"tetrahedra": len(mesh.tets), "first_layer_mm": spec.first_layer, "steps": solver.step_count,
           "residual": residual, "imbalance": info.imbalance,
           "split_error": float(np.abs(info.outflow / info.inflow - solver.split).max()),
           "imbalance_p1": info.imbalance_p1,
           "split_error_p1": float(np.abs(info.outflow_p1 / info.inflow - solver.split).max())}
    if split_outlet:  # the septum's leading edge has no wall normal; only the mass balance is of interest
        return res
    rr = np.hypot(mesh.points[:, 0], mesh.points[:, 1])
    z = mesh.points[:, 2] / 1e-3
    axis = (rr < 1e-9) & (z > 0.3 * spec.length) & (z < 0.7 * spec.length)
    wall = WallShear(mesh, solver.volumes)
    tau = wall.nodes_wss(wall.faces_wss(solver.velocity_gradients(), MU))[_mid_wall(mesh, wall, spec), 2]
    tau_exact = 4 * MU * q / (np.pi * r**3)
    dpdz = RHO * axial_gradient(mesh.points[:, 2], solver.p)  # the solver's pressure is p / rho
    return {**res, "centreline_error": float(solver.u[axis, 2].mean() / (2 * q / (np.pi * r**2)) - 1),
            "wss_mean_error": float(tau.mean() / tau_exact - 1),
            "wss_max_error": float(np.abs(tau / tau_exact - 1).max()),
            "pressure_gradient_error": float(dpdz / (-8 * MU * q / (np.pi * r**4)) - 1)}


def durst_development_length(re: float) -> float:
    """Development length of laminar pipe flow from a uniform inlet profile, in diameters.

    ``L / D = [0.619^1.6 + (0.0567 Re)^1.6]^(1/1.6)`` (Durst, Ray, Uensal & Bayoumi 2005, "The development
    lengths of laminar pipe and channel flows", J Fluids Eng 127:1154), ``L`` where the centreline velocity
    reaches 99 % of its fully developed value, ``Re = U D / nu`` with the mean velocity U; a fit to their
    computations for 0 < Re < 1000 (the creeping-flow limit 0.619 D; 0.0567 Re at high Re, close to
    the boundary-layer value 0.056 Re).
    """
    return float((0.619**1.6 + (0.0567 * re) ** 1.6) ** (1 / 1.6))


def entrance(spec: TubeSpec = ENTRANCE, re: float = 50.0, viscous: str = "explicit", max_steps: int = 20000,
             tol: float = 1e-3) -> dict:
    """Developing flow from a uniform (plug) inlet profile at Reynolds number ``re``, started from rest.

    The inlet speed is uniform on the inlet face (zero on its rim) with flux ``Q = U pi R^2``,
    ``U = re nu / D``.  Downstream the centreline velocity rises from U to the developed value: convection
    carries the plug core down the pipe while the wall layers grow, so the development length is about
    0.057 Re diameters, against 0.6 D for creeping flow (:func:`durst_development_length`).  The run stops at
    a steady state (relative velocity change rate below ``tol`` 1/s); the development length is where the
    centreline velocity first reaches 99 % of the developed centreline velocity of the section (the discrete
    fully developed profile, the 2D P1 solution of ``nu Lap w = -1`` on the section scaled to the flux Q,
    which is within the mesh error of ``2U``), interpolated linearly between axis nodes.

    Returns
    -------
    dict
        ``development_length_d`` and the correlation's ``expected_d`` (diameters), ``length_error``
        (relative, signed), ``developed_centreline_error`` (the section profile against 2U), ``centreline``
        (z in mm and u_c / U along the axis), ``steps``, ``residual``, ``tetrahedra``, ``re``.
    """
    from carotid.flow.cbs import CBSSolver

    mesh = tube_mesh(spec)
    r = spec.radius * 1e-3
    u_mean = re * NU / (2 * r)
    q = u_mean * np.pi * r**2
    nodes, w = mesh.flux_weights(2)
    rim = np.isin(nodes, mesh.face_nodes(WALL))
    plug = np.where(rim, 0.0, q / np.linalg.norm(w[~rim], axis=1).sum())
    solver = CBSSolver(mesh, lambda t: plug, NU, safety=0.8, viscous=viscous, velocity_scale=2 * u_mean)
    solver.reset()
    residual, _ = _run_to_steady(solver, max_steps, tol)
    developed = section_profile(mesh, constant_waveform(q), 0).velocity(0.0)
    centre = np.flatnonzero(np.hypot(mesh.points[:, 0], mesh.points[:, 1]) < 1e-9)
    centre = centre[np.argsort(mesh.points[centre, 2])]
    u_dev = developed[np.isin(nodes, centre)].max()
    uc, z = solver.u[centre, 2], mesh.points[centre, 2]
    above = np.flatnonzero(uc >= 0.99 * u_dev)
    if len(above) and above[0] > 0:
        k = above[0]
        length = z[k - 1] + (0.99 * u_dev - uc[k - 1]) / (uc[k] - uc[k - 1]) * (z[k] - z[k - 1])
    else:  # never developed (or at the inlet plane itself)
        length = np.inf if not len(above) else 0.0
    expected = durst_development_length(re)
    return {"tetrahedra": len(mesh.tets), "steps": solver.step_count, "residual": residual, "re": re,
            "development_length_d": float(length / (2 * r)), "expected_d": expected,
            "length_error": float(length / (2 * r) / expected - 1),
            "developed_centreline_error": float(u_dev / (2 * u_mean) - 1),
            "centreline": {"z_mm": (z / 1e-3).tolist(), "u_over_mean": (uc / u_mean).tolist()}}


def ethier_steinman_mesh(size: float, layers: int) -> FlowMesh:
    """The mesh stage's boundary-layer mesh (:func:`carotid.mesh.build_mesh`) of a capped tube of radius
    ``ES_RADIUS`` and length ``2 ES_RADIUS`` (mm) along +z from z = 0, core edge ``size`` (mm), ``layers``
    prism sub-layers."""
    from carotid.mesh.mesher import build_mesh
    from carotid.mesh.testing import labelled_tube

    surface = labelled_tube(radius=ES_RADIUS, length=2.0 * ES_RADIUS, size=size)
    grid, _ = build_mesh(surface, layers=layers, size=size, lloyd_iterations=2)
    return FlowMesh.from_pyvista(grid)


def ethier_steinman(size: float, layers: int, steps: int, viscous: str = "explicit", re: float = ES_RE) -> dict:
    """The Ethier-Steinman solution (:class:`carotid.flow.exact.EthierSteinman`) in a boundary-layer tube mesh.

    The tube (radius L = ``ES_RADIUS``, the solution's length scale, centred on the solution's origin) is
    meshed by the mesh stage; the exact velocity is imposed on its whole boundary and the exact pressure
    on the outlet nodes.  The run starts from the exact field at t = 0 and takes ``steps`` fixed steps to
    ``ES_DURATION`` convective times ``L/U`` (``U = re nu / L``), over which the exact velocity decays by a
    factor ``exp(-d^2 ES_DURATION / re)`` (0.78 at Re 20): a solver that does not move the flow is off by
    ``change`` (0.28).  The convective term matters through the pressure that balances it.

    Returns
    -------
    dict
        Relative L2 errors at the end: ``velocity_error`` and ``pressure_error`` (nodal, lumped-mass
        weighted), ``gradient_error`` (element velocity gradients, whose wall projection is the WSS,
        against the exact gradient at the element centroids, volume weighted); ``change`` (the exact
        velocity's relative change over the run), ``h_mm`` (representative size ``(V/N)^(1/3)``), ``dt``,
        ``steps``, ``tetrahedra``, ``re``.
    """
    from carotid.flow import assembly as asm
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.convergence import representative_size
    from carotid.flow.exact import EthierSteinman

    mesh = ethier_steinman_mesh(size, layers)
    length = ES_RADIUS * 1e-3
    exact = EthierSteinman(length, re * NU / length, NU, (0.0, 0.0, length))
    t_end = ES_DURATION * length / exact.speed
    u0 = exact.velocity(mesh.points, 0.0)
    solver = CBSSolver(mesh, None, NU, dt=t_end / steps, viscous=viscous, exact=exact,
                       velocity_scale=float(np.linalg.norm(u0, axis=1).max()))
    solver.reset(u0)
    for _ in range(steps):
        solver.step()
    m, t = solver.mass, solver.t
    u, p = exact.velocity(mesh.points, t), exact.pressure(mesh.points, t)
    g = exact.velocity_gradient(mesh.points[mesh.tets].mean(axis=1), t)
    gh = np.empty_like(g)
    asm.velocity_gradients(mesh.tets, solver.grads, solver.u, gh)

    def rel(err, ref, w):
        return float(np.sqrt((w * err).sum() / (w * ref).sum()))

    return {"velocity_error": rel(((solver.u - u) ** 2).sum(1), (u**2).sum(1), m),
            "pressure_error": rel((solver.p - p) ** 2, p**2, m),
            "gradient_error": rel(((gh - g) ** 2).sum((1, 2)), (g**2).sum((1, 2)), solver.volumes),
            "change": rel(((u0 - u) ** 2).sum(1), (u**2).sum(1), m), "re": re, "steps": steps, "dt": t / steps,
            "h_mm": float(representative_size(solver.volumes.sum(), len(mesh.tets))) / 1e-3,
            "tetrahedra": len(mesh.tets)}


def power_law(spec: TubeSpec = POWER_LAW, q: float = 1e-6, n: float = 0.6, k: float = 0.035,
              max_steps: int = 6000, tol: float = 1e-3, viscous: str = "implicit") -> dict:
    """Power-law flow (``mu = k gamma_dot^(n-1)``) developing in a straight tube from a parabolic inlet, from rest.

    The exact solution for the flow rate Q in a pipe of radius R (mean speed U = Q / (pi R^2)):
    ``u(r) = U (3n + 1)/(n + 1) [1 - (r/R)^((n + 1)/n)]``, ``tau_w = k ((3n + 1)/n U/R)^n`` and
    ``dp/dz = -2 tau_w / R`` (e.g. Bird, Armstrong & Hassager 1987, Dynamics of Polymeric Liquids, vol. 1).
    The inlet carries the Newtonian (parabolic) profile of the same flow, whose centreline speed 2U exceeds
    the power law's (1.75 U for n = 0.6), so the profile must develop: the tube is four diameters long, about
    twice the development length at this Reynolds number (about 25), and centreline velocity, WSS and axial
    pressure gradient are taken between 60 % and 90 % of its length.  The solver's element viscosity follows
    the law (:class:`carotid.flow.rheology.Rheology`, ``gamma_dot`` held above 0.01 1/s).

    Returns
    -------
    dict
        ``centreline_error``, ``wss_mean_error``, ``pressure_gradient_error`` (relative, signed),
        ``wss_max_error`` (relative, absolute), ``steps``, ``residual``, ``tetrahedra``, ``n``.
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.rheology import Rheology
    from carotid.flow.wss import WallShear

    mesh = tube_mesh(spec)
    r = spec.radius * 1e-3
    u_mean = q / (np.pi * r**2)
    nodes, pts, _ = mesh.face_patch(2)
    rr = np.minimum(np.hypot(pts[:, 0], pts[:, 1]) / r, 1.0)
    profile = 2.0 * u_mean * (1 - rr**2)
    law = Rheology("power", n=n, k=k)
    solver = CBSSolver(mesh, lambda t: profile, NU, safety=0.8, viscous=viscous, rheology=law, rho=RHO,
                       velocity_scale=2 * u_mean)
    solver.reset()
    residual, _ = _run_to_steady(solver, max_steps, tol)
    tau_exact = k * ((3 * n + 1) / n * u_mean / r) ** n
    rr = np.hypot(mesh.points[:, 0], mesh.points[:, 1])
    z = mesh.points[:, 2] / 1e-3
    axis = (rr < 1e-9) & (z > 0.6 * spec.length) & (z < 0.9 * spec.length)
    wall = WallShear(mesh, solver.volumes)
    zw = z[wall.nodes]
    tau = wall.nodes_wss(wall.faces_wss(solver.velocity_gradients(), law))[(zw > 0.6 * spec.length)
                                                                            & (zw < 0.9 * spec.length), 2]
    part = (z > 0.6 * spec.length) & (z < 0.9 * spec.length)
    dpdz = RHO * axial_gradient(mesh.points[part, 2], solver.p[part])
    return {"centreline_error": float(solver.u[axis, 2].mean() / (u_mean * (3 * n + 1) / (n + 1)) - 1),
            "wss_mean_error": float(tau.mean() / tau_exact - 1),
            "wss_max_error": float(np.abs(tau / tau_exact - 1).max()),
            "pressure_gradient_error": float(dpdz / (-2 * tau_exact / r) - 1), "steps": solver.step_count,
            "residual": residual, "tetrahedra": len(mesh.tets), "n": n}


def rcr_outlet(spec: TubeSpec = SPLIT, period: float = 0.5, steps_per_period: int = 200, periods: int = 3,
               viscous: str = "implicit") -> dict:
    """A straight tube with a three-element Windkessel outlet under a sinusoidal inflow, from rest.

    Inflow ``Q(t) = Q0 (1 + 0.5 sin(omega t))`` (Q0 = 6 mL/s) with the developed Womersley profile; the
    outlet is an RCR with ``R_p = 0.1 R_T``, ``R_d = 0.9 R_T`` (``R_T Q0`` = 93 mmHg) and
    ``omega R_d C = 1``.  Over the last period, the mean and the first harmonic of the outlet pressure are
    compared with the analytic 0D solution ``P = Z(0) Q0 + |Z(omega)| Q1 sin(omega t + arg Z(omega))``,
    ``Z = R_p + R_d / (1 + i omega R_d C)``: what the implicitly coupled backward-Euler law must give
    (its own error is ``O(omega dt)``).

    Returns
    -------
    dict
        ``mean_error``, ``amplitude_error`` (relative, signed), ``phase_error`` (relative to the exact phase
        lag, signed), ``phase_deg`` and ``expected_phase_deg``, ``steps``, ``tetrahedra``.
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.outlets import MMHG, OutletModel
    from carotid.flow.waveform import Waveform

    mesh = tube_mesh(spec)
    omega, q0 = 2 * np.pi / period, 6e-6
    t = np.linspace(0.0, period, 65)[:-1]
    wave = Waveform(period, t, q0 * (1 + 0.5 * np.sin(omega * t)))
    r_total = 93.0 * MMHG / q0
    rd = 0.9 * r_total
    model = OutletModel([0.1 * r_total], [1.0 / (omega * rd)], [rd])
    expected = model.impedance([0.0, omega])[0]
    profile = section_profile(mesh, wave, 2)
    dt = period / steps_per_period
    solver = CBSSolver(mesh, profile.velocity, NU, dt=dt, viscous=viscous, outlets=model, rho=RHO,
                       velocity_scale=2 * q0 / mesh.face_area(2))
    solver.reset()
    nodes = mesh.face_nodes(3)
    times, pressure = [], []
    for _ in range(periods * steps_per_period):
        solver.step()
        times.append(solver.t)
        pressure.append(RHO * solver.p[nodes].mean())
    times, pressure = np.array(times[-steps_per_period:]), np.array(pressure[-steps_per_period:])
    first = 2.0 * np.mean(pressure * np.exp(-1j * omega * times))  # P1 with P = Re(P1 e^{i w t})
    exact_first = expected[1] * (-0.5j * q0)  # Q1 = 0.5 q0 sin(wt) = Re(-0.5i q0 e^{i w t})
    phase, exact_phase = np.angle(first / (-0.5j * q0)), np.angle(expected[1])
    return {"mean_error": float(pressure.mean() / (expected[0].real * q0) - 1),
            "amplitude_error": float(abs(first) / abs(exact_first) - 1),
            "phase_error": float(phase / exact_phase - 1), "phase_deg": float(np.degrees(phase)),
            "expected_phase_deg": float(np.degrees(exact_phase)), "steps": solver.step_count,
            "tetrahedra": len(mesh.tets)}


def womersley(spec: TubeSpec | None = None, window: float = 1.0, samples: int = 24, settle: float = 0.5,
              n_harmonics: int = 10, viscous: str = "explicit") -> dict:
    """The carotid waveform in a straight tube with the generalised Womersley inlet profile, from rest.

    The run starts from rest at ``t = -settle`` s.  With the flow rate imposed, the start-up transient of a
    pipe decays as ``exp(-lambda^2 nu t / R^2)`` with ``lambda = 5.136`` the first zero of J2 (the slowest
    flux-free mode ``J0(lambda r/R) - J0(lambda)``): 0.12 s for R = 3.25 mm, so 0.5 s leaves 1.6 % of the
    flow at the start, less than 0.5 % of the peak.  Then ``samples + 1`` times over ``window`` cycles from
    t = 0 compare, on the section between two diameters from the inlet and two from the outlet: the axial
    velocity at its nodes against :func:`carotid.flow.womersley.womersley_velocity`, the mean WSS of its wall
    nodes against :func:`carotid.flow.womersley.womersley_wss`, and the least-squares axial pressure gradient
    of its nodes against :func:`carotid.flow.womersley.womersley_pressure_gradient`; each error is the largest over the samples,
    relative to the analytic peak of its quantity over them (the centreline velocity for the velocity).
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.simulate import stabilisation_velocity
    from carotid.flow.waveform import carotid_waveform
    from carotid.flow.womersley import womersley_pressure_gradient, womersley_velocity, womersley_wss
    from carotid.flow.wss import WallShear

    spec = spec or WOMERSLEY
    wave = carotid_waveform()
    mesh = tube_mesh(spec)
    r = spec.radius * 1e-3
    profile = section_profile(mesh, wave, n_harmonics)
    solver = CBSSolver(mesh, profile.velocity, NU, safety=0.8,
                       velocity_scale=stabilisation_velocity(wave, mesh.face_area(2)), viscous=viscous)
    solver.reset(t0=-settle)
    wall = WallShear(mesh, solver.volumes)
    z = mesh.points[:, 2]
    margin = 4 * r  # two diameters
    inside = (z >= margin - 1e-9) & (z <= spec.length * 1e-3 - margin + 1e-9)
    wall_inside = inside[wall.nodes]
    rr = np.hypot(mesh.points[inside, 0], mesh.points[inside, 1])
    times = wave.period_s * window * np.arange(samples + 1) / samples
    sim = {"velocity": [], "wss": [], "gradient": []}
    exact = {"velocity": [], "wss": [], "gradient": []}
    for t_sample in times:
        while solver.t < t_sample - 1e-12:
            solver.step(max_dt=t_sample - solver.t)
        sim["velocity"].append(solver.u[inside, 2])
        exact["velocity"].append(womersley_velocity(np.minimum(rr, r), solver.t, r, wave, NU, n_harmonics))
        sim["wss"].append(wall.nodes_wss(wall.faces_wss(solver.velocity_gradients(), MU))[wall_inside, 2].mean())
        exact["wss"].append(womersley_wss(solver.t, r, wave, MU, NU, n_harmonics))
        sim["gradient"].append(-axial_gradient(z[inside], solver.p[inside]))
        exact["gradient"].append(womersley_pressure_gradient(solver.t, r, wave, NU, n_harmonics))
    sim = {k: np.array(v) for k, v in sim.items()}
    exact = {k: np.array(v) for k, v in exact.items()}
    peak = {"velocity": np.abs(exact["velocity"]).max(), "wss": np.abs(exact["wss"]).max(),
            "gradient": np.abs(exact["gradient"]).max()}
    err = {k: float(np.abs(sim[k] - exact[k]).max() / peak[k]) for k in sim}
    return {"tetrahedra": len(mesh.tets), "steps": solver.step_count, "window_cycles": window,
            "times": times.tolist(), "wss": sim["wss"].tolist(), "wss_exact": exact["wss"].tolist(),
            "pressure_gradient": sim["gradient"].tolist(), "pressure_gradient_exact": exact["gradient"].tolist(),
            "velocity_error_of_peak": err["velocity"], "max_error_of_peak": err["wss"],
            "pressure_gradient_error_of_peak": err["gradient"], "alpha": r * np.sqrt(wave.omega / NU)}


def inlet_profiles(spec: TubeSpec = WOMERSLEY, n_harmonics: int = 10, samples: int = 24,
                   ellipse_mm: tuple[float, float] = (4.0, 2.5), q: float = 6e-6) -> dict:
    """The generalised Womersley inlet (:func:`carotid.flow.womersley.inlet_profile`) on two faces.

    * circular: the O-grid section of ``spec`` with the carotid waveform; the profile at ``samples`` times over
      a cycle against the analytic Womersley velocity (:func:`carotid.flow.womersley.womersley_velocity`) at
      every node, the error relative to the analytic peak centreline velocity;
    * elliptic: the same triangulation stretched to semi-axes ``ellipse_mm`` (rim nodes on the ellipse) with
      the steady flow ``q`` m^3/s, against the exact elliptic-pipe profile
      ``u = 2U (1 - x^2/a^2 - y^2/b^2)``, ``U = q / (pi a b)`` (the solution of ``nu Lap u = const`` vanishing on
      the ellipse), the error relative to ``2U``.

    Returns
    -------
    dict
        ``circle_error`` and ``ellipse_error`` (relative, largest over nodes and times), ``nodes``.
    """
    from carotid.flow.waveform import carotid_waveform
    from carotid.flow.womersley import inlet_profile, womersley_velocity

    pts2, tri, _ = disc_mesh(spec)
    d1, d2 = pts2[tri[:, 1]] - pts2[tri[:, 0]], pts2[tri[:, 2]] - pts2[tri[:, 0]]
    tri = np.where((d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)[:, None], tri, tri[:, ::-1])  # one orientation
    r = spec.radius * 1e-3
    xy = pts2 * 1e-3
    wave = carotid_waveform()
    circle = inlet_profile(np.column_stack([xy, np.zeros(len(xy))]), tri, [0.0, 0.0, 1.0], wave, NU, n_harmonics)
    times = wave.period_s * np.arange(samples) / samples
    rr = np.minimum(np.hypot(xy[:, 0], xy[:, 1]), r)
    exact = np.array([womersley_velocity(rr, t, r, wave, NU, n_harmonics) for t in times])
    a, b = ellipse_mm[0] * 1e-3, ellipse_mm[1] * 1e-3
    xe, ye = xy[:, 0] * a / r, xy[:, 1] * b / r
    ellipse = inlet_profile(np.column_stack([xe, ye, np.zeros(len(xy))]), tri, [0.0, 0.0, 1.0],
                            constant_waveform(q), NU, 0)
    u_mean = q / (np.pi * a * b)
    exact_e = 2 * u_mean * np.maximum(1 - (xe / a) ** 2 - (ye / b) ** 2, 0.0)
    return {"nodes": len(xy),
            "circle_error": float(np.abs(circle.velocity(times) - exact).max() / np.abs(exact[:, rr == 0]).max()),
            "ellipse_error": float(np.abs(ellipse.velocity(0.0) - exact_e).max() / (2 * u_mean))}


def _order(runs: list[dict], key: str, size: str = "first_layer_mm") -> list[float]:
    """Observed orders ``log(e_k / e_k+1) / log(h_k / h_k+1)`` of ``|run[key]|`` between successive meshes,
    ``h = run[size]``."""
    e = np.array([abs(r[key]) for r in runs])
    h = np.array([r[size] for r in runs])
    return (np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:])).tolist()


def _time_order(runs: list[dict], key: str) -> list[float]:
    """Observed orders in time from runs whose step halves from one to the next: ``log2((e_k - e_k+1) /
    (e_k+1 - e_k+2))``, which cancels the part of the error ``e = e_space + C dt^q`` that the mesh sets."""
    e = np.array([r[key] for r in runs])
    d = e[:-1] - e[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.log2(d[:-1] / d[1:]).tolist()


def convective_cases(viscous: str, quick: bool):
    """The Ethier-Steinman case (:func:`ethier_steinman`) under refinement in space, then in time.

    Space: three meshes (core edge and layer count scaled together by about 1.4 per level) with a step
    small enough that the time error is a few % of the space error; the nodal velocity converges at
    order 2 for P1 elements, the element gradients (hence the WSS) at order 1.  Time: three (``quick``) or
    four steps halving on the middle mesh, the largest near the explicit viscous limit of its thinnest
    layer; the scheme is first order in time (backward Euler pressure and viscosity), and its velocity
    comes out at about 2 in this case.
    Limits: velocity order >= 1.6 and error <= 1 % on the finest mesh, gradient order >= 0.8 and error <=
    10 %, pressure error <= 2 %; time orders of velocity and pressure >= 0.8.

    Yields
    ------
    name, passed, text, data
        As :func:`solver_cases`.
    """
    sizes = ((1.0, 2), (0.7, 3), (0.5, 4)) if quick else ((0.7, 3), (0.5, 4), (0.35, 6))
    runs = [ethier_steinman(size, layers, 800 if quick else 1600, viscous) for size, layers in sizes]
    orders = {key: _order(runs, key, "h_mm") for key in ("velocity_error", "gradient_error", "pressure_error")}
    f = runs[-1]
    yield ("convective (Ethier-Steinman) in space",
           min(orders["velocity_error"]) >= 1.6 and f["velocity_error"] <= 0.01
           and min(orders["gradient_error"]) >= 0.8 and f["gradient_error"] <= 0.1 and f["pressure_error"] <= 0.02,
           f"Re {f['re']:.0f}, exact velocity on the boundary of a {sizes[-1][1]}-layer mesh, {f['tetrahedra']} tets: "
           f"velocity {100 * f['velocity_error']:.2f}% (<=1%), gradient {100 * f['gradient_error']:.1f}% "
           f"(<=10%), pressure {100 * f['pressure_error']:.2f}% (<=2%) (a solver that does not move: "
           f"{100 * f['change']:.0f}%); orders in h: velocity " + ", ".join(f"{o:.2f}" for o in orders["velocity_error"])
           + " (>=1.6), gradient " + ", ".join(f"{o:.2f}" for o in orders["gradient_error"]) + " (>=0.8), pressure "
           + ", ".join(f"{o:.2f}" for o in orders["pressure_error"]), {"orders": orders, "runs": runs})
    size, layers = sizes[1]
    steps = (100, 200, 400) if quick else (200, 400, 800, 1600)
    runs = [ethier_steinman(size, layers, n, viscous) for n in steps]
    orders = {key: _time_order(runs, key) for key in ("velocity_error", "pressure_error")}
    yield ("convective (Ethier-Steinman) in time",
           all(min(v) >= 0.8 for v in orders.values()),
           f"{runs[0]['tetrahedra']} tets, {'/'.join(map(str, steps))} steps: velocity errors "
           + ", ".join(f"{100 * r['velocity_error']:.2f}%" for r in runs) + ", pressure "
           + ", ".join(f"{100 * r['pressure_error']:.2f}%" for r in runs) + "; orders in dt: velocity "
           + ", ".join(f"{o:.2f}" for o in orders["velocity_error"]) + ", pressure "
           + ", ".join(f"{o:.2f}" for o in orders["pressure_error"]) + " (>=0.8)", {"orders": orders, "runs": runs})


def _pct(x: float) -> str:
    return f"{100 * x:+.2f}%"


def solver_cases(viscous: str, quick: bool):
    """The flow cases with one treatment of the viscous term, run lazily one after the other.

    Yields
    ------
    name : str
    passed : bool
    text : str
        The errors and their limits.
    data : dict
        The case's results.

    A consumer may stop early: the mutation tests stop at the first failure.  Limits: Poiseuille 1 % (3 %
    for the worst WSS point), P1 mass balance 0.1 % (straight pipe) and 1 % (split tube, whose septum and
    outlet element layers carry pressure-stabilisation flux), P1 outlet fractions 2 points of the inflow,
    development length 10 % of the correlation (its own scatter is a few %), Womersley 3 % of the peak
    (pressure gradient 5 %).  With ``quick`` the Poiseuille runs use two meshes and the Womersley run a quarter
    cycle, and the explicit scheme skips Womersley (its step is bound by the wall layer: three minutes).
    """
    yield from convective_cases(viscous, quick)
    runs = []
    for k in ((1, 2) if quick else (1, 2, 3)):
        runs.append(poiseuille(POISEUILLE.refined(k), viscous=viscous))
        if k == 1:
            p = runs[0]
            yield ("mass (straight pipe)", abs(p["imbalance_p1"]) <= 1e-3,
                   f"P1 int u.n imbalance {100 * p['imbalance_p1']:+.4f}% of the inflow (<=0.1%), from rest "
                   f"({p['steps']} steps; consistent-flux imbalance {p['imbalance']:+.1e}, imposed)", p)
    p = runs[1]
    yield ("Poiseuille", abs(p["centreline_error"]) <= 0.01 and abs(p["wss_mean_error"]) <= 0.01
           and p["wss_max_error"] <= 0.03 and abs(p["pressure_gradient_error"]) <= 0.01,
           f"from rest: centreline {_pct(p['centreline_error'])} (<=1%), WSS mean {_pct(p['wss_mean_error'])} "
           f"(<=1%), max {100 * p['wss_max_error']:.2f}% (<=3%), dp/dz {_pct(p['pressure_gradient_error'])} "
           f"(<=1%), {p['tetrahedra']} tets, {p['steps']} steps", p)
    orders = {key: _order(runs, key) for key in ("wss_mean_error", "wss_max_error", "centreline_error",
                                                 "pressure_gradient_error")}
    yield ("Poiseuille convergence", min(orders["wss_mean_error"]) > 1.0,
           "observed orders under refinement (x" + ", x".join(str(k) for k in range(2, len(runs) + 1)) + "): "
           + "; ".join(f"{key} " + ", ".join(f"{o:.2f}" for o in v) for key, v in orders.items())
           + " | mean WSS errors " + ", ".join(_pct(r["wss_mean_error"]) for r in runs) + " (orders > 1)",
           {"orders": orders, "runs": runs})
    s = poiseuille(SPLIT, split_outlet=True, split=(0.7, 0.3), viscous=viscous)
    yield ("mass split 70:30", abs(s["imbalance_p1"]) <= 1e-2 and s["split_error_p1"] <= 0.02,
           f"P1 int u.n: outlet fractions off by {100 * s['split_error_p1']:.2f} points (<=2), imbalance "
           f"{_pct(s['imbalance_p1'])} (<=1%); consistent fluxes (imposed): {s['split_error']:.1e}, "
           f"{s['imbalance']:+.1e}", s)
    if viscous == "implicit":  # explicit, the power law's high low-shear viscosity would bind the step
        w = power_law(viscous=viscous)
        yield ("power-law fluid", abs(w["centreline_error"]) <= 0.02 and abs(w["wss_mean_error"]) <= 0.02
               and abs(w["pressure_gradient_error"]) <= 0.02,
               f"n {w['n']:g}, developed from a parabolic inlet, from rest: centreline "
               f"{_pct(w['centreline_error'])}, WSS mean {_pct(w['wss_mean_error'])}, dp/dz "
               f"{_pct(w['pressure_gradient_error'])} (all <=2%), {w['tetrahedra']} tets, {w['steps']} steps", w)
    if viscous == "implicit":  # its fixed step (period / 200) is above the explicit limit of the wall layer
        r = rcr_outlet(viscous=viscous)
        yield ("RCR outlet", abs(r["mean_error"]) <= 0.02 and abs(r["amplitude_error"]) <= 0.02
               and abs(r["phase_error"]) <= 0.02,
               f"sinusoidal inflow, outlet pressure over the third period against the 0D impedance: mean "
               f"{_pct(r['mean_error'])}, first harmonic amplitude {_pct(r['amplitude_error'])}, phase "
               f"{r['phase_deg']:.2f} deg for {r['expected_phase_deg']:.2f} ({_pct(r['phase_error'])}) (all <=2%), "
               f"{r['steps']} steps", r)
    e = entrance(viscous=viscous)
    yield ("entrance length", abs(e["length_error"]) <= 0.1,
           f"Re {e['re']:.0f}, plug inlet, from rest: centreline at 99% after {e['development_length_d']:.2f} D, "
           f"Durst et al. 2005: {e['expected_d']:.2f} D, error {_pct(e['length_error'])} (<=10%), "
           f"{e['tetrahedra']} tets, {e['steps']} steps", e)
    if quick and viscous == "explicit":
        return
    w = womersley(window=0.25 if quick else 1.0, samples=8 if quick else 24, settle=0.4 if quick else 0.5,
                  viscous=viscous)
    yield ("Womersley", w["velocity_error_of_peak"] <= 0.03 and w["max_error_of_peak"] <= 0.03
           and w["pressure_gradient_error_of_peak"] <= 0.05,
           f"alpha {w['alpha']:.1f}, from rest, section 2 D from both ends, over "
           f"{'the systolic quarter cycle' if quick else 'one cycle'}: velocity "
           f"{100 * w['velocity_error_of_peak']:.2f}% (<=3%), WSS {100 * w['max_error_of_peak']:.2f}% (<=3%), "
           f"dp/dz {100 * w['pressure_gradient_error_of_peak']:.2f}% (<=5%) of the peak, {w['tetrahedra']} tets, "
           f"{w['steps']} steps", w)


@threadpool_limits.wrap(limits=1, user_api="blas")  # as carotid.flow.simulate.simulate
def run_verification(quick: bool = False, out=None) -> list[dict]:
    """Run the cases, print one pass/fail line each to ``out``, return the results."""
    import sys
    import time

    out = out or sys.stdout
    results = []

    def report(name, passed, text, data):
        results.append({"case": name, "passed": bool(passed), **data})
        print(f"[{'PASS' if passed else 'FAIL'}] {name}: {text}", file=out, flush=True)

    start = time.perf_counter()
    g = inlet_profiles()
    report("generalised inlet", g["circle_error"] <= 0.02 and g["ellipse_error"] <= 0.02,
           f"circular face vs Womersley over a cycle {100 * g['circle_error']:.2f}%, elliptic face vs "
           f"2U(1 - x^2/a^2 - y^2/b^2) {100 * g['ellipse_error']:.2f}% of the peak (both <=2%)", g)
    for viscous in ("explicit", "implicit"):
        tag = "" if viscous == "explicit" else " [implicit viscosity]"
        try:
            for name, passed, text, data in solver_cases(viscous, quick):
                report(name + tag, passed, text, data)
        except CarotidError as error:  # a solver that breaks down (e.g. a diverging implicit solve) fails
            report("remaining cases" + tag, False, str(error), {})
    print(f"verification took {time.perf_counter() - start:.0f} s", file=out)
    return results
