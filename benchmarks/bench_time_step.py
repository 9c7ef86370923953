"""Adaptive time step of the implicit-viscosity CBS: bounded per node against bounded per element.

Case: the real carotid surface of SPHinXsys (``../shared/data/carotid-surface-sphinxsys/fluid.stl``) meshed
as a user meshes it, ``carotid mesh --from-surface`` with the defaults (10 layers; ``--quick``: 4 layers),
with the built-in waveform.  The flow is run from rest to ``START_S`` (peak systole nears) with the nodal
rule; from that state three runs cover the same ``WINDOW_S``:

* ``element``: the step bounded by the largest directional rate of any element (the rule before);
* ``nodal``: the default, bounded by the lumped-mass root mean square of the rates at each node
  (:meth:`carotid.flow.cbs.CBSSolver.time_step`);
* ``reference``: the element rule at a quarter of the safety factor (0.2), the temporal reference.

Per run: steps, wall seconds (and per step, min and median), the largest element CFL it took, the largest
speed (a blow-up shows there), and its distance from the reference at the window's end: velocity (relative
RMS over the nodes, largest difference) and wall shear stress (relative L2 over the wall faces, and the 99th
percentile of the absolute difference, Pa).  The rule is a better default when it takes
fewer steps for no more than a small share of the error the element rule already has.
"""

import time

import _common
import numpy as np

SURFACE = _common.REPO.parent / "shared/data/carotid-surface-sphinxsys/fluid.stl"
START_S, WINDOW_S = 0.15, 0.005
QUICK_START_S, QUICK_WINDOW_S = 0.05, 0.002


def element_step(solver) -> tuple[float, float]:
    """The step and CFL of the element rule, ``safety / max_e c_e`` (at least the rest floor)."""
    from carotid.flow import assembly as asm

    asm.element_convective_rate(solver.mesh.tets, solver.grads, solver.u, solver._rate)
    rate = float(solver._rate.max())
    dt = solver.safety / max(rate, solver.velocity_scale / solver._h_rest)
    return dt, rate * dt


def advance(solver, end: float, rule: str) -> dict:
    """Step ``solver`` to the time ``end`` (s) with ``rule`` ("nodal" or "element"): steps, seconds, the
    largest element CFL ``max_e c_e dt`` taken and the largest speed at the end (m/s)."""
    from carotid.flow import assembly as asm

    if rule == "element":
        solver.time_step = lambda nu_e: element_step(solver)
    seconds, cfl = [], 0.0
    while solver.t < end * (1 - 1e-12):
        asm.element_convective_rate(solver.mesh.tets, solver.grads, solver.u, solver._rate)
        rate = float(solver._rate.max())
        t0 = time.perf_counter()
        info = solver.step(max_dt=end - solver.t)
        seconds.append(time.perf_counter() - t0)
        cfl = max(cfl, rate * info.dt)
    seconds = np.array(seconds)
    return {"steps": len(seconds), "seconds": float(seconds.sum()), "seconds_per_step_min": float(seconds.min()),
            "seconds_per_step_median": float(np.median(seconds)), "max_element_cfl": cfl,
            "max_speed_m_s": float(np.linalg.norm(solver.u, axis=1).max())}


def wall_shear(solver, wall, mu: float) -> np.ndarray:
    """Magnitude of the WSS on the wall faces for the dynamic viscosity ``mu`` (Pa s), Pa."""
    return np.linalg.norm(wall.faces_wss(solver.velocity_gradients(), mu), axis=1)


def main() -> None:
    args = _common.parse_args(__doc__.split("\n")[0])
    git = _common.git_state()
    import tempfile
    from pathlib import Path

    from carotid.cli import main as carotid
    from carotid.flow.mesh import FlowMesh
    from carotid.flow.simulate import FlowParameters, _build

    start, window = (QUICK_START_S, QUICK_WINDOW_S) if args.quick else (START_S, WINDOW_S)
    with tempfile.TemporaryDirectory() as tmp:
        case = Path(tmp) / "case"
        layers = "4" if args.quick else "10"
        assert carotid(["mesh", "--from-surface", str(SURFACE), "-o", str(case), "--layers", layers]) == 0
        mesh = FlowMesh.from_vtu(case / "mesh.vtu")
    params = FlowParameters(cycles=1).validate()
    _, solver, wall = _build(mesh, params)
    t0 = time.perf_counter()
    warm = advance(solver, start, "nodal")
    print(f"rest to {start} s: {warm['steps']} steps in {time.perf_counter() - t0:.0f} s", flush=True)
    state = solver.state()  # load_state copies it
    runs, fields = {}, {}
    for name, rule, safety in (("element", "element", 0.8), ("nodal", "nodal", 0.8), ("reference", "element", 0.2)):
        _, run, _ = _build(mesh, FlowParameters(cycles=1, safety=safety).validate())
        run.load_state(state)
        runs[name] = {"rule": rule, "safety": safety, **advance(run, start + window, rule)}
        fields[name] = (run.u, wall_shear(run, wall, params.mu))
        print(name, {k: v for k, v in runs[name].items() if k != "rule"}, flush=True)
    u_ref, w_ref = fields["reference"]
    for name in ("element", "nodal"):
        u, w = fields[name]
        du = np.linalg.norm(u - u_ref, axis=1)
        runs[name]["vs_reference"] = {
            "velocity_rel_rms": float(np.sqrt((du**2).mean() / (np.linalg.norm(u_ref, axis=1) ** 2).mean())),
            "velocity_max_abs_m_s": float(du.max()),
            "wss_rel_l2": float(np.linalg.norm(w - w_ref) / np.linalg.norm(w_ref)),
            "wss_p99_abs_pa": float(np.percentile(np.abs(w - w_ref), 99)),
        }
    runs["nodal"]["steps_ratio_element_over_nodal"] = runs["element"]["steps"] / runs["nodal"]["steps"]
    _common.write_results("time_step", {
        "git": git, "case": {"surface": str(SURFACE.name), "layers": int(layers), "tetrahedra": len(mesh.tets),
                             "nodes": mesh.n_points},
        "start_s": start, "window_s": window, "warm_up": warm, "runs": runs}, quick=args.quick)


if __name__ == "__main__":
    main()
