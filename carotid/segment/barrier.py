"""Where the lumen cannot be: what keeps the front out of touching neighbours.

The GPF potential, a long-range integral, is negative in the thin, blurred gap
between the artery and an enhancing vein or a neighbouring artery 0.3-2 mm
away (both sides are bright), and once the front has crossed such a gap it
runs along the whole neighbour.  Three mechanisms, each a set of voxels where
the force is set to push the front out, keep it in the lumen:

* ``half_level_barrier``: a blurred wall lies where the intensity has fallen
  half-way from the lumen to its surroundings, so a voxel below half of the
  brightest value within 3 mm is not lumen.  The threshold follows that local
  maximum, so a fading bolus or an MR bias field does not move it, and a dimmer
  structure touching the lumen (fat in a time-of-flight MRA) is held over about
  2 mm beyond the blurred wall.  It acts in the capture stage, where it holds a
  gap that dips below half; there a short, tight throat dimmed by the blur may
  fall under half of the wider lumen within reach, which only narrows the
  captured front: the refining stage, without it, takes the throat's wall back.
* ``under_enhanced`` and ``competing_region``: a wide region (a plateau) that
  stays below 80 % of the brightest lumen nearby is a neighbour with less
  contrast, however thin and blurred the gap to it.  Its core is found by a
  minimum filter; a marker-based watershed between it and the lumen's markers
  then gives it everything up to the darkest surface between them, the gap.
* the user's stop points (VMTK's stoppers, 3D Slicer's background seeds) are
  markers of that same watershed, for a neighbour as bright as the lumen.
* ``chamber_cores``: a cavity as bright as the lumen and joined to it without
  any gap (a heart chamber behind an open valve) is told by its size: where the
  captured region is much wider than the vessel at the seeds, its core becomes
  a marker of that same watershed, which cuts at the darkest surface between;
  ``chamber_neck`` moves that cut back to the narrowest section within a
  vessel radius (an open valve's annulus), where nothing darker marks it.
* ``companion_basins``: a neighbour as bright as the lumen (a jugular vein at
  80-90 % of the artery's enhancement, where the bolus has faded along the
  artery) behind a gap of a few tenths of a millimetre, which the blur leaves
  at 70-80 % of the contrast, above every threshold above, is told by its
  shape: the captured region's bright basins, cut where the intensity dips,
  follow one another along a vessel (the dimmer throat of a stenosis between
  two), but a companion lies beside the vessel, joined along its length.
  Its basin becomes a marker of the same watershed.

A gap to a neighbour as bright as the lumen that dips too little for a basin
of its own (the companions' ``depth``, 5 % of the contrast after a 0.5 mm
smoothing), or a neighbour that joins the vessel end to end, is not seen by
any of them: that limit is reported, not hidden.  The filters are scipy's and
scikit-image's.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from carotid.segment.intensity import region_box
from carotid.segment.preprocess import gaussian_filter, maximum_filter


def half_level_barrier(contrast: np.ndarray, spacing_kji, fraction: float = 0.5, sigma_mm: float = 0.3,
                       reach_mm: float = 3.0) -> np.ndarray:
    """Voxels darker than ``fraction`` of the brightest lumen-like value around them.

    Parameters
    ----------
    contrast : ndarray, shape (nk, nj, ni), float32
        Image in units of the lumen contrast: ``(I - B) / (A - B)``, 0 background, 1 lumen
        (``A`` may vary along the vessel).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm.
    fraction : float
        Half level: 0.5 for a symmetric blur.
    sigma_mm : float
        Gaussian smoothing (mm) against noise, at least half a voxel.
    reach_mm : float
        Half-width (mm) of the box in which the local maximum is taken.  The barrier
        reaches this far from the lumen into a dimmer structure touching it, less the
        blurred wall's width: about 2 mm at 3 mm.

    Returns
    -------
    ndarray of bool, same shape
    """
    spacing_kji = np.asarray(spacing_kji, float)
    smooth = _smooth(contrast, spacing_kji, sigma_mm)
    peak = maximum_filter(smooth, size=_box(reach_mm, spacing_kji))
    return smooth < np.float32(fraction) * peak


def half_maximum_speed(contrast: np.ndarray, spacing_kji, sigma_mm: float = 0.3, reach_mm: float = 1.5,
                       width: float = 0.1) -> np.ndarray:
    """A force whose zero is the lumen's half-maximum surface: ``tanh((peak / 2 - I) / width)``.

    ``peak`` is the brightest smoothed contrast within ``reach_mm`` (at most the lumen
    level): the lumen level for a lumen wider than the blur, whose blurred wall lies at
    half of it; its own dimmed peak for a lumen narrower than the blur (a tight
    stenosis), whose half-maximum radius stays close to the true one.  On a convex
    wall the half level lies inside by about ``sigma^2 kappa / 2`` (sigma the blur,
    kappa the mean curvature), opposite to the GPF potential's outward bias.
    Negative inside (the front expands), positive outside, like the normalised potential.

    Parameters
    ----------
    contrast : ndarray, shape (nk, nj, ni), float32
        Image in units of the lumen contrast (0 background, 1 lumen).
    spacing_kji : array_like, shape (3,)
    sigma_mm : float
        Gaussian smoothing (mm) against noise, at least half a voxel.
    reach_mm : float
        Half-width (mm) of the box in which the peak is taken.
    width : float
        Contrast over which the force saturates.

    Returns
    -------
    ndarray, float32, same shape, in (-1, 1)
    """
    spacing_kji = np.asarray(spacing_kji, float)
    smooth = _smooth(contrast, spacing_kji, sigma_mm)
    peak = maximum_filter(smooth, size=_box(reach_mm, spacing_kji))
    return np.tanh((np.float32(0.5) * peak - smooth) / np.float32(width)).astype(np.float32)


def _smooth(contrast: np.ndarray, spacing_kji: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Gaussian-smoothed contrast (at least half a voxel), capped at the lumen level 1."""
    sigma = np.maximum(sigma_mm, 0.5 * spacing_kji) / spacing_kji
    return gaussian_filter(np.minimum(contrast, np.float32(1.0)), sigma)


