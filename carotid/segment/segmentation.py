"""GPF level-set segmentation of a CT angiogram: the stage's plain-function API.

``segment`` runs the whole stage in memory (pre-processing, potential,
initialisation, evolution, clean-up, signed distance); ``write_segmentation``
stores its result in ``CASE_DIR/segmentation/`` atomically.
"""

from __future__ import annotations

import resource
import time
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume, atomic_dir, write_image, write_json
from carotid.segment.init import automatic_region, mask_levelset, seed_levelset
from carotid.segment.levelset import evolve, signed_distance
from carotid.segment.potential import gpf_potential
from carotid.segment.preprocess import denoise, edge_stopping, window_hu
from carotid.segment.wall import outer_wall, trunk


@dataclass
class SegmentParameters:
    """Parameters of the GPF segmentation, with their units.

    Attributes
    ----------
    alpha : float
        Weight of the curvature term in eq. (1), 0 <= alpha < 1, capture stage.
    hu_low, hu_high : float
        Intensity window in HU; brighter values are folded back (calcium, bone).
    hu_fold : float
        Slope of that fold (0 clips instead).
    denoise_iterations : int
        Curvature anisotropic diffusion iterations before the potential (0: off).
    kernel_radius_mm : float
        Support of the GPF kernel in mm (padding is at least as wide).
    sigma_mm : float
        Gaussian pre-smoothing folded into the kernel spectrum, in mm.
    refine_radius_mm, refine_sigma_mm, refine_alpha : float
        The same three for a second, refining stage started from the converged
        front (``refine_radius_mm = 0`` skips it).  A long kernel gives the
        capture range the GPF is known for, but on a curved, blurred wall its
        zero crossing lies outside the wall by about
        ``s^2 ln(R_eff / s) kappa`` (s the blur, R_eff the smaller of the
        kernel radius and the vessel radius); a short kernel and a little more
        curvature cut that bias by about half.
    potential_scale : float
        Saturation scale of the potential in window units per mm:
        ``Ghat = tanh(G / potential_scale)``.
    edge_beta : float
        Gradient scale of the edge-stopping function in window units per mm.
    seed_radius_mm : float
        Radius of the sphere placed at each seed, in mm.
    cfl : float
        Safety factor (< 1) on the stable forward-Euler step.
    max_iterations : int
        Safety limit of the evolution.
    tolerance : float
        Convergence: fraction of front voxels allowed to change side per window.
    far_mm : float
        Distances beyond this are clamped in the output level set, in mm.
    wall : bool
        Also segment the whole vessel (lumen, non-enhancing thrombus, wall) from the lumen (``wall`` module).
    wall_hu_low, wall_hu_high : float
        HU window of the outer-wall stage, clipped: fat and lung at or below ``wall_hu_low``; thrombus and
        wall at ``wall_hu_high``, which 0 measures in a ring 1.5-4.5 mm outside the lumen.
    wall_level_mm : float
        Gaussian (mm) over which that level is measured locally; 0: one level, the ring's median.
    wall_contrast_hu : float
        Outside the lumen, voxels above this HU count as dark in that stage (contrast-filled neighbours).
    wall_alpha : float
        Curvature weight of the outer-wall stage, 0 <= alpha < 1.
    wall_kernel_mm : float
        GPF kernel support of the outer-wall stage, mm: its capture range across thrombus.
    wall_max_mm : float
        Largest thickness of thrombus and wall beyond the lumen, mm.
    wall_close_mm, wall_open_mm : float
        Radii (mm) of the closing and opening of the outer-wall region by a ball, 0: none.
    wall_trunk_mm : float
        Keep only the vessel's trunk: what lies within this margin (mm) of the balls along its main axis
        (``wall.trunk``; for the aorta, without its branches).  0: off.
    """

    alpha: float = 0.2
    hu_low: float = -100.0
    hu_high: float = 550.0
    hu_fold: float = 3.0
    denoise_iterations: int = 0
    kernel_radius_mm: float = 10.0
    sigma_mm: float = 0.6
    refine_radius_mm: float = 1.5
    refine_sigma_mm: float = 0.3
    refine_alpha: float = 0.5
    potential_scale: float = 1.0
    edge_beta: float = 0.1
    seed_radius_mm: float = 1.5
    cfl: float = 0.9
    max_iterations: int = 4000
    tolerance: float = 2e-3
    far_mm: float = 20.0
    wall: bool = False
    wall_hu_low: float = 0.0
    wall_hu_high: float = 0.0
    wall_level_mm: float = 15.0
    wall_contrast_hu: float = 700.0
    wall_alpha: float = 0.7
    wall_kernel_mm: float = 5.0
    wall_max_mm: float = 25.0
    wall_close_mm: float = 0.0
    wall_open_mm: float = 0.0
    wall_trunk_mm: float = 0.0

    def stages(self) -> list[tuple[float, float, float]]:
        """(kernel radius mm, pre-smoothing mm, alpha) of each evolution stage: capture, then refinement."""
        out = [(self.kernel_radius_mm, self.sigma_mm, self.alpha)]
        if self.refine_radius_mm > 0:
            out.append((self.refine_radius_mm, self.refine_sigma_mm, self.refine_alpha))
        return out

    def validate(self) -> "SegmentParameters":
        """Raise CarotidError for values outside their meaningful range."""
        checks = [
            (0.0 <= self.alpha < 1.0 and 0.0 <= self.refine_alpha < 1.0, "alpha must lie in [0, 1)"),
            (self.refine_radius_mm >= 0 and self.refine_sigma_mm >= 0, "refine_* must not be negative"),
            (self.hu_high > self.hu_low, "hu_high must exceed hu_low"),
            (self.kernel_radius_mm > 0, "kernel_radius_mm must be positive"),
            (self.sigma_mm >= 0, "sigma_mm must not be negative"),
            (self.potential_scale > 0, "potential_scale must be positive"),
            (self.edge_beta > 0, "edge_beta must be positive"),
            (self.seed_radius_mm > 0, "seed_radius_mm must be positive"),
            (0 < self.cfl < 1, "cfl must lie in (0, 1)"),
            (self.max_iterations > 0, "max_iterations must be positive"),
            (self.denoise_iterations >= 0, "denoise_iterations must not be negative"),
            (self.wall_hu_low < self.wall_contrast_hu and (
                self.wall_hu_high == 0 or self.wall_hu_low < self.wall_hu_high < self.wall_contrast_hu),
             "wall_hu_low < wall_hu_high (0: measured) < wall_contrast_hu required"),
            (0.0 <= self.wall_alpha < 1.0, "wall_alpha must lie in [0, 1)"),
            (self.wall_max_mm > 0 and self.wall_kernel_mm > 0, "wall_max_mm and wall_kernel_mm must be positive"),
            (self.wall_close_mm >= 0 and self.wall_open_mm >= 0, "wall_close_mm and wall_open_mm must not be negative"),
            (self.wall_level_mm >= 0 and self.wall_trunk_mm >= 0,
             "wall_level_mm and wall_trunk_mm must not be negative"),
            (self.wall or not (self.wall_close_mm or self.wall_open_mm or self.wall_trunk_mm),
             "wall_close_mm, wall_open_mm and wall_trunk_mm act on the outer-wall stage: set wall = true"),
        ]
        for ok, message in checks:
            if not ok:
                raise CarotidError(f"bad segmentation parameter: {message}")
        return self


