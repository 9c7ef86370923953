"""Helpers shared by the benchmark scripts: command line, machine description,
peak memory of a function run in a fresh process, JSON results, and the
geodesic active contour (GAC) baseline that the segmentation benchmarks
compare against.

The scripts import this module as ``_common``; they are run as
``python benchmarks/bench_X.py``, which puts this folder on ``sys.path``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import resource
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from carotid.io import Volume, to_sitk, write_json

REPO = Path(__file__).resolve().parent.parent
RESULTS_DIR = REPO / "benchmarks" / "results"
RESULTS_PREFIX = RESULTS_DIR.relative_to(REPO).as_posix() + "/"
PACKAGES = ("numpy", "scipy", "SimpleITK", "numba", "scikit-image", "carotid")


def parse_args(description: str) -> argparse.Namespace:
    """Command line common to every benchmark: ``--quick`` for a small smoke run.

    Parameters
    ----------
    description : str
        Text shown by ``--help``.

    Returns
    -------
    argparse.Namespace
        With the boolean attribute ``quick``.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true",
                        help="small smoke run (results are written with a '_quick' suffix)")
    return parser.parse_args()


def machine_info() -> dict:
    """Description of the machine and of the library versions the figures depend on.

    Returns
    -------
    dict
        Platform, Python, logical and usable CPU counts, total RAM in GiB,
        and the installed version of each package in ``PACKAGES``.
    """
    import psutil

    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
        "cpu_count": os.cpu_count(),
        "cpu_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "ram_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "versions": versions,
    }


def peak_rss_mb() -> float:
    """Peak resident set size of the calling process so far, in MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def vm_hwm_mb() -> float | None:
    """Peak RSS of the current address space (``VmHWM``, reset by exec) in MiB; None off Linux."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _measured(func, args, kwargs) -> dict:
    """Child side of ``run_isolated``: the function's result and the child's peak RSS."""
    result = func(*args, **kwargs)
    return {"result": result, "peak_rss_mb": peak_rss_mb(), "vm_hwm_mb": vm_hwm_mb()}


def run_isolated(func, *args, **kwargs) -> dict:
    """Run ``func(*args, **kwargs)`` in a fresh process and measure its peak memory.

    The process is started with the 'spawn' method, so it inherits no memory
    from this one: its peak RSS is that of a new interpreter, the imports of
    the calling script and the work of ``func`` alone.  One caveat: on Linux
    the spawned child is forked before it executes the new interpreter, and
    ``ru_maxrss`` keeps the high-water mark across that exec, so it is at
    least this process's RSS at the time of the call.  Keep the caller small
    (make big inputs in a child too); ``vm_hwm_mb`` (``/proc/self/status``,
    reset by exec) is reported as a cross-check.

    Parameters
    ----------
    func : callable
        A module-level (picklable) function returning something small and picklable.
    *args, **kwargs
        Its arguments (picklable).

    Returns
    -------
    dict
        ``result`` (what ``func`` returned), ``peak_rss_mb`` (the child's
        ``ru_maxrss`` in MiB) and ``vm_hwm_mb``.
    """
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        return pool.submit(_measured, func, args, kwargs).result()


def timed(func, *args, **kwargs) -> tuple[object, float]:
    """``(func(*args, **kwargs), seconds of wall-clock time)``."""
    start = time.perf_counter()
    out = func(*args, **kwargs)
    return out, time.perf_counter() - start