def _box(half_width_mm: float, spacing_kji: np.ndarray) -> tuple[int, ...]:
    """Odd box size (voxels per axis) of a half-width in mm, at least 3."""
    return tuple(2 * np.maximum(np.round(half_width_mm / spacing_kji), 1).astype(int) + 1)


def under_enhanced(contrast: np.ndarray, spacing_kji, level: float = 0.8, width_mm: float = 2.0,
                   reach_mm: float = 10.0, sigma_mm: float = 0.5) -> np.ndarray:
    """Cores of plateaus dimmer than ``level`` of the brightest lumen nearby: enhancing neighbours.

    A lumen narrower than the blur looks dimmer than the lumen level, but only over
    a width of the order of the blur.  A region at least ``width_mm`` wide in every
    direction (all voxels within that half-width above half of its own value) whose
    intensity stays below ``level`` of the brightest value within ``reach_mm`` is a
    wide structure with less contrast: a vein, a false lumen, a neighbouring artery
    further from the bolus.  Only its core is returned (it lies ``width_mm`` inside
    the neighbour); ``competing_region`` finds the rest of it, up to the gap.

    Parameters
    ----------
    contrast : ndarray, shape (nk, nj, ni), float32
        Image in units of the lumen contrast (0 background, 1 lumen).
    spacing_kji : array_like, shape (3,)
    level : float
        Fraction of the local lumen brightness below which a plateau is a neighbour.
    width_mm : float
        Half-width (mm) a plateau must exceed: above about 2.5 blur standard deviations,
        where the blur no longer dims a lumen.
    reach_mm : float
        Half-width (mm) of the box in which the lumen brightness is taken.
    sigma_mm : float
        Gaussian smoothing (mm) against noise.

    Returns
    -------
    ndarray of bool, same shape
    """
    spacing_kji = np.asarray(spacing_kji, float)
    smooth = _smooth(contrast, spacing_kji, sigma_mm)
    brightest = maximum_filter(_smooth(contrast, spacing_kji, 2.0 * sigma_mm), size=_box(reach_mm, spacing_kji))
    dim = (smooth < np.float32(level) * brightest) & (smooth > np.float32(0.1))
    return dim & (ndimage.minimum_filter(smooth, size=_box(width_mm, spacing_kji)) >= np.float32(0.5) * smooth)


