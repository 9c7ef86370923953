"""The flow stage driver: mesh + waveform -> CBS run -> ``CASE_DIR/flow`` (series, WSS, indices, summary).

Blood is Newtonian by default (rho 1060 kg/m^3, mu 3.5e-3 Pa s; validation.md), or shear-thinning
(:mod:`carotid.flow.rheology`).  The inlet carries the generalised Womersley profile of the waveform
(:func:`carotid.flow.womersley.inlet_profile`, solved on the actual inlet face); the outlets share the inflow
by Murray's law or user ratios, imposed every step, or follow resistance / RCR laws (:mod:`carotid.flow.cbs`,
:mod:`carotid.flow.outlets`).  Outputs are written every ``output_every`` steps and checkpoints every
``checkpoint_every`` steps, and at the step a Ctrl-C (SIGINT) interrupts; ``resume=True`` continues from the
last checkpoint and, the run being deterministic (the time-step sequence follows from the stored state, the
pressure warm start is stored), ends with the same fields as an uninterrupted run.  Probes (the user's points, the
Doppler gates, the centreline probes; :mod:`carotid.flow.probes`, :mod:`carotid.flow.duplex`) are sampled from the
solver's state after every step, their series kept in the checkpoints, and the virtual duplex of the last cycle
goes to the summary; with measured CCA velocities the inflow is calibrated to them first.
"""

from __future__ import annotations

import hashlib
import json
import math
import signal
import threading
import time as _time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from carotid.errors import CarotidError, CarotidWarning
from carotid.flow.cbs import CBSSolver, PressureSolver
from carotid.flow.duplex import case_probes, duplex_summary
from carotid.flow.mesh import INLET, MM, FlowMesh
from carotid.flow.output import FlowWriter, load_checkpoint, save_checkpoint, write_wall_vtp
from carotid.flow.probes import ProbeRecorder
from carotid.flow.wss import WallShear
from carotid.io import write_json


# Version of what a checkpoint stores (its output records carry per-outlet P1 fluxes from version 2, the volumes
# passed since t = 0 from version 3): a checkpoint of another version does not match the fingerprint, so a run
# starts afresh instead of resuming.
CHECKPOINT_FORMAT = 3


