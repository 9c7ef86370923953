"""Benchmark of the generalised Womersley inlet against the analytic (circular) Womersley profile.

On P1 triangulations of a disc of radius 3.25 mm (a common carotid inlet, alpha = 4.7 with the built-in
waveform and nu = 3.3e-6 m^2/s), each size in its own fresh process (peak RSS):

* ``generalised``: ``inlet_profile`` with 10 harmonics (11 sparse complex 2D solves), then one
  evaluation of ``velocity(t)`` (what the solver does every time step);
* ``analytic``: ``womersley_velocity`` at the same nodes at one time, the closed form a circular-inlet
  tool evaluates instead (the peer: exact on a circle, unusable on a real, non-circular inlet).

Also reported: the generalised profile's error against the analytic one (max over 12 times, relative to
the peak) and its flux error.

Usage (from the repository root)::

    /tmp/venv/bin/python benchmarks/bench_inlet.py [--quick]
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from _common import parse_args, run_isolated, timed, write_results
from carotid.flow.waveform import carotid_waveform
from carotid.flow.womersley import inlet_profile, womersley_number, womersley_velocity

RADIUS_M = 3.25e-3
NU = 3.3e-6
HARMONICS = 10
FULL = {"rings": (25, 50, 100), "repeats": 3}  # 1951, 7651 and 30301 nodes
QUICK = {"rings": (10, 25), "repeats": 1}


def disc(rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Face points (p, 3) m on the plane z = 0 and the Delaunay triangles of concentric rings of 6 i nodes."""
    pts = [np.zeros((1, 2))]
    for i in range(1, rings + 1):
        theta = 2 * np.pi * (np.arange(6 * i) + 0.5 * (i % 2)) / (6 * i)
        pts.append(RADIUS_M * i / rings * np.column_stack([np.cos(theta), np.sin(theta)]))
    xy = np.vstack(pts)
    return np.column_stack([xy, np.zeros(len(xy))]), Delaunay(xy).simplices


def run(method: str, rings: int, repeats: int) -> dict:
    """Best-of-``repeats`` seconds of one method on one disc, with the accuracy of the generalised profile."""
    points, triangles = disc(rings)
    waveform = carotid_waveform()
    r = np.minimum(np.linalg.norm(points[:, :2], axis=1), RADIUS_M)
    out = {"nodes": len(points), "triangles": len(triangles)}
    if method == "analytic":
        out["seconds"] = min(timed(womersley_velocity, r, 0.15, RADIUS_M, waveform, NU, HARMONICS)[1]
                             for _ in range(repeats))
        return out
    runs = [timed(inlet_profile, points, triangles, [0, 0, 1], waveform, NU, HARMONICS) for _ in range(repeats)]
    profile = runs[0][0]
    out["seconds"] = min(s for _, s in runs)
    out["velocity_eval_microseconds"] = 1e6 * min(timed(profile.velocity, 0.15)[1] for _ in range(max(repeats, 20)))
    times = np.linspace(0, waveform.period_s, 12, endpoint=False)
    exact = np.array([womersley_velocity(r, t, RADIUS_M, waveform, NU, HARMONICS) for t in times])
    out["max_error_vs_analytic"] = float(np.max(np.abs(profile.velocity(times) - exact)) / np.max(np.abs(exact)))
    flux_error = np.max(np.abs(profile.flux(times) - profile.flow(times)) / profile.flow(times))
    out["max_flux_error"] = f"{flux_error:.2e}"  # a string: write_results rounds floats to 6 decimals
    return out


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    setting = QUICK if args.quick else FULL
    cases = []
    for rings in setting["rings"]:
        for method in ("generalised", "analytic"):
            measured = run_isolated(run, method, rings, setting["repeats"])
            row = {"method": method, "rings": rings, **measured["result"],
                   "peak_rss_mb": measured["peak_rss_mb"], "vm_hwm_mb": measured["vm_hwm_mb"]}
            print(row)
            cases.append(row)
    write_results("inlet", {
        "radius_mm": RADIUS_M * 1e3, "nu_mm2s": NU * 1e6, "harmonics": HARMONICS,
        "womersley_alpha": womersley_number(RADIUS_M, carotid_waveform().period_s, NU),
        "cases": cases,
    }, quick=args.quick)


if __name__ == "__main__":
    main()