def competing_region(contrast: np.ndarray, lumen: np.ndarray, others: np.ndarray, spacing_kji,
                     floor: float = 0.25, sigma_mm: float = 0.5) -> np.ndarray:
    """The part of the bright structures nearer ``others`` than the ``lumen`` markers.

    A marker-based watershed (scikit-image) on the inverted, smoothed contrast grows
    both sets of markers together through the voxels brighter than ``floor``; they
    meet along the darkest surface between them, the gap to a neighbour where there
    is one, however blurred.  The neighbours' markers are the user's stop points
    (VMTK's stoppers, 3D Slicer's background seeds) and the cores of under-enhanced
    plateaus (``under_enhanced``).

    Parameters
    ----------
    contrast : ndarray, shape (nk, nj, ni), float32
        Image in units of the lumen contrast (0 background, 1 lumen).
    lumen, others : ndarray of bool, same shape
        Markers of the lumen (seeds, initial region) and of what must stay out of it.
    spacing_kji : array_like, shape (3,)
    floor : float
        Contrast below which voxels take part in neither region.
    sigma_mm : float
        Gaussian smoothing (mm) before the watershed.

    Returns
    -------
    ndarray of bool, same shape
    """
    from skimage.segmentation import watershed

    smooth = _smooth(contrast, np.asarray(spacing_kji, float), sigma_mm)
    markers = np.where(others, np.int32(2), np.int32(0))
    markers[lumen] = 1
    mask = (smooth > np.float32(floor)) | (markers > 0)
    return watershed(-smooth, markers, mask=mask) == 2


