"""CBS flow solver speed: seconds per time step, tetrahedron-steps per second and peak memory.

Meshes: the structured layered tube of carotid.flow.verify, ~500k tetrahedra with 10 graded wall layers
(``--quick``: ~20k), started from its developed profile; and a carotid mesh: the demo phantom's surface by
carotid's surface stage (0.55 mm edge) meshed with 10 layers (~500k tetrahedra), started from rest with the
built-in waveform (its step, from a fluid nearly at rest, is not representative; its seconds per step are).
Pressure
strategies compared in the same run: CHOLMOD's sparse Cholesky (cholespy, factorised once; ``setup_s``
includes the factorisation), pyamg smoothed-aggregation CG (warm start) and Jacobi-CG on the big mesh,
Cholesky, SuperLU and pyamg on a small mesh; and the viscous term, explicit (the paper's CBS) against
implicit (backward Euler), by the step each allows and the wall seconds per simulated second.  Each row
runs in a fresh process (peak RSS).
"""

import _common

from carotid.flow.verify import TubeSpec

BIG = TubeSpec(n_square=12, n_core=6, n_layers=10, first_layer=0.02, growth=1.25, n_axial=90, length=40.0)
SMALL = TubeSpec(n_axial=6, length=6.5)
CAROTID_EDGE = 0.55  # mm: ~500k tetrahedra with 10 layers


def run(spec: TubeSpec, pressure: str, steps: int, viscous: str = "explicit") -> dict:
    """Time ``steps`` steps on a structured tube from its developed Poiseuille profile."""
    import time

    from carotid.flow.cbs import CBSSolver
    from carotid.flow.verify import NU, developed_start, tube_mesh
    from carotid.flow.waveform import constant_waveform
    from carotid.flow.womersley import inlet_profile

    mesh = tube_mesh(spec)
    nodes, pts, tris = mesh.face_patch(2)
    profile = inlet_profile(pts, tris, mesh.face_normal(2), constant_waveform(6e-6), NU, 0)
    t0 = time.perf_counter()
    solver = CBSSolver(mesh, profile.velocity, NU, pressure=pressure, safety=0.8, viscous=viscous)
    setup = time.perf_counter() - t0
    solver.reset(developed_start(mesh, profile))
    return {"mesh": "tube", "first_layer_mm": spec.first_layer, **_time_steps(solver, steps, setup)}


def run_carotid(edge: float, pressure: str, steps: int, viscous: str) -> dict:
    """Time ``steps`` steps (after 5) on the demo phantom meshed with 10 layers, from rest."""
    import time
    import warnings

    from bench_surface import _inputs

    from carotid.flow.mesh import FlowMesh
    from carotid.flow.simulate import FlowParameters, _build
    from carotid.mesh import build_mesh
    from carotid.surface.pipeline import build_surface

    surface = build_surface(*_inputs(False), target_edge_mm=edge)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grid, quality = build_mesh(surface, layers=10)
    mesh = FlowMesh.from_pyvista(grid)
    t0 = time.perf_counter()
    _, solver, _ = _build(mesh, FlowParameters(viscous=viscous, pressure=pressure))
    setup = time.perf_counter() - t0
    solver.reset()
    for _ in range(5):
        solver.step()
    return {"mesh": "carotid", "surface_edge_mm": edge,
            "first_layer_mm": quality["boundary_layer"]["first_height_mm"]["mean"], **_time_steps(solver, steps, setup)}


def _time_steps(solver, steps: int, setup: float) -> dict:
    import time

    import numpy as np

    solver.step()  # numba compilation / first solve
    its, dts = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        dts.append(solver.step().dt)
        its.append(solver.pressure.iterations)
    sec = (time.perf_counter() - t0) / steps
    tets = len(solver.mesh.tets)
    return {"tetrahedra": tets, "nodes": solver.mesh.n_points, "pressure": solver.pressure.method,
            "viscous": solver.viscous, "setup_s": setup, "seconds_per_step": sec, "tet_steps_per_s": tets / sec,
            "pressure_iterations_mean": float(np.mean(its)), "dt_mean_s": float(np.mean(dts)),
            "seconds_per_simulated_s": sec / float(np.mean(dts)),
            "hours_per_cycle_at_dt_1e-4": sec * 0.917 / 1e-4 / 3600.0}


def main():
    args = _common.parse_args(__doc__)
    big = TubeSpec(n_square=4, n_core=3, n_layers=4, n_axial=6) if args.quick else BIG
    steps = 5 if args.quick else 20
    rows = []
    carotid = 1.0 if args.quick else CAROTID_EDGE
    cases = [(run, big, "cholesky", "explicit"), (run, big, "amg", "explicit"), (run, big, "jacobi", "explicit"),
             (run, big, "cholesky", "implicit"), (run, big, "amg", "implicit"),
             (run, SMALL, "cholesky", "explicit"), (run, SMALL, "lu", "explicit"), (run, SMALL, "amg", "explicit"),
             (run_carotid, carotid, "cholesky", "explicit"), (run_carotid, carotid, "cholesky", "implicit"),
             (run_carotid, carotid, "amg", "implicit")]
    for func, spec, pressure, viscous in cases:
        out = _common.run_isolated(func, spec, pressure, steps, viscous)
        rows.append({**out["result"], "peak_rss_mb": out["peak_rss_mb"], "vm_hwm_mb": out["vm_hwm_mb"]})
        print(rows[-1])
    _common.write_results("flow", {"steps_timed": steps, "runs": rows,
                                   "target_tet_steps_per_s": 1.5e6}, quick=args.quick)


if __name__ == "__main__":
    main()
