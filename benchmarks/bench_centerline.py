"""Benchmark of ``compute_centerlines``: seconds, peak memory and accuracy against the phantom's truth.

VMTK (the field's centerline tool) needs its own Python 3.12 environment, so
there is no peer in this process (``bench_segmentation.py`` runs VMTK's
centerlines as the grading's peer); instead the figures compare carotid's settings
on the same input, the demo phantom (``make_phantom(stenosis=0.7, noise=20,
seed=0)``, 98 x 98 x 120 voxels of 0.45 x 0.45 x 0.625 mm) with its true
signed distance as the level set and its true mask:

* ``smoothing_0.5``, ``smoothing_1.0`` (default), ``smoothing_2.0``: the
  Gaussian along the arc length, in mm;
* ``plain_thinning``: no recentring, and the radius read as ``-phi``
  interpolated trilinearly at the thinned axis (what a direct implementation
  of "skeletonize, smooth, sample the level set" gives).

Each run is in its own fresh process (peak RSS is clean); ``baseline`` only
loads the input.  Accuracy: bifurcation error, distance of the axis to the true
axis and radius error (median and 95th percentile, away from the ends and the
bifurcation by three CCA radii), and the NASCET error in percentage points.
A larger 256^3 phantom (0.45 mm isotropic) is timed with the default settings.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_centerline.py [--quick]
"""

from __future__ import annotations

import pickle
import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from _common import parse_args, run_isolated, timed, write_results
from carotid.centerline import Branch, compute_centerlines, stenosis
from carotid.centerline.axes import arclength, sample

DEMO = {"stenosis": 0.7, "noise": 20.0, "seed": 0}
LARGE = {**DEMO, "spacing": (0.45, 0.45, 0.45), "extent": (115.2, 115.2, 115.2)}
QUICK_LARGE = {**DEMO, "spacing": (0.45, 0.45, 0.45), "extent": (57.6, 57.6, 57.6)}
SETTINGS = {"smoothing_0.5": {"smoothing": 0.5}, "smoothing_1.0": {"smoothing": 1.0},
            "smoothing_2.0": {"smoothing": 2.0}, "plain_thinning": {"smoothing": 1.0, "centre": False}}


def input_task(path: str, params: dict) -> dict:
    """Make a phantom and pickle its SDF, mask, true branches and info (in a child process)."""
    from carotid.phantom import make_phantom

    ph, seconds = timed(make_phantom, **params)
    truth = [(b.name, b.points, b.radii) for b in ph.branches]
    with open(path, "wb") as f:
        pickle.dump({"sdf": ph.sdf, "mask": ph.mask, "truth": truth, "info": ph.info}, f)
    return {"shape_kji": list(ph.sdf.array.shape), "spacing_mm": list(ph.sdf.spacing), "seconds": seconds}


def _load(path: str) -> dict:
    with open(path, "rb") as f:
        return pickle.load(f)


def baseline_task(path: str) -> dict:
    """Load the input only."""
    data = _load(path)
    return {"input_mb": (data["sdf"].array.nbytes + data["mask"].array.nbytes) / 2**20}


def accuracy(cl, data: dict, trilinear: bool) -> dict:
    """Errors of centerlines against the phantom's truth (mm; NASCET in percentage points)."""
    truth = {name: (p, r) for name, p, r in data["truth"]}
    r_cca = truth["CCA"][1][0]
    dist, rerr = [], []
    for b in cl.branches:
        points, radii = min(truth.values(), key=lambda t: np.median(cKDTree(t[0]).query(b.points)[0]))
        d, i = cKDTree(points).query(b.points)
        s = arclength(b.points)
        away = ((s > 3 * r_cca) & (s < s[-1] - 3 * r_cca)
                & (np.linalg.norm(b.points - cl.bifurcation, axis=1) > 3 * r_cca))
        found = -sample(data["sdf"], b.points) if trilinear else b.radii
        dist.append(d[away])
        rerr.append(np.abs(found - radii[i])[away])
    dist, rerr = np.concatenate(dist), np.concatenate(rerr)
    ica = cl.branch("ICA")
    graded = stenosis(Branch("ICA", ica.points, -sample(data["sdf"], ica.points)) if trilinear else ica)
    return {"names": [b.name for b in cl.branches],
            "bifurcation_error_mm": float(np.linalg.norm(cl.bifurcation - data["info"]["bifurcation_mm"])),
            "axis_distance_median_mm": float(np.median(dist)), "axis_distance_p95_mm": float(np.percentile(dist, 95)),
            "radius_error_median_mm": float(np.median(rerr)), "radius_error_p95_mm": float(np.percentile(rerr, 95)),
            "nascet_error_pp": 100.0 * abs(graded["nascet"] - data["info"]["stenosis"]["nascet"])}


def centerline_task(path: str, setting: str, score: bool = True) -> dict:
    """Seconds of ``compute_centerlines`` with one setting, and its accuracy."""
    data = _load(path)
    kwargs = dict(SETTINGS[setting])
    cl, seconds = timed(compute_centerlines, data["sdf"], data["mask"], **kwargs)
    out = {"seconds": seconds, "settings": kwargs}
    if score:
        out.update(accuracy(cl, data, trilinear=not kwargs.get("centre", True)))
    return out


def run_case(params: dict, settings: list[str], score: bool) -> dict:
    """Input, baseline and each setting in fresh processes."""
    figures: dict = {"phantom": params}
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "input.pkl")
        figures["input"] = run_isolated(input_task, path, params)["result"]
        base = run_isolated(baseline_task, path)
        figures["baseline"] = {**base["result"], "peak_rss_mb": base["peak_rss_mb"]}
        for name in settings:
            run = run_isolated(centerline_task, path, name, score)
            figures[name] = {**run["result"], "peak_rss_mb": run["peak_rss_mb"], "vm_hwm_mb": run["vm_hwm_mb"],
                             "extra_rss_mb": run["peak_rss_mb"] - base["peak_rss_mb"]}
            print(f"{name:15s} {figures[name]}", flush=True)
    return figures


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    figures = {"peer": "none: VMTK has no wheel for Python 3.11 on this machine; settings compared instead",
               "demo": run_case(DEMO, list(SETTINGS), score=True),
               "large": run_case(QUICK_LARGE if args.quick else LARGE, ["smoothing_1.0"], score=False)}
    write_results("centerline", figures, quick=args.quick)


if __name__ == "__main__":
    main()
