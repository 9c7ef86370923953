"""The wall where a blurred model of the lumen explains the image (partial-volume refinement).

Every edge-based front, the paper's GPF included, settles where the blurred
image changes fastest, and on a curved wall that is not where the wall is:
blur moves the steepest point (and the half level) towards the centre of
curvature by about ``sigma^2 kappa / 2``, ``kappa`` the sum of the principal
curvatures.  A straight tube of radius ``R`` comes out ``sigma^2 / (2 R)``
too narrow; a short, tight stenosis, whose wall is sharply concave along the
axis, too wide, because blur fills the notch from the wider lumen on either
side.  With a scanner blur of 0.6-0.8 mm a 2.3 mm throat reads 0.3-0.6 mm
too wide, and NASCET 10-20 points too low.

``refine`` removes that bias.  It models the image near the wall as
``M = G_sigma * (A H(-phi) + B (1 - H(-phi)))``: the lumen indicator (with a
partial-volume ramp one voxel wide) between the lumen level ``A``, followed
along the vessel, and the tissue level ``B``, blurred by a Gaussian of the
image's own blur (``intensity.edge_blur``) less the ramp's share
(``gaussian_part``), widened along a thicker voxel's axis by the rest of its
boxcar (``axis_blur``).  ``A`` is measured on the
lumen's core with the blur taken out of it (``lumen_level``): the blur darkens a
core near its wall and in a narrow vessel, and the plain mean of the core of
a 4 mm vessel blurred by 0.8 mm, 4 % low, moves its wall out by 0.08 mm.
``B`` varies around the vessel
(fat at -100 HU and muscle at +50 HU may share one wall), so each voxel takes
it from the image along its wall normal just beyond the blur's reach
(``normal_background``).  It then descends the least-squares misfit ``|I - M|^2``
restricted to a band around the wall: the speed of the wall is
``G_sigma * (I - M) / (A - B)`` (smoothed over ``smooth_mm`` more), positive (outward) where the image is
brighter than the model.  The displacement is bounded by one blur width
from the front the evolution converged to, so the refinement corrects a
position and never changes what the front captured; voxels where a
neighbour's blur (a vein held out of the lumen) or a calcification's reaches
are left out of the misfit, and on request (``neighbours``) any enhancing
structure beyond the wall's blur with its own blur (``bright_neighbours``).

Written here because no segmentation library offers a blur-model
refinement of a level set; the filters are scipy's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from carotid.segment.calcium import TISSUE_FRACTION
from carotid.segment.intensity import local_level, local_linear_level, region_box

def refine(image: np.ndarray, phi: np.ndarray, spacing_kji, lumen: float, background: float, blur_mm: float,
           exclude: np.ndarray | None = None, iterations: int = 20, gain: float = 2.0, smooth_mm: float = 1.0,
           normal: bool = True, level_mm: float = 0.0, linear_level: bool = False, slices: bool = True,
           thickness_mm: float | None = None, neighbours: bool = False, smooth_radius: float = 0.0) -> np.ndarray:
    """Level set moved to the wall that best explains the image under a Gaussian blur.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
        The image (calcium already removed), in its own units.
    phi : ndarray, float32, same shape
        Signed distance (mm, negative inside) of the converged front.
    spacing_kji : array_like, shape (3,)
    lumen : float
        Lumen level ``A``: everywhere when ``level_mm`` is 0, else where no lumen core lies within reach.
    background : float
        Background level where no local one can be measured.
    blur_mm : float
        Standard deviation of the image's Gaussian blur, mm.
    exclude : ndarray of bool, same shape, optional
        Voxels whose intensity the model does not describe (neighbours, calcium); their surroundings out to
        two blur widths are left out of the misfit.
    iterations : int
        Gradient steps.
    gain : float
        Step length in blur widths per unit of normalised misfit.
    smooth_mm : float
        Extra Gaussian smoothing (mm) of the wall's speed: the model corrects a position, not the noise.
    smooth_radius : float
        Where positive, the smoothing is at most this fraction of the lumen's local radius
        (``wall_radius``), and no less than half ``smooth_mm``: a wall is corrected at the scale of the
        vessel it bounds, so that a tight throat's notch is not smoothed away with the noise.  0: ``smooth_mm``
        everywhere.
    normal : bool
        Take the tissue level along each wall normal (``normal_background``); False keeps the shell's
        smoothed mean (``local_background``) everywhere.
    level_mm : float
        Scale (mm) over which the lumen level is followed along the vessel (``lumen_level``); 0: ``lumen``
        everywhere.
    linear_level : bool
        Follow it by a local linear fit (``intensity.local_linear_level``) instead of a local mean.
    slices : bool
        Blur each axis by ``axis_blur`` (the thicker voxels' boxcar added along their axis); False: by
        ``blur_mm`` along every axis.
    thickness_mm : float, optional
        Slice thickness along k (mm) for ``axis_blur``; None: the slice spacing.
    neighbours : bool
        Leave the bright structures beyond the wall's blur (``bright_neighbours``) out of the misfit, as
        ``exclude``, and out of the tissue level with their blur (two blur widths around them).

    Returns
    -------
    ndarray, float32, same shape
        The refined level set (no longer a signed distance; within ``blur_mm`` of ``phi``).
    """
    model = blur_model(image, phi, spacing_kji, lumen, background, blur_mm, exclude, normal=normal,
                       level_mm=level_mm, linear_level=linear_level, slices=slices, thickness_mm=thickness_mm,
                       neighbours=neighbours)
    if model is None:
        return phi
    spacing, sigma_mm, sigma_axes, phi0 = model.spacing, model.blur_mm, model.sigma_mm, model.phi0
    smoothing = np.hypot(sigma_axes, smooth_mm) / spacing
    finer, share = None, None
    if smooth_radius > 0:
        finest = 0.5 * smooth_mm
        near = np.abs(phi0) < model.band
        scale = np.clip(smooth_radius * wall_radius(phi0, spacing, near, smooth_mm / smooth_radius + model.band),
                        finest, smooth_mm)
        if np.any(scale < smooth_mm):
            finer = np.hypot(sigma_axes, finest) / spacing
            share = np.zeros(phi0.shape, np.float32)
            share[near] = (smooth_mm - scale) / (smooth_mm - finest)
    step = np.float32(gain * sigma_mm)
    out = phi0.copy()
    for _ in range(iterations):
        misfit = model_misfit(model, out)
        speed = ndimage.gaussian_filter(misfit, smoothing)
        if finer is not None:  # the speed at the finer scale where the lumen is narrow
            speed += share * (ndimage.gaussian_filter(misfit, finer) - speed)
        speed /= model.contrast
        out = np.clip(out - step * speed, phi0 - np.float32(sigma_mm), phi0 + np.float32(sigma_mm))
    result = np.array(phi, np.float32, copy=True)
    result[model.box] = out
    return result


@dataclass
class BlurModel:
    """``refine``'s model of the image near a wall, within ``box``: ``M = seen_tissue + G * (contrast chi)``,
    ``chi`` the lumen indicator of a level set with its partial-volume ramp.

    Attributes
    ----------
    box : tuple of slices
        The region of the image the model covers (the wall's band and the blur's reach).
    spacing : ndarray, shape (3,)
    blur_mm : float
        The Gaussian's standard deviation within the slices, mm.
    sigma_mm : ndarray, shape (3,)
        Its standard deviation per axis (``model_blur``), mm.
    band : float
        Half-width (mm) of the band around the wall where the misfit is read.
    ramp : float
        Width (mm) of the partial-volume ramp (``ramp_width``).
    phi0, crop : ndarray, float32, shape of the box
        The starting level set and the image.
    weight : ndarray of bool, shape of the box
        Voxels whose misfit counts: the band, clear of what the model leaves out, no deeper than half a blur
        width outside the starting wall.
    seen_tissue, contrast : ndarray, float32, shape of the box
        The blurred tissue level ``G * B`` and the lumen's contrast ``A - B`` over it.
    """

    box: tuple
    spacing: np.ndarray
    blur_mm: float
    sigma_mm: np.ndarray
    band: float
    ramp: float
    phi0: np.ndarray
    crop: np.ndarray
    weight: np.ndarray
    seen_tissue: np.ndarray
    contrast: np.ndarray


def blur_model(image: np.ndarray, phi: np.ndarray, spacing_kji, lumen: float, background: float, blur_mm: float,
               exclude: np.ndarray | None = None, normal: bool = True, level_mm: float = 0.0,
               linear_level: bool = False, slices: bool = True, thickness_mm: float | None = None,
               neighbours: bool = False) -> BlurModel | None:
    """``refine``'s blurred model of the lumen around the wall of ``phi``: its levels, blur and band.

    The tissue level is read along the wall normals of ``phi`` (``normal_background``), the lumen level on its
    core with the blur taken out (``lumen_level``); the arguments are ``refine``'s.

    Returns
    -------
    BlurModel or None
        None when ``phi`` has no wall.
    """
    spacing = np.asarray(spacing_kji, float)
    sigma_mm = float(blur_mm)
    band = 2.0 * sigma_mm + float(spacing.max())
    box = region_box(phi < band + 3.0 * sigma_mm, spacing, 3.0 * sigma_mm)
    if box is None:
        return None
    phi0 = np.asarray(phi[box], np.float32)
    crop = np.asarray(image[box], np.float32)
    excluded = None if exclude is None else exclude[box]
    around = None
    if neighbours:
        bright = bright_neighbours(crop, phi0, spacing, sigma_mm, lumen, background)
        if bright.any():
            excluded = bright if excluded is None else excluded | bright
            around = ndimage.distance_transform_edt(~bright, sampling=spacing) <= 2.0 * sigma_mm
    clear = np.ones(phi0.shape, bool)
    if excluded is not None and excluded.any():
        clear = ndimage.distance_transform_edt(~excluded, sampling=spacing) > 2.0 * sigma_mm
    weight = (np.abs(phi0) < band) & clear & (phi0 < np.float32(0.5 * sigma_mm))
    if around is not None:  # the tissue level is read clear of the bright neighbours' blur as well
        excluded = excluded | around
    tissue = local_background(crop, phi0, spacing, sigma_mm, excluded, background)
    if normal:
        tissue = normal_background(crop, phi0, spacing, sigma_mm, excluded, tissue)
    sigma_axes = model_blur(sigma_mm, spacing, slices, thickness_mm)
    ramp = float(ramp_width(spacing))
    seen_tissue = ndimage.gaussian_filter(tissue, sigma_axes / spacing)
    level = np.float32(lumen)
    if level_mm > 0:
        core = clear & (phi0 < -np.float32(max(2.0 * sigma_mm, float(spacing.max()))))
        level = lumen_level(crop, tissue, phi0, core, spacing, sigma_axes, np.float32(ramp), level_mm, lumen,
                            (phi0 < band) if linear_level else None)
    contrast = np.maximum(level - tissue, np.float32(1e-6))
    return BlurModel(box, spacing, sigma_mm, sigma_axes, band, ramp, phi0, crop, weight, seen_tissue, contrast)


def model_misfit(model: BlurModel, phi: np.ndarray) -> np.ndarray:
    """``I - M``, the image less the model of the wall of ``phi`` (level set on ``model.box``, mm), on
    ``model.weight`` (0 elsewhere); image units, float32, the box's shape."""
    ramp = np.float32(model.ramp)
    lumen_part = ndimage.gaussian_filter(model.contrast * np.clip(np.float32(0.5) - phi / ramp, 0, 1),
                                         model.sigma_mm / model.spacing)
    return np.where(model.weight, model.crop - model.seen_tissue - lumen_part, np.float32(0))


def wall_radius(phi: np.ndarray, spacing, where: np.ndarray, reach_mm: float) -> np.ndarray:
    """The lumen's radius beside each voxel of ``where``: how far down its inward normal the medial axis lies.

    Down the ray ``-grad phi`` from a voxel on or near the wall the depth ``-phi`` grows by the distance
    travelled until the ray meets the medial axis, where it peaks: the voxel's depth plus the distance to
    that peak is the radius of the inscribed ball touching the wall there (the ``MaximumInscribedSphereRadius``
    of VMTK's centerlines).  The peak's place is read rather than its height, which interpolation between
    voxels cuts off at a tube's axis.  Unlike a ball holding the voxel (the local thickness), the radius read
    beside a short throat is the throat's own, not its wider neighbours'.

    Parameters
    ----------
    phi : ndarray, float32, shape (nk, nj, ni)
        Signed distance to the wall, mm, negative inside.
    spacing : array_like, shape (3,)
    where : ndarray of bool, same shape
        Voxels to measure.
    reach_mm : float
        Length of the ray, mm: deeper axes read as ``reach_mm`` less the voxel's distance outside.

    Returns
    -------
    ndarray, float32, shape (count of ``where``,)
    """
    spacing = np.asarray(spacing, float)
    idx = np.nonzero(where)
    normal = np.stack([g[idx] for g in np.gradient(phi, *spacing)], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-6)
    step = (normal / spacing).astype(np.float32)
    start = np.stack(idx, axis=1).astype(np.float32)
    h = 0.5 * float(spacing.min())
    along = np.arange(0.0, reach_mm + 1e-9, h)
    depth = np.stack([-ndimage.map_coordinates(phi, (start - np.float32(t) * step).T, order=1, mode="nearest")
                      for t in along])  # (steps, voxels), each step vectorised over the voxels
    k = np.clip(np.argmax(depth, axis=0), 1, len(along) - 2) if len(along) > 2 else np.argmax(depth, axis=0)
    peak = along[k]
    if len(along) > 2:  # the parabola through the peak and its neighbours: a cut tip's middle
        cols = np.arange(depth.shape[1])
        before, at, after = depth[k - 1, cols], depth[k, cols], depth[k + 1, cols]
        curve = before - 2.0 * at + after
        shift = np.where(curve < -1e-6, 0.5 * (before - after) / np.where(curve < -1e-6, curve, -1.0), 0.0)
        peak = peak + h * np.clip(shift, -0.5, 0.5)
    return (-phi[idx] + peak).astype(np.float32)


def reach_mm(blur_mm: float, spacing_kji, thickness_mm: float | None = None) -> float:
    """Distance (mm) from the wall beyond which ``refine`` does not read its level set's values.

    The misfit lives in a band ``2 blur_mm + h`` wide; the model's Gaussians (truncated at four standard
    deviations per axis, so up to ``4 sqrt(3)`` of them diagonally) reach further, and each voxel they read
    takes its tissue level along the gradient of the level set, a voxel further.  Beyond this distance a
    level set clamped to it (``levelset.signed_distance``) refines to the same wall as an unclamped one.

    Parameters
    ----------
    blur_mm : float
    spacing_kji : array_like, shape (3,)
    thickness_mm : float, optional
        Slice thickness (``axis_blur``).

    Returns
    -------
    float
    """
    h = float(np.max(spacing_kji))
    sigma = float(axis_blur(blur_mm, spacing_kji, thickness_mm).max())
    return 2.0 * blur_mm + h + 4.0 * np.sqrt(3.0) * sigma + 2.0 * h


def gaussian_part(blur_mm: float, spacing_kji) -> float:
    """The Gaussian (mm) of ``refine``'s model for a blur measured on the image's edges.

    ``intensity.edge_blur`` measures the whole width of an edge, whatever makes it (the scanner's point
    spread, the voxel's extent), while ``refine`` blurs a lumen indicator that already carries a
    partial-volume ramp one finest voxel ``h`` wide, whose slope is a boxcar of variance ``h^2 / 12`` across
    the wall.  Blurred by the measured width, the model's edge is wider than the image's (by 1-6 % at blurs
    of 0.4-0.8 mm in 0.4-0.5 mm voxels), and a short, tight throat, which the blur fills from the wider lumen
    beside it, is matched with a wider wall.  The Gaussian takes the rest of the variance,
    ``sqrt(blur_mm^2 - h^2 / 12)``, never less than half the measured blur.

    Parameters
    ----------
    blur_mm : float
        Blur measured on the image, mm.
    spacing_kji : array_like, shape (3,)
        Voxel size, mm.

    Returns
    -------
    float
    """
    return float(np.sqrt(max(blur_mm ** 2 - ramp_width(spacing_kji) ** 2 / 12.0, 0.25 * blur_mm ** 2)))


def ramp_width(spacing_kji) -> float:
    """Width (mm) of the partial-volume ramp of ``refine``'s lumen indicator: the finest voxel size."""
    return float(np.min(spacing_kji))


def model_blur(blur_mm: float, spacing_kji, slices: bool = True, thickness_mm: float | None = None) -> np.ndarray:
    """Standard deviation (mm) per axis (k, j, i) of the blur in ``refine``'s model: ``axis_blur`` with
    ``slices``, else ``blur_mm`` along every axis."""
    return axis_blur(blur_mm, spacing_kji, thickness_mm) if slices else np.full(3, float(blur_mm))


def axis_blur(blur_mm: float, spacing_kji, thickness_mm: float | None = None) -> np.ndarray:
    """Standard deviation (mm) of the blur along each axis: ``sqrt(blur_mm^2 + (w_a^2 - h_min^2) / 12)``,
    at least the boxcar's own ``w_a / sqrt(12)``.

    A voxel integrates the image over its own extent ``w_a``, a boxcar of variance ``w_a^2 / 12`` along each
    axis: the voxel size in plane, and along the slice axis k the slice thickness when the scan records one
    (overlapping reconstructions, 1 mm slices every 0.5 mm, are the rule in CT angiography), else the slice
    spacing.  The blur measured on a vessel's edges (``intensity.edge_blur``), whose normals run across the
    vessel and so mostly within the slices, holds the boxcar of the finest voxel size ``h_min``; a thicker
    slice (0.5 x 0.5 x 1.0 mm, an MR angiogram's 1.5 mm slices) adds the rest of its own along its axis.  A
    short, tight stenosis is concave along the vessel, and a model blurred too little along it matches the
    brighter throat the slices leave with a wider wall.

    Parameters
    ----------
    blur_mm : float
        Blur measured within the slices, mm.
    spacing_kji : array_like, shape (3,)
        Voxel size, mm.
    thickness_mm : float, optional
        Slice thickness along k, mm; None: the slice spacing.

    Returns
    -------
    ndarray, shape (3,)
    """
    h = np.asarray(spacing_kji, float)
    width = h.copy()
    if thickness_mm is not None:
        width[0] = thickness_mm
    return np.sqrt(np.maximum(blur_mm ** 2 + (width ** 2 - h.min() ** 2) / 12.0, width ** 2 / 12.0))


def lumen_level(image: np.ndarray, tissue: np.ndarray, phi: np.ndarray, core: np.ndarray, spacing,
                blur_mm, ramp_mm: float, scale_mm: float, default: float,
                linear: np.ndarray | None = None) -> np.ndarray:
    """Lumen level ``A`` followed along the vessel, with the blur taken out of the core it is read on.

    Even two blur widths inside the wall the blur still mixes tissue into the lumen (2 % of the contrast at a
    flat wall, 4 % at the axis of a 2 mm vessel blurred by 0.8 mm), so the plain mean of a core is too dark,
    and a model built on it too dark near the wall, which the descent then pushes out.  Under the model a
    voxel holds ``A f + G * (B (1 - H(-phi)))``, ``f = G * H(-phi)`` the lumen fraction the blur leaves it,
    so each core voxel gives ``A = (I - G * (B (1 - H))) / f``; their Gaussian-weighted mean over
    ``scale_mm`` (``intensity.local_level``) follows the bolus fade and an MR bias field.

    Parameters
    ----------
    image, tissue, phi : ndarray, float32, shape (nk, nj, ni)
        The image, the tissue level ``B`` and the signed distance (mm) of the wall.
    core : ndarray of bool, same shape
        Voxels deep in the lumen and clear of anything the model leaves out.
    spacing : array_like, shape (3,)
    blur_mm : float or array_like, shape (3,)
        The blur's standard deviation (per axis), mm.
    ramp_mm : float
        The partial-volume ramp's width, mm.
    scale_mm : float
        Scale of the Gaussian mean, mm.
    default : float
        Level where no core voxel lies within reach.
    linear : ndarray of bool, same shape, optional
        Voxels where the level is a local linear fit (``intensity.local_linear_level``) rather than a local
        mean; None: nowhere.

    Returns
    -------
    ndarray, float32, same shape
    """
    sigma = blur_mm / np.asarray(spacing, float)
    inside = np.clip(np.float32(0.5) - phi / np.float32(ramp_mm), 0, 1)
    fraction = ndimage.gaussian_filter(inside, sigma)
    core = core & (fraction > np.float32(0.5))
    if not core.any():
        return np.full(phi.shape, default, np.float32)
    outside = ndimage.gaussian_filter(tissue * (1 - inside), sigma)
    unblurred = (image - outside) / np.maximum(fraction, np.float32(0.5))
    if linear is not None:
        return local_linear_level(unblurred, core, spacing, scale_mm, default, linear)
    return local_level(unblurred, core, spacing, scale_mm, default)


def bright_neighbours(image: np.ndarray, phi: np.ndarray, spacing, blur_mm: float, lumen: float,
                      background: float, fraction: float = TISSUE_FRACTION) -> np.ndarray:
    """Voxels beyond the reach of the wall's blur brighter than the tissue by ``fraction`` of the contrast.

    Beyond two blur widths (and a voxel) outside the wall, the lumen's own blur adds at most a few per cent
    of its contrast; what exceeds the tissue level ``B`` by a quarter of the contrast ``A - B`` there is
    another enhancing structure (a jugular vein, an artery the front never reached, enhancing bone), and
    the same quarter bounds the tissue in ``calcium``.  Sampled as tissue, its level raises the model's
    background, and the wall facing it is pulled into the lumen by the whole bound of one blur width (a
    jugular vein 1-2 mm from the ICA of a contrast-enhanced MR angiogram blurred by 0.67 mm: the throat
    graded 14 NASCET points too tight).  Decided on the image smoothed by the blur, so that the tissue's
    noise does not cross the level.

    Parameters
    ----------
    image : ndarray, float32, shape (nk, nj, ni)
    phi : ndarray, float32, same shape
        Signed distance to the wall, mm, negative inside.
    spacing : array_like, shape (3,)
    blur_mm : float
    lumen, background : float
        Lumen and tissue levels ``A`` and ``B``.
    fraction : float

    Returns
    -------
    ndarray of bool, same shape
    """
    spacing = np.asarray(spacing, float)
    beyond = phi > np.float32(2.0 * blur_mm + spacing.min())
    if not beyond.any():
        return beyond
    level = np.float32(background + fraction * (lumen - background))
    return beyond & (ndimage.gaussian_filter(image, blur_mm / spacing) > level)


def local_background(image: np.ndarray, phi: np.ndarray, spacing, blur_mm: float, exclude: np.ndarray | None,
                     default: float, width_mm: float = 2.0, scale_mm: float = 3.0) -> np.ndarray:
    """Tissue level around the lumen: Gaussian-weighted mean over a shell beyond the blur's reach.

    The shell lies between ``2.5 blur_mm`` and ``2.5 blur_mm + width_mm`` outside the wall (``exclude`` left
    out); ``scale_mm`` is the Gaussian of the normalised convolution (``intensity.local_level``).

    Returns
    -------
    ndarray, float32, ``image``'s shape
    """
    inner = 2.5 * blur_mm
    shell = (phi > inner) & (phi < inner + width_mm)
    if exclude is not None:
        shell &= ~exclude
    return local_level(image, shell, spacing, scale_mm, default)


def normal_background(image: np.ndarray, phi: np.ndarray, spacing, blur_mm: float, exclude: np.ndarray | None,
                      fallback: np.ndarray, width_mm: float = 1.5, samples: int = 4) -> np.ndarray:
    """Tissue level each voxel near the wall sees: the image along its wall normal, beyond the blur's reach.

    The shell mean of ``local_background`` averages whatever lies around the vessel over millimetres, and
    where fat (-100 HU) and muscle (+50 HU) meet along the wall it puts the level between the two, so the
    model pulls the wall in beside the fat and pushes it out beside the muscle.  Here the level of a voxel
    at signed distance ``phi`` is the mean of the (trilinear) image at ``samples`` points on its normal
    ``grad phi``, from ``2.5 blur_mm`` to ``2.5 blur_mm + width_mm`` outside the wall (from the voxel itself
    outward beyond that): the tissue that the blur mixes into that voxel.  A sample is dropped where it lies
    in ``exclude`` or within the blur's reach of another part of the wall (a neighbouring branch, whose lumen
    the normal may enter); where every sample is dropped, and deep inside the lumen, ``fallback`` is kept.

    Parameters
    ----------
    image : ndarray, float32, shape (nk, nj, ni)
    phi : ndarray, float32, same shape
        Signed distance to the wall, mm, negative inside.
    spacing : array_like, shape (3,)
        Voxel size (k, j, i), mm.
    blur_mm : float
        Standard deviation of the image's blur, mm.
    exclude : ndarray of bool, same shape, or None
        Voxels whose intensity is not tissue (neighbours held out, calcium).
    fallback : ndarray, float32, same shape
        Level kept where no sample is valid (``local_background``).
    width_mm : float
        Length of the sampled stretch of the normal, mm.
    samples : int
        Points on it.

    Returns
    -------
    ndarray, float32, same shape
    """
    spacing = np.asarray(spacing, np.float32)
    inner = np.float32(2.5 * blur_mm)
    near = np.nonzero(phi > -np.float32(blur_mm + 2.0 * spacing.max()))
    grad = np.stack([g[near] for g in np.gradient(phi, *spacing)])
    grad /= np.maximum(np.linalg.norm(grad, axis=0), np.float32(1e-6))
    start = np.maximum(inner - phi[near], 0)
    index = np.stack(near).astype(np.float32)
    total = np.zeros(start.shape, np.float32)
    count = np.zeros(start.shape, np.float32)
    for offset in np.linspace(0.0, width_mm, samples, dtype=np.float32):
        points = index + grad * ((start + offset) / spacing[:, None])
        valid = ndimage.map_coordinates(phi, points, order=1, mode="nearest") > np.float32(0.9) * inner
        if exclude is not None:
            valid &= ~ndimage.map_coordinates(exclude, points, order=0, mode="nearest")
        total += np.where(valid, ndimage.map_coordinates(image, points, order=1, mode="nearest"), 0)
        count += valid
    out = np.array(fallback, np.float32, copy=True)
    out[near] = np.where(count > 0, total / np.maximum(count, 1), out[near])
    return out
