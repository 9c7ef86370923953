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
from carotid.segment.barrier import (chamber_cores, chamber_neck, companion_basins, competing_region,
                                     half_level_barrier, half_maximum_speed, point_mask, under_enhanced)
from carotid.segment.calcium import hyperdense_edge
from carotid.segment.deblur import gaussian_part, model_blur, reach_mm, refine
from carotid.segment.handles import cavities, remove_handles
from carotid.segment.init import (automatic_region, check_points, fork_seeds, mask_levelset, seed_levelset,
                                  seed_sample)
from carotid.segment.intensity import (VALIDATED_CONTRAST_TO_NOISE, IntensityModel, estimate_from_sample,
                                       local_level, local_radius, lumen_ceiling, lumen_noise,
                                       provisional_window, through_plane_variance)
from carotid.segment.join import join_seeds
from carotid.segment.levelset import evolve, signed_distance
from carotid.segment.metrics import topology
from carotid.segment.potential import gpf_potential
from carotid.segment.preprocess import denoise, edge_stopping, window_hu
from carotid.segment.wall import outer_wall, trunk


MAX_KERNEL_MM = 100.0
"""Largest GPF kernel support, mm: five times the default, past an aorta's radius; the kernel's FFT grid is
padded by it."""
MAX_DENOISE_ITERATIONS = 1000
"""Most curvature-diffusion iterations: a few tens smooth a CT's noise; 1000 take minutes on a 256^3 region."""
MAX_INITIAL_SHARE = 0.5
"""Largest share of the image an initial region (``init_mask``) may cover: a lumen fills a few per cent of an
angiogram's region, the aorta of a thoracic CTA a tenth; past half the image it is not a lumen (a mask of ones)."""
MAX_DEBLUR_ITERATIONS = 1000
"""Most blur-model refinement steps: 20 are the default, 100 run it to convergence (``benchmarks/refine_budget.py``)."""
MAX_DEBLUR_GAIN = 10.0
"""Largest refinement step, in blur widths per unit of normalised misfit: 2 is the default, 6 the converged
oracle's; beyond it the step exceeds the one blur width the wall may move."""
MAX_SEED_RADIUS_MM = 20.0
"""Largest seed sphere, mm: a thoracic aorta's radius; a larger sphere reaches out of any vessel."""
MIN_LUMEN_SHARE = 0.1
"""Smallest share of a seed's neighbourhood (``lumen_sample``) that Otsu's upper class must hold to be its lumen."""
MAX_SLICE_THICKNESS_MM = 10.0
"""Thickest slice, mm: a 5 mm clinical reconstruction is not an angiogram; 10 mm is past any."""


