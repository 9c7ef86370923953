"""Benchmark of the GPF potential: scalar kernel (eq. 5) against the vector kernel (eq. 2).

On a 512 x 512 x 400 float32 volume (0.45 x 0.45 x 0.625 mm) of smooth noise
and bright tubes, each of these runs in its own fresh process, so that its
peak RSS is clean:

* ``baseline``: load the input only (what every other run starts from);
* ``scalar``: ``gpf_potential``;
* ``vector``: ``gpf_potential_vector``;
* ``fft_floor``: one forward and one inverse real FFT (``scipy.fft.rfftn`` /
  ``irfftn``, all cores) of the volume zero-padded to the same FFT grid, the
  least any FFT convolution can cost.

The agreement of the two forms is measured on a smaller phantom (128^3 by
default) as the correlation of their z-scored potentials.

Usage (from the repository root)::

    /tmp/venv/bin/python benchmarks/bench_potential.py [--quick]
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from _common import parse_args, run_isolated, timed, write_results
from carotid.phantom import make_phantom
from carotid.segment import SegmentParameters
from carotid.segment.potential import gpf_potential, gpf_potential_vector, padded_shape
from carotid.segment.preprocess import window_hu

SPACING_KJI = (0.625, 0.45, 0.45)
RADIUS_MM = 10.0
SIGMA_MM = 0.6
FULL = {"shape": (400, 512, 512), "agreement_extent_mm": (57.6, 57.6, 80.0)}  # 128^3 phantom
QUICK = {"shape": (96, 128, 128), "agreement_extent_mm": (28.8, 28.8, 40.0)}  # 64^3 phantom
PAPER_MEMORY_RATIO = 1.0 / 3.0


def synthetic_volume(shape: tuple[int, int, int], spacing_kji, seed: int = 0) -> np.ndarray:
    """A CT-like float32 volume in HU, quick to make at any size.

    Soft tissue (40 HU) with smooth texture (box-filtered noise) and fine
    noise, crossed along k by four bright (400 HU) winding tubes of 2 to 6 mm
    radius with a one-voxel partial-volume edge.

    Parameters
    ----------
    shape : tuple of 3 int
        (nk, nj, ni).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    seed : int
        Random seed.

    Returns
    -------
    ndarray, float32, shape ``shape``
    """
    rng = np.random.default_rng(seed)
    hu = rng.standard_normal(shape, dtype=np.float32)
    ndimage.uniform_filter(hu, size=5, output=hu)
    hu *= np.float32(25.0 / hu.std())
    hu += np.float32(40.0)
    hu += rng.standard_normal(shape, dtype=np.float32) * np.float32(10.0)
    hk, hj, hi = (float(h) for h in spacing_kji)
    y = (np.arange(shape[1], dtype=np.float32) * hj)[:, None]
    x = (np.arange(shape[2], dtype=np.float32) * hi)[None, :]
    size_y, size_x = shape[1] * hj, shape[2] * hi
    tubes = [(rng.uniform(0.2, 0.8) * size_y, rng.uniform(0.2, 0.8) * size_x, rng.uniform(2.0, 6.0),
              rng.uniform(0.0, 2 * np.pi)) for _ in range(4)]
    for k in range(shape[0]):
        z = k * hk
        for cy, cx, radius, phase in tubes:
            wobble = 0.05 * min(size_y, size_x) * np.sin(2 * np.pi * z / 80.0 + phase)
            d = np.sqrt((y - cy - wobble) ** 2 + (x - cx + wobble) ** 2) - np.float32(radius)
            occupancy = np.clip(0.5 - d / np.float32(hi), 0.0, 1.0)
            hu[k] += occupancy * (np.float32(400.0) - hu[k])
    return hu


def input_task(path: str, shape: tuple[int, int, int]) -> dict:
    """Make the synthetic input and store it as ``.npy`` (in a child, so that this process stays small)."""
    image, seconds = timed(synthetic_volume, shape, SPACING_KJI)
    np.save(path, image)
    return {"mb": image.nbytes / 2**20, "generation_seconds": seconds}


def baseline_task(path: str) -> dict:
    """Load the input and nothing else: the memory every other run starts from."""
    image = np.load(path)
    return {"input_mb": image.nbytes / 2**20}


def scalar_task(path: str) -> dict:
    """Seconds of ``gpf_potential`` on the stored input."""
    image = np.load(path)
    _, seconds = timed(gpf_potential, image, SPACING_KJI, RADIUS_MM, SIGMA_MM)
    return {"seconds": seconds}


def vector_task(path: str) -> dict:
    """Seconds of ``gpf_potential_vector`` on the stored input."""
    image = np.load(path)
    _, seconds = timed(gpf_potential_vector, image, SPACING_KJI, RADIUS_MM, SIGMA_MM)
    return {"seconds": seconds}


def _fft_round_trip(padded: np.ndarray) -> np.ndarray:
    """One forward and one inverse real FFT over all axes, all cores."""
    return sfft.irfftn(sfft.rfftn(padded, workers=-1), s=padded.shape, workers=-1)


def fft_floor_task(path: str) -> dict:
    """Seconds of one rfftn + irfftn of the input zero-padded to the potential's FFT grid."""
    image = np.load(path)
    grid, pad = padded_shape(image.shape, SPACING_KJI, RADIUS_MM)
    padded = np.zeros(grid, np.float32)
    padded[tuple(slice(p, p + n) for p, n in zip(pad, image.shape))] = image
    _, seconds = timed(_fft_round_trip, padded)
    return {"seconds": seconds}