@dataclass
class FlowParameters:
    """Settings of one simulation (SI units).

    Attributes
    ----------
    cycles : float
        Cardiac cycles to run.
    dt : float or None
        Fixed time step, s; None: adaptive (``safety`` x the convective/diffusive limit).
    safety : float
        Safety factor of the adaptive step.
    waveform : Waveform or None
        Inlet flow; None: :func:`carotid.flow.waveform.carotid_waveform`.
    n_harmonics : int
        Harmonics of the inlet profile.
    split : sequence of float or None
        Flow fraction per outlet (ascending label: 3, 4, ...); None: Murray's law.
    outlets : {"murray", "split", "resistance", "rcr"}
        Outlet model: a prescribed split (Murray's law, or ``split``), or resistance / RCR outlets
        (:mod:`carotid.flow.outlets`) calibrated for that split as the mean share, or given explicitly.
    mean_pressure_mmhg, pulse_pressure_mmhg : float
        Calibration targets of the resistance (mean) and RCR (mean and pulse) outlets, mmHg.
    proximal_fraction : float
        ``R_p / (R_p + R_d)`` of the calibrated RCR outlets.
    distal_pressure_mmhg : float
        Pressure downstream of the lumped outlets, mmHg.
    resistance : sequence of float or None
        Explicit outlet resistances, Pa s/m^3 (``outlets="resistance"``; None: calibrated).
    rcr : sequence of (R_p, C, R_d) or None
        Explicit RCR parameters per outlet, Pa s/m^3, m^3/Pa, Pa s/m^3 (``outlets="rcr"``; None: calibrated).
    backflow : float
        Coefficient of the outlet backflow stabilisation (Esmaily-Moghadam et al. 2011; 0: none).
    turbulence : {"none", "sa"}
    viscous : {"explicit", "implicit"}
        Molecular viscous term of the momentum step: explicit (the paper's CBS; step bounded by the thinnest
        wall layer) or backward Euler (step bounded by convection); see :mod:`carotid.flow.cbs`.
    output_every, checkpoint_every : int
        Steps between outputs and between checkpoints.
    rho, mu : float
        Density kg/m^3 and dynamic viscosity Pa s.
    rheology : {"newtonian", "carreau", "casson"}
        Viscosity law (:mod:`carotid.flow.rheology`, published blood parameters); "newtonian" uses ``mu``.
    max_speed : float
        |u| above which the run is declared blown up, m/s.
    pressure : str
        Pressure solver, see :class:`carotid.flow.cbs.PressureSolver`.
    force : bool
        Run even when :func:`run_estimate` exceeds ``MAX_STEPS`` or the free disk space.
    periodic_tol : float
        Stop at the end of the first whole cycle whose TAWSS differs from the previous cycle's by less than
        this area-weighted L2 relative change (:class:`CyclePeriodicity`), ``cycles`` being then the maximum;
        0: run exactly ``cycles``.
    probes : tuple of (name, (x, y, z))
        Probe points, mm LPS (:mod:`carotid.flow.probes`): their velocity and pressure series go to
        ``flow/probes.csv`` and ``flow/probes.xdmf`` with the Doppler gates and the centreline probes.
    doppler_cca : (float, float) or None
        Measured CCA peak systolic and end-diastolic velocity, cm/s: the inflow is mapped to ``a q + b`` so that
        the inlet's Womersley centreline velocity matches them (:func:`carotid.flow.duplex.calibrate_inflow`).
    """

    cycles: float = 3.0
    dt: float | None = None
    safety: float = 0.8
    waveform: object = None
    n_harmonics: int = 10
    split: tuple | None = None
    outlets: str = "murray"
    mean_pressure_mmhg: float = 93.0
    pulse_pressure_mmhg: float = 40.0
    proximal_fraction: float = 0.09
    distal_pressure_mmhg: float = 0.0
    resistance: tuple | None = None
    rcr: tuple | None = None
    backflow: float = 0.2
    turbulence: str = "none"
    viscous: str = "implicit"
    output_every: int = 50
    checkpoint_every: int = 500
    rho: float = 1060.0
    mu: float = 3.5e-3
    rheology: str = "newtonian"
    max_speed: float = 20.0
    pressure: str = "auto"
    force: bool = False
    periodic_tol: float = 0.0
    probes: tuple = ()
    doppler_cca: tuple | None = None
    extra: dict = field(default_factory=dict)

    def validate(self) -> FlowParameters:
        if not self.cycles > 0:
            raise CarotidError(f"--cycles must be positive (got {self.cycles})")
        if self.dt is not None and not self.dt > 0:
            raise CarotidError(f"--dt must be positive (got {self.dt})")
        if self.outlets not in OUTLET_MODELS:
            raise CarotidError(f"--outlets must be one of {', '.join(OUTLET_MODELS)} (got {self.outlets!r})")
        if self.outlets == "split" and self.split is None:
            raise CarotidError("--outlets split needs the fractions: --split 0.65:0.35")
        if self.resistance is not None and not all(math.isfinite(r) and r > 0 for r in self.resistance):
            raise CarotidError(f"outlet resistances must be positive numbers, Pa s/m^3 (got {list(self.resistance)})")
        if self.rcr is not None and not all(len(row) == 3 and all(math.isfinite(v) and v > 0 for v in row)
                                            for row in self.rcr):
            raise CarotidError("each RCR outlet needs three positive values: R_p (Pa s/m^3), C (m^3/Pa), R_d "
                               f"(Pa s/m^3) (got {[list(row) for row in self.rcr]})")
        if not self.backflow >= 0:
            raise CarotidError(f"the backflow stabilisation coefficient must be >= 0 (got {self.backflow})")
        if self.rheology not in ("newtonian", "carreau", "casson"):
            raise CarotidError(f"--rheology must be newtonian, carreau or casson (got {self.rheology!r})")
        if self.turbulence not in ("none", "sa"):
            raise CarotidError(f"--turbulence must be 'sa' or 'none' (got {self.turbulence!r})")
        if self.viscous not in CBSSolver.VISCOUS:
            raise CarotidError(f"--viscous must be 'explicit' or 'implicit' (got {self.viscous!r})")
        if self.pressure not in PressureSolver.METHODS:
            raise CarotidError(f"--pressure must be one of {', '.join(PressureSolver.METHODS)} (got {self.pressure!r})")
        if self.output_every < 1 or self.checkpoint_every < 1:
            raise CarotidError("--output-every and the checkpoint interval must be at least 1 step")
        if not (0 <= self.periodic_tol < 1):
            raise CarotidError(f"--periodic-tol must be in [0, 1) (got {self.periodic_tol})")
        if not (0 < self.safety <= 1):
            raise CarotidError(f"the time-step safety factor must be in (0, 1] (got {self.safety})")
        if self.doppler_cca is not None:
            from carotid.flow.duplex import check_doppler

            check_doppler(*self.doppler_cca)
        # The sign only: the physiological bounds of check_inflow hold the user's input (a waveform file, a
        # steady flow), not the API's, whose verification cases run small tubes on short periods.
        if self.waveform is not None:
            from carotid.flow.waveform import ML, check_inflow_sign

            check_inflow_sign(self.waveform.mean_m3s / ML, "the inlet waveform")
        return self

    def fingerprint(self, waveform, mesh: FlowMesh) -> str:
        """Hash of everything that changes the solution: these settings (not ``cycles``, ``periodic_tol`` nor
        output settings), the waveform and the mesh."""
        keys = {k: v for k, v in asdict(self).items()
                if k not in ("cycles", "periodic_tol", "output_every", "checkpoint_every", "waveform", "extra",
                             "force", "probes")}
        keys["waveform"] = np.round(np.r_[waveform.period_s, waveform.times_s, waveform.flow_m3s], 15).tolist()
        keys["checkpoint_format"] = CHECKPOINT_FORMAT
        digest = hashlib.sha256(json.dumps(keys, sort_keys=True, default=str).encode())
        for array in (mesh.points, mesh.tets, mesh.faces, mesh.labels):
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.hexdigest()[:16]


OUTLET_MODELS = ("murray", "split", "resistance", "rcr")