def chamber_cores(region: np.ndarray, seeds_kji: np.ndarray, spacing_kji, ratio: float = 2.0,
                  reach_mm: float = 20.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Cores of the chambers a captured region has run into, and markers of the vessel before them.

    A vessel's radius changes slowly along it; a cavity the front reaches through an open valve (a heart
    chamber) is much wider than the vessel it came from.  The vessel's radius ``R`` is the largest
    inscribed radius of the region within ``reach_mm`` of the seeds, measured through the region (a
    geodesic distance, scikit-image's ``MCP_Geometric``).  Where the inscribed radius exceeds
    ``ratio R``, the region is in a chamber.  The chamber's body is the union of its inscribed balls;
    the vessel's markers are the voxels of the region nearer the seeds, through the region, than any
    chamber body by more than ``R``.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
        The captured lumen.
    seeds_kji : ndarray, shape (m, 3)
        Continuous array indices of the seeds.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm.
    ratio : float
        How many vessel radii a chamber's inscribed radius exceeds.
    reach_mm : float
        Geodesic distance (mm) from the seeds over which the vessel's radius is taken.

    Returns
    -------
    cores, vessel : ndarray of bool, shape of ``region``
        The chambers' cores (inscribed radius above ``ratio R``) and the vessel's markers; both empty
        when there is no chamber.
    radius : float
        ``R`` in mm (0 for an empty region).
    """
    spacing_kji = np.asarray(spacing_kji, float)
    cores = np.zeros(region.shape, bool)
    vessel = np.zeros(region.shape, bool)
    box = region_box(region, spacing_kji, float(spacing_kji.max()))  # one voxel of background around it
    if box is None:
        return cores, vessel, 0.0
    sub = ndimage.binary_fill_holes(region[box])  # holes in a cavity (noise, trabeculae) are not its wall
    depth = ndimage.distance_transform_edt(sub, sampling=spacing_kji)
    geodesic = _geodesic(sub, np.atleast_2d(seeds_kji) - np.array([s.start for s in box]), spacing_kji)
    near = geodesic <= reach_mm
    radius = float(depth[near].max()) if near.any() else 0.0
    core = (depth > ratio * radius) & np.isfinite(geodesic)
    if radius == 0.0 or not core.any():
        return cores, vessel, radius
    distance, owner = ndimage.distance_transform_edt(~core, sampling=spacing_kji, return_indices=True)
    body = distance < depth[tuple(owner)]
    cores[box] = core
    vessel[box] = np.isfinite(geodesic) & (geodesic < float(geodesic[body].min()) - radius)
    return cores, vessel, radius


def companion_basins(region: np.ndarray, contrast: np.ndarray, seeds_kji: np.ndarray, spacing_kji,
                     depth: float = 0.05, sigma_mm: float = 0.5, tube_mm: float = 2.0, across: float = 0.3,
                     min_volume_mm3: float = 20.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Markers of the vessel and of the bright neighbours the captured region runs beside (companions).

    A front that crosses a gap to a neighbour as bright as the lumen captures both, and the gap stays in the
    image as a dip of the intensity between them.  The captured region's smoothed contrast is cut into basins
    around its maxima that stand ``depth`` above every path to a brighter one (scikit-image's ``h_maxima``,
    then a watershed): the vessel at the seeds, a vessel beyond the dimmer throat of a stenosis, and a
    neighbour behind a gap.  A vessel beyond a throat follows the seeds' basin along the vessel: their
    common surface faces along the vessel's axis.  A neighbour lies beside it: the surface faces across.  The
    axis is the direction along which the contrast smoothed over ``tube_mm`` curves least (the eigenvector
    of its Hessian whose eigenvalue is nearest zero), read on a grid of ``tube_mm / 2``; the surface's
    normal is the gradient of its basin's smoothed indicator.  A basin without a seed, touching the seeds'
    basins, of at least ``min_volume_mm3``, whose surface with them has a median ``|normal . axis|`` below
    ``across`` is a companion, unless it joins seeds that the region holds apart without it
    (``linking_seeds``): a neighbour lies beside the seeds' vessel, never between two of its seeds, while a
    kink of the vessel between two seeds can be a basin of its own, and the axis read across a kink is not
    the vessel's.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
        The captured lumen.
    contrast : ndarray, float32, same shape
        Image in units of the lumen contrast (0 background, 1 lumen).
    seeds_kji : ndarray, shape (m, 3)
        Continuous array indices of the seeds.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm.
    depth : float
        Least dip (contrast units) between two basins.
    sigma_mm : float
        Gaussian smoothing (mm) of the contrast against noise.
    tube_mm : float
        Scale (mm) of the vessel's axis.
    across : float
        Largest median ``|cos|`` between the surface's normal and the axis for a companion.
    min_volume_mm3 : float
        Smallest companion.

    Returns
    -------
    (vessel, companions) : tuple of ndarray of bool, shape of ``region``, or None
        The seeds' basins and the companions' (parts of ``region``); None when there is no companion.
    """
    from skimage.morphology import h_maxima
    from skimage.segmentation import watershed

    spacing_kji = np.asarray(spacing_kji, float)
    box = region_box(region, spacing_kji, 2.0 * tube_mm)
    if box is None:
        return None
    inside = region[box]
    capped = np.minimum(contrast[box], np.float32(1.0))
    smooth = np.where(inside, _smooth(capped, spacing_kji, sigma_mm), np.float32(0.0))
    peaks, n = ndimage.label(h_maxima(smooth, depth) & inside, structure=np.ones((3, 3, 3), bool))
    if n < 2:
        return None
    basins = watershed(-smooth, peaks, mask=inside)
    starts = _nearest_voxels(basins > 0, np.atleast_2d(seeds_kji) - [s.start for s in box])
    seeded = np.isin(basins, [basins[start] for start in starts])
    touching = ndimage.binary_dilation(seeded) & ~seeded & (basins > 0)
    volumes = np.bincount(basins.ravel(), minlength=n + 1) * float(np.prod(spacing_kji))
    candidates = [b for b in np.unique(basins[touching]) if volumes[b] >= min_volume_mm3]
    if not candidates:
        return None
    surfaces = touching & np.isin(basins, candidates)
    axis = np.zeros(basins.shape + (3,), np.float32)
    axis[surfaces] = tube_axes(capped, spacing_kji, tube_mm, np.nonzero(surfaces))
    pad = np.ceil(4.0 / spacing_kji).astype(int) + 2  # the 1 mm Gaussian's reach, and a voxel for the gradient
    extents = ndimage.find_objects(basins)
    found = []
    for basin in candidates:
        sub = tuple(slice(max(e.start - p, 0), e.stop + p) for e, p in zip(extents[basin - 1], pad))
        own = basins[sub] == basin
        surface = np.nonzero(surfaces[sub] & own)
        normal = np.stack(np.gradient(gaussian_filter(own.astype(np.float32), 1.0 / spacing_kji), *spacing_kji),
                          axis=-1)[surface]
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), np.float32(1e-6))
        if np.median(np.abs(np.einsum("ni,ni->n", normal, axis[sub][surface]))) < across:
            found.append(basin)
    links = linking_seeds(basins, found, starts)
    found = [basin for basin in found if basin not in links]
    if not found:
        return None
    vessel, companions = np.zeros(region.shape, bool), np.zeros(region.shape, bool)
    vessel[box] = seeded
    companions[box] = np.isin(basins, found)
    return vessel, companions


