"""CBS flow solver speed: seconds per time step, tetrahedron-steps per second and peak memory.

Mesh: the structured layered tube of carotid.flow.verify (no carotid volume mesh is available to the
benchmark; the JSON says so), ~500k tetrahedra with 10 graded wall layers (``--quick``: ~20k).  Pressure
strategies compared in the same run: pyamg smoothed-aggregation CG (warm start) and Jacobi-CG on the big
mesh, sparse LU against pyamg on a small mesh; and the viscous term, explicit (the paper's CBS) against
implicit (backward Euler), by the step each allows and the wall seconds per simulated second.  Each row
runs in a fresh process (peak RSS).
"""

import _common

from carotid.flow.verify import TubeSpec

BIG = TubeSpec(n_square=12, n_core=6, n_layers=10, first_layer=0.02, growth=1.25, n_axial=90, length=40.0)
SMALL = TubeSpec(n_axial=6, length=6.5)


def run(spec: TubeSpec, pressure: str, steps: int, viscous: str = "explicit") -> dict:
    import time

    import numpy as np

    from carotid.flow.cbs import CBSSolver
    from carotid.flow.verify import NU, developed_start, steady_waveform, tube_mesh
    from carotid.flow.womersley import inlet_profile

    mesh = tube_mesh(spec)
    nodes, pts, tris = mesh.face_patch(2)
    profile = inlet_profile(pts, tris, mesh.face_normal(2), steady_waveform(6e-6), NU, 0)
    t0 = time.perf_counter()
    solver = CBSSolver(mesh, profile.velocity, NU, pressure=pressure, safety=0.8, viscous=viscous)
    setup = time.perf_counter() - t0
    solver.reset(developed_start(mesh, profile))
    solver.step()  # numba compilation / first solve
    its, dts = [], []
    t0 = time.perf_counter()
    for _ in range(steps):
        dts.append(solver.step().dt)
        its.append(solver.pressure.iterations)
    sec = (time.perf_counter() - t0) / steps
    return {"tetrahedra": len(mesh.tets), "nodes": mesh.n_points, "pressure": pressure, "viscous": viscous,
            "first_layer_mm": spec.first_layer, "setup_s": setup, "seconds_per_step": sec,
            "tet_steps_per_s": len(mesh.tets) / sec, "pressure_iterations_mean": float(np.mean(its)),
            "dt_mean_s": float(np.mean(dts)), "seconds_per_simulated_s": sec / float(np.mean(dts))}


def main():
    args = _common.parse_args(__doc__)
    big = TubeSpec(n_square=4, n_core=3, n_layers=4, n_axial=6) if args.quick else BIG
    steps = 5 if args.quick else 20
    rows = []
    cases = [(big, "amg", "explicit"), (big, "amg", "implicit"), (big, "jacobi", "explicit"),
             (SMALL, "lu", "explicit"), (SMALL, "amg", "explicit")]
    for spec, pressure, viscous in cases:
        out = _common.run_isolated(run, spec, pressure, steps, viscous)
        rows.append({**out["result"], "peak_rss_mb": out["peak_rss_mb"], "vm_hwm_mb": out["vm_hwm_mb"]})
        print(rows[-1])
    _common.write_results("flow", {"mesh": "structured layered tube (carotid.flow.verify), not a carotid mesh",
                                   "steps_timed": steps, "runs": rows,
                                   "target_tet_steps_per_s": 1.5e6}, quick=args.quick)


if __name__ == "__main__":
    main()
