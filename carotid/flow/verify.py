"""Analytic verification of the flow solver on the user's machine (``carotid verify``).

Cases (formulas in validation.md):

* Poiseuille: steady flow in a straight rigid pipe; centreline velocity and wall shear stress (mean and
  worst point around the circumference) against ``u_max = 2Q/(pi R^2)``, ``tau_w = 4 mu Q/(pi R^3)``, on two
  or three refinements of the tube mesh, with the observed order of the WSS error;
* Womersley: the built-in carotid waveform (alpha ~ 4.7) in a straight pipe, started from the analytic
  solution; WSS at the mid-length wall over the last cycle against the analytic Womersley WSS, relative to
  its peak, at every output time;
* mass split: a pipe whose outlet disc is cut in two outlets with a prescribed 70:30 split.

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

from carotid.flow.mesh import WALL, FlowMesh

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


# Poiseuille base mesh (refined x2 for the pass/fail figures), split-outlet tube, Womersley tube
POISEUILLE = TubeSpec(n_square=8, n_core=4, n_layers=4, first_layer=0.06, growth=1.25, n_axial=2, length=2.0)
SPLIT = TubeSpec(n_square=8, n_core=4, n_layers=4, first_layer=0.06, growth=1.25, n_axial=6, length=6.5)
WOMERSLEY = TubeSpec(n_square=12, n_core=6, n_layers=5, first_layer=0.05, growth=1.25, n_axial=2, length=2.0)


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


def steady_waveform(q_m3s: float, period: float = 1.0):
    """A constant flow rate as a :class:`carotid.flow.waveform.Waveform`."""
    from carotid.flow.waveform import Waveform

    return Waveform(period, np.linspace(0.0, period, 9)[:-1], np.full(8, q_m3s))


def developed_start(mesh: FlowMesh, profile) -> np.ndarray:
    """Initial velocity (n, 3): the inlet profile at t = 0 carried along the tube axis (+z)."""
    from scipy.spatial import cKDTree

    nodes, pts, _ = mesh.face_patch(2)
    idx = cKDTree(pts[:, :2]).query(mesh.points[:, :2])[1]
    u = np.zeros((mesh.n_points, 3))
    u[:, 2] = profile.velocity(0.0)[idx]
    return u


def _mid_wall(mesh: FlowMesh, wall, spec: TubeSpec) -> np.ndarray:
    z = mesh.points[wall.nodes, 2] / 1e-3
    return (z > 0.3 * spec.length) & (z < 0.7 * spec.length)


def poiseuille(spec: TubeSpec = POISEUILLE, q: float = 6e-6, max_steps: int = 6000, tol: float = 1e-3,
               split_outlet: bool = False, split=None, viscous: str = "explicit") -> dict:
    """Steady Poiseuille flow in a tube; errors of centreline velocity and WSS (mid-length third).

    The run starts from the inlet profile carried along the tube and stops when the relative velocity
    change rate ``max|du|/(dt max|u|)`` drops below ``tol`` 1/s or after ``max_steps``.

    Returns
    -------
    dict
        ``centreline_error``, ``wss_mean_error``, ``wss_max_error`` (relative, signed / absolute; not for a
        split tube), ``imbalance`` ((inflow - outflow) / inflow) and ``split_error`` (max |Q_i / Q_in - s_i|)
        with the consistent outlet fluxes, the same with the P1 flux ``int u.n`` (``..._p1``), ``steps``,
        ``residual``, mesh sizes.
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.womersley import inlet_profile
    from carotid.flow.wss import WallShear

    mesh = tube_mesh(spec, split_outlet=split_outlet)
    r = spec.radius * 1e-3
    nodes, pts, tris = mesh.face_patch(2)
    profile = inlet_profile(pts, tris, mesh.face_normal(2), steady_waveform(q), NU, 0)
    solver = CBSSolver(mesh, profile.velocity, NU, split=split, safety=0.8, viscous=viscous)
    solver.reset(developed_start(mesh, profile))
    residual = np.inf
    for _ in range(max_steps):
        before = solver.u.copy()
        info = solver.step()
        residual = float(np.abs(solver.u - before).max() / (info.dt * np.abs(solver.u).max()))
        if residual < tol:
            break
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
    return {**res, "centreline_error": float(solver.u[axis, 2].mean() / (2 * q / (np.pi * r**2)) - 1),
            "wss_mean_error": float(tau.mean() / tau_exact - 1),
            "wss_max_error": float(np.abs(tau / tau_exact - 1).max())}