@dataclass
class Segmentation:
    """Result of ``segment``.

    Attributes
    ----------
    levelset : Volume
        float32 signed distance to the lumen wall in mm, negative inside,
        clamped to +-``far_mm``.
    mask : Volume
        uint8 lumen mask, 1 inside.
    report : dict
        Parameters, initialisation, iterations, convergence, seconds, volume.
    wall : Volume or None
        uint8 mask of the whole vessel (lumen, thrombus, wall), 1 inside, when ``params.wall`` asked for it.
    """

    levelset: Volume
    mask: Volume
    report: dict = field(default_factory=dict)
    wall: Volume | None = None


def check_image(volume: Volume) -> None:
    """Raise CarotidError for images no segmentation can use: NaN/inf voxels or a constant image."""
    array = volume.array
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise CarotidError(f"image has {bad} NaN or infinite voxels")
    if float(array.max()) == float(array.min()):
        raise CarotidError(f"image is constant ({float(array.min()):g} everywhere): nothing to segment")


def speed_fields(image01: np.ndarray, spacing_kji, radius_mm: float, sigma_mm: float,
                 params: SegmentParameters) -> tuple[np.ndarray, np.ndarray]:
    """Normalised potential ``Ghat = tanh(G / potential_scale)`` and edge-stopping ``g``, float32."""
    ghat = gpf_potential(image01, spacing_kji, radius_mm, sigma_mm)
    ghat /= np.float32(params.potential_scale)
    np.tanh(ghat, out=ghat)
    return ghat, edge_stopping(image01, spacing_kji, params.edge_beta, sigma_mm)