def outlet_model(params: FlowParameters, waveform, mesh: FlowMesh):
    """The lumped outlets of ``params`` (None for a prescribed split): explicit values, or calibrated for the
    target share (``split``, else Murray's law) with :func:`carotid.flow.outlets.tune_rcr`."""
    from carotid.flow.cbs import murray_split
    from carotid.flow.outlets import MMHG, OutletModel, tune_rcr

    if params.outlets in ("murray", "split"):
        return None
    m, pd = len(mesh.outlet_labels), params.distal_pressure_mmhg * MMHG
    explicit = params.resistance if params.outlets == "resistance" else params.rcr
    if explicit is not None:
        values = np.asarray(explicit, dtype=float)
        if len(values) != m:
            raise CarotidError(f"{len(values)} outlet {params.outlets} values for {m} outlets")
        if params.outlets == "resistance":
            return OutletModel.resistance(values, pd)
        if values.shape != (m, 3):
            raise CarotidError("each RCR outlet needs three values: R_p (Pa s/m^3), C (m^3/Pa), R_d (Pa s/m^3)")
        model = OutletModel(values[:, 0], values[:, 1], values[:, 2], pd)
        # start at the mean state of a flow shared as the distal conductances are (P_c equal on every outlet)
        conductance = 1.0 / (values[:, 0] + values[:, 2])
        model.pc = pd + values[:, 2] * conductance / conductance.sum() * waveform.mean_m3s
        return model
    share = np.asarray(params.split, dtype=float) if params.split is not None else murray_split(mesh)
    if params.outlets == "resistance":
        return OutletModel.resistance((params.mean_pressure_mmhg * MMHG - pd) / (share * waveform.mean_m3s), pd)
    model = tune_rcr(waveform, share, params.mean_pressure_mmhg * MMHG, params.pulse_pressure_mmhg * MMHG,
                     params.proximal_fraction, pd)
    model.pc = pd + model.rd * share * waveform.mean_m3s  # start at the mean state, not from P_d: no slow charging
    return model


def stabilisation_velocity(waveform, inlet_area: float) -> float:
    """Velocity scale U of the pressure stabilisation time ``tau_e`` (:class:`CBSSolver`), m/s.

    Twice the cycle-mean inlet speed (``inlet_area`` in m^2).  Not the systolic peak: the smaller
    ``tau_e`` it gives lets near-wall transverse velocity oscillations grow (measured on the Womersley
    verification tube: |u_transverse| 0.6 m/s after 0.015 s with U = 2 peak / A, 1e-4 m/s with this U).
    """
    t = np.linspace(0.0, waveform.period_s, 256, endpoint=False)
    return 2.0 * float(np.mean(np.abs(waveform.flow(t)))) / inlet_area


def _inflow(mesh: FlowMesh, params: FlowParameters):
    """The inflow waveform, its inlet profile and the Doppler calibration record (None without ``doppler_cca``)."""
    from carotid.flow.duplex import calibrate_inflow
    from carotid.flow.waveform import carotid_waveform
    from carotid.flow.womersley import inlet_profile

    waveform = params.waveform if params.waveform is not None else carotid_waveform()  # checked by validate
    nu = params.mu / params.rho
    nodes, pts, tris = mesh.face_patch(INLET)
    if params.doppler_cca is None:
        return waveform, inlet_profile(pts, tris, mesh.face_normal(INLET), waveform, nu, params.n_harmonics), None
    psv, edv = params.doppler_cca
    return calibrate_inflow(waveform, pts, tris, mesh.face_normal(INLET), nu, params.n_harmonics, psv / 100,
                            edv / 100)


def _build(mesh: FlowMesh, params: FlowParameters, inflow=None):
    """Waveform, solver and wall shear of a run; ``inflow``: :func:`_inflow`'s result when already computed."""
    from carotid.flow.rheology import Rheology
    from carotid.flow.turbulence import SpalartAllmaras

    waveform, profile, _ = inflow or _inflow(mesh, params)
    nu = params.mu / params.rho
    turbulence = SpalartAllmaras(mesh, nu) if params.turbulence == "sa" else None
    solver = CBSSolver(mesh, profile.velocity, nu, split=params.split, dt=params.dt, safety=params.safety,
                       velocity_scale=stabilisation_velocity(waveform, mesh.face_area(INLET)),
                       turbulence=turbulence, pressure=params.pressure, viscous=params.viscous,
                       outlets=outlet_model(params, waveform, mesh), rho=params.rho, backflow=params.backflow,
                       rheology=Rheology(params.rheology, mu=params.mu))
    wall = WallShear(mesh, solver.volumes, distance=None if turbulence is None else turbulence.d)
    return waveform, solver, wall


# Steps beyond which a run must be confirmed (``force``): the default implicit viscosity needs thousands of steps
# per cycle on a patient mesh, the paper's explicit scheme up to a few million for three cycles.
MAX_STEPS = 5_000_000