def linking_seeds(basins: np.ndarray, companions: list[int], starts: list[tuple[int, int, int]]) -> set[int]:
    """The basins of ``companions`` that join seeds the labelled region holds apart once every one of
    ``companions`` is taken out.

    Parameters
    ----------
    basins : ndarray of int, shape (nk, nj, ni)
        Basin labels of the region (0 outside it).
    companions : list of int
        Basins taken for companions.
    starts : list of tuple
        The seeds' voxels (indices into ``basins``), each in a basin that is not a companion.

    Returns
    -------
    set of int
        Each companion with which the seeds lie in fewer connected pieces (face connectivity, as the lumen's
        pieces are counted) than without all of them.
    """
    def pieces(out: list[int]) -> int:
        labels, _ = ndimage.label((basins > 0) & ~np.isin(basins, out))
        return len({int(labels[start]) for start in starts} - {0})

    apart = pieces(companions)
    return {basin for basin in companions if pieces([b for b in companions if b != basin]) < apart}


def tube_axes(contrast: np.ndarray, spacing_kji, scale_mm: float, points: tuple) -> np.ndarray:
    """Direction of least curvature of the contrast smoothed over ``scale_mm`` at ``points``: a tube's axis.

    The smoothed image is sampled every ``scale_mm / 2`` (at least a voxel) along each axis and its Hessian
    taken by central differences on that grid; at the grid point holding each of ``points`` the eigenvector
    whose eigenvalue is nearest zero is kept: along a bright tube the intensity hardly curves, across it it
    falls off on either side.

    Parameters
    ----------
    contrast : ndarray, float32, shape (nk, nj, ni)
    spacing_kji : array_like, shape (3,)
    scale_mm : float
    points : tuple of 3 ndarray of int, shape (n,)
        Voxel indices (``np.nonzero`` form).

    Returns
    -------
    ndarray, float32, shape (n, 3)
        Unit vectors (k, j, i components, mm).
    """
    spacing_kji = np.asarray(spacing_kji, float)
    step = np.maximum(np.floor(0.5 * scale_mm / spacing_kji), 1).astype(int)
    coarse = gaussian_filter(contrast, scale_mm / spacing_kji)[::step[0], ::step[1], ::step[2]]
    h = spacing_kji * step
    cells, where = np.unique(np.stack([np.minimum(p // s, m - 1) for p, s, m in zip(points, step, coarse.shape)]),
                             axis=1, return_inverse=True)
    hessian = np.stack([np.stack([d[tuple(cells)] for d in np.gradient(g, *h)], axis=-1)
                        for g in np.gradient(coarse, *h)], axis=-2)
    values, vectors = np.linalg.eigh(0.5 * (hessian + np.swapaxes(hessian, -1, -2)))
    flattest = np.argmin(np.abs(values), axis=-1)
    axes = np.take_along_axis(vectors, flattest[:, None, None], axis=-1)[..., 0]
    return axes[where.ravel()].astype(np.float32)


def chamber_neck(region: np.ndarray, chamber: np.ndarray, seeds_kji: np.ndarray, spacing_kji,
                 margin_mm: float) -> np.ndarray:
    """A chamber cut from its vessel at the narrowest section between them rather than at the darkest one.

    The watershed on the image (``competing_region``) cuts a chamber from its vessel along the darkest
    surface between them: a closed valve, a gap.  Behind an open valve the blood is uniformly bright, that
    surface can lie anywhere between the valve and the cavity, and the outflow tract before it stays on the
    vessel's side.  A cavity joins its vessel at a neck (a valve's annulus, an aneurysm's neck), where the
    captured region is narrowest.  A marker-based watershed (scikit-image) on the inscribed radius, the
    negated distance to the region's boundary, grows the chamber and the vessel more than ``margin_mm``
    from it (measured through the region from the seeds) together, deepest voxels first; they meet at the
    narrowest section in between.  The chamber only grows, by at most ``margin_mm`` of vessel.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
        The captured lumen.
    chamber : ndarray of bool, same shape
        What the image's watershed gave the chamber (part of ``region``).
    seeds_kji : ndarray, shape (m, 3)
        Continuous array indices of the seeds.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm.
    margin_mm : float
        Length of vessel (mm, through the region) before the chamber within which the cut may move.

    Returns
    -------
    ndarray of bool, shape of ``region``
        The chamber, grown to the neck.
    """
    from skimage.segmentation import watershed

    spacing_kji = np.asarray(spacing_kji, float)
    box = region_box(region, spacing_kji, float(spacing_kji.max()))
    if box is None or not chamber[box].any():
        return chamber
    filled = ndimage.binary_fill_holes(region[box])
    own = chamber[box]
    vessel = filled & ~own
    geodesic = _geodesic(vessel, np.atleast_2d(seeds_kji) - np.array([s.start for s in box]), spacing_kji)
    touching = ndimage.binary_dilation(own) & np.isfinite(geodesic)
    if not touching.any():
        return chamber
    markers = np.where(own, np.int32(2), np.int32(0))
    markers[geodesic < float(geodesic[touching].min()) - margin_mm] = 1
    depth = ndimage.distance_transform_edt(filled, sampling=spacing_kji)
    out = chamber.copy()
    out[box] |= (watershed(-depth, markers, mask=filled) == 2) & region[box]
    return out


def _geodesic(region: np.ndarray, seeds_kji: np.ndarray, spacing_kji: np.ndarray) -> np.ndarray:
    """Distance (mm) through ``region`` from the region's voxels nearest the seeds (scikit-image's
    ``MCP_Geometric``); inf outside the region and where it is not connected to a seed.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
    seeds_kji : ndarray, shape (m, 3)
        Continuous array indices of the seeds in ``region``'s grid (clipped to it).
    spacing_kji : ndarray, shape (3,)
        Voxel size in mm.
    """
    from skimage.graph import MCP_Geometric

    starts = set(_nearest_voxels(region, seeds_kji))
    geodesic, _ = MCP_Geometric(np.where(region, 1.0, np.inf), sampling=tuple(spacing_kji)).find_costs(list(starts))
    return geodesic


def _nearest_voxels(region: np.ndarray, points_kji: np.ndarray) -> list[tuple[int, int, int]]:
    """For each point (continuous array indices, shape (m, 3), rounded and clipped to the grid), the voxel of
    ``region`` nearest it (``distance_transform_edt``'s indices)."""
    nearest = ndimage.distance_transform_edt(~region, return_distances=False, return_indices=True)
    idx = np.clip(np.round(np.atleast_2d(points_kji)).astype(int), 0, np.asarray(region.shape) - 1)
    return [tuple(int(nearest[a][tuple(i)]) for a in range(3)) for i in idx]


def point_mask(points_kji: np.ndarray, shape) -> np.ndarray:
    """Boolean volume with the voxels nearest the given continuous indices (m, 3) set."""
    out = np.zeros(shape, bool)
    idx = np.clip(np.round(np.atleast_2d(points_kji)).astype(int), 0, np.asarray(shape) - 1)
    out[tuple(idx.T)] = True
    return out