def memory_and_time(shape: tuple[int, int, int]) -> dict:
    """Seconds and peak RSS of the baseline, the two kernels and the FFT floor, each in a fresh process."""
    grid, pad = padded_shape(shape, SPACING_KJI, RADIUS_MM)
    figures = {
        "input": {"shape_kji": list(shape), "spacing_kji_mm": list(SPACING_KJI), "dtype": "float32"},
        "fft_grid": {"shape": list(grid), "pad": list(pad), "real_mb": float(np.prod(grid)) * 4 / 2**20,
                     "half_spectrum_mb": grid[0] * grid[1] * (grid[2] // 2 + 1) * 8 / 2**20},
        "kernel": {"radius_mm": RADIUS_MM, "sigma_mm": SIGMA_MM},
    }
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "input.npy")
        figures["input"].update(run_isolated(input_task, path, shape)["result"])
        for name, task in (("baseline", baseline_task), ("scalar", scalar_task), ("vector", vector_task),
                           ("fft_floor", fft_floor_task)):
            run = run_isolated(task, path)
            figures[name] = {**run["result"], "peak_rss_mb": run["peak_rss_mb"], "vm_hwm_mb": run["vm_hwm_mb"]}
            print(f"{name:10s} {figures[name]}", flush=True)
    base = figures["baseline"]["peak_rss_mb"]
    for name in ("scalar", "vector", "fft_floor"):
        figures[name]["extra_rss_mb"] = figures[name]["peak_rss_mb"] - base
    return figures


def zscore(a: np.ndarray) -> np.ndarray:
    """``(a - mean) / std`` in float64."""
    a = np.asarray(a, np.float64)
    return (a - a.mean()) / a.std()


def agreement(extent_mm: tuple[float, float, float]) -> dict:
    """Correlation of the scalar and vector potentials of a windowed phantom after z-scoring.

    Parameters
    ----------
    extent_mm : tuple of 3 float
        Field of view (x, y, z) of the phantom; its voxels are 0.45 x 0.45 x 0.625 mm.

    Returns
    -------
    dict
        Shape, Pearson correlation, RMS and maximum of the z-score difference,
        and the seconds of each form at this size.
    """
    params = SegmentParameters()
    phantom = make_phantom(spacing=SPACING_KJI[::-1], extent=extent_mm)
    image = window_hu(phantom.image.array, params.hu_low, params.hu_high, params.hu_fold)
    scalar, t_scalar = timed(gpf_potential, image, SPACING_KJI, RADIUS_MM, SIGMA_MM)
    vector, t_vector = timed(gpf_potential_vector, image, SPACING_KJI, RADIUS_MM, SIGMA_MM)
    za, zb = zscore(scalar), zscore(vector)
    return {
        "input": "phantom (make_phantom defaults) windowed to [0, 1] with the SegmentParameters HU window",
        "shape_kji": list(image.shape),
        "pearson_r_zscore": float(np.mean(za * zb)),
        "rms_zscore_difference": float(np.sqrt(np.mean((za - zb) ** 2))),
        "max_abs_zscore_difference": float(np.max(np.abs(za - zb))),
        "std_ratio_scalar_over_vector": float(scalar.std() / vector.std()),
        "seconds_scalar": t_scalar,
        "seconds_vector": t_vector,
    }


def summary(figures: dict) -> dict:
    """Ratios of memory and time, and the paper's memory claim."""
    scalar, vector, floor = figures["scalar"], figures["vector"], figures["fft_floor"]
    ratio_extra = scalar["extra_rss_mb"] / vector["extra_rss_mb"]
    return {
        "extra_memory_ratio_scalar_over_vector": ratio_extra,
        "peak_memory_ratio_scalar_over_vector": scalar["peak_rss_mb"] / vector["peak_rss_mb"],
        "speedup_scalar_over_vector": vector["seconds"] / scalar["seconds"],
        "scalar_seconds_over_fft_floor": scalar["seconds"] / floor["seconds"],
        "claim": {"text": "the scalar form needs at most 1/3 of the vector form's memory "
                          "(compared on the memory beyond the input, extra_rss_mb)",
                  "bound": PAPER_MEMORY_RATIO, "met": ratio_extra <= PAPER_MEMORY_RATIO},
    }


def main() -> None:
    """Run the benchmark and write ``results/potential.json``."""
    args = parse_args(__doc__.splitlines()[0])
    config = QUICK if args.quick else FULL
    figures = memory_and_time(config["shape"])
    figures["agreement"] = agreement(config["agreement_extent_mm"])
    print("agreement", figures["agreement"], flush=True)
    figures["summary"] = summary(figures)
    print("summary", figures["summary"])
    write_results("potential", figures, args.quick)


if __name__ == "__main__":
    main()