def run_estimate(solver: CBSSolver, wall: WallShear, params: FlowParameters, t_end: float) -> dict:
    """Steps and output size of a run from the solver's current state to ``t_end`` (s).

    The step is the solver's next one: with a fixed step the count is exact.  The adaptive step of the
    current velocity (at rest: with implicit viscosity the one of twice the cycle-mean inlet speed, with
    explicit viscosity the diffusive bound of the thinnest element) only gives a lower bound, since the
    step shrinks where systole and a stenotic jet speed the flow up (on the demo case 995 estimated, 4644
    taken).  Each output writes velocity and pressure (and ``nu_t``) on every node and the wall shear
    stress on the wall nodes and faces, in float64.

    Returns
    -------
    dict
        ``steps``, ``dt_s`` (s), ``outputs``, ``bytes`` and ``exact`` (False: lower bounds).
    """
    dt, _ = solver.time_step(solver.element_viscosity())
    steps = int(np.ceil(max(t_end - solver.t, 0.0) / dt))
    outputs = steps // params.output_every + 1
    per_node = 4 + (solver.turbulence is not None)
    size = 8 * (solver.mesh.n_points * per_node + 3 * len(wall.nodes) + 3 * len(wall.faces))
    return {"steps": steps, "dt_s": dt, "outputs": outputs, "bytes": outputs * size,
            "exact": solver.fixed_dt is not None}


def check_estimate(estimate: dict, params: FlowParameters, flow_dir: Path) -> None:
    """Raise CarotidError, unless ``params.force``, for a run beyond ``MAX_STEPS`` or the free disk space."""
    import shutil

    folder = next(p for p in (flow_dir, *flow_dir.parents) if p.exists())
    free = shutil.disk_usage(folder).free
    if params.force or (estimate["steps"] <= MAX_STEPS and estimate["bytes"] < free):
        return
    raise CarotidError(f"the run would take {'' if estimate['exact'] else 'at least '}{estimate['steps']:,} steps of {estimate['dt_s']:.2g} s and write "
                       f"{estimate['bytes'] / 1e9:.3g} GB ({free / 1e9:.3g} GB free, at most {MAX_STEPS:,} steps "
                       "without --force): use a larger --dt, fewer --cycles or a larger --output-every, "
                       "or --force")


def _diagnostics(solver: CBSSolver, info, rho: float) -> dict:
    mesh = solver.mesh
    p = solver.pressure_pa(rho)
    nodes, w = mesh.flux_weights(INLET)
    a = np.linalg.norm(w, axis=1)
    p_in = float(a @ p[nodes] / a.sum())
    p_out = [float(np.linalg.norm(wj, axis=1) @ p[nj] / np.linalg.norm(wj, axis=1).sum())
             for nj, wj in solver.out_flux]
    return {"dt": info.dt, "cfl": info.cfl, "inflow": info.inflow, "outflow": info.outflow.tolist(),
            "outflow_p1": info.outflow_p1.tolist(), "imbalance": info.imbalance, "imbalance_p1": info.imbalance_p1,
            "passed_m3": solver.passed.tolist(), "dp": p_in - float(np.average(p_out, weights=solver.outlet_areas)),
            "inlet_pressure": p_in, "outlet_pressure": p_out}


def outlet_shares(records: list[dict], t0: float, t1: float) -> np.ndarray:
    """Share of the inflow volume that left through each outlet between the output records at ``t0`` and ``t1``
    (s; the first record at or after each), from the volumes passed (:attr:`CBSSolver.passed`), shape
    (outlets,): the share of the mean flow over the window, not the mean of the instantaneous shares, which
    over-weights the diastole's small flows and the short steps of the systole."""
    def passed(t: float) -> np.ndarray:
        return np.array(next(r for r in records if r["time"] >= t * (1 - 1e-12) - 1e-15)["diagnostics"]["passed_m3"])

    volume = passed(t1) - passed(t0)
    return volume[1:] / volume[0] if volume[0] > 0 else np.full(len(volume) - 1, np.nan)


