"""Calcification (and bone) removed with its blur before the potential.

In a CT angiogram a calcified plaque is brighter than the iodinated lumen, and
the scanner's blur spreads it over a millimetre or more ("blooming").  Two
things then go wrong for a lumen segmentation:

* where the calcification touches the lumen, a window that folds intensities
  above the lumen level back down puts the edge where the blurred profile
  crosses the fold, inside the lumen, instead of where the two materials meet,
  the half-way level between lumen and calcium (the segmentation then grades
  a calcified stenosis too tight);
* on the tissue side, the blurred profile falls from the calcium's level to
  the tissue's through the lumen's own levels: a shell of lumen-like
  intensity surrounds every calcification and every bone, which the front
  follows (into the vertebra next to the carotid), and which widens a
  calcified stenosis (too mild a grade).

``hyperdense_edge`` removes both.  Calcified structures are found above the
window top (on a lightly smoothed image, so that noise in the lumen is never
taken for calcium); their extent is where a marker watershed (scikit-image)
on the gradient magnitude, between the calcium cores and the lumen-level and
tissue-level voxels around them, puts it: on the steepest edge, which for a
blurred step is the half-way level, towards the lumen and towards the tissue
alike, placed to a fraction of a voxel (``edge_fraction``: the steepest point
moved out by the blur's curvature shift, or the edge of the blurred plate,
rod or nodule whose steepest point and ridge lie where the image's do).  Its blur, a Gaussian of the image's own width (``intensity.edge_blur``)
times an amplitude fitted on its tissue side (with, on request, that tissue's own level:
``tissue_offset``), is subtracted from the image,
so that the lumen next to it keeps only its own intensity; the structure
itself becomes background, except within two blur widths of its edge, where
what remains after the subtraction (the lumen's own blur, at most half its
contrast) is kept, so that the lumen's edge stays where the two meet.  On
request (``depth_cap``) it is kept only up to what the lumen's blur can leave
at its depth (``lumen_blur_cap``: half the contrast at the edge, a Gaussian
tail behind it): a nodule a few blur widths across, whose core the fitted
blur under-subtracts, is then not left at the lumen's half level throughout.  In an MR angiogram
calcium and bone are dark and nothing lies above the window: nothing changes.

Written here because no library offers this step; the filters are scipy's and
the watershed scikit-image's.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage, special, stats
from skimage.segmentation import watershed

from carotid.segment.intensity import region_box
from carotid.segment.preprocess import gaussian_filter

TISSUE, LUMEN, STRUCTURE = 1, 2, 3
# Tissue level: below the background plus this fraction of the lumen's contrast (lightly smoothed image).
TISSUE_FRACTION = 0.25
# Gaussian smoothing (mm) of the image on which hyperdense structures are found, at the finest voxels.
DECISION_SMOOTH_MM = 0.5


def hyperdense_edge(image: np.ndarray, top: float, lumen: float, background: float, spacing_kji,
                    blur_mm: float | None, reach_mm: float = 3.0, sigma_mm: float = DECISION_SMOOTH_MM,
                    balls: bool = False, depth_cap: bool = False,
                    tissue_offset: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """The image with each hyperdense structure (calcium, bone) and its blur replaced by the background.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    top : float
        Window top: the lumen never exceeds it; brighter (after smoothing) is hyperdense.
    lumen, background : float
        Lumen level ``A`` and tissue level ``B``.
    spacing_kji : array_like, shape (3,)
    blur_mm : float or None
        Standard deviation (mm) of the image's blur; None: only the structure itself is replaced.
    reach_mm : float
        A structure's edge, and its blur, are looked for within this distance (mm) of its voxels above ``top``.
    sigma_mm : float
        Gaussian smoothing (mm) of the image on which the decisions are taken; at least half the coarsest
        voxel, so that single noisy voxels of a coarse scan are not taken for calcium.
    balls : bool
        Place each structure's edge by the blurred-ball model (``edge_fraction(balls=True)``).
    depth_cap : bool
        Keep what remains within two blur widths of a structure's edge only up to ``lumen_blur_cap`` at its
        depth; False: up to the lumen's half level at every depth.
    tissue_offset : bool
        Fit the level of the tissue around each structure with its blur (``structure_blur``); False: the
        tissue is taken at ``background``.

    Returns
    -------
    corrected : ndarray, float32, same shape
    extent : ndarray of bool, same shape
        The structures' voxels.
    info : dict
        Number of hyperdense structures, volume (mm^3) set to the background, and the largest blur amplitude
        subtracted (image units).
    """
    spacing_kji = np.asarray(spacing_kji, float)
    sigma_mm = decision_smoothing(spacing_kji, sigma_mm)
    image = np.asarray(image, np.float32)
    smooth = gaussian_filter(image, sigma_mm / spacing_kji)
    hot = smooth > np.float32(top)
    if not hot.any():
        return image, hot, {"structures": 0, "volume_mm3": 0.0, "blur_amplitude_max": 0.0}
    # Distances to the structures only where they can reach (the transform of a whole 256^3 image with a
    # vertebra in it took 3.5 s; its crop gives the same distances within reach).
    outer = region_box(hot, spacing_kji, reach_mm)
    distance = ndimage.distance_transform_edt(~hot[outer], sampling=spacing_kji)
    near = np.zeros(image.shape, bool)
    near[outer] = distance <= reach_mm
    box = region_box(near, spacing_kji, 0.0)
    # Lumen-level voxels closer than two blur widths may be a structure's own blurred edge: no lumen marker there.
    clear = distance[within(box, outer)] > 2.0 * (blur_mm or sigma_mm)
    regions = np.zeros(image.shape, np.int8)
    regions[box] = structure_regions(image[box], smooth[box], hot[box], near[box], clear, lumen, background,
                                     spacing_kji, sigma_mm)
    del distance
    extent = regions == STRUCTURE
    tissue = near[box] & (smooth[box] < np.float32(background + TISSUE_FRACTION * (lumen - background)))
    extent[box] = in_the_wall(extent[box], tissue, spacing_kji, reach_mm)
    del tissue
    amplitude_max = 0.0
    if blur_mm and extent.any():
        fraction = np.zeros(image.shape, np.float32)
        fraction[box] = edge_fraction(image[box], extent[box], near[box], spacing_kji, blur_mm, sigma_mm,
                                      balls=balls)
        extent = fraction > 0.5
    # Everything below happens within the structures' box grown by their blur's reach: beyond it the image is
    # left as it is (a whole 256^3 image's filters took a second).
    wide = region_box(near, spacing_kji, 4.0 * (blur_mm or 0.0) + float(spacing_kji.max()))
    inside = extent[wide]
    labels, n = ndimage.label(inside)
    crop = image[wide]
    local = np.where(inside, np.float32(background), crop)
    if blur_mm and n:
        reach = 2 * np.ceil(reach_mm / spacing_kji).astype(int) + 1
        grown = ndimage.maximum_filter(labels, size=reach)
        owner = np.where((regions[wide] == TISSUE) & ~inside, grown, 0)
        belongs = np.where(fraction[wide] > 0, np.where(labels > 0, labels, grown), 0)
        blurred, amplitude = structure_blur(crop, belongs, n, fraction[wide], owner, background, spacing_kji,
                                            blur_mm, tissue_offset)
        # Within a blur width or two of its edge a structure holds its neighbours' blur too (the lumen's, up
        # to half the contrast at a shared edge): what remains after the subtraction, kept below the half level
        # or below what the lumen's blur can leave at its depth.
        depth = ndimage.distance_transform_edt(extent[box], sampling=spacing_kji)
        rim = np.zeros(image.shape, bool)
        rim[box] = extent[box] & (depth < 2.0 * blur_mm)
        cap = np.float32(0.5 * (lumen + background))
        if depth_cap:  # in the box's part of the wide crop; beyond it no structure, no rim
            cap = np.full(crop.shape, np.float32(background), np.float32)
            cap[within(box, wide)] = lumen_blur_cap(depth.astype(np.float32), lumen, background, blur_mm,
                                                    spacing_kji)
        del depth
        remains = np.clip(crop - blurred, np.float32(background), cap)
        local = np.where(inside, np.where(rim[wide], remains, local), crop - blurred)
        amplitude_max = float(amplitude.max())
    out = image.copy()
    out[wide] = local
    volume = float(np.count_nonzero(extent) * np.prod(spacing_kji))
    return out, extent, {"structures": int(n), "volume_mm3": volume, "blur_amplitude_max": amplitude_max}


def decision_smoothing(spacing_kji, sigma_mm: float = DECISION_SMOOTH_MM) -> float:
    """Gaussian smoothing (mm) of the image ``hyperdense_edge`` takes its decisions on: ``sigma_mm``, and at
    least half the coarsest voxel (``spacing_kji``, mm), so that single noisy voxels of a coarse scan are not
    taken for calcium."""
    return max(float(sigma_mm), 0.5 * float(np.max(spacing_kji)))


def within(box: tuple[slice, ...], outer: tuple[slice, ...]) -> tuple[slice, ...]:
    """The slices of ``box`` relative to ``outer``, a box of the same image that holds it."""
    return tuple(slice(b.start - o.start, b.stop - o.start) for b, o in zip(box, outer))


def lumen_blur_cap(depth: np.ndarray, lumen: float, background: float, blur_mm: float,
                   spacing_kji) -> np.ndarray:
    """The most the lumen's blur can leave inside a structure at each depth from its edge.

    A lumen filling the whole half-space beyond the structure's nearest edge, blurred by a Gaussian of
    standard deviation ``blur_mm``, leaves ``B + (A - B) Phi(-d / sigma)`` at a depth ``d`` behind that edge:
    half the contrast on the edge, 16 % of it one blur width in.  Any real lumen leaves less.  The edge lies
    within the structure's outermost voxels (``edge_fraction`` places it to a fraction of one), so ``d`` is
    counted from one voxel of the finest axis in: those voxels keep the half level, and with it the lumen's
    edge where the two meet.

    Parameters
    ----------
    depth : ndarray, float32, shape (nk, nj, ni)
        Distance (mm) from each voxel inside the structure to the nearest voxel outside it (the Euclidean
        distance transform).
    lumen, background : float
        Lumen level ``A`` and tissue level ``B``.
    blur_mm : float
        Standard deviation (mm) of the image's blur.
    spacing_kji : array_like, shape (3,)

    Returns
    -------
    ndarray, float32, ``depth``'s shape
    """
    behind = np.maximum(depth - np.float32(float(np.min(spacing_kji))), np.float32(0.0)) / np.float32(blur_mm)
    return (np.float32(background)
            + np.float32(lumen - background) * special.ndtr(-behind).astype(np.float32))


def in_the_wall(extent: np.ndarray, tissue: np.ndarray, spacing_kji, reach_mm: float) -> np.ndarray:
    """The structures of ``extent`` with tissue within ``reach_mm``.

    Calcium lies in the vessel's wall and bone in the tissue: both have tissue next to them.  A bright spot
    with nothing but lumen around it (contrast streaming, noise on a coarse scan) is lumen, and cutting it
    out, or subtracting a blur fitted to the lumen around it, would darken the lumen.

    Parameters
    ----------
    extent, tissue : ndarray of bool, shape (nk, nj, ni)
        Structures, and tissue-level voxels.
    spacing_kji : array_like, shape (3,)
    reach_mm : float

    Returns
    -------
    ndarray of bool, same shape
    """
    labels, n = ndimage.label(extent)
    if n == 0 or not tissue.any():
        return np.zeros_like(extent)
    gap = ndimage.minimum(ndimage.distance_transform_edt(~tissue, sampling=spacing_kji), labels, np.arange(1, n + 1))
    return np.concatenate([[False], np.asarray(gap) <= reach_mm])[labels]


def structure_regions(image: np.ndarray, smooth: np.ndarray, hot: np.ndarray, near: np.ndarray, clear: np.ndarray,
                      lumen: float, background: float, spacing_kji, sigma_mm: float) -> np.ndarray:
    """Hyperdense structures up to their steepest edge, and what surrounds them.

    Markers: the cores (brighter than half-way between the lumen level and the structure's own peak), the
    lumen-level voxels (within 15 % of the contrast of ``lumen``) where ``clear`` of the structures' blur, and
    the tissue-level voxels (below a quarter of the contrast) within ``near``; a watershed on the gradient
    magnitude grows them into ``near``.  Arrays share one shape (a box of the image).

    Returns
    -------
    ndarray of int8
        ``STRUCTURE``, ``LUMEN`` or ``TISSUE`` within ``near``, 0 elsewhere.
    """
    contrast = lumen - background
    labels, n = ndimage.label(hot)
    peaks = np.concatenate([[np.inf], ndimage.maximum(smooth, labels, np.arange(1, n + 1))]).astype(np.float32)
    cores = hot & (smooth > np.float32(0.5) * (peaks[labels] + np.float32(lumen)))
    markers = np.zeros(image.shape, np.int8)
    markers[near & (smooth < np.float32(background + TISSUE_FRACTION * contrast))] = TISSUE
    markers[near & clear & (np.abs(smooth - np.float32(lumen)) < np.float32(0.15 * contrast))] = LUMEN
    markers[cores] = STRUCTURE
    gradient = ndimage.gaussian_gradient_magnitude(image, sigma_mm / np.asarray(spacing_kji, float))
    return watershed(gradient, markers, mask=near).astype(np.int8)


def label_maximum(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Largest of ``values`` (k,) over each label 1..n of ``labels`` (k,), shape (n,); -inf for an absent label.

    ``ndimage.maximum`` gives the same but sorts the whole array it is given; this scatters, so a caller
    passes only the labelled voxels (a few thousand of a 256^3 image: 7 s -> milliseconds)."""
    out = np.full(n + 1, -np.inf)
    np.maximum.at(out, labels, values)
    return out[1:]


def structure_blur(image: np.ndarray, labels: np.ndarray, n: int, fraction: np.ndarray, owner: np.ndarray,
                   background: float, spacing_kji, blur_mm: float,
                   tissue_offset: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Blur the structures spread into their surroundings: ``sum_i a_i G * chi_i`` (image units).

    The amplitude ``a_i`` of structure ``i`` is the least-squares fit of ``a_i G * chi_i`` to ``image - B``
    over the tissue it owns (``owner == i``), where nothing but the structure's blur raises the intensity:
    the structure's blurred density, which for a structure smaller than the blur is less than its true one.
    It is bounded by the structure's peak excess over ``B`` divided by the kernel there.

    With ``tissue_offset`` the fit is ``a_i G * chi_i + c_i``: the tissue around a structure has its own
    level ``B + c_i``.  The image's background ``B`` is one level for the whole neck, between fat (-100 HU)
    and muscle or plaque (+40 HU); a calcification lies in plaque, and without the offset the plaque's excess
    over ``B`` is taken for the structure's blur.  The amplitude then comes out too large, and the surplus is
    subtracted from the lumen beside the structure as well.  Where the owned tissue cannot separate the two
    (all of it at one kernel value) the fit keeps ``c_i = 0``.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
    labels : ndarray of int, same shape
        Structure (1..n) each voxel of ``fraction > 0`` belongs to.
    n : int
    fraction : ndarray, float32, same shape
        Occupancy ``chi`` of each voxel by a structure, in [0, 1] (``edge_fraction``).
    owner : ndarray of int, same shape
        Tissue voxels next to structure ``i`` hold ``i``; 0 elsewhere.
    background : float
    spacing_kji : array_like, shape (3,)
    blur_mm : float
        Standard deviation of the Gaussian blur, mm.
    tissue_offset : bool
        Fit each structure's tissue level as well (``c_i``); False: ``c_i = 0``.

    Returns
    -------
    blurred : ndarray, float32, image's shape
    amplitude : ndarray, shape (n,)
    """
    sigma = blur_mm / np.asarray(spacing_kji, float)
    kernel = gaussian_filter(fraction, sigma)
    excess = np.asarray(image, np.float32) - np.float32(background)
    # Sums over the voxels each structure owns, by bincount on those voxels alone (ndimage.sum over the whole
    # image took a second of a 256^3 run).
    fit = np.nonzero((kernel > np.float32(0.05)) & (owner > 0))
    which, weight, value = owner[fit], kernel[fit], excess[fit]
    total = functools.partial(np.bincount, which, minlength=n + 1)
    sww, swe = total(weight * weight)[1:], total(weight * value)[1:]
    amplitude = swe / np.maximum(sww, 1e-6)
    if tissue_offset:  # normal equations of a G * chi + c, per structure
        count, sw, se = total()[1:], total(weight)[1:], total(value)[1:]
        det = count * sww - sw * sw
        separable = det > 1e-3 * count * sww
        amplitude = np.where(separable, (count * swe - sw * se) / np.where(separable, det, 1.0), amplitude)
    # The blurred structure cannot be brighter than it is: at most its own excess where it is most itself.
    inside = labels > 0
    peak, reach = (label_maximum(v[inside], labels[inside], n) for v in (excess, kernel))
    amplitude = np.clip(amplitude, 0.0, peak / np.maximum(reach, 0.5))
    values = np.concatenate([[0.0], amplitude]).astype(np.float32)[labels] * fraction
    return gaussian_filter(values, sigma), amplitude


def edge_fraction(image: np.ndarray, extent: np.ndarray, near: np.ndarray, spacing_kji, blur_mm: float,
                  sigma_mm: float, curvature: bool = True, balls: bool = False) -> np.ndarray:
    """Occupancy of each voxel by the structures, with the edge placed to a fraction of a voxel.

    A voxel-wise extent misplaces a structure's edge by up to a voxel, and the blur of a dense calcification
    subtracted with it is then wrong by a third of its density next to the lumen.  Across a blurred step the
    steepest point is where the second derivative along the gradient vanishes: a voxel at distance ``x``
    (mm, positive on the bright side) from it has ``I'' / I' = -x / s^2``, ``s^2`` the blur's variance plus
    the derivative filter's, so ``x = -s^2 I'' / I'``.  On a curved structure the steepest point lies inside
    the true edge by ``s^2 kappa / 2`` (``kappa`` the sum of the principal curvatures of the isophote,
    ``(I'' - Laplacian I) / |grad I|``, positive on a convex structure), which is added back; for a calcified
    nodule of radius 1.5 mm this is 0.3-0.5 mm, more than a voxel.  Voxels on either side of the extent's
    boundary get the occupancy ``0.5 + x / h`` (clipped to [0, 1]), ``h`` the voxel's width along the
    gradient; the others keep 0 or 1.  Gaussian derivatives are scipy's.

    Parameters
    ----------
    image : ndarray, float32, shape (nk, nj, ni)
    extent : ndarray of bool, same shape
        Voxel-wise structures (``structure_regions``).
    near : ndarray of bool, same shape
        Where an edge may be.
    spacing_kji : array_like, shape (3,)
    blur_mm, sigma_mm : float
        The image's blur and the derivative filter's scale, mm.
    curvature : bool
        Add the curvature shift (off: the steepest point is taken for the edge).
    balls : bool
        Where the structure's ridge lies within ``RIDGE_REACH`` blur widths along the gradient, place the edge
        by the blurred ball of ``ball_radius`` instead: the curvature shift is that model's limit for a
        structure much wider than the blur, and wrong for a thinner one (a nodule of 1 mm, a calcified
        layer against the lumen).

    Returns
    -------
    ndarray, float32, same shape
    """
    spacing = np.asarray(spacing_kji, float)
    sigma = sigma_mm / spacing
    boundary = near & ndimage.binary_dilation(extent) & ~ndimage.binary_erosion(extent)
    fraction = extent.astype(np.float32)
    if not boundary.any():
        return fraction
    gradient = np.stack([ndimage.gaussian_filter(image, sigma, order=tuple(int(a == b) for b in range(3)))[boundary]
                         / spacing[a] for a in range(3)], axis=1)
    slope = np.linalg.norm(gradient, axis=1)
    n = gradient / np.maximum(slope, 1e-12)[:, None]
    second = np.zeros_like(slope)
    laplacian = np.zeros_like(slope)
    for a in range(3):
        for b in range(a, 3):
            order = [0, 0, 0]
            order[a] += 1
            order[b] += 1
            h_ab = ndimage.gaussian_filter(image, sigma, order=order)[boundary] / (spacing[a] * spacing[b])
            second += (1 if a == b else 2) * h_ab * n[:, a] * n[:, b]
            if a == b:
                laplacian += h_ab
    width = np.abs(n) @ spacing
    variance = blur_mm ** 2 + sigma_mm ** 2
    kappa = np.clip((second - laplacian) / np.maximum(slope, 1e-12), -2.0 / width, 2.0 / width)
    flank = -variance * second / np.maximum(slope, 1e-12)
    x = flank + (0.5 * variance * kappa if curvature else 0.0)
    if balls:
        s = np.sqrt(variance)
        ridge, found = ridge_distance(ndimage.gaussian_filter(image, sigma), boundary, n, spacing, RIDGE_REACH * s,
                                      0.05 * s)
        centre = ridge + flank  # from the steepest point to the ridge, mm
        radius = s * ball_radius(np.maximum(centre, 0.0) / s, kappa * centre)
        x = np.where(found & (centre < ball_flanks()[1][:, -1].min() * s), radius - ridge, x)
    fraction[boundary] = np.clip(0.5 + np.clip(x, -width, width) / width, 0.0, 1.0)
    return fraction


# How far (blur widths, the image's and the derivative filter's together) the ridge of a structure is looked
# for beyond its edge: past it a ball's steepest point and the curvature shift agree to 0.02 blur widths.
RIDGE_REACH = 4.0


def ridge_distance(smooth: np.ndarray, boundary: np.ndarray, normals: np.ndarray, spacing, reach_mm: float,
                   step_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance (mm) from each boundary voxel to the brightest point of ``smooth`` along its normal.

    Parameters
    ----------
    smooth : ndarray, float32, shape (nk, nj, ni)
        The smoothed image.
    boundary : ndarray of bool, same shape
        The voxels, ``m`` of them.
    normals : ndarray, shape (m, 3)
        Unit vectors (k, j, i) towards the brighter side.
    spacing : array_like, shape (3,)
    reach_mm, step_mm : float
        Length of the stretch sampled (trilinear) and the step along it, mm.

    Returns
    -------
    distance : ndarray, shape (m,)
    found : ndarray of bool, shape (m,)
        Whether the brightest point lies strictly within the stretch (a ridge, not a rise beyond its end).
    """
    offsets = np.arange(0.0, reach_mm + 0.5 * step_mm, step_mm, dtype=np.float32)
    points = np.stack(np.nonzero(boundary)).astype(np.float32)
    per_mm = (np.asarray(normals, np.float32) / np.asarray(spacing, np.float32)).T
    profile = np.stack([ndimage.map_coordinates(smooth, points + per_mm * u, order=1, mode="nearest")
                        for u in offsets])
    top = np.argmax(profile, axis=0)
    return offsets[top].astype(float), (top > 0) & (top < offsets.size - 1)


@functools.lru_cache(maxsize=None)
def ball_flanks() -> tuple[np.ndarray, np.ndarray]:
    """Where a blurred ball is steepest: ``r_s(R)`` for a ball of radius ``R`` in 1, 2 and 3 dimensions.

    A ball of radius ``R`` (a plate of half-thickness ``R``, a rod, a nodule) blurred by a unit Gaussian has,
    along a line through its centre, the profile ``Phi(R - r) - Phi(-R - r)`` (1-D), ``P(chi'^2_2(r^2) <=
    R^2)`` (2-D, the noncentral chi-square) or ``(erf((R - r) / sqrt 2) + erf((R + r) / sqrt 2)) / 2 -
    (exp(-(R - r)^2 / 2) - exp(-(R + r)^2 / 2)) / (r sqrt(2 pi))`` (3-D).  Its steepest point ``r_s`` tends
    to the Gaussian's own inflection, 1, as ``R -> 0``, and to ``R - (n - 1) / (2 R)`` as ``R`` grows, the
    curvature shift of ``edge_fraction``.

    Returns
    -------
    radii : ndarray, shape (q,)
        ``R``, 0 to 6 (units of the blur).
    steepest : ndarray, shape (3, q)
        ``r_s(R)`` for 1, 2 and 3 dimensions (non-decreasing).
    """
    radii = np.linspace(0.0, 6.0, 121)
    steepest = np.empty((3, radii.size))
    for row, dimension in enumerate((1, 2, 3)):
        for column, radius in enumerate(np.maximum(radii, 1e-3)):
            r = np.linspace(1e-3, radius + 5.0, 4001)
            if dimension == 1:
                profile = stats.norm.cdf(radius - r) - stats.norm.cdf(-radius - r)
            elif dimension == 2:
                profile = stats.ncx2.cdf(radius ** 2, 2, r ** 2)
            else:
                profile = 0.5 * (special.erf((radius - r) / np.sqrt(2)) + special.erf((radius + r) / np.sqrt(2))) - (
                    np.exp(-0.5 * (radius - r) ** 2) - np.exp(-0.5 * (radius + r) ** 2)) / (r * np.sqrt(2 * np.pi))
            steepest[row, column] = r[np.argmin(np.gradient(profile, r))]
    return radii, np.maximum.accumulate(steepest, axis=1)


def ball_radius(distance: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """Radius of the blurred ball whose steepest point lies ``distance`` from its centre (units of the blur).

    ``shape`` is the isophote's curvature times that distance, ``n - 1`` for a ball in ``n`` dimensions: 0 for
    a plate, 1 for a rod, 2 for a nodule; clipped to [0, 2] and interpolated between them (``ball_flanks``).

    Parameters
    ----------
    distance, shape : ndarray, shape (m,)

    Returns
    -------
    ndarray, shape (m,)
    """
    radii, steepest = ball_flanks()
    per_dimension = np.stack([np.interp(distance, row, radii) for row in steepest])
    shape = np.clip(shape, 0.0, 2.0)
    low = np.minimum(np.floor(shape).astype(int), 1)
    weight = shape - low
    columns = np.arange(np.size(distance))
    return per_dimension[low, columns] * (1.0 - weight) + per_dimension[low + 1, columns] * weight