def _jsonable(value):
    """Convert numpy scalars and arrays (also nested) into plain Python for ``json``."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float):
        return float(f"{value:.7g}")  # 7 significant digits: small values (viscosities) survive
    return value


def git_state() -> dict:
    """The code a benchmark runs: HEAD, its branch, whether the working tree differs from it (the changed
    paths), a hash of the tracked diff and a hash of every ``carotid/**/*.py`` (untracked ones too).

    ``dirty`` counts changes outside ``benchmarks/results/`` only: a result file written by an earlier run
    (untracked, or tracked and rewritten) is no change to the code that runs; ``changed`` lists every path.

    Returns
    -------
    dict
        ``commit``, ``branch``, ``dirty``, ``changed``, ``tracked_diff_sha1``, ``carotid_sources_sha1``.
    """
    def git(*args):
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True).stdout

    status = [line for line in git("status", "--porcelain").splitlines() if line.strip()]
    sources = hashlib.sha1()
    for path in sorted((REPO / "carotid").rglob("*.py")):
        sources.update(str(path.relative_to(REPO)).encode() + b"\0" + path.read_bytes())
    return {"commit": git("rev-parse", "HEAD").strip(), "branch": git("rev-parse", "--abbrev-ref", "HEAD").strip(),
            "dirty": any(not line[3:].strip('"').startswith(RESULTS_PREFIX) for line in status), "changed": status,
            "tracked_diff_sha1": hashlib.sha1(git("diff", "HEAD").encode()).hexdigest(),
            "carotid_sources_sha1": sources.hexdigest()}


def write_results(name: str, figures: dict, quick: bool = False) -> Path:
    """Write ``results/NAME.json`` (``NAME_quick.json`` for a smoke run).

    Parameters
    ----------
    name : str
        Benchmark name, for instance ``"potential"``.
    figures : dict
        The measurements (numpy values are converted); a ``git`` entry (:func:`git_state` taken when the
        run started) stands for the state at writing, which is recorded otherwise.
    quick : bool
        Whether this was a ``--quick`` run.

    Returns
    -------
    Path
        The file written.
    """
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}{'_quick' if quick else ''}.json"
    document = {
        "benchmark": name,
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "quick": quick,
        "machine": machine_info(),
        "git": git_state(),
        **figures,
    }
    write_json(_jsonable(document), path)
    print(f"wrote {path}")
    return path


@dataclass(frozen=True)
class GacSetting:
    """One GAC configuration.

    Attributes
    ----------
    feature : str
        ``"sigmoid"``: ``1 / (1 + exp((|grad I| - beta) / -alpha))`` (ITK's
        Sigmoid with a negative ``alpha``, the usual GAC speed image);
        ``"reciprocal"``: ``1 / (1 + |grad I| / beta)``, VMTK's 'gradient'
        feature with the gradient expressed in units of ``beta``.
    sigma_mm : float
        Scale of the Gaussian gradient magnitude (recursive Gaussian), in mm.
    alpha, beta : float
        Sigmoid width and centre in HU/mm (``alpha`` unused by "reciprocal").
    propagation, curvature, advection : float
        Scalings of the three GAC terms.
    """

    feature: str
    sigma_mm: float
    alpha: float
    beta: float
    propagation: float
    curvature: float
    advection: float


@dataclass(frozen=True)
class GacStop:
    """When GAC stops: after ``max_iterations``, or when over one chunk of
    ``chunk`` iterations the inside volume changes by at most ``tolerance``
    (relative), or when ITK's RMS change falls below ``rms``."""

    chunk: int = 250
    max_iterations: int = 8000
    tolerance: float = 2e-3
    rms: float = 1e-3


def feature_image(image: sitk.Image, setting: GacSetting) -> sitk.Image:
    """GAC speed image from the Gaussian gradient magnitude (HU/mm) of ``image``, float32 in (0, 1]."""
    grad = sitk.GradientMagnitudeRecursiveGaussian(image, setting.sigma_mm)
    if setting.feature == "sigmoid":
        speed = sitk.Sigmoid(grad, alpha=setting.alpha, beta=setting.beta, outputMaximum=1.0, outputMinimum=0.0)
    else:
        speed = sitk.BoundedReciprocal(grad / setting.beta)
    return sitk.Cast(speed, sitk.sitkFloat32)


def run_gac(volume: Volume, phi0: np.ndarray, setting: GacSetting, stop: GacStop) -> dict:
    """Evolve ``phi0`` (negative inside) by GAC on ``volume`` in chunks until it stops.

    Returns
    -------
    dict
        ``levelset`` (float32 array, negative inside), ``iterations``,
        ``converged`` and ``seconds`` (feature image included).
    """
    def evolve() -> tuple[np.ndarray, int, bool]:
        speed = feature_image(to_sitk(volume.with_array(volume.array.astype(np.float32))), setting)
        gac = sitk.GeodesicActiveContourLevelSetImageFilter()
        gac.SetPropagationScaling(setting.propagation)
        gac.SetCurvatureScaling(setting.curvature)
        gac.SetAdvectionScaling(setting.advection)
        gac.SetMaximumRMSError(stop.rms)
        gac.SetNumberOfIterations(stop.chunk)
        phi, iterations, inside = phi0, 0, int(np.count_nonzero(phi0 < 0))
        while iterations < stop.max_iterations:
            phi = sitk.GetArrayFromImage(gac.Execute(to_sitk(volume.with_array(phi.astype(np.float32))), speed))
            iterations += gac.GetElapsedIterations()
            now = int(np.count_nonzero(phi < 0))
            if gac.GetElapsedIterations() < stop.chunk or abs(now - inside) <= stop.tolerance * max(now, 1):
                return phi, iterations, True
            inside = now
        return phi, iterations, False

    (phi, iterations, converged), seconds = timed(evolve)
    return {"levelset": phi.astype(np.float32), "iterations": iterations, "converged": converged,
            "seconds": seconds}