# The solver's BLAS calls are vector-sized (CG dot products and updates on the nodes): a second BLAS thread
# gains nothing alone and halves the step when another process holds the other core (measured 0.047 s ->
# 0.096 s per step on a 164k-tetrahedron tube; 0.049 s with one thread).
@threadpool_limits.wrap(limits=1, user_api="blas")
def simulate(mesh, case_dir, params: FlowParameters | None = None, resume: bool | str = False,
             progress: Callable[[dict], None] | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Run the flow stage and write ``CASE_DIR/flow``.

    Parameters
    ----------
    mesh : FlowMesh or path
        The volume mesh (a path is read with :meth:`FlowMesh.from_vtu`).
    case_dir : path
        Case folder; outputs go to ``case_dir/flow``.
    params : FlowParameters
    resume : bool or "auto"
        Continue from ``flow/checkpoint.npz`` (an error when there is none or it was made with other settings
        or another mesh); ``"auto"``: continue when a matching checkpoint exists, else start afresh.
    progress : callable, optional
        Called after every step with ``{"step", "time", "cycle", "cfl", "imbalance", "end"}``.
    log : callable, optional
        Receives one line before the run: its estimated steps and output size (:func:`run_estimate`).

    Returns
    -------
    dict
        The summary also written to ``flow/summary.json``.
    """
    params = (params or FlowParameters()).validate()
    mesh = mesh if isinstance(mesh, FlowMesh) else FlowMesh.from_vtu(mesh)
    flow_dir = Path(case_dir) / "flow"
    ckpt = flow_dir / "checkpoint.npz"
    probes, duplex = case_probes(case_dir, mesh, params.probes)  # a probe outside the fluid stops here
    inflow = _inflow(mesh, params)
    waveform, solver, wall = _build(mesh, params, inflow)
    recorder = ProbeRecorder(probes, waveform.period_s)
    period = waveform.period_s
    t_end = params.cycles * period
    fp = params.fingerprint(waveform, mesh)
    seconds = 0.0
    if resume == "auto":
        resume = _matching_checkpoint(ckpt, fp)
    if resume:
        if not ckpt.is_file():
            raise CarotidError(f"no checkpoint to resume from in {flow_dir}: run without --resume")
        try:
            state, meta = load_checkpoint(ckpt)
        except CarotidError as exc:
            raise CarotidError(f"{exc}: delete it to start from t = 0") from None
        if meta.get("fingerprint") != fp:
            raise CarotidError("the checkpoint was made with other settings (dt, split, waveform, turbulence...) "
                               "or another mesh: use the same options or run without --resume")
        solver.load_state(state)
        seconds = meta["seconds"]
    else:
        solver.reset()
    estimate = run_estimate(solver, wall, params, t_end)
    check_estimate(estimate, params, flow_dir)
    if log is not None:
        bound = "" if estimate["exact"] else " or more (the adaptive step shrinks as the flow speeds up)"
        log(f"from t = {solver.t:.4f} s to {t_end:.4f} s: {estimate['steps']:,} steps of {estimate['dt_s']:.2g} s, "
            f"{estimate['outputs']:,} outputs, {estimate['bytes'] / 1e6:,.0f} MB{bound}")
    writer = FlowWriter(flow_dir, mesh, wall.nodes, wall.local_faces)
    if resume:
        writer.truncate(meta["records"])
        recorder.load(state, meta["records"], flow_dir)
    else:
        _output(writer, solver, wall, params, {"dt": 0.0, "cfl": 0.0, "inflow": solver.inflow(solver.u),
                                               "outflow": solver.outflows(solver.u).tolist(),
                                               "outflow_p1": solver.outflows(solver.u).tolist(), "imbalance": 0.0,
                                               "imbalance_p1": 0.0, "passed_m3": solver.passed.tolist(),
                                               "dp": 0.0})
        recorder.record(solver.t, solver.u, solver.pressure_pa(params.rho), force=True)
        _checkpoint(ckpt, solver, writer, fp, seconds, recorder)
    start = _time.perf_counter() - seconds
    periodicity = CyclePeriodicity(writer, mesh, wall, period)
    with _DeferredInterrupt() as interrupt:
        _run_steps(solver, writer, wall, params, ckpt, fp, start, t_end, period, interrupt, progress, periodicity,
                   recorder)
    seconds = _time.perf_counter() - start
    summary = _finish(flow_dir, mesh, solver, wall, writer, params, waveform, seconds, periodicity)
    summary.update(_probe_summary(flow_dir, solver, params, waveform, recorder, duplex, inflow[2]))
    write_json(summary, flow_dir / "summary.json")
    return summary


class _DeferredInterrupt:
    """Ctrl-C (SIGINT) during the time loop sets ``requested`` instead of raising mid-step; the loop then writes
    a checkpoint and raises KeyboardInterrupt, so a rerun resumes at that step.  A second Ctrl-C raises at once.
    Signal handlers belong to the main thread: elsewhere (a Dask worker) SIGINT is left alone."""

    def __init__(self):
        self.requested = False
        self._installed = False
        self._previous = None

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self) -> _DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if self._installed:  # None: a handler not set from Python, for which Python's own stands in
            signal.signal(signal.SIGINT, signal.default_int_handler if self._previous is None else self._previous)


class FlowBlowUp(CarotidError):
    """The solution left the finite or physical range (``|u|`` above ``max_speed``) at time ``time_s`` (s) of
    the time loop; the last good checkpoint is kept.  ``detail`` says where: the step, the time, the speed and
    the node (mm)."""

    def __init__(self, message: str, time_s: float, detail: str):
        super().__init__(message)
        self.time_s, self.detail = time_s, detail


def _blow_up_hint(params: FlowParameters) -> str:
    """What to try after a blow-up.  A prescribed split forces each outlet's share through the lumen at
    whatever pressure it takes; behind a tight stenosis that can diverge with a smaller time step and a finer
    mesh alike, while lumped outlets let the flow redistribute."""
    if params.outlets in ("murray", "split"):
        return ("a prescribed split forces each outlet's share through a tight stenosis: try lumped outlets, "
                "--outlets rcr; else a smaller --dt or a finer mesh")
    return "try a smaller --dt or a finer mesh"


def _run_steps(solver: CBSSolver, writer: FlowWriter, wall: WallShear, params: FlowParameters, ckpt: Path, fp: str,
               start: float, t_end: float, period: float, interrupt: _DeferredInterrupt,
               progress: Callable[[dict], None] | None, periodicity: CyclePeriodicity,
               recorder: ProbeRecorder) -> None:
    """Step to ``t_end`` (s), writing outputs and checkpoints; KeyboardInterrupt after the checkpoint of an
    interrupted step.

    Every cycle end k T is stepped onto exactly and written, and closes the cycle's entry of ``periodicity``;
    with ``params.periodic_tol`` > 0 the run stops at the first cycle end where it is met.  The probes are sampled
    after every step (:class:`carotid.flow.probes.ProbeRecorder` keeps those it needs)."""
    mesh = solver.mesh
    periodicity.update(solver.t)
    while solver.t < t_end * (1 - 1e-12) and not periodicity.reached(params.periodic_tol):
        boundary = (np.floor(solver.t / period * (1 + 1e-12)) + 1) * period
        info = solver.step(max_dt=min(t_end, boundary) - solver.t)
        ok, node = solver.check_finite(params.max_speed)
        if not ok:
            speed = float(np.linalg.norm(solver.u[node]))
            where = np.round(mesh.points[node] / MM, 2).tolist()
            detail = f"step {solver.step_count} (t = {solver.t:.5f} s): |u| = {speed:.3g} m/s at {where} mm"
            raise FlowBlowUp(f"the flow solution blew up at {detail}; the last good checkpoint is kept in {ckpt} "
                             f"({_blow_up_hint(params)})", solver.t, detail)
        cycle_end = solver.t >= boundary * (1 - 1e-12)
        output = solver.step_count % params.output_every == 0 or cycle_end or solver.t >= t_end * (1 - 1e-12)
        if recorder.due(solver.t, force=output):  # the pressure in Pa only for a sample that is kept
            recorder.record(solver.t, solver.u, solver.pressure_pa(params.rho), force=True)
        if output:
            _output(writer, solver, wall, params, _diagnostics(solver, info, params.rho))
        if cycle_end:
            periodicity.update(solver.t)
        last = solver.t >= t_end * (1 - 1e-12) or periodicity.reached(params.periodic_tol)
        if solver.step_count % params.checkpoint_every == 0 or last:
            _checkpoint(ckpt, solver, writer, fp, _time.perf_counter() - start, recorder)
        if progress is not None:
            progress({"step": solver.step_count, "time": solver.t, "cycle": solver.t / period, "cfl": info.cfl,
                      "imbalance": info.imbalance, "end": t_end})
        if interrupt.requested:
            _checkpoint(ckpt, solver, writer, fp, _time.perf_counter() - start, recorder)
            raise KeyboardInterrupt


def _matching_checkpoint(path: Path, fp: str) -> bool:
    """Whether ``resume="auto"`` continues from the checkpoint ``path``: it exists and was made with the
    fingerprint ``fp``.  One that cannot be read is set aside as ``<name>.corrupt`` (a CarotidWarning says so),
    so that the run, starting at t = 0, overwrites nothing that could still be examined."""
    if not path.is_file():
        return False
    try:
        return load_checkpoint(path)[1].get("fingerprint") == fp
    except CarotidError as exc:
        aside = path.with_name(f"{path.name}.corrupt")
        path.replace(aside)
        warnings.warn(f"{exc}: moved to {aside.name}; the run starts at t = 0", CarotidWarning, stacklevel=3)
        return False


def _output(writer: FlowWriter, solver: CBSSolver, wall: WallShear, params: FlowParameters, diag: dict) -> None:
    faces = wall.faces_wss(solver.velocity_gradients(), params.mu if solver.rheology is None else solver.rheology)
    fields = {"velocity": solver.u, "pressure": solver.pressure_pa(params.rho)}
    if solver.turbulence is not None:
        fields["nu_t"] = solver.turbulence.nu_t(solver.nut_hat)
    writer.write(solver.step_count, solver.t, fields, {"WSS": wall.nodes_wss(faces), "WSS_face": faces})
    writer.records[-1]["diagnostics"] = diag


def _checkpoint(path: Path, solver: CBSSolver, writer: FlowWriter, fp: str, seconds: float,
                recorder: ProbeRecorder) -> None:
    save_checkpoint(path, {**solver.state(), **recorder.state()},
                    {"records": writer.records, "fingerprint": fp, "seconds": seconds})


class CyclePeriodicity:
    """TAWSS of each whole cycle of a run and its change from the previous cycle.

    At the end of cycle k (t = k T) the TAWSS of ``[(k - 1) T, k T]`` is computed from the stored wall WSS
    outputs of that cycle (:func:`carotid.flow.indices.wall_indices`, trapezoidal in time) and compared with
    cycle k - 1's by

    * the area-weighted L2 relative change ``sqrt(sum_i A_i (T_k - T_{k-1})_i^2 / sum_i A_i T_{k,i}^2)``, the
      criterion of ``periodic_tol``, and
    * the relative change of the area-weighted mean TAWSS, ``|mean_k - mean_{k-1}| / mean_k``,

    beside the cycle's share of the inflow volume through each outlet (:func:`outlet_shares`), which with
    lumped outlets settles over the cycles as their compliances charge,

    A_i the wall area of node i (:func:`carotid.flow.indices.node_areas`).  The entries are rebuilt from the
    outputs, so a resumed run has the same ones.

    Parameters
    ----------
    writer : FlowWriter
        Holds the output records of the run.
    mesh : FlowMesh
    wall : WallShear
    period : float
        Cycle length T, s.
    """

    def __init__(self, writer: FlowWriter, mesh: FlowMesh, wall: WallShear, period: float):
        from carotid.flow.indices import node_areas

        self.writer, self.normals, self.period = writer, wall.node_normals, period
        self.areas = node_areas(mesh.points[wall.nodes], wall.local_faces)
        self.entries: list[dict] = []
        self._tawss = None

    def update(self, t: float) -> None:
        """Add the entries of the cycles ending at or before ``t`` (s) not yet added."""
        from carotid.flow.indices import wall_indices

        while (len(self.entries) + 1) * self.period <= t * (1 + 1e-12):
            k = len(self.entries) + 1
            times, wss = self.writer.read_wall("WSS", (k - 1) * self.period)
            keep = times <= k * self.period * (1 + 1e-12)
            tawss = wall_indices(times[keep], wss[keep], self.normals)["TAWSS"]
            mean = float(self.areas @ tawss / self.areas.sum())
            share = outlet_shares(self.writer.records, (k - 1) * self.period, k * self.period)
            entry = {"cycle": k, "tawss_mean_pa": mean, "relative_change": None, "mean_change": None,
                     "outlet_share": share.tolist()}
            if self._tawss is not None:
                previous = float(self.areas @ self._tawss / self.areas.sum())
                entry["relative_change"] = float(np.sqrt(self.areas @ (tawss - self._tawss) ** 2 /
                                                         max(self.areas @ tawss ** 2, 1e-300)))
                entry["mean_change"] = abs(mean - previous) / max(abs(mean), 1e-300)
            self.entries.append(entry)
            self._tawss = tawss

    def reached(self, tol: float) -> bool:
        """Whether ``tol`` > 0 and the last cycle's TAWSS changed by less than ``tol`` from the one before."""
        change = self.entries[-1]["relative_change"] if self.entries else None
        return tol > 0 and change is not None and change < tol

    def summary(self, tol: float) -> dict:
        """The ``periodic`` part of summary.json: ``status`` "periodic" or "not periodic" (``tol`` > 0), or
        "not assessed" (``tol`` 0, or under two whole cycles), with the last relative change."""
        change = self.entries[-1]["relative_change"] if self.entries else None
        status = ("not assessed" if tol <= 0 or change is None else
                  "periodic" if change < tol else "not periodic")
        return {"tolerance": tol, "status": status, "last_relative_change": change,
                "criterion": "area-weighted L2 relative change of the TAWSS of a whole cycle from the previous "
                             "cycle's"}


def _outlet_summary(solver: CBSSolver, params: FlowParameters, diag: list[dict], labels: list[int]) -> dict:
    """The outlet model, its parameters and the inlet and outlet pressures over the recorded steps, mmHg."""
    from carotid.flow.outlets import MMHG

    def stats(values) -> dict:
        v = np.asarray(values, dtype=float) / MMHG
        return {"mean": float(v.mean()), "min": float(v.min()), "max": float(v.max())}

    outlet_p = np.array([d.get("outlet_pressure", [np.nan] * len(labels)) for d in diag])
    lumped = solver.lumped is not None
    return {"model": params.outlets if lumped or params.split is None else "split",
            "parameters": solver.lumped.as_dict() if lumped else None,
            "calibration_share": [float(v) for v in solver.split] if lumped else None,
            "pressure_reference": "absolute above the distal pressure" if lumped else
            "relative: the area-weighted mean outlet pressure is 0 at every step",
            "inlet_pressure_mmhg": stats([d.get("inlet_pressure", np.nan) for d in diag]),
            "outlet_pressure_mmhg": {str(lab): stats(outlet_p[:, j]) for j, lab in enumerate(labels)}}


def _finish(flow_dir, mesh, solver, wall, writer, params, waveform, seconds, periodicity) -> dict:
    from carotid.flow.indices import wall_indices
    from carotid.flow.regions import REGION_NAMES, case_regions

    period = waveform.period_s
    since = max(solver.t - period, 0.0)
    fraction = (solver.t - since) / period
    times, wss = writer.read_wall("WSS", since)
    indices, regions = {}, {}
    if len(times) >= 2:
        indices = wall_indices(times, wss, wall.node_normals)
        points = mesh.points[wall.nodes] / MM
        cells, regions = case_regions(Path(flow_dir).parent, points, wall.local_faces, indices)
        named = {} if cells is None else {"cell_data": {"Region": cells},
                                          "field_data": {"RegionNames": np.array(REGION_NAMES)}}
        write_wall_vtp(flow_dir / "indices.vtp", points, wall.local_faces, {**indices, "WSS_last": wss[-1]}, **named)
    recs = [r for r in writer.records if r["time"] >= since - 1e-12 and r["step"] > 0]
    diag = [r["diagnostics"] for r in recs]
    inflow = np.array([d["inflow"] for d in diag])
    frac = np.array([d["outflow_p1"] for d in diag]) / inflow[:, None]  # int u.n of the P1 velocity
    share = outlet_shares(writer.records, since, solver.t)
    consistent = np.array([d["outflow"] for d in diag])
    labels = mesh.outlet_labels
    mag = np.linalg.norm(wss[-1], axis=1) if len(wss) else np.zeros(1)
    finite = {k: v[np.isfinite(v)] for k, v in indices.items()}
    return {
        "steps": solver.step_count, "time_s": solver.t, "cycles": solver.t / period, "seconds": seconds,
        "seconds_per_step": seconds / max(solver.step_count, 1),
        "mesh": {"nodes": mesh.n_points, "tetrahedra": len(mesh.tets), "wall_triangles": len(wall.faces)},
        "dt_s": {"min": min(d["dt"] for d in diag), "max": max(d["dt"] for d in diag)},
        "cfl_max": max(d["cfl"] for d in diag),
        "mass_balance": {
            "inflow_mean_m3s": float(inflow.mean()),
            "imbalance_p1_max_abs": float(np.max(np.abs([d["imbalance_p1"] for d in diag]))),
            "imbalance_max_abs": float(np.max(np.abs([d["imbalance"] for d in diag]))),
            "note": "imbalance_p1 and the outlet fractions are int u.n of the P1 velocity over the outlets against "
                    "the inflow: what the velocity field carries.  They differ from the imposed values by the "
                    "pressure-stabilisation flux through the element layer at each outlet (sum_e tau_e "
                    "int grad N . (grad p - P grad p), largest where the pressure gradient is not linear there: "
                    "coarse outlet layers, flow not developed at the outlet) and by the pressure solver's "
                    "tolerance.  fraction_of_inflow_mean is the outlet's share of the inflow volume over the window "
                    "of the indices (the share of the mean flow).  imbalance_max_abs and "
                    "consistent_fraction_of_inflow_mean are the consistent "
                    "fluxes (the continuity residual at the outlet nodes), on which the scheme imposes the "
                    "balance and the split: zero and the target by construction, not a check",
            "outlets": {str(lab): {"target_fraction": float(solver.split[j]),
                                   "fraction_of_inflow_mean": float(share[j]),
                                   "error_max": None if solver.lumped is not None else
                                   float(np.max(np.abs(frac[:, j] - solver.split[j]))),
                                   "consistent_fraction_of_inflow_mean": float(np.mean(consistent[:, j] / inflow))}
                        for j, lab in enumerate(labels)}},
        "pressure_drop_pa": {"last": diag[-1]["dp"], "cycle_mean": float(np.mean([d["dp"] for d in diag]))},
        "outlets": _outlet_summary(solver, params, diag, labels),
        "wss_pa_last_step": {"mean": float(mag.mean()), "max": float(mag.max())},
        "indices": {k: {"min": float(v.min()), "mean": float(v.mean()), "max": float(v.max())}
                    for k, v in finite.items() if len(v)},
        "indices_cycle_fraction": fraction,
        "partial": bool(fraction < 1 - 1e-9),
        "indices_note": ("the indices average the last cycle" if fraction >= 1 - 1e-9 else
                         f"PARTIAL: the indices average only {fraction:.3g} of a cycle (from t = 0), not a "
                         "cardiac cycle: they are not comparable with the indices of a whole cycle"),
        **regions,
        "periodicity": periodicity.entries,
        "periodic": periodicity.summary(params.periodic_tol),
        "twssg": "temporal: (1/T) int |d tau/dt| dt",
        "settings": {k: v for k, v in asdict(params).items() if k not in ("waveform", "extra")},
        "outputs": len(writer.records),
    }


def _probe_summary(flow_dir: Path, solver: CBSSolver, params: FlowParameters, waveform, recorder: ProbeRecorder,
                   duplex: dict, calibration: dict | None) -> dict:
    """Write the probe series (``probes.csv``, ``probes.xdmf``) and return the ``probes``, ``duplex`` and
    ``inflow_calibration`` parts of summary.json."""
    out = {"inflow_calibration": calibration}
    if not len(recorder.probes):
        return {**out, "probes": None, "duplex": {"reason": duplex.get("reason", "no probes")}}
    recorder.write(flow_dir)
    period = waveform.period_s
    since = max(solver.t - period, 0.0)
    times, values = recorder.arrays(since)
    grid = np.linspace(0.0, period, 4096, endpoint=False)
    peak = grid[np.argmax(waveform.flow(grid))]
    out["probes"] = {"files": ["probes.csv", "probes.xdmf"], "samples": len(recorder.times),
                     "interval_s": recorder.interval, "points": recorder.probes.describe()}
    if "reason" in duplex or len(times) < 3:
        out["duplex"] = {"reason": duplex.get("reason", "under three probe samples")}
        return out
    index = {name: k for k, name in enumerate(recorder.probes.names)}
    specs = {spec.name: spec for spec in recorder.probes.specs}
    result = duplex_summary(times, {name: values[:, index[name]] for name in ("ICA_gate", "CCA_gate",
                                                                             "ICA_distal")},
                            specs, period, since + np.mod(peak - since, period), solver.lumped is not None, duplex)
    result["partial"] = bool(solver.t - since < period * (1 - 1e-9))
    if calibration is not None:
        calibration.update(gate_psv_cm_s=result["gates"]["CCA"]["psv_cm_s"],
                           gate_edv_cm_s=result["gates"]["CCA"]["edv_cm_s"])
    out["duplex"] = result
    return out