@dataclass
class SegmentParameters:
    """Parameters of the GPF segmentation, with their units.

    Attributes
    ----------
    alpha : float
        Weight of the curvature term in eq. (1), 0 <= alpha < 1, capture stage.
    window : list of float
        ``[low, high]``: intensity window in the image's units (HU for CT); brighter values are folded back
        (calcium, bone).  Empty (the default): estimated from the image (``intensity``), from the lumen level
        ``A`` at the seeds and the background ``B`` around them, as ``[B - window_margins[0] (A - B),
        A + max(window_margins[1] (A - B), 3 spread)]``, and followed along the vessel (``level_mm``).
    window_margins : list of float
        Fractions of the contrast ``A - B`` below the background and above the lumen level that the estimated
        window spans.
    level_mm : float
        Scale (mm) over which the lumen level is followed along the vessel (bolus fade, MR bias field) for the
        refining stage; 0: one level for the whole image.
    fold : float
        Slope of a fold above the window: ``top + d`` maps like ``top - fold d`` (0 clips).  With
        ``calcium_edge`` calcium is already at the background and the window only needs to clip; a fold then
        also darkens the lumen's side of a calcification's blur, which can close a calcified stenosis.
    calcium_edge : bool
        Set calcium and bone to the background out to their steepest edge and subtract their blur from the
        surroundings (``calcium`` module), instead of relying on the fold alone, whose edge lies inside the
        lumen next to a calcification (too tight a calcified stenosis) and whose blur on the tissue side
        looks like lumen (a leak into a vertebra, too mild a calcified stenosis).
    calcium_balls : bool
        Place a hyperdense structure's edge by the blurred ball (plate, rod or nodule) that has its steepest
        point and its ridge where the image has them (``calcium.edge_fraction(balls=True)``), instead of the
        steepest point moved out by the blur's curvature shift, which is right for structures much wider than
        the blur and puts the edge of a 1 mm nodule 0.4-0.65 mm into the lumen.  Off: the tight throats beside
        a nodule then read wider (``benchmarks/README.md``).
    calcium_depth_cap : bool
        Keep what the subtraction of a hyperdense structure's blur leaves within two blur widths of its edge
        only up to what the lumen's blur can leave at that depth (``calcium.lumen_blur_cap``), instead of up
        to the lumen's half level at every depth, which a nodule a few blur widths across, its core
        under-subtracted, holds throughout and the front may take for lumen.  Off: not yet run through every
        benchmark (``benchmarks/README.md``).
    calcium_tissue_level : bool
        Fit the level of the tissue around each hyperdense structure together with the amplitude of its blur
        (``calcium.structure_blur(tissue_offset=True)``), instead of taking that tissue at the image's
        background level: plaque above the background was taken for the calcium's blur, and the surplus
        subtracted from the lumen beside it narrowed a calcified throat.  Off: where a thin shell's extent
        reaches into the lumen, the lumen beside it goes with the shell, and it loses on the family's rescans
        and on the second generator as a whole (``benchmarks/README.md``).
    barrier : float
        Half level of the barrier (``barrier.half_level_barrier``): voxels darker than this fraction of the
        brightest lumen-like value within ``barrier_reach_mm`` push the front out (a blurred gap to an enhancing
        neighbour), in the capture stage.  The refining stage keeps only the neighbours held out: after the
        blur-model refinement, a barrier there too left the minimal diameter of 11 of 30 family cases beyond
        0.25 mm against 8 without it (``benchmarks/README.md``).  0: off (the paper's GPF alone).
    barrier_reach_mm : float
        Half-width (mm) of the neighbourhood of that local maximum.  Further from the lumen, a structure under
        half the lumen's level that touches it (fat in a time-of-flight MRA, at a quarter to a half of the
        blood's level) is compared with its own brightness and holds no barrier: at 3 mm the barrier is about
        2 mm thick beyond the blurred wall; at 1.5 mm it was half a millimetre, which the noise opened on 3 of
        30 family anatomies scanned as time-of-flight (``benchmarks/README.md``).
    plateau : float
        Wide regions dimmer than this fraction of the brightest lumen within 10 mm (a vein, a false lumen:
        ``barrier.under_enhanced``) and what the watershed gives them up to the darkest gap
        (``barrier.competing_region``) are kept out of the lumen.  0: off.
    chamber_ratio : float
        A region the captured front reaches whose inscribed radius exceeds this many times the vessel's radius
        near the seeds is a chamber (a heart cavity behind an open valve, an aneurysm): it is kept out of the
        lumen up to the darkest surface between (``barrier.chamber_cores``) or, within one vessel radius of
        that surface, the narrowest section (``barrier.chamber_neck``: an open valve's annulus), and the
        capture stage resumes.  Only with seeds.  0: off.
    chamber_reach_mm : float
        Geodesic distance (mm) from the seeds over which the vessel's radius is taken.
    companion_depth : float
        Least dip of the intensity (in units of the lumen's contrast, after a 0.5 mm smoothing) that sets two
        bright basins of the captured region apart.  A basin beside the seeds' vessel rather than along it is
        a companion (a vein as bright as the artery, behind a gap the blur nearly fills;
        ``barrier.companion_basins``): it is kept out of the lumen up to the darkest surface between, as a
        chamber is, and the capture stage resumes.  Only with seeds.  0: off.
    half_maximum : float
        Weight of the half-maximum force (``barrier.half_maximum_speed``) blended with the potential in the
        refining stage.  The potential's zero lies outside a curved, blurred wall and the half maximum inside
        it, both by about the blur squared times the curvature: their blend stays on a tight stenosis's wall.
        0: the paper's potential alone.
    join_contrast : float
        Where the seeds end the evolution in separate components (the front pinched at a long, tight stenosis
        thinner than the blur: a string sign), join each to the first seed's along the minimal path through
        the image if its smoothed intensity stays at or above this fraction of the lumen's contrast all along
        and crosses no held-out neighbour, as a tube whose blurred axis matches that intensity
        (``join.join_seeds``); an occlusion stays open.  0: off.
    deblur : bool
        Move the converged front to the wall of the blurred lumen model that best explains the image
        (``deblur`` module): an edge-based front lies inside a straight vessel's wall and outside a short,
        tight stenosis's by about the blur squared times the wall's curvature.
    deblur_iterations : int
        Gradient steps of that refinement (``deblur.refine``): more narrow a short, tight throat further but
        let the image's noise roughen the wall (``benchmarks/README.md``, ``--variant``).
    deblur_gain : float
        Its step length, in blur widths per unit of normalised misfit.
    deblur_smooth_mm : float
        Extra Gaussian smoothing (mm) of the wall's speed in that refinement.
    deblur_smooth_radius : float
        Where positive, that smoothing is at most this fraction of the lumen's radius beside the wall (and no
        less than half ``deblur_smooth_mm``): a tight throat is corrected at its own scale (``deblur.refine``,
        ``deblur.wall_radius``).  0 smooths by ``deblur_smooth_mm`` everywhere.
    deblur_slices : bool
        Blur that refinement's model along each axis by the measured blur plus the part of the voxel's
        boxcar beyond the finest axis's (``deblur.axis_blur``): thick slices blur a throat along the vessel
        more than within the slices.  False: the measured blur along every axis.
    deblur_linear_level : bool
        Follow that refinement's lumen level along the vessel by a local linear fit
        (``intensity.local_linear_level``), which does not lean towards a stenosis's wider bulb, instead of a
        local mean.  On with ``deblur_smooth_radius``: the leaning level pulls a mild throat's wall in, and
        under a millimetre's smoothing everywhere its lean is what holds a tight throat in
        (``benchmarks/README.md``).
    deblur_neighbours : bool
        Leave enhancing structures beyond the wall's blur (a jugular vein or an artery the front never
        reached: ``deblur.bright_neighbours``) out of that refinement's tissue level, with their own blur,
        instead of letting them pull the wall facing them into the lumen.  Off: on the phantom family a vein
        sampled as tissue beside a tight throat hides part of the throat's widening, and leaving it out
        widens those throats past the criterion until that widening is mended (``benchmarks/README.md``).
    slice_thickness_mm : float
        Slice thickness (mm) whose boxcar that model adds along the slice axis; 0: the thickness the scan
        records (``Volume.slice_thickness``: DICOM SliceThickness, a dcm2niix sidecar), else the slice
        spacing.  Overlapping slices (1 mm every 0.5 mm) blur along the vessel more than their spacing says.
    measure_slice_blur : bool
        Unless ``slice_thickness_mm`` is given, blur that model along the slice axis by the blur measured on the
        image (``intensity.through_plane_variance``: the tilt dependence of the tissue edges' width), as the
        slice thickness that reproduces it; the scan's record or the slice spacing where it cannot be measured.
        A scanner's slice profile blurs along the vessel more than the in-plane blur plus the slice's boxcar,
        and a model blurred too little there matches a short, tight throat with a wider wall.
    handle_mm : float
        Largest half-width (mm) of a bridge cut or a tunnel filled to remove the lumen's handles, which a vessel
        tree does not have (``handles`` module); 0 keeps them.
    denoise_iterations : int
        Curvature anisotropic diffusion iterations before the potential (0: off).
    kernel_radius_mm : float
        Support of the GPF kernel in mm (padding is at least as wide).
    sigma_mm : float
        Gaussian pre-smoothing folded into the kernel spectrum, in mm.
    refine_radius_mm : float
        GPF kernel support (mm) of a second, refining stage started from the converged front (0 skips it).
        A long kernel gives the capture range the GPF is known for, but on a curved, blurred wall its zero
        crossing lies outside the wall by about ``s^2 ln(R_eff / s) kappa`` (s the blur, R_eff the smaller
        of the kernel radius and the vessel radius); a short kernel and a little more curvature cut that
        bias by about half.
    refine_sigma_mm : float
        Gaussian pre-smoothing (mm) of the refining stage.
    refine_alpha : float
        Curvature weight of the refining stage, 0 <= alpha < 1.
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
    wall_hu_low : float
        Bottom (HU) of the outer-wall stage's clipped window: fat and lung at or below it.
    wall_hu_high : float
        Top (HU) of that window, thrombus and wall; 0 measures it in a ring 1.5-4.5 mm outside the lumen.
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
    wall_close_mm : float
        Radius (mm) of the ball closing the outer-wall region, 0: none.
    wall_open_mm : float
        Radius (mm) of the ball opening it after the closing, 0: none.
    wall_trunk_mm : float
        Keep only the vessel's trunk: what lies within this margin (mm) of the balls along its main axis
        (``wall.trunk``; for the aorta, without its branches).  0: off.
    """

    alpha: float = 0.2
    window: list = field(default_factory=list)
    window_margins: list = field(default_factory=lambda: [0.1, 0.25])
    level_mm: float = 10.0
    fold: float = 0.0
    calcium_edge: bool = True
    calcium_balls: bool = False
    calcium_depth_cap: bool = False
    calcium_tissue_level: bool = False
    barrier: float = 0.5
    barrier_reach_mm: float = 3.0
    plateau: float = 0.8
    chamber_ratio: float = 2.0
    chamber_reach_mm: float = 20.0
    companion_depth: float = 0.05
    half_maximum: float = 0.5
    join_contrast: float = 0.25
    deblur: bool = True
    deblur_iterations: int = 20
    deblur_gain: float = 2.0
    deblur_smooth_mm: float = 1.0
    deblur_smooth_radius: float = 0.5
    deblur_slices: bool = True
    deblur_linear_level: bool = True
    deblur_neighbours: bool = False
    slice_thickness_mm: float = 0.0
    measure_slice_blur: bool = True
    handle_mm: float = 1.5
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

    def stages(self, spacing_kji) -> list[tuple[float, float, float]]:
        """(kernel radius mm, pre-smoothing mm, alpha) of each evolution stage: capture, then refinement.

        Lengths are at least what the grid resolves: pre-smoothing half the largest voxel size, the refining
        kernel three (on 1.5 mm voxels a 1.5 mm kernel has one tap and only amplifies noise).
        """
        h = float(np.max(spacing_kji))
        out = [(max(self.kernel_radius_mm, 3 * h), max(self.sigma_mm, 0.5 * h), self.alpha)]
        if self.refine_radius_mm > 0:
            out.append((max(self.refine_radius_mm, 3 * h), max(self.refine_sigma_mm, 0.5 * h), self.refine_alpha))
        return out

    def validate(self) -> "SegmentParameters":
        """Raise CarotidError for values outside their meaningful range."""
        for name, value in vars(self).items():
            numbers = value if isinstance(value, list) else [value]
            if any(isinstance(v, float) and not np.isfinite(v) for v in numbers):
                raise CarotidError(f"bad segmentation parameter: {name} must be a finite number (got {value!r})")
        checks = [
            (0.0 <= self.alpha < 1.0 and 0.0 <= self.refine_alpha < 1.0, "alpha must lie in [0, 1)"),
            (self.refine_radius_mm >= 0 and self.refine_sigma_mm >= 0, "refine_* must not be negative"),
            (len(self.window) == 0 or (len(self.window) == 2 and self.window[1] > self.window[0]),
             "window must be empty (estimated) or [low, high] with high > low"),
            (len(self.window_margins) == 2 and min(self.window_margins) >= 0,
             "window_margins must be two fractions >= 0"),
            (self.level_mm >= 0 and self.fold >= 0, "level_mm and fold must not be negative"),
            (0 <= self.barrier < 1 and self.barrier_reach_mm > 0, "barrier must lie in [0, 1), barrier_reach_mm > 0"),
            (0 <= self.half_maximum <= 1, "half_maximum must lie in [0, 1]"),
            (0 <= self.plateau < 1, "plateau must lie in [0, 1) (0: off)"),
            (0 <= self.join_contrast < 1, "join_contrast must lie in [0, 1)"),
            (self.chamber_ratio == 0 or self.chamber_ratio > 1, "chamber_ratio must be 0 (off) or above 1"),
            (self.chamber_reach_mm > 0, "chamber_reach_mm must be positive"),
            (0 <= self.companion_depth < 1, "companion_depth must lie in [0, 1)"),
            (0 < self.kernel_radius_mm <= MAX_KERNEL_MM and self.refine_radius_mm <= MAX_KERNEL_MM,
             f"kernel_radius_mm must lie in (0, {MAX_KERNEL_MM:g}] mm, refine_radius_mm at most that"),
            (self.sigma_mm >= 0, "sigma_mm must not be negative"),
            (self.potential_scale > 0, "potential_scale must be positive"),
            (self.edge_beta > 0, "edge_beta must be positive"),
            (0 < self.seed_radius_mm <= MAX_SEED_RADIUS_MM,
             f"seed_radius_mm must lie in (0, {MAX_SEED_RADIUS_MM:g}] mm"),
            (0 < self.cfl < 1, "cfl must lie in (0, 1)"),
            (self.max_iterations > 0, "max_iterations must be positive"),
            (0 < self.tolerance < 1, "tolerance must lie in (0, 1) (the fraction of front voxels that may still move)"),
            (self.far_mm > 0, "far_mm must be positive"),
            (0 <= self.denoise_iterations <= MAX_DENOISE_ITERATIONS,
             f"denoise_iterations must lie in [0, {MAX_DENOISE_ITERATIONS}]"),
            (self.handle_mm >= 0, "handle_mm must not be negative"),
            (0 <= self.deblur_iterations <= MAX_DEBLUR_ITERATIONS and 0 < self.deblur_gain <= MAX_DEBLUR_GAIN
             and self.deblur_smooth_mm >= 0 and self.deblur_smooth_radius >= 0,
             f"deblur_iterations must lie in [0, {MAX_DEBLUR_ITERATIONS}], deblur_gain in (0, {MAX_DEBLUR_GAIN:g}], "
             "deblur_smooth_mm and deblur_smooth_radius must not be negative"),
            (0 <= self.slice_thickness_mm <= MAX_SLICE_THICKNESS_MM,
             f"slice_thickness_mm must lie in [0, {MAX_SLICE_THICKNESS_MM:g}] mm (0: the scan's own)"),
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


# A front kept out of one chamber may reach another (the heart's cavities): as many rounds of the capture stage.
CHAMBER_ROUNDS = 4


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
    calcium : Volume or None
        uint8 mask of the hyperdense structures (calcium, bone) taken out before the evolution
        (``calcium.hyperdense_edge``), 1 inside; None when ``params.calcium_edge`` is off.
    """

    levelset: Volume
    mask: Volume
    report: dict = field(default_factory=dict)
    wall: Volume | None = None
    calcium: Volume | None = None


# Voxel sizes the segmentation accepts, mm: angiography spans about 0.1-5 mm, specimen micro-CT 0.01 mm; outside
# this range the size is in the wrong unit (metres, micrometres) and the millimetre kernels would span
# millions of voxels or none.
VOXEL_MM = (0.01, 20.0)


def check_image(volume: Volume) -> None:
    """Raise CarotidError for images no segmentation can use: a voxel size outside ``VOXEL_MM``, NaN/inf voxels
    or a constant image."""
    low, high = VOXEL_MM
    if not all(low <= s <= high for s in volume.spacing):
        raise CarotidError(f"voxel size {' x '.join(f'{s:g}' for s in volume.spacing)} mm is outside {low:g}-{high:g} "
                           "mm: is the spacing in another unit (metres, micrometres)? Correct the image's header")
    array = volume.array
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise CarotidError(f"image has {bad} NaN or infinite voxels")
    if float(array.max()) == float(array.min()):
        raise CarotidError(f"image is constant ({float(array.min()):g} everywhere): nothing to segment")


def speed_fields(image01: np.ndarray, spacing_kji, radius_mm: float, sigma_mm: float,
                 params: SegmentParameters, barrier: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normalised potential ``Ghat`` (``normalised_potential``, +1 on ``barrier``) and edge-stopping ``g``."""
    ghat = normalised_potential(image01, spacing_kji, radius_mm, sigma_mm, params)
    if barrier is not None:
        ghat[barrier] = 1.0
    return ghat, edge_stopping(image01, spacing_kji, params.edge_beta, sigma_mm)


def normalised_potential(image01: np.ndarray, spacing_kji, radius_mm: float, sigma_mm: float,
                         params: SegmentParameters) -> np.ndarray:
    """The GPF potential squashed to (-1, 1): ``Ghat = tanh(G / potential_scale)`` (float32)."""
    ghat = gpf_potential(image01, spacing_kji, radius_mm, sigma_mm)
    ghat /= np.float32(params.potential_scale)
    return np.tanh(ghat, out=ghat)


def automatic_inputs(image: np.ndarray, source: np.ndarray, spacing_kji,
                     params: SegmentParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the seedless start (``init.automatic_region``) is found on.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
        The image the evolution reads (denoised on request).
    source : ndarray, same shape
        The image as given, whose voxels above the provisional window's ceiling are too bright to be lumen.
    spacing_kji : array_like, shape (3,)
    params : SegmentParameters

    Returns
    -------
    image01 : ndarray, float32
        ``image`` in the provisional window (``intensity.provisional_window``, or ``params.window``).
    ghat : ndarray, float32
        The capture stage's normalised potential on it.
    excluded : ndarray of bool
        The voxels above the ceiling.
    """
    low, high, ceiling = provisional_window(image)
    image01 = window_hu(image, *(params.window or (low, high)), fold=0.0)
    ghat = normalised_potential(image01, spacing_kji, *params.stages(spacing_kji)[0][:2], params)
    return image01, ghat, source > ceiling


def contrast_units(image01: np.ndarray, window, model: IntensityModel, level=None) -> np.ndarray:
    """The windowed (folded) image in units of the lumen contrast: 0 background, 1 lumen level (float32)."""
    low, high = (np.asarray(w, np.float32) for w in window)
    lumen = np.float32(model.lumen) if level is None else level
    background = np.float32(model.background)
    return ((image01 * (high - low) + low - background) / np.maximum(lumen - background, 1e-6)).astype(np.float32)


def neighbours(image01: np.ndarray, window, model: IntensityModel, spacing_kji, params: SegmentParameters,
               lumen: np.ndarray, stops: np.ndarray | None) -> np.ndarray | None:
    """What the lumen must not take: the territory of the stop points and of under-enhanced plateaus
    (``barrier.competing_region``), or None when there is neither."""
    contrast = contrast_units(image01, window, model)
    others = np.zeros(contrast.shape, bool) if stops is None else stops
    if params.plateau > 0:
        others = others | under_enhanced(contrast, spacing_kji, params.plateau)
    if not others.any():
        return None
    return competing_region(contrast, lumen & ~others, others, spacing_kji)


def barrier_of(image01: np.ndarray, window, model: IntensityModel, spacing_kji, params: SegmentParameters,
               excluded: np.ndarray | None = None) -> np.ndarray | None:
    """Where the force pushes the front out whatever the potential: the half-level barrier
    (``barrier.half_level_barrier``) and ``excluded``; None when there is none."""
    out = excluded
    if params.barrier > 0:
        found = half_level_barrier(contrast_units(image01, window, model), spacing_kji, params.barrier,
                                   reach_mm=params.barrier_reach_mm)
        out = found if out is None else out | found
    return out


def slice_thickness(volume: Volume, params: SegmentParameters, model: IntensityModel) -> tuple[float | None, str]:
    """Slice thickness (mm) the blur model adds along k, and where it comes from: the parameter, the blur
    measured on the image (``measure_slice_blur``), the scan's record (``Volume.slice_thickness``) or, as None,
    the slice spacing.

    A measured through-plane variance ``v`` (``intensity.through_plane_variance``) is given as the thickness
    ``T = sqrt(12 v + h_min^2)`` whose boxcar ``deblur.axis_blur`` adds to the in-plane blur as ``v``."""
    if params.slice_thickness_mm > 0:
        return float(params.slice_thickness_mm), "parameter"
    if params.measure_slice_blur:
        variance = through_plane_variance(volume.array, model.box, model.half_level, volume.spacing_kji)
        if variance is not None:
            return float(np.sqrt(12.0 * variance + float(np.min(volume.spacing_kji)) ** 2)), "measured"
    if volume.slice_thickness is not None:
        return float(volume.slice_thickness), "image"
    return None, "slice spacing"


def deblur(image: np.ndarray, phi: np.ndarray, spacing_kji, model: IntensityModel, params: SegmentParameters,
           stopped: np.ndarray | None, dense: np.ndarray | None,
           thickness_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The converged front moved to the wall of the blurred lumen model that best explains ``image``
    (``deblur.refine``, blurred by the Gaussian part of the measured blur, ``deblur.gaussian_part``), with the
    lumen level followed along the vessel and neighbours and calcium left out; ``thickness_mm`` is the slice
    thickness (None: the slice spacing).

    Returns
    -------
    phi : ndarray, float32, ``image``'s shape
        The refined level set.
    blur_kji_mm : ndarray, shape (3,)
        The standard deviation (mm) per axis of the model's blur (``deblur.model_blur``).
    """
    # The evolution's level set is clipped to its band; the refinement reads it out to reach_mm.
    phi = signed_distance(phi, spacing_kji, min(params.far_mm, reach_mm(model.blur, spacing_kji, thickness_mm)))
    exclude = stopped
    if dense is not None:
        exclude = dense if exclude is None else exclude | dense
    sigma = gaussian_part(model.blur, spacing_kji)
    refined = refine(image, phi, spacing_kji, model.lumen, model.background, sigma, exclude,
                     iterations=params.deblur_iterations, gain=params.deblur_gain, smooth_mm=params.deblur_smooth_mm,
                     smooth_radius=params.deblur_smooth_radius,
                     level_mm=params.level_mm, linear_level=params.deblur_linear_level, slices=params.deblur_slices,
                     neighbours=params.deblur_neighbours, thickness_mm=thickness_mm)
    return refined, model_blur(sigma, spacing_kji, params.deblur_slices, thickness_mm)


def lumen_levelset(phi: np.ndarray, stopped: np.ndarray | None, seeds_kji: np.ndarray | None, spacing_kji,
                   params: SegmentParameters) -> tuple[np.ndarray, np.ndarray, list[dict], dict]:
    """The lumen from the refined front: neighbours held out, the seeds' components kept, cavities filled
    (``handles.cavities``), handles removed.

    Held-out voxels the lumen encloses are filled too: an enclosed neighbour is a dark noise pit taken for an
    under-enhanced plateau's core (``barrier.under_enhanced``), not a neighbour.

    Parameters
    ----------
    phi : ndarray, float32, shape (nk, nj, ni)
        Level set of the refined front (negative inside).
    stopped : ndarray of bool, same shape, or None
        Neighbours held out of the lumen.
    seeds_kji : ndarray, shape (m, 3), or None
        Seed voxels (fractional indices); None keeps the largest component.
    spacing_kji : array_like, shape (3,)
    params : SegmentParameters

    Returns
    -------
    phi : ndarray, float32, same shape
        Signed distance (mm) of the lumen, clamped to ``params.far_mm``.
    mask : ndarray, uint8, same shape
    handles_removed : list of dict
        ``handles.remove_handles``' report.
    cavities_filled : dict
        ``count`` and ``volume_mm3`` of the cavities filled.
    """
    inside = phi < 0
    if stopped is not None:
        inside &= ~stopped
    inside = keep_components(inside, seeds_kji, spacing_kji)
    voids = cavities(inside, spacing_kji)
    inside |= voids
    inside, handles_removed = remove_handles(inside, spacing_kji, params.handle_mm)
    phi = np.where(inside, np.minimum(phi, -1e-3), np.maximum(phi, 0)).astype(np.float32)
    phi = signed_distance(phi, spacing_kji, params.far_mm)
    filled = {"count": int(ndimage.label(voids)[1]) if voids.any() else 0,  # labelling 256^3 takes 0.26 s
              "volume_mm3": float(np.count_nonzero(voids) * np.prod(spacing_kji))}
    return phi, (phi < 0).astype(np.uint8), handles_removed, filled


def chambers(phi: np.ndarray, image01: np.ndarray, window, model: IntensityModel, spacing_kji,
             params: SegmentParameters, seeds_kji: np.ndarray) -> tuple[np.ndarray | None, dict | None]:
    """The chambers and companions the captured front ``phi`` has run into, up to the darkest surface between
    them and the vessel (``barrier.chamber_cores``, ``barrier.companion_basins``,
    ``barrier.competing_region``) or, for a chamber, within one vessel radius of it, the narrowest section
    (``barrier.chamber_neck``: an open valve's annulus), and their report (centres as array indices); (None,
    None) when there is neither."""
    captured = phi < 0
    contrast = contrast_units(image01, window, model)
    region = None
    report = {"cores": 0, "vessel_radius_mm": None, "companions": 0}
    markers = np.zeros(captured.shape, bool)
    if params.chamber_ratio > 0:
        cores, vessel, radius = chamber_cores(captured, seeds_kji, spacing_kji, params.chamber_ratio,
                                              params.chamber_reach_mm)
        if cores.any():
            region = competing_region(contrast, vessel, cores, spacing_kji)
            region = chamber_neck(captured, region & captured, seeds_kji, spacing_kji, radius) | region
            report.update(cores=int(ndimage.label(cores)[1]), vessel_radius_mm=radius)
            markers |= cores
    found = (companion_basins(captured, contrast, seeds_kji, spacing_kji, params.companion_depth)
             if params.companion_depth > 0 else None)
    if found is not None:
        vessel, companions = found
        beside = competing_region(contrast, vessel, companions, spacing_kji)
        region = beside if region is None else region | beside
        report["companions"] = int(ndimage.label(companions)[1])
        markers |= companions
    if region is None:
        return None, None
    labels, n = ndimage.label(markers)
    report.update(centres_kji=np.array(ndimage.center_of_mass(markers, labels, range(1, n + 1)), float),
                  excluded_mm3=float(np.count_nonzero(region) * np.prod(spacing_kji)))
    return region, report


def capture_without_chambers(volume: Volume, phi: np.ndarray, ghat: np.ndarray, g: np.ndarray, image01: np.ndarray,
                             window, model: IntensityModel, params: SegmentParameters, seeds_kji: np.ndarray,
                             stopped: np.ndarray | None, alpha: float, progress=None):
    """Resume the capture stage without each chamber and companion its converged front ``phi`` ran into
    (``chambers``) and without what lies beyond it, up to ``CHAMBER_ROUNDS`` times (a front kept out of one
    heart cavity may reach another).  ``ghat`` is modified in place.

    Returns
    -------
    phi : ndarray, float32
    result : EvolutionResult or None
        The last evolution (None when there was no chamber).
    iterations : int
        Iterations of the resumed evolutions.
    stopped : ndarray of bool or None
        ``stopped`` with the chambers and companions.
    reports : list of dict or None
        One per round: the number of chamber cores and the vessel's radius (None without a chamber), the number
        of companions, their centres in world mm, the volume kept out.
    """
    spacing = volume.spacing_kji
    result, iterations, reports = None, 0, None
    for _ in range(CHAMBER_ROUNDS):
        chamber, found = chambers(phi, image01, window, model, spacing, params, seeds_kji)
        if chamber is None:
            break
        found["centres_mm"] = volume.index_to_world(found.pop("centres_kji")).round(1).tolist()
        reports = [*(reports or []), found]
        stopped = chamber if stopped is None else stopped | chamber
        ghat[chamber] = 1.0
        kept = keep_components((phi < 0) & ~chamber, seeds_kji, spacing)  # what lay beyond goes too
        phi = signed_distance(np.where(kept, phi, np.maximum(phi, np.float32(spacing.max()))), spacing,
                              params.far_mm)
        result = evolve(phi, ghat, g, spacing, alpha=alpha, cfl=params.cfl, max_iterations=params.max_iterations,
                        tolerance=params.tolerance, progress=progress)
        phi, iterations = result.phi, iterations + result.iterations
    return phi, result, iterations, stopped, reports


def lumen_window(model: IntensityModel, params: SegmentParameters, level=None) -> tuple:
    """``(low, high)`` of the window: the override, or the model's window around ``level`` (default: its lumen).

    ``level`` may be an array (the lumen level followed along the vessel); the margins then scale with the
    local contrast.
    """
    if params.window:
        return float(params.window[0]), float(params.window[1])
    lo_margin, hi_margin = params.window_margins
    if level is None:
        return model.window(lo_margin, hi_margin)
    contrast = np.maximum(level - np.float32(model.background), np.float32(0.25 * model.contrast))
    low = np.float32(model.background) - np.float32(lo_margin) * contrast
    high = np.float32(model.background) + contrast + np.maximum(np.float32(hi_margin) * contrast,
                                                                 np.float32(3.0 * model.spread))
    return low, high


def lumen_sample(array: np.ndarray, region: np.ndarray) -> np.ndarray:
    """The part of a region meant to lie in the lumen that is lumen.

    A seed's neighbourhood near the wall, or an initial region across it, also holds tissue, and near a plaque
    or a dissection flap calcium: the voxels above ``lumen_ceiling`` (calcium and bone in CT) are dropped when
    they are a minority of the region (a lumen enhanced above it is the majority), then the upper Otsu class
    of the rest is lumen.  Without the first step Otsu's upper class of lumen, tissue and calcium is calcium.
    An upper class of fewer than ``MIN_LUMEN_SHARE`` of the voxels is not the lumen around a seed but its
    outliers (a noise peak, a calcification's halo): it is dropped and the rest split again.  In a ball of 31
    lumen voxels with one at +6 standard deviations, Otsu's upper class held that voxel and one more.

    Parameters
    ----------
    array : ndarray, shape (nk, nj, ni)
    region : ndarray of bool, same shape

    Returns
    -------
    ndarray of bool, same shape, within ``region``
    """
    from skimage.filters import threshold_otsu

    below = region & (array <= lumen_ceiling(array))
    if 2 * np.count_nonzero(below) > np.count_nonzero(region):
        region = below
    values = np.sort(array[region])
    while values.size >= 4 and values[-1] > values[0]:
        threshold = threshold_otsu(values)
        upper = values.size - np.searchsorted(values, threshold, side="right")
        if upper >= MIN_LUMEN_SHARE * values.size:
            return region & (array > threshold)
        values = values[:-upper]
    return region & (array <= values[-1]) if values.size else region


def sample_radius(radius_mm: float, spacing_kji) -> float:
    """Radius (mm) of the ball a seed's lumen sample is drawn from: the seed sphere's, and at least two voxels
    (of the voxel's geometric mean size), a ball of 33 voxels on an isotropic grid, so that the lumen level is
    a median of many voxels, not of the one or three a 1.5 mm sphere holds in 1.5 mm voxels."""
    return max(float(radius_mm), 2.0 * float(np.prod(spacing_kji)) ** (1.0 / 3.0))


def seed_start(volume: Volume, seeds_xyz: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spheres of ``radius_mm`` at the seeds (world mm, shape (n, 3); validated first), the seeds' voxel
    indices (n, 3) and the lumen sample the intensity model is estimated from (``lumen_sample`` of the balls
    of ``sample_radius`` at the seeds, with the seeds' own voxels).  The spheres' signed distance less the
    difference of the radii is the balls'."""
    phi = seed_levelset(volume, seeds_xyz, radius_mm)
    seeds_kji = volume.world_to_index(seeds_xyz)
    grow = np.float32(sample_radius(radius_mm, volume.spacing_kji) - radius_mm)
    return phi, seeds_kji, lumen_sample(volume.array, seed_sample(phi - grow, seeds_kji))


def keep_components(inside: np.ndarray, seeds_kji: np.ndarray | None, spacing_kji,
                    reach_mm: float = 5.0) -> np.ndarray:
    """The connected components holding a seed, or within ``reach_mm`` of it for a seed the front left (one
    placed on a calcification or a flap); the largest one when no seed has any."""
    labels, n = ndimage.label(inside)
    if n == 0:
        raise CarotidError("segmentation is empty: the front vanished (check the seeds and the HU window)")
    if seeds_kji is not None:
        idx = tuple(np.clip(np.round(seeds_kji).astype(int), 0, np.asarray(inside.shape) - 1).T)
        keep = labels[idx]
        if not keep.all():
            distance, nearest = ndimage.distance_transform_edt(labels == 0, sampling=spacing_kji,
                                                               return_indices=True)
            keep = np.where(distance[idx] <= reach_mm, labels[tuple(nearest[(slice(None), *idx)])], 0)
        keep = np.unique(keep[keep > 0])
        if keep.size:
            return np.isin(labels, keep)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == np.argmax(sizes)


def segment(volume: Volume, seeds_xyz=None, init_mask: np.ndarray | None = None,
            params: SegmentParameters | None = None, progress=None, stops_xyz=None) -> Segmentation:
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
    stops_xyz : array_like, shape (s, 3), optional
        Stop points in world mm: the bright structure around each (up to the darkest surface between it and
        the seeds, ``barrier.stop_region``) is kept out of the lumen.

    Without seeds and initial region the initialisation is automatic: the core of the bright structure that
    forks (``automatic_region``), and when it does fork, one seed in its trunk and one near the end of each
    branch (``fork_seeds``, recorded as ``seeds_mm``), from which the segmentation runs as from a user's.

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
        phi, seeds_kji, sample = seed_start(volume, seeds_xyz, params.seed_radius_mm)
        how = "seed"
    elif init_mask is not None:
        if init_mask.shape != volume.array.shape:
            raise CarotidError(f"initial region has shape {init_mask.shape}, image has {volume.array.shape}")
        share = np.count_nonzero(init_mask) / init_mask.size
        if share > MAX_INITIAL_SHARE:
            raise CarotidError(f"the initial region covers {100 * share:.0f} % of the image: it should mark the "
                               f"lumen, at most {100 * MAX_INITIAL_SHARE:.0f} %")
        phi = mask_levelset(init_mask, spacing)
        sample = lumen_sample(volume.array, np.asarray(init_mask, bool))
        how = "region"
    else:
        phi = None
        how = "automatic"

    source = image = volume.array
    if params.denoise_iterations:
        image = denoise(volume, params.denoise_iterations).array
    if phi is None:
        image01, ghat, excluded = automatic_inputs(image, source, spacing, params)
        region = automatic_region(image01, ghat, spacing, excluded=excluded)
        found = fork_seeds(region, spacing)
        if found is None:
            phi = mask_levelset(region, spacing)
            sample = lumen_sample(source, region)
        else:
            seeds_xyz = volume.index_to_world(found)
            phi, seeds_kji, sample = seed_start(volume, seeds_xyz, params.seed_radius_mm)
        del image01, ghat, excluded
    model = estimate_from_sample(source, sample, spacing, {"seed": "seeds"}.get(how, how))
    window = lumen_window(model, params)
    hyperdense, dense = None, None
    if params.calcium_edge:
        image, dense, hyperdense = hyperdense_edge(image, window[1], model.lumen, model.background, spacing,
                                                   model.blur, balls=params.calcium_balls,
                                                   depth_cap=params.calcium_depth_cap,
                                                   tissue_offset=params.calcium_tissue_level)
    stops = None
    if stops_xyz is not None and len(stops_xyz):
        stops_xyz = np.atleast_2d(np.asarray(stops_xyz, float))
        check_points(volume, stops_xyz, "stop point")
        if seeds_xyz is not None and len(seeds_xyz):
            gap = np.linalg.norm(stops_xyz[:, None] - np.atleast_2d(seeds_xyz)[None], axis=2)
            if np.any(gap <= params.seed_radius_mm):
                raise CarotidError(f"a stop point lies within {params.seed_radius_mm:g} mm of a seed (the seed's "
                                   "sphere): a stop point marks a structure to keep out, away from the seeds")
        stops = point_mask(volume.world_to_index(stops_xyz), image.shape)
    if seeds_kji is not None:
        # Each seed sphere grows to half the lumen's radius measured there, so that in a wide vessel (an aorta)
        # the front starts within the potential's reach of the wall.
        radii = 0.5 * local_radius(model.box, model.bright, seeds_kji, spacing)
        phi = seed_levelset(volume, seeds_xyz, np.maximum(params.seed_radius_mm, radii))
    image01 = window_hu(image, *window, params.fold)
    stopped = neighbours(image01, window, model, spacing, params, sample, stops)
    stages = params.stages(spacing)
    ghat, g = speed_fields(image01, spacing, *stages[0][:2], params,
                           barrier_of(image01, window, model, spacing, params, stopped))
    timings["potential_s"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    iterations, converged = [], []
    level, chamber_report = None, None
    for number, (radius, sigma, alpha) in enumerate(stages):
        if number:
            if params.level_mm > 0 and not params.window:
                core = phi < -float(spacing.max())
                level = local_level(source, core if core.any() else phi < 0, spacing, params.level_mm, model.lumen)
                window = lumen_window(model, params, level)
                image01 = window_hu(image, *window, params.fold)
            ghat, g = speed_fields(image01, spacing, radius, sigma, params)
            if params.half_maximum > 0:
                half = half_maximum_speed(contrast_units(image01, window, model, level), spacing)
                ghat = (1.0 - params.half_maximum) * ghat + params.half_maximum * half
                del half
            if stopped is not None:
                ghat[stopped] = 1.0
        result = evolve(phi, ghat, g, spacing, alpha=alpha, cfl=params.cfl, max_iterations=params.max_iterations,
                        tolerance=params.tolerance, progress=progress)
        phi = result.phi
        iterations.append(result.iterations)
        if number == 0 and (params.chamber_ratio > 0 or params.companion_depth > 0) and seeds_kji is not None:
            phi, resumed, more, stopped, chamber_report = capture_without_chambers(
                volume, phi, ghat, g, image01, window, model, params, seeds_kji, stopped, alpha, progress)
            result = resumed or result
            iterations[-1] += more
        converged.append(result.converged)
    del ghat, g, image01
    joins = []
    if params.join_contrast > 0 and seeds_kji is not None and len(seeds_kji) > 1:
        phi, joins = join_seeds(image, phi, seeds_kji, spacing, model.lumen, model.background,
                                model.blur or float(np.max(spacing)), stopped, params.join_contrast)
    thickness, thickness_source, model_blur_kji = None, "no refinement", None
    if params.deblur and model.blur:
        thickness, thickness_source = slice_thickness(volume, params, model)
        phi, model_blur_kji = deblur(image, phi, spacing, model, params, stopped, dense, thickness)
    timings["evolution_s"] = time.perf_counter() - t1
    intensity = {**model.as_dict(), "window": [float(w) for w in lumen_window(model, params)], "hyperdense": hyperdense,
                 "window_source": "override" if params.window else "estimated",
                 "slice_thickness_mm": thickness, "slice_thickness_source": thickness_source,
                 "model_blur_kji_mm": None if model_blur_kji is None else model_blur_kji.tolist()}
    if level is not None:
        inside = phi < 0
        intensity["followed_lumen_level_percentiles_5_50_95"] = (
            np.percentile(level[inside], [5, 50, 95]).tolist() if inside.any() else None)

    t2 = time.perf_counter()
    phi, mask, handles_removed, cavities_filled = lumen_levelset(phi, stopped, seeds_kji, spacing, params)
    timings["distance_s"] = time.perf_counter() - t2
    noise = lumen_noise(source, phi < -(2.0 * (model.blur or 0.0) + float(spacing.max())),
                        model.lumen if level is None else level)
    intensity.update(noise=noise, contrast_to_noise=None if not noise else model.contrast / noise,
                     contrast_to_noise_validated=VALIDATED_CONTRAST_TO_NOISE)

    wall, wall_report = None, None
    if params.wall:
        speeds = partial(speed_fields, spacing_kji=spacing, radius_mm=params.wall_kernel_mm,
                         sigma_mm=params.sigma_mm, params=params)
        region, wall_report = outer_wall(volume, mask > 0, speeds, params, progress)
        wall = keep_components(region, seeds_kji, spacing)
        if params.wall_trunk_mm > 0:
            t3 = time.perf_counter()
            wall = keep_components(trunk(wall, spacing, params.wall_trunk_mm), seeds_kji, spacing)
            wall_report["trunk_seconds"] = time.perf_counter() - t3
        wall = wall.astype(np.uint8)
        wall_report["volume_mm3"] = float(wall.sum() * np.prod(spacing))
    timings["total_s"] = time.perf_counter() - t0

    report = {
        "method": "GPF level set (scalar kernel, eq. 5)",
        "intensity": intensity,
        "parameters": asdict(params),
        "initialisation": how,
        "seeds_mm": None if seeds_kji is None else np.asarray(seeds_xyz).tolist(),
        "stops_mm": None if stops is None else np.asarray(stops_xyz).tolist(),
        "excluded_neighbour_mm3": 0.0 if stopped is None else float(np.count_nonzero(stopped) * np.prod(spacing)),
        "chambers": chamber_report,
        "seed_joins": joins,
        "iterations": iterations,
        "converged": all(converged),
        "seconds": timings,
        "lumen_volume_mm3": float(mask.sum() * np.prod(spacing)),
        "topology": topology(mask > 0),
        "cavities_filled": cavities_filled,
        "handles_removed": [{**{k: v for k, v in change.items() if k != "centre_kji"},
                             "centre_mm": volume.index_to_world(change["centre_kji"]).round(1).tolist()}
                            for change in handles_removed],
        "wall": wall_report,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "image": {"shape_kji": list(volume.array.shape), "spacing_mm": list(volume.spacing),
                  "origin_mm": list(volume.origin), "slice_thickness_mm": volume.slice_thickness},
    }
    return Segmentation(volume.with_array(phi), volume.with_array(mask), report,
                        None if wall is None else volume.with_array(wall),
                        None if dense is None else volume.with_array(dense.astype(np.uint8)))


@dataclass
class SegmentStageParameters(SegmentParameters):
    """The ``[segment]`` section of a run configuration: ``SegmentParameters`` and the seeds.

    Attributes
    ----------
    seeds_mm : list of [x, y, z]
        Seed points in world mm (LPS), one per branch at best; empty for automatic initialisation.
    stops_mm : list of [x, y, z]
        Stop points in world mm (LPS): the bright structure around each is kept out of the lumen.
    """

    seeds_mm: list = field(default_factory=list)
    stops_mm: list = field(default_factory=list)

    def validate(self) -> "SegmentStageParameters":
        """Raise CarotidError for bad values, seeds and stop points included."""
        points = [*self.seeds_mm, *self.stops_mm]
        if any(not isinstance(point, list) or len(point) != 3 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in point)
               for point in points):
            raise CarotidError("bad segmentation parameter: each seed and stop point must be [x, y, z] in mm, "
                               "finite numbers")
        super().validate()
        return self


def run_stage(case_dir: Path, params: dict, inputs: list[Path], progress=None) -> None:
    """The ``segment`` stage of ``carotid run``: read ``inputs[0]``, segment it, write ``CASE_DIR/segmentation``.

    ``progress`` (a :class:`carotid.pipeline.StageProgress`) receives the level-set iterations.
    """
    from carotid.io import read_image

    params = SegmentStageParameters(**params).validate()
    fields = {k: v for k, v in asdict(params).items() if k not in ("seeds_mm", "stops_mm")}
    report = None if progress is None else (
        lambda iterations, changed, front: progress(iterations, None, iterations=iterations, front=front))
    result = segment(read_image(inputs[0]), seeds_xyz=params.seeds_mm or None, params=SegmentParameters(**fields),
                     stops_xyz=params.stops_mm or None, progress=report)
    write_segmentation(result, case_dir, inputs[0])


def write_segmentation(result: Segmentation, case_dir: str | Path, image_path: str | Path | None = None) -> Path:
    """Write ``levelset.nii.gz``, ``mask.nii.gz``, ``report.json`` (and ``wall_mask.nii.gz``,
    ``calcium_mask.nii.gz``) atomically.

    ``image_path``, the segmented image's file or DICOM folder, is recorded as ``report.json``
    ``image.path`` (absolute), so that a case built stage by stage still finds its scan.
    """
    if image_path is not None:
        result.report["image"]["path"] = str(Path(image_path).resolve())
    out = Path(case_dir) / "segmentation"
    with atomic_dir(out) as tmp:
        write_image(result.levelset, tmp / "levelset.nii.gz")
        write_image(result.mask, tmp / "mask.nii.gz")
        if result.wall is not None:
            write_image(result.wall, tmp / "wall_mask.nii.gz")
        if result.calcium is not None:
            write_image(result.calcium, tmp / "calcium_mask.nii.gz")
        write_json(result.report, tmp / "report.json")
    return out
