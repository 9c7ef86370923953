"""The lumen's intensity, estimated from the image instead of HU constants.

The GPF method itself is modality-agnostic: it needs an image in which the
lumen is bright and its surroundings dark.  What differs between a CT
angiogram at any contrast level, a contrast-enhanced MR angiogram and a
time-of-flight MRA is only where the lumen and its surroundings lie on the
intensity axis.  This module measures that on the image:

* ``IntensityModel`` holds the lumen level ``A`` (median of the voxels at the
  seeds or deep in the initial region), its spread (robust standard deviation,
  noise included) and the background level ``B`` (median of a shell 1.5-4 mm
  outside the bright region connected to the seeds, in which soft tissue and
  fat dominate).  Every intensity threshold of the segmentation is a fraction
  of the contrast ``C = A - B`` (or a multiple of the spread) above ``B``.
* ``provisional_window`` is the window of the automatic initialisation
  (no seeds): from the histogram mode (soft tissue) to the bright end of the
  image; the model is then estimated from the region that initialisation finds.
* ``local_level`` follows ``A`` along the vessel: the bolus fades by 20-30 %
  from the common to the distal internal carotid, and an MR bias field varies
  the level by tens of percent.  It is the Gaussian-weighted mean of the image
  over the lumen's core (normalised convolution, Knutsson & Westin 1993), so it
  is defined wherever some lumen lies within a few ``sigma_mm``.  Its wide
  Gaussian is computed on a coarser grid (``wide_gaussian``): scipy has no
  multiresolution Gaussian, and the direct one took a third of a 256^3 run.
  ``local_linear_level`` fits a line instead of a mean with the same weights,
  so that the level does not lean towards where the core is densest.

* ``lumen_noise`` measures the noise, the spread of the segmented lumen's core
  about the followed level; with the contrast it gives the contrast-to-noise
  ratio that ``VALIDATED_CONTRAST_TO_NOISE`` bounds.
* ``edge_blur`` measures the scanner's blur on the lumen's own edge: the
  width of a Gaussian step fitted to the median intensity profile across it,
  each profile read between its own plateaus (``edge_plateaus``), so that a
  fading bolus or a bias field does not widen the median.
  The calcium model (``calcium``) needs it to predict how far a calcification's
  blur reaches.
* ``through_plane_variance`` measures what the slice axis adds to that blur, on
  the edges between the two commonest tissues (fat and muscle), which face
  every way: their width grows with their tilt out of the slices.

Written here because the estimate is specific to a bright tubular lumen; the
statistics themselves are numpy/scipy, the isosurface scikit-image's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, special
from skimage.measure import marching_cubes

from carotid.errors import CarotidError

MAD_TO_SD = 1.4826
# Iodinated blood stays below this in any CT angiography protocol; cortical bone and calcium lie above it.
CT_NOT_LUMEN_HU = 800.0
TILT_BINS = (0.0, 0.25, 0.5, 0.75, 1.0 + 1e-9)  # |n_k| bins of through_plane_variance
# The lowest lumen contrast-to-noise ratio (``lumen_noise``) among the phantom family's benchmark cases
# (``benchmarks/README.md``): the segmentation's accuracy is measured down to it, not below.  At the family's
# weakest, most fading bolus under its strongest noise (5.4) the wall follows the noise.
VALIDATED_CONTRAST_TO_NOISE = 7.5


@dataclass(frozen=True)
class IntensityModel:
    """Lumen and background levels of one image, in its own units (HU for CT).

    Attributes
    ----------
    lumen : float
        Median lumen intensity near the seeds.
    spread : float
        Robust standard deviation of the lumen sample (noise and enhancement variation).
    background : float
        Level of the tissue around the lumen.
    source : str
        What the lumen sample came from: "seeds", "region" or "automatic".
    box : tuple of slices, optional
        Box around the sample in which ``bright`` was found.
    bright : ndarray of bool, optional
        Voxels of that box above the half level ``(A + B) / 2`` connected to the sample.
    blur : float, optional
        Standard deviation (mm) of the image's blur across the lumen's edge (``edge_blur``); None where the
        edge could not be measured.
    """

    lumen: float
    spread: float
    background: float
    source: str
    box: tuple | None = None
    bright: np.ndarray | None = None
    blur: float | None = None

    @property
    def contrast(self) -> float:
        """Lumen minus background level."""
        return self.lumen - self.background

    @property
    def half_level(self) -> float:
        """Half-way from the background to the lumen level: where a blurred wall lies."""
        return self.background + 0.5 * self.contrast

    def window(self, low_margin: float, high_margin: float) -> tuple[float, float]:
        """Window ``(B - low_margin C, A + max(high_margin C, 3 spread))``: the lumen sits just below its top.

        Parameters
        ----------
        low_margin, high_margin : float
            Fractions of the contrast ``C`` below the background and above the lumen level.
        """
        c = self.contrast
        return self.background - low_margin * c, self.lumen + max(high_margin * c, 3.0 * self.spread)

    def as_dict(self) -> dict:
        """JSON-ready description (with the contrast)."""
        return {"lumen": self.lumen, "spread": self.spread, "background": self.background, "source": self.source,
                "contrast": self.contrast, "blur_mm": self.blur}


def _check_contrast(lumen: float, background: float, spread: float, where: str) -> None:
    """Refuse a lumen that is not clearly brighter than its surroundings."""
    if not lumen - background > max(2.0 * spread, 1e-6 * max(abs(lumen), 1.0)):
        raise CarotidError(f"the lumen at the {where} ({lumen:.4g}) is not brighter than its surroundings "
                           f"({background:.4g}, spread {spread:.3g}): check the seeds, or give --hu-window")


def robust_level(values: np.ndarray) -> tuple[float, float]:
    """Median and robust standard deviation (1.4826 MAD) of a sample."""
    values = np.asarray(values, np.float64)
    median = float(np.median(values))
    return median, MAD_TO_SD * float(np.median(np.abs(values - median)))


def _box(kji: np.ndarray, shape, margin) -> tuple[slice, ...]:
    """Bounding box (slices) of integer points (n, 3) grown by ``margin`` voxels per axis, clipped."""
    lo = np.maximum(kji.min(axis=0) - margin, 0)
    hi = np.minimum(kji.max(axis=0) + margin + 1, shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))


def region_box(region: np.ndarray, spacing_kji, margin_mm: float) -> tuple[slice, ...] | None:
    """Bounding box (slices) of ``region`` grown by ``margin_mm`` (at least that, per axis) and clipped; None if
    it is empty."""
    found = ndimage.find_objects(region.astype(np.uint8))
    if not found or found[0] is None:
        return None
    grow = np.ceil(margin_mm / np.asarray(spacing_kji, float)).astype(int)
    return tuple(slice(max(s.start - g, 0), min(s.stop + g, n)) for s, g, n in zip(found[0], grow, region.shape))


def bright_region(image: np.ndarray, sample: np.ndarray, threshold: float, spacing_kji,
                  reach_mm: float = 30.0) -> tuple[tuple[slice, ...], np.ndarray]:
    """The bright region connected to a lumen sample, within a box around it.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    sample : ndarray of bool, same shape
        Voxels known to be lumen.
    threshold : float
        Intensity above which a voxel counts as bright (after a 0.5 mm Gaussian).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm.
    reach_mm : float
        The box extends this far (mm, per axis) beyond the sample.

    Returns
    -------
    box : tuple of slices
        The box in the image.
    bright : ndarray of bool, the box's shape
    """
    spacing_kji = np.asarray(spacing_kji, float)
    margin = np.ceil(reach_mm / spacing_kji).astype(int)
    box = _box(np.argwhere(sample), image.shape, margin)
    smooth = ndimage.gaussian_filter(image[box].astype(np.float32), 0.5 / spacing_kji)
    labels, _ = ndimage.label(smooth >= threshold)
    keep = np.unique(labels[sample[box]])
    return box, np.isin(labels, keep[keep > 0]) | sample[box]


def background_level(image: np.ndarray, box, bright: np.ndarray, spacing_kji,
                     shell_mm: tuple[float, float] = (1.5, 4.0)) -> float:
    """Median intensity of a shell outside a bright region (``bright_region``).

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    box : tuple of slices
    bright : ndarray of bool, the box's shape
    spacing_kji : array_like, shape (3,)
    shell_mm : (float, float)
        Inner and outer distance (mm) of the shell from the region, at least one and 2.5 voxels.

    Returns
    -------
    float
    """
    spacing_kji = np.asarray(spacing_kji, float)
    h = spacing_kji.max()
    inner, outer = max(shell_mm[0], h), max(shell_mm[1], 2.5 * h)
    # The distances on the region's own box grown by the shell: every voxel of the region lies in it, so they
    # are exact there (the whole box, 14 times as large at 256^3, took a second).
    near = region_box(bright, spacing_kji, outer + h)
    if near is not None:
        distance = ndimage.distance_transform_edt(~bright[near], sampling=spacing_kji)
        shell = (distance >= inner) & (distance <= outer)
        if shell.any():
            return float(np.median(image[box][near][shell]))
    outside = ~bright
    return float(np.median(image[box][outside])) if outside.any() else float(np.median(image))


def local_radius(box, bright: np.ndarray, points_kji: np.ndarray, spacing_kji) -> np.ndarray:
    """Distance (mm) from each point to the edge of the bright region: the lumen's local radius there.

    Parameters
    ----------
    box : tuple of slices
    bright : ndarray of bool, the box's shape
    points_kji : ndarray, shape (m, 3)
        Continuous array indices in the whole image.
    spacing_kji : array_like, shape (3,)

    Returns
    -------
    ndarray, shape (m,)
    """
    spacing_kji = np.asarray(spacing_kji, float)
    depth = np.zeros(bright.shape)
    # The region's box grown by a voxel holds the nearest outside voxel of every region voxel.
    near = region_box(bright, spacing_kji, float(spacing_kji.min()))
    if near is not None:
        depth[near] = ndimage.distance_transform_edt(bright[near], sampling=spacing_kji)
    offset = np.array([s.start for s in box])
    idx = np.clip(np.round(points_kji).astype(int) - offset, 0, np.asarray(bright.shape) - 1)
    return depth[tuple(idx.T)]


def lumen_noise(image: np.ndarray, core: np.ndarray, level) -> float | None:
    """Robust standard deviation (1.4826 MAD) of the image over the lumen's core about its level: the noise.

    The seed sample's spread also holds the partial volume of a seed near the wall and of a narrow branch; the
    core of the whole segmented lumen, two blur widths and a voxel inside the wall, about the level followed
    along the vessel (bolus fade, MR bias field), holds the noise alone.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    core : ndarray of bool, same shape
    level : float or ndarray of the image's shape
        Lumen level (``local_level``).

    Returns
    -------
    float or None
        In the image's units; None when the core holds fewer than 100 voxels.
    """
    if np.count_nonzero(core) < 100:
        return None
    residual = np.asarray(image, np.float32)[core] - (level[core] if np.ndim(level) else np.float32(level))
    return robust_level(residual)[1]


def estimate_from_sample(image: np.ndarray, sample: np.ndarray, spacing_kji, source: str) -> IntensityModel:
    """Intensity model from voxels known to be lumen.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    sample : ndarray of bool, same shape
        Lumen voxels: the seed spheres, or the inner part of an initial region.
    spacing_kji : array_like, shape (3,)
    source : str
        Recorded in the model ("seeds", "region", "automatic").

    Raises
    ------
    CarotidError
        If the sample is empty or not brighter than its surroundings.
    """
    if not sample.any():
        raise CarotidError(f"no voxel to estimate the lumen intensity from ({source})")
    lumen, spread = robust_level(image[sample])
    box, bright = bright_region(image, sample, lumen - 3.0 * spread, spacing_kji)
    background = background_level(image, box, bright, spacing_kji)
    # The shell can still hold some partial volume or a neighbour: the threshold is re-derived from it once,
    # at the half level where the lumen's wall lies.
    box, bright = bright_region(image, sample, 0.5 * (lumen + background), spacing_kji)
    background = background_level(image, box, bright, spacing_kji)
    _check_contrast(lumen, background, spread, source)
    # The most common intensity is soft tissue (or an MR image's background): a lumen is clearly brighter.
    _check_contrast(lumen, histogram_mode(image), spread, source)
    blur = edge_blur(image, box, bright, 0.5 * (lumen + background), spacing_kji)
    return IntensityModel(lumen, spread, background, source, box, bright, blur)


def edge_blur(image: np.ndarray, box, bright: np.ndarray, level: float, spacing_kji, depth_mm: float = 2.0,
              reach_mm: float = 2.5, min_points: int = 50, locate_mm: float | None = 0.6, max_tilt: float = 0.3,
              order: int = 3, own_levels: bool = True, plateau_mm: float = 1.0,
              flat_fraction: float = 0.15) -> float | None:
    """Standard deviation (mm) of the blur across the edge of a bright region within the slices, from the image.

    The edge is the ``level`` isosurface (marching cubes, scikit-image) of the box smoothed by ``locate_mm``,
    where the region is at least ``depth_mm`` thick and nothing bright lies within ``depth_mm`` outside it, so
    that the edge is a clean step between two plateaus.  The raw image is sampled along the normals out to
    ``reach_mm`` on both sides, the median profile taken over the edge, and the step response of a Gaussian
    blur, ``B + C Phi(-(d - d0) / sigma)``, fitted to it (scipy's ``curve_fit``).  Four choices keep the median
    profile as wide as the blur:

    * each profile is read between its own plateaus (``own_levels``, ``edge_plateaus``): its last
      ``plateau_mm`` at either end, on the smoothed image, must be flat to ``flat_fraction`` of the step
      expected at ``level``; it is centred where it crosses half-way between them and scaled to run from 0
      to 1.  A bolus fading along the vessel or an MR bias field moves the lumen's level by up to 40 %:
      where it is dimmer, the ``level`` isosurface lies off the edge's own half level, and the median of
      steps shifted by up to a blur width is a wider step (MR family: up to 17 % too wide).  A bright
      structure joined to the region, a vertebra's cortex and marrow behind a low-contrast lumen, has no
      flat plateau; read as the lumen's edge it made the blur 24-27 % too narrow on two family scans;
    * the edge is located on an image smoothed at about a scanner's blur.  Located on the lightly smoothed
      image, each edge point follows the noise of its own profile: the profiles are aligned on the noise and
      their median is too sharp (centred on the isosurface, over the phantom family, by 2 % at a
      contrast-to-noise ratio above 15 and by 6 % below it; centred on their own half levels, 1-3 % on a tube
      at 7);
    * only edges facing within the slices (``|n_k| <= max_tilt``) are used: an edge tilted out of them is
      blurred by the slice profile too (``through_plane_variance``), which ``deblur.axis_blur`` adds along k
      (5-7 % wider on the phantoms whose lumen runs across the slices);
    * the profiles are sampled by cubic spline interpolation: linear interpolation is itself a blur and
      widens them by about 5 % in 0.4-0.5 mm voxels.

    The wall's curvature adds 1-2 % (a cylinder of radius 2.5 mm blurred by 0.7 mm reads 0.715 mm).

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    box : tuple of slices
    bright : ndarray of bool, the box's shape
        The bright region (``bright_region``).
    level : float
        Intensity of the edge (half-way between the region's level and its surroundings').
    spacing_kji : array_like, shape (3,)
    depth_mm, reach_mm : float
        Required plateau on each side, and half-length of the profiles, mm.
    min_points : int
        Fewer clean edge points than this: no estimate.
    locate_mm : float or None
        Gaussian smoothing (mm) of the image the edge is located on; None: half the finest voxel size.
    max_tilt : float
        Largest component of an edge's normal along the slice axis k.
    order : int
        Order of the spline interpolation of the raw image (1: linear).
    own_levels : bool
        Read each profile between its own plateaus (above); False: every profile as sampled, centred on the
        ``level`` isosurface.
    plateau_mm, flat_fraction : float
        With ``own_levels``, the length (mm) of each plateau at a profile's ends, and its largest variation
        (peak to peak) as a fraction of the step expected at ``level`` (``edge_plateaus``).

    Returns
    -------
    float or None
        sigma in mm, or None if the edge is too small or the fit fails.
    """
    spacing = np.asarray(spacing_kji, float)
    crop = np.asarray(image[box], np.float32)
    smooth = ndimage.gaussian_filter(crop, (0.5 * spacing.min() if locate_mm is None else locate_mm) / spacing)
    near = ndimage.binary_dilation(bright, iterations=2)
    field = np.where(near, smooth, np.float32(min(level, float(smooth.min())) - 1.0))
    if not (field.max() > level > field.min()):
        return None
    d, points, outward, profiles = normal_profiles(field, smooth, level, spacing, reach_mm)
    clean = np.all(profiles[d <= -depth_mm] > level, axis=0) & np.all(profiles[d >= depth_mm] < level, axis=0)
    clean &= np.abs(outward[:, 0]) <= max_tilt
    if own_levels:
        upper, lower, shift, flat = edge_plateaus(d, profiles, level, plateau_mm, flat_fraction)
        clean &= flat
    if np.count_nonzero(clean) < min_points:
        return None
    if not own_levels:
        return step_width(d, np.median(sample(crop, points[:, clean], spacing, order), axis=1), float(spacing.min()))
    centred = points[:, clean] + shift[clean][None, :, None] * outward[clean][None]
    raw = (sample(crop, centred, spacing, order) - lower[clean]) / (upper[clean] - lower[clean])
    return step_width(d, np.median(raw, axis=1), float(spacing.min()))


def edge_plateaus(d: np.ndarray, profiles: np.ndarray, level: float, plateau_mm: float,
                  flat_fraction: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each profile's own levels on either side of its edge, and where it crosses half-way between them.

    Parameters
    ----------
    d : ndarray, shape (m,)
        Distances (mm) along the profiles, increasing, negative on the bright side.
    profiles : ndarray, shape (m, n)
        Intensity profiles of a smoothed image across an edge, bright at negative ``d``.
    level : float
        The edge's expected half level: a profile's step is expected to be ``2 (level - lower)``.
    plateau_mm : float
        Length (mm) of each end of a profile taken as its plateau.
    flat_fraction : float
        Largest variation (peak to peak) along a plateau, as a fraction of the expected step.  A bright
        structure behind the edge (a vertebra's cortex and marrow) has a step several times the expected one
        and varies by as much along its bright side.

    Returns
    -------
    upper, lower : ndarray, shape (n,)
        Mean of each profile along its bright and its dark plateau.
    shift : ndarray, shape (n,)
        Distance (mm) along the profile of its half-level crossing nearest ``d = 0`` (linear interpolation).
    flat : ndarray of bool, shape (n,)
        Both plateaus flat, the step positive and the half level crossed.
    """
    top, bottom = profiles[d <= d[0] + plateau_mm], profiles[d >= d[-1] - plateau_mm]
    upper, lower = top.mean(axis=0), bottom.mean(axis=0)
    tolerance = 2.0 * flat_fraction * (level - lower)
    flat = (upper > lower) & (np.ptp(top, axis=0) < tolerance) & (np.ptp(bottom, axis=0) < tolerance)
    above = profiles - 0.5 * (upper + lower)
    falls = (above[:-1] > 0) & (above[1:] <= 0)
    gap = np.where(falls, np.abs(0.5 * (d[:-1] + d[1:]))[:, None], np.inf)
    nearest = np.argmin(gap, axis=0)
    columns = np.arange(profiles.shape[1])
    before, after = above[nearest, columns], above[nearest + 1, columns]
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = d[nearest] + (d[nearest + 1] - d[nearest]) * before / (before - after)
    flat &= np.isfinite(gap[nearest, columns])
    return upper, lower, np.where(flat, shift, 0.0), flat


def normal_profiles(field: np.ndarray, smooth: np.ndarray, level: float, spacing: np.ndarray, reach_mm: float,
                    step_size: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Intensity profiles of ``smooth`` across the ``level`` isosurface of ``field``, along its normals.

    Parameters
    ----------
    field : ndarray, shape (nk, nj, ni)
        Image whose isosurface is taken (marching cubes, scikit-image; ``step_size`` voxels per cube).
    smooth : ndarray, same shape
        Smoothed image whose gradient gives the normals and which the profiles sample (linear interpolation).
    level : float
    spacing : ndarray, shape (3,)
    reach_mm : float
        Half-length of the profiles, mm, sampled every quarter of the finest voxel size.
    step_size : int

    Returns
    -------
    d : ndarray, shape (m,)
        Distances (mm) along the normals, negative on the brighter side.
    points : ndarray, shape (m, n, 3)
        Sample positions (mm, (k, j, i)) of the n profiles.
    outward : ndarray, shape (n, 3)
        Unit normals, towards the darker side.
    profiles : ndarray, shape (m, n)
    """
    verts, _, _, _ = marching_cubes(field, level, spacing=tuple(spacing), step_size=step_size, method="lewiner")
    grad = np.stack([ndimage.map_coordinates(g, (verts / spacing).T, order=1)
                     for g in np.gradient(smooth, *spacing)], axis=1)
    norm = np.linalg.norm(grad, axis=1)
    ok = norm > 0
    outward = -grad[ok] / norm[ok, None]
    d = np.linspace(-reach_mm, reach_mm, 4 * int(np.ceil(reach_mm / spacing.min())) + 1)
    points = verts[ok][None] + d[:, None, None] * outward[None]
    return d, points, outward, sample(smooth, points, spacing)


def sample(image: np.ndarray, points: np.ndarray, spacing: np.ndarray, order: int = 1) -> np.ndarray:
    """``image`` at ``points`` (mm, (k, j, i), shape (m, n, 3)) by spline interpolation of ``order`` (1:
    linear), shape (m, n)."""
    return ndimage.map_coordinates(image, (points.reshape(-1, 3) / spacing).T, order=order,
                                   mode="nearest").reshape(points.shape[:2])


def step_width(d: np.ndarray, profile: np.ndarray, start_mm: float) -> float | None:
    """Standard deviation (mm) of the Gaussian step ``B + C Phi(-(d - d0) / sigma)``, ``C >= 0``, fitted to an
    intensity profile (scipy's ``curve_fit``), bright at negative ``d``.

    Parameters
    ----------
    d : ndarray, shape (n,)
        Distances along the profile, mm, symmetric about the edge.
    profile : ndarray, shape (n,)
    start_mm : float
        Initial guess of sigma.

    Returns
    -------
    float or None
        None if the fit fails.
    """
    reach = float(d[-1])

    def step(x, b, c, x0, sigma):
        return b + c * special.ndtr(-(x - x0) / sigma)

    start = [float(profile[-1]), float(profile[0] - profile[-1]), 0.0, start_mm]
    try:
        bounds = ([-np.inf, 0, -reach, 0.05], [np.inf, np.inf, reach, reach])
        (_, _, _, sigma), _ = optimize.curve_fit(step, d, profile, p0=start, bounds=bounds)
    except (RuntimeError, ValueError):
        return None
    return float(sigma)


def through_plane_variance(image: np.ndarray, box, ceiling: float, spacing_kji, smooth_mm: float = 0.7,
                           depth_mm: float = 1.2, reach_mm: float = 2.0, min_points: int = 200) -> float | None:
    """Variance (mm^2) the blur adds along the slice axis k beyond its in-plane variance, from the image alone.

    A scanner blurs along its slice axis by its slice sensitivity profile, which is independent of the blur
    within the slices and, in CT, usually wider than it; ``edge_blur`` cannot see it, because the lumen's
    edges face sideways.  The edges between the two most common tissues below ``ceiling`` (fat and muscle,
    ``tissue_levels``) face every way.  An edge whose normal ``n`` tilts out of the slices is blurred across
    by ``sigma_p^2 (1 - n_k^2) + sigma_k^2 n_k^2`` (plus the edge's own width, the same on average whatever
    its tilt), so the squared width of the median step across the edges, binned by ``n_k^2``, grows linearly
    with it with slope ``sigma_k^2 - sigma_p^2``.  The profiles are sampled by linear interpolation, which
    widens them by ``h^2 / 6`` along an axis of spacing ``h``; the slope loses the slices' share of that,
    ``(h_k^2 - h_min^2) / 6``.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    box : tuple of slices
        Region to measure in (the intensity model's box).
    ceiling : float
        Intensities above this are left out of the tissue classes (the lumen's half level).
    spacing_kji : array_like, shape (3,)
    smooth_mm : float
        Gaussian smoothing (mm) of the image the edges and their normals are taken from; the profiles are
        read on the raw image.
    depth_mm, reach_mm : float
        Plateau required on each side (within a quarter of the tissues' contrast of their levels), and the
        profiles' half-length, mm.
    min_points : int
        Fewest edge points in a tilt bin; fewer than three such bins: no estimate.

    Returns
    -------
    float or None
        ``sigma_k^2 - sigma_p^2`` (mm^2, at least 0), or None if the image has too few clean tissue edges.
    """
    spacing = np.asarray(spacing_kji, float)
    crop = np.asarray(image[box], np.float32)
    smooth = ndimage.gaussian_filter(crop, smooth_mm / spacing)
    levels = tissue_levels(smooth[smooth < ceiling])
    if levels is None:
        return None
    low, high = levels
    d, points, outward, profiles = normal_profiles(smooth, smooth, 0.5 * (low + high), spacing, reach_mm, 2)
    tolerance = 0.25 * (high - low)
    clean = (np.all(np.abs(profiles[d <= -depth_mm] - high) < tolerance, axis=0)
             & np.all(np.abs(profiles[d >= depth_mm] - low) < tolerance, axis=0))
    raw = sample(crop, points[:, clean], spacing)
    tilt2 = outward[clean, 0] ** 2
    rows = []
    for lo, hi in zip(TILT_BINS[:-1], TILT_BINS[1:]):
        in_bin = (tilt2 >= lo ** 2) & (tilt2 < hi ** 2)
        if np.count_nonzero(in_bin) >= min_points:
            width = step_width(d, np.median(raw[:, in_bin], axis=1), float(spacing.min()))
            if width is not None:
                rows.append((float(tilt2[in_bin].mean()), width ** 2, np.count_nonzero(in_bin)))
    if len(rows) < 3:
        return None
    x, y, n = np.array(rows).T
    weight = np.sqrt(n)
    _, slope = np.linalg.lstsq(np.column_stack([np.ones_like(x), x]) * weight[:, None], y * weight, rcond=None)[0]
    return max(float(slope - (spacing[0] ** 2 - spacing.min() ** 2) / 6.0), 0.0)


def tissue_levels(values: np.ndarray, bins: int = 200) -> tuple[float, float] | None:
    """The two most common intensities among ``values``: the two highest peaks of their histogram (1st-99th
    percentile, 200 bins smoothed by 2), in increasing order; None if it has fewer than two peaks."""
    if values.size < 1000:
        return None
    lo, hi = np.percentile(values, [1, 99])
    counts, edges = np.histogram(values[(values > lo) & (values < hi)], bins)
    counts = ndimage.gaussian_filter1d(counts.astype(float), 2.0)
    peaks = np.flatnonzero((counts > np.roll(counts, 1)) & (counts >= np.roll(counts, -1)))
    peaks = peaks[(peaks > 0) & (peaks < bins - 1)]
    if len(peaks) < 2:
        return None
    centres = 0.5 * (edges[1:] + edges[:-1])
    two = np.sort(centres[peaks[np.argsort(counts[peaks])[-2:]]])
    return float(two[0]), float(two[1])


def provisional_window(image: np.ndarray) -> tuple[float, float, float]:
    """Seed-free window for the automatic initialisation, and the level above which nothing is lumen.

    The window runs from the histogram mode (soft tissue, or the background of an MR
    angiogram) to the 99.9th percentile, clipped.  In a CT image (recognised by
    negative intensities, i.e. fat or air in Hounsfield units; magnitude MR images are never
    negative) voxels above
    ``CT_NOT_LUMEN_HU`` are bone or calcium whatever the contrast protocol; an MR
    angiogram has no structure brighter than its enhanced lumen (bone and calcium are
    dark), so nothing is excluded there.

    Returns
    -------
    low, high, ceiling : float
        Window and the level above which voxels are not lumen (inf for MR).
    """
    hi = float(np.percentile(_subsample(image), 99.9))
    ceiling = lumen_ceiling(image)
    return histogram_mode(image), min(hi, ceiling), ceiling


def lumen_ceiling(image: np.ndarray) -> float:
    """The level above which no voxel is lumen: ``CT_NOT_LUMEN_HU`` in a CT image, recognised by negative
    intensities (fat or air in Hounsfield units; more than 0.5 % of the voxels below 0), inf otherwise (a
    magnitude MR image, in which bone and calcium are dark)."""
    return CT_NOT_LUMEN_HU if float(np.percentile(_subsample(image), 0.5)) < 0.0 else np.inf


def _subsample(image: np.ndarray) -> np.ndarray:
    """About 64 slices' worth of voxels, enough for histogram statistics."""
    return image[:: max(1, image.shape[0] // 64)].ravel()


def histogram_mode(image: np.ndarray) -> float:
    """Most frequent intensity (smoothed 256-bin histogram between the 0.5th and 99.9th percentiles)."""
    values = _subsample(image)
    lo, hi = np.percentile(values, [0.5, 99.9])
    if hi <= lo:
        raise CarotidError("image has no contrast to segment")
    hist, edges = np.histogram(values, bins=256, range=(lo, hi))
    peak = int(np.argmax(ndimage.gaussian_filter1d(hist.astype(float), 2.0)))
    return float(0.5 * (edges[peak] + edges[peak + 1]))


def local_level(image: np.ndarray, core: np.ndarray, spacing_kji, sigma_mm: float, default: float) -> np.ndarray:
    """Lumen level followed along the vessel: Gaussian-weighted mean of ``image`` over ``core``.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    core : ndarray of bool, same shape
        Voxels deep inside the lumen.
    spacing_kji : array_like, shape (3,)
    sigma_mm : float
        Scale (mm) of the Gaussian: the length over which the level may change.
    default : float
        Level where no core voxel lies within a few ``sigma_mm``.

    Returns
    -------
    ndarray, float32, same shape
    """
    sigma = sigma_mm / np.asarray(spacing_kji, float)
    weight = wide_gaussian(core.astype(np.float32), sigma)
    total = wide_gaussian(np.where(core, image, 0).astype(np.float32), sigma)
    return _normalised(weight, total, default)


def _normalised(weight: np.ndarray, total: np.ndarray, default: float) -> np.ndarray:
    """Normalised convolution ``total / weight`` (float32), blended towards ``default`` where the weight (the
    smoothed core indicator) is too small to rest on."""
    floor = np.float32(1e-4)  # a core voxel within about 4 sigma
    level = np.where(weight > floor, total / np.maximum(weight, floor), np.float32(default))
    # Where the core is barely within reach the estimate rests on few voxels: blend towards the default there.
    blend = np.clip(weight / np.float32(1e-3), 0, 1)
    return (blend * level + (1 - blend) * np.float32(default)).astype(np.float32)


def local_linear_level(image: np.ndarray, core: np.ndarray, spacing_kji, sigma_mm: float, default: float,
                       where: np.ndarray, ridge: float = 0.02) -> np.ndarray:
    """Lumen level followed along the vessel by a Gaussian-weighted local linear fit over ``core``.

    ``local_level``'s weighted mean leans towards wherever the core is densest: near a stenosis the wider
    bulb's many core voxels outweigh the throat's few, and where the bolus fades along the vessel that
    puts the throat's level nearer the bulb's.  A local linear fit (kernel regression of order one) has no
    such design bias to first order: at each voxel ``x0`` it fits ``a + g . (x - x0)`` to the core's
    intensities with the Gaussian weights of ``local_level`` and returns ``a``.  Its weighted moments are
    wide Gaussians (``wide_gaussian``) of the core's intensity and coordinates; the 3 x 3 normal equations
    of the slope are solved voxel by voxel (batched).  A ridge of ``ridge * sigma_mm^2`` on the slope's
    second moments keeps a direction the core does not span from extrapolating: across a vessel the core's
    variance is ``R^2 / 4``, 2.25 mm^2 for a 3 mm core radius, and the default ridge is 2 mm^2 at
    ``sigma_mm`` = 10, so the fit is linear along the vessel and nearly flat across it.  On a fade of 0.5 %
    of the contrast per mm the ridge leaves a bias of at most 0.3 % of the contrast where a 4 mm bulb
    narrows to a 1.2 mm branch (the mean: 7.5 %).

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    core : ndarray of bool, same shape
        Voxels deep inside the lumen.
    spacing_kji : array_like, shape (3,)
    sigma_mm : float
        Scale (mm) of the Gaussian weights.
    default : float
        Level where no core voxel lies within a few ``sigma_mm``.
    where : ndarray of bool, same shape
        Voxels at which the fit is made; elsewhere ``local_level``.
    ridge : float
        Ridge on the slope, in units of the weights' variance ``sigma_mm^2``.

    Returns
    -------
    ndarray, float32, same shape
    """
    spacing = np.asarray(spacing_kji, float)
    sigma = sigma_mm / spacing
    weight = core.astype(np.float32)
    values = np.where(core, image, 0).astype(np.float32)
    s0 = wide_gaussian(weight, sigma)
    t0 = wide_gaussian(values, sigma)
    level = _normalised(s0, t0, default)
    # Coordinates (mm) from the array's centre keep the float32 moments well conditioned.
    axes = [((np.arange(n, dtype=np.float32) - (n - 1) / 2) * np.float32(h)).reshape([-1 if a == b else 1
                                                                                       for b in range(3)])
            for a, (n, h) in enumerate(zip(core.shape, spacing))]
    fit = where & (s0 > np.float32(1e-3))
    index = np.nonzero(fit)
    x = np.stack([np.broadcast_to(axes[a], core.shape)[index] for a in range(3)], axis=1).astype(np.float64)
    s0 = s0[index].astype(np.float64)
    t0 = t0[index].astype(np.float64)
    s1 = np.stack([wide_gaussian(weight * axes[a], sigma)[index] for a in range(3)], axis=1).astype(np.float64)
    t1 = np.stack([wide_gaussian(values * axes[a], sigma)[index] for a in range(3)], axis=1).astype(np.float64)
    s2 = np.empty((len(s0), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            raw = wide_gaussian(weight * axes[a] * axes[b], sigma)[index]
            s2[:, a, b] = s2[:, b, a] = raw - x[:, a] * s1[:, b] - x[:, b] * s1[:, a] + x[:, a] * x[:, b] * s0
    s1 -= x * s0[:, None]  # moments about each voxel
    t1 -= x * t0[:, None]
    s2 += (ridge * sigma_mm ** 2) * s0[:, None, None] * np.eye(3)
    u = np.linalg.solve(s2, s1[..., None])[..., 0]
    v = np.linalg.solve(s2, t1[..., None])[..., 0]
    level[index] = ((t0 - np.einsum("ij,ij->i", s1, v)) / (s0 - np.einsum("ij,ij->i", s1, u))).astype(np.float32)
    return level


def wide_gaussian(array: np.ndarray, sigma, voxels_per_step: float = 3.0) -> np.ndarray:
    """Gaussian filter (``mode="nearest"``) of a wide kernel, computed on a coarser grid.

    A Gaussian of standard deviation ``sigma`` voxels varies over ``sigma``: the array is averaged over blocks
    of ``f = sigma / voxels_per_step`` voxels per axis, filtered there by the Gaussian whose variance plus
    the block's ``(f^2 - 1) / 12`` is ``sigma^2``, and interpolated back (linear, block-aligned).  On a 256^3
    array with ``sigma`` = 22 voxels this is 4 times faster than the direct filter, and on smooth data within
    one percent of its range, most of it at the array's faces, where the last half block is extrapolated flat;
    axes where ``sigma < 2 voxels_per_step`` are not coarsened.

    Parameters
    ----------
    array : ndarray, float32, shape (nk, nj, ni)
    sigma : array_like, shape (3,)
        Standard deviation per axis, voxels.
    voxels_per_step : float
        Standard deviation, in coarse voxels, below which no axis is coarsened.

    Returns
    -------
    ndarray, float32, same shape
    """
    sigma = np.asarray(sigma, float)
    factor = np.clip(np.floor(sigma / voxels_per_step), 1, array.shape).astype(int)
    if np.all(factor == 1):
        return ndimage.gaussian_filter(array, sigma, mode="nearest")
    shape = np.array(array.shape)
    padded = np.pad(array, [(0, int(p)) for p in -shape % factor], mode="edge")
    coarse_shape = np.array(padded.shape) // factor
    blocks = padded.reshape(coarse_shape[0], factor[0], coarse_shape[1], factor[1], coarse_shape[2], factor[2])
    coarse = blocks.mean(axis=(1, 3, 5), dtype=np.float32)
    coarse_sigma = np.sqrt(np.maximum(sigma ** 2 - (factor ** 2 - 1) / 12.0, 0.0)) / factor
    fine = ndimage.gaussian_filter(coarse, coarse_sigma, mode="nearest")
    for axis in range(3):
        fine = _upsample_linear(fine, axis, int(factor[axis]), int(shape[axis]))
    return fine


def _upsample_linear(array: np.ndarray, axis: int, factor: int, size: int) -> np.ndarray:
    """Linear interpolation of block values to the first ``size`` voxels of blocks of ``factor`` along ``axis``.

    Voxel ``o`` lies at block coordinate ``(o + 0.5) / factor - 0.5`` (block-aligned: ``ndimage.zoom`` with
    ``grid_mode=True``); beyond the first and last block centre the value is held (``mode="nearest"``).  One
    axis at a time, so the full-size array is formed once instead of interpolating eight corners per voxel.
    """
    n = array.shape[axis]
    if factor == 1:
        return array
    if n == 1:
        return np.repeat(array, size, axis=axis)
    c = np.clip((np.arange(size) + 0.5) / factor - 0.5, 0.0, n - 1)
    low = np.minimum(c.astype(int), n - 2)
    w = np.expand_dims((c - low).astype(np.float32), [a for a in range(3) if a != axis])
    return array.take(low, axis=axis) * (1 - w) + array.take(low + 1, axis=axis) * w