def womersley(spec: TubeSpec | None = None, cycles: float = 1.0, samples: int = 24, n_harmonics: int = 10,
              viscous: str = "explicit") -> dict:
    """The carotid waveform in a straight tube with the generalised Womersley inlet profile.

    The run starts from the inlet profile at t = 0 carried along the tube (zero pressure: the discrete
    periodic solution of the section, so no spin-up cycle is needed) and lasts ``cycles`` cycles; the
    WSS (mean over the mid-length wall nodes) is sampled ``samples + 1`` times over the last cycle (or
    over the whole run if shorter) and compared with the analytic Womersley WSS of the
    circular pipe (:func:`carotid.flow.womersley.womersley_wss`); the error is relative to the analytic
    peak |tau|.
    """
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.simulate import stabilisation_velocity
    from carotid.flow.waveform import carotid_waveform
    from carotid.flow.womersley import inlet_profile, womersley_wss
    from carotid.flow.wss import WallShear

    spec = spec or WOMERSLEY
    wave = carotid_waveform()
    mesh = tube_mesh(spec)
    r = spec.radius * 1e-3
    nodes, pts, tris = mesh.face_patch(2)
    profile = inlet_profile(pts, tris, mesh.face_normal(2), wave, NU, n_harmonics)
    solver = CBSSolver(mesh, profile.velocity, NU, safety=0.8,
                       velocity_scale=stabilisation_velocity(wave, mesh.face_area(2)), viscous=viscous)
    solver.reset(developed_start(mesh, profile))
    wall = WallShear(mesh, solver.volumes)
    mid = _mid_wall(mesh, wall, spec)
    t_end = cycles * wave.period_s
    times = t_end - wave.period_s * min(cycles, 1.0) * (1 - np.arange(samples + 1) / samples)
    sim, exact = [], []
    for t_sample in times:
        while solver.t < t_sample - 1e-12:
            solver.step(max_dt=t_sample - solver.t)
        sim.append(wall.nodes_wss(wall.faces_wss(solver.velocity_gradients(), MU))[mid, 2].mean())
        exact.append(womersley_wss(solver.t, r, wave, MU, NU, n_harmonics))
    sim, exact = np.array(sim), np.array(exact)
    peak = np.abs(exact).max()
    return {"tetrahedra": len(mesh.tets), "steps": solver.step_count, "cycles": cycles, "times": times.tolist(),
            "wss": sim.tolist(), "wss_exact": exact.tolist(),
            "max_error_of_peak": float(np.abs(sim - exact).max() / peak),
            "alpha": r * np.sqrt(wave.omega / NU)}


def _order(runs: list[dict], key: str) -> list[float]:
    """Observed orders ``log(e_k / e_k+1) / log(h_k / h_k+1)`` of ``|run[key]|`` between successive meshes."""
    e = np.array([abs(r[key]) for r in runs])
    h = np.array([r["first_layer_mm"] for r in runs])
    return (np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:])).tolist()


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
    for viscous in ("explicit", "implicit"):
        _verify_scheme(viscous, quick, report)
    print(f"verification took {time.perf_counter() - start:.0f} s", file=out)
    return results


def _verify_scheme(viscous: str, quick: bool, report) -> None:
    """The Poiseuille, mass and Womersley cases with one treatment of the viscous term (see run_verification)."""
    tag = "" if viscous == "explicit" else " [implicit viscosity]"
    runs = [poiseuille(POISEUILLE.refined(k), viscous=viscous) for k in ((1, 2) if quick else (1, 2, 3))]
    p = runs[1]
    report(f"Poiseuille{tag}", abs(p["centreline_error"]) <= 0.01 and abs(p["wss_mean_error"]) <= 0.01
           and p["wss_max_error"] <= 0.03,
           f"centreline {100 * p['centreline_error']:+.2f}% (<=1%), WSS mean {100 * p['wss_mean_error']:+.2f}% "
           f"(<=1%), max {100 * p['wss_max_error']:.2f}% (<=3%), {p['tetrahedra']} tets, {p['steps']} steps", p)
    orders = {key: _order(runs, key) for key in ("wss_mean_error", "wss_max_error", "centreline_error")}
    report(f"Poiseuille convergence{tag}", min(orders["wss_mean_error"]) > 1.0,
           "observed orders under refinement (x" + ", x".join(str(k) for k in range(2, len(runs) + 1)) + "): "
           + "; ".join(f"{key} " + ", ".join(f"{o:.2f}" for o in v) for key, v in orders.items())
           + " | mean WSS errors " + ", ".join(f"{100 * r['wss_mean_error']:+.2f}%" for r in runs),
           {"orders": orders, "runs": runs})
    for name, r in (("mass (straight pipe)", p), ("mass split 70:30", poiseuille(SPLIT, split_outlet=True,
                                                                                 split=(0.7, 0.3), viscous=viscous))):
        report(name + tag, r["split_error"] <= 1e-3 and abs(r["imbalance"]) <= 1e-3,
               f"outlet flow error {100 * r['split_error']:.2e}% of the inflow, imbalance {100 * r['imbalance']:+.2e}% "
               f"(both <= 0.1%, consistent flux); P1 n.u flux: imbalance {100 * r['imbalance_p1']:+.3f}%, "
               f"outlet error {100 * r['split_error_p1']:.3f}%", r)
    w = womersley(cycles=0.25 if quick else 1.0, samples=6 if quick else 24, viscous=viscous)
    report(f"Womersley{tag}", w["max_error_of_peak"] <= 0.03,
           f"alpha {w['alpha']:.1f}, WSS error {100 * w['max_error_of_peak']:.2f}% of the peak (<=3%) over "
           f"{'the first quarter cycle' if quick else 'one cycle'}, {w['tetrahedra']} tets, "
           f"{w['steps']} steps", w)