def windowed_image(volume: Volume, params: SegmentParameters) -> np.ndarray:
    """The image the potential sees: optionally denoised, then HU-windowed to [0, 1], float32."""
    if params.denoise_iterations:
        volume = denoise(volume, params.denoise_iterations)
    return window_hu(volume.array, params.hu_low, params.hu_high, params.hu_fold)


def keep_components(inside: np.ndarray, seeds_kji: np.ndarray | None) -> np.ndarray:
    """The connected components holding a seed, or the largest one without seeds."""
    labels, n = ndimage.label(inside)
    if n == 0:
        raise CarotidError("segmentation is empty: the front vanished (check the seeds and the HU window)")
    if seeds_kji is not None:
        idx = np.clip(np.round(seeds_kji).astype(int), 0, np.asarray(inside.shape) - 1)
        keep = np.unique(labels[tuple(idx.T)])
        keep = keep[keep > 0]
        if keep.size:
            return np.isin(labels, keep)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == np.argmax(sizes)


def segment(volume: Volume, seeds_xyz=None, init_mask: np.ndarray | None = None,
            params: SegmentParameters | None = None, progress=None) -> Segmentation:
    """Segment the arterial lumen of a CT angiogram with the GPF deformable model.

    Parameters
    ----------
    volume : Volume
        CT image in HU, float32.
    seeds_xyz : array_like, shape (m, 3), optional
        Seed points in world mm; a sphere of ``seed_radius_mm`` is placed at each.
    init_mask : ndarray of bool, shape volume.array.shape, optional
        Initial region (it may cross the boundary); used when no seed is given.
    params : SegmentParameters, optional
    progress : callable, optional
        ``progress(iterations, changed, front_voxels)`` after every re-initialisation.

    Without seeds and initial region the initialisation is automatic
    (``automatic_region``).

    Returns
    -------
    Segmentation
    """
    params = (params or SegmentParameters()).validate()
    check_image(volume)
    spacing = volume.spacing_kji
    timings = {}
    t0 = time.perf_counter()

    seeds_kji = None
    if seeds_xyz is not None and len(seeds_xyz):
        seeds_xyz = np.atleast_2d(np.asarray(seeds_xyz, float))
        phi = seed_levelset(volume, seeds_xyz, params.seed_radius_mm)  # validates the seeds first
        seeds_kji = volume.world_to_index(seeds_xyz)
        how = "seed"
    elif init_mask is not None:
        if init_mask.shape != volume.array.shape:
            raise CarotidError(f"initial region has shape {init_mask.shape}, image has {volume.array.shape}")
        phi = mask_levelset(init_mask, spacing)
        how = "region"
    else:
        phi = None
        how = "automatic"

    image01 = windowed_image(volume, params)
    stages = params.stages()
    ghat, g = speed_fields(image01, spacing, *stages[0][:2], params)
    timings["potential_s"] = time.perf_counter() - t0
    if phi is None:
        region = automatic_region(image01, ghat, spacing, excluded=volume.array > params.hu_high)
        phi = mask_levelset(region, spacing)

    t1 = time.perf_counter()
    iterations, converged = [], []
    for number, (radius, sigma, alpha) in enumerate(stages):
        if number:
            ghat, g = speed_fields(image01, spacing, radius, sigma, params)
        result = evolve(phi, ghat, g, spacing, alpha=alpha, cfl=params.cfl, max_iterations=params.max_iterations,
                        tolerance=params.tolerance, progress=progress)
        phi = result.phi
        iterations.append(result.iterations)
        converged.append(result.converged)
    del ghat, g, image01
    timings["evolution_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    inside = keep_components(phi < 0, seeds_kji)
    phi = np.where(inside, np.minimum(phi, -1e-3), np.maximum(phi, 0)).astype(np.float32)
    phi = signed_distance(phi, spacing, params.far_mm)
    mask = (phi < 0).astype(np.uint8)
    timings["distance_s"] = time.perf_counter() - t2

    wall, wall_report = None, None
    if params.wall:
        speeds = partial(speed_fields, spacing_kji=spacing, radius_mm=params.wall_kernel_mm,
                         sigma_mm=params.sigma_mm, params=params)
        region, wall_report = outer_wall(volume, mask > 0, speeds, params, progress)
        wall = keep_components(region, seeds_kji)
        if params.wall_trunk_mm > 0:
            t3 = time.perf_counter()
            wall = keep_components(trunk(wall, spacing, params.wall_trunk_mm), seeds_kji)
            wall_report["trunk_seconds"] = time.perf_counter() - t3
        wall = wall.astype(np.uint8)
        wall_report["volume_mm3"] = float(wall.sum() * np.prod(spacing))
    timings["total_s"] = time.perf_counter() - t0

    report = {
        "method": "GPF level set (scalar kernel, eq. 5)",
        "parameters": asdict(params),
        "initialisation": how,
        "seeds_mm": None if seeds_kji is None else np.asarray(seeds_xyz).tolist(),
        "iterations": iterations,
        "converged": all(converged),
        "seconds": timings,
        "lumen_volume_mm3": float(mask.sum() * np.prod(spacing)),
        "wall": wall_report,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "image": {"shape_kji": list(volume.array.shape), "spacing_mm": list(volume.spacing),
                  "origin_mm": list(volume.origin)},
    }
    return Segmentation(volume.with_array(phi), volume.with_array(mask), report,
                        None if wall is None else volume.with_array(wall))


@dataclass
class SegmentStageParameters(SegmentParameters):
    """The ``[segment]`` section of a run configuration: ``SegmentParameters`` and the seeds.

    Attributes
    ----------
    seeds_mm : list of [x, y, z]
        Seed points in world mm (LPS); empty for automatic initialisation.
    """

    seeds_mm: list = field(default_factory=list)

    def validate(self) -> "SegmentStageParameters":
        """Raise CarotidError for bad values, seeds included."""
        if any(len(seed) != 3 for seed in self.seeds_mm):
            raise CarotidError("bad segmentation parameter: each seed must be [x, y, z] in mm")
        super().validate()
        return self


def run_stage(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``segment`` stage of ``carotid run``: read ``inputs[0]``, segment it, write ``CASE_DIR/segmentation``."""
    from carotid.io import read_image

    params = SegmentStageParameters(**params).validate()
    fields = {k: v for k, v in asdict(params).items() if k != "seeds_mm"}
    result = segment(read_image(inputs[0]), seeds_xyz=params.seeds_mm or None, params=SegmentParameters(**fields))
    write_segmentation(result, case_dir)


def write_segmentation(result: Segmentation, case_dir: str | Path) -> Path:
    """Write ``levelset.nii.gz``, ``mask.nii.gz``, ``report.json`` (and ``wall_mask.nii.gz``) atomically."""
    out = Path(case_dir) / "segmentation"
    with atomic_dir(out) as tmp:
        write_image(result.levelset, tmp / "levelset.nii.gz")
        write_image(result.mask, tmp / "mask.nii.gz")
        if result.wall is not None:
            write_image(result.wall, tmp / "wall_mask.nii.gz")
        write_json(result.report, tmp / "report.json")
    return out
