"""Initial level sets: seed spheres, a given initial region, or automatic from the image."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.segment.intensity import MAD_TO_SD

FORK_FIT = 0.75
"""Smallest ``fork_score`` of a start that forks: a Y whose trunk and branches each hold one piece in at least
three slices of four."""


def grid_mm(shape) -> list[np.ndarray]:
    """Open grid of index coordinates (broadcastable (nk,1,1), (1,nj,1), (1,1,ni)), float32."""
    return [np.arange(n, dtype=np.float32).reshape([-1 if a == b else 1 for b in range(3)])
            for a, n in enumerate(shape)]


def check_points(volume: Volume, points_xyz: np.ndarray, what: str) -> None:
    """Raise CarotidError if a world point (mm) is not finite or lies outside the image."""
    points = np.atleast_2d(np.asarray(points_xyz, float))
    if not np.isfinite(points).all():
        bad = points[~np.isfinite(points).all(axis=1)][0]
        raise CarotidError(f"{what} ({bad[0]:g}, {bad[1]:g}, {bad[2]:g}) mm is not a finite point")
    outside = ~volume.contains(points)
    if outside.any():
        bad = np.atleast_2d(points_xyz)[outside][0]
        lo = volume.index_to_world(np.zeros(3))
        hi = volume.index_to_world(np.asarray(volume.array.shape) - 1)
        raise CarotidError(f"{what} ({bad[0]:.1f}, {bad[1]:.1f}, {bad[2]:.1f}) mm lies outside the image "
                           f"(corners {np.round(lo, 1).tolist()} and {np.round(hi, 1).tolist()} mm)")


def seed_levelset(volume: Volume, seeds_xyz: np.ndarray, radius_mm) -> np.ndarray:
    """Signed distance (mm) to the union of spheres of ``radius_mm`` around world seed points.

    Parameters
    ----------
    volume : Volume
        Grid on which the level set lives.
    seeds_xyz : ndarray, shape (m, 3)
        Seed points (x, y, z) in world mm.
    radius_mm : float or array_like, shape (m,)
        Sphere radius, one for all or one per seed.

    Returns
    -------
    ndarray, shape volume.array.shape, float32, negative inside the spheres

    Raises
    ------
    CarotidError
        If a seed lies outside the image.
    """
    seeds_xyz = np.atleast_2d(np.asarray(seeds_xyz, float))
    check_points(volume, seeds_xyz, "seed")
    return ball_levelset(volume.array.shape, volume.world_to_index(seeds_xyz), radius_mm, volume.spacing_kji)


def ball_levelset(shape, centres_kji: np.ndarray, radius_mm, spacing_kji) -> np.ndarray:
    """Signed distance (mm, float32, negative inside) to the union of balls on a grid of ``shape``.

    Parameters
    ----------
    shape : tuple of 3 int
    centres_kji : ndarray, shape (m, 3)
        Ball centres as (fractional) array indices.
    radius_mm : float or array_like, shape (m,)
        Ball radius, one for all or one per ball.
    spacing_kji : array_like, shape (3,)
        Voxel size, mm.

    Loops over the balls, not over voxels.
    """
    h = np.asarray(spacing_kji, np.float32)
    axes = grid_mm(shape)
    phi = np.full(shape, np.inf, np.float32)
    radii = np.broadcast_to(np.asarray(radius_mm, np.float32), (len(centres_kji),))
    for kji, radius in zip(centres_kji, radii):
        d2 = sum(((axes[a] - np.float32(kji[a])) * h[a]) ** 2 for a in range(3))
        np.minimum(phi, np.sqrt(d2) - radius, out=phi)
    return phi


def seed_sample(phi: np.ndarray, seeds_kji: np.ndarray) -> np.ndarray:
    """Voxels inside the seed spheres (``phi < 0``), plus the voxel nearest each seed (never empty).

    Parameters
    ----------
    phi : ndarray, shape (nk, nj, ni)
        Seed level set from ``seed_levelset``.
    seeds_kji : ndarray, shape (m, 3)
        Continuous array indices of the seeds.

    Returns
    -------
    ndarray of bool, same shape
    """
    sample = phi < 0
    idx = np.clip(np.round(seeds_kji).astype(int), 0, np.asarray(phi.shape) - 1)
    sample[tuple(idx.T)] = True
    return sample


def mask_levelset(mask: np.ndarray, spacing_kji) -> np.ndarray:
    """Approximate signed distance (mm) of a binary region, negative inside, from two EDTs."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise CarotidError("the initial region is empty")
    half = 0.5 * float(np.mean(spacing_kji))
    d_out = ndimage.distance_transform_edt(~mask, sampling=spacing_kji).astype(np.float32)
    d_in = ndimage.distance_transform_edt(mask, sampling=spacing_kji).astype(np.float32)
    return np.where(mask, half - d_in, d_out - half).astype(np.float32)


def automatic_region(image01: np.ndarray, ghat: np.ndarray, spacing_kji, excluded: np.ndarray | None = None,
                     min_volume_mm3: float = 10.0, min_length_mm: float = 10.0, min_depth_mm: float = 1.0,
                     min_core_mm: float = 1.5, core: float = -0.5, fork_fit: float = FORK_FIT,
                     fork_mm: float = 5.0) -> np.ndarray:
    """Find the arterial lumen's core without a seed.

    Candidates are voxels deep inside bright structures (``ghat < core``),
    not ``excluded`` (too bright to be lumen: bone and calcium in CT).  Their cores (at least
    ``min_depth_mm`` from the candidates' edge, which removes the thin bright
    rims that blur leaves around cortical bone and calcium) are split into
    connected regions; those at least ``min_volume_mm3`` large, ``min_length_mm``
    long and ``min_core_mm`` deep somewhere (a carotid's core is several mm
    across; the cortex of a bone is a thin shell) are kept.  A carotid
    bifurcation is one tube that forks into two (``fork_score``), a jugular
    vein one tube and bone an irregular set of pieces, and brightness alone
    cannot tell them apart (a vein brighter than the artery under an MR
    bias field, dense bone below the window's top in CT): the candidates
    that fork (a score of at least ``fork_fit``, each side at least
    ``fork_mm`` long) are preferred.  A thin branch (an ECA of 1.5 mm radius
    beside a wide bulb) can lose its core at that depth, which cuts the
    fork in pieces; when no candidate forks, the cores are taken again at
    half the depth.  Among the forking candidates (or all those kept at the
    full depth, when none forks at either) the one that is brightest and
    homogeneous (largest median minus one robust standard deviation: in an
    angiogram the arteries carry more contrast than the veins, and bone
    mixes bright cortex with darker marrow) is returned.

    Returns
    -------
    ndarray of bool, same shape

    Raises
    ------
    CarotidError
        If no bright tubular structure is found.
    """
    spacing_kji = np.asarray(spacing_kji, float)
    deep = ghat < core
    if excluded is not None:
        deep &= ~excluded
    if deep.sum() < 10:
        raise CarotidError("automatic initialisation found no bright structure; give a --seed")
    depth = ndimage.distance_transform_edt(deep, sampling=spacing_kji)
    first = None
    for level in (min_depth_mm, 0.5 * min_depth_mm):
        labels, ok, forks, score = _candidates(depth, image01, spacing_kji, level, min_volume_mm3, min_length_mm,
                                               min_core_mm, fork_mm, fork_fit)
        if forks.any():
            return labels == 1 + np.flatnonzero(forks)[np.argmax(score[forks])]
        first = first or (labels, ok, score)
    labels, ok, score = first
    if not labels.any():
        raise CarotidError("automatic initialisation found no bright structure; give a --seed")
    if not ok.any():
        raise CarotidError("automatic initialisation found no vessel-like structure; give a --seed")
    return labels == 1 + np.flatnonzero(ok)[np.argmax(score[ok])]


def _candidates(depth: np.ndarray, image01: np.ndarray, spacing_kji: np.ndarray, min_depth_mm: float,
                min_volume_mm3: float, min_length_mm: float, min_core_mm: float, fork_mm: float,
                fork_fit: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cores at least ``min_depth_mm`` deep, which of them are vessel-like and fork, and their brightness.

    Returns
    -------
    labels : ndarray of int, shape depth.shape
        The cores, labelled 1..n.
    ok, forks : ndarray of bool, shape (n,)
        Vessel-like (volume, length and depth as in ``automatic_region``); vessel-like and forking.
    score : ndarray, shape (n,)
        Median minus one robust standard deviation of ``image01`` over each core.
    """
    labels, n = ndimage.label(depth >= min_depth_mm)
    if n == 0:
        return labels, np.zeros(0, bool), np.zeros(0, bool), np.zeros(0)
    index = np.arange(1, n + 1)
    voxel = float(np.prod(spacing_kji))
    volumes = ndimage.sum_labels(np.ones_like(labels, np.float32), labels, index) * voxel
    medians = np.asarray(ndimage.median(image01, labels, index))
    deviation = np.abs(image01 - np.concatenate([[0.0], medians]).astype(np.float32)[labels])
    spreads = np.asarray(ndimage.median(deviation, labels, index))
    slices = ndimage.find_objects(labels)
    lengths = np.array([max((s.stop - s.start) * h for s, h in zip(sl, spacing_kji)) for sl in slices])
    thickness = np.asarray(ndimage.maximum(depth, labels, index))
    ok = (volumes >= min_volume_mm3) & (lengths >= min_length_mm) & (thickness >= min_core_mm)
    forks = np.zeros(n, bool)
    forks[ok] = [fork_score(labels[slices[i]] == i + 1, spacing_kji, fork_mm) >= fork_fit for i in np.flatnonzero(ok)]
    return labels, ok, forks, medians - MAD_TO_SD * spreads


def slice_pieces(region: np.ndarray, spacing_kji, min_area_mm2: float = 2.0) -> tuple[int, np.ndarray, np.ndarray]:
    """Cross-sections of a region along its longest axis: the pieces of each slice and how many there are.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
    spacing_kji : array_like, shape (3,)
    min_area_mm2 : float
        Smallest piece counted.

    Returns
    -------
    axis : int
        The longest axis (mm).
    pieces : ndarray of int, same shape as ``region``
        Labels of the pieces, each connected within one slice across ``axis`` (0 outside).
    counts : ndarray of int, shape (region.shape[axis],)
        Pieces of at least ``min_area_mm2`` in each slice.
    """
    spacing = np.asarray(spacing_kji, float)
    axis = int(np.argmax(np.asarray(region.shape) * spacing))
    within = np.zeros((3, 3, 3), bool)
    centre = [slice(None)] * 3
    centre[axis] = 1
    within[tuple(centre)] = ndimage.generate_binary_structure(2, 2)
    pieces, n = ndimage.label(region, structure=within)
    if n == 0:
        return axis, pieces, np.zeros(region.shape[axis], int)
    area = ndimage.sum_labels(np.ones(pieces.shape, np.float32), pieces, np.arange(1, n + 1)) * (
        float(np.prod(spacing)) / spacing[axis])
    where = np.array([s[axis].start for s in ndimage.find_objects(pieces)])
    return axis, pieces, np.bincount(where[area >= min_area_mm2], minlength=region.shape[axis])


def fork_step(counts: np.ndarray, step_mm: float, min_mm: float) -> tuple[float, int, bool]:
    """The step along the slices that best splits them into one piece on one side and two on the other.

    The score of a step is the smaller of the fraction of slices with one piece on the one side and with two
    on the other; only steps that leave at least ``min_mm`` on either side count.

    Parameters
    ----------
    counts : ndarray of int, shape (n,)
        Pieces per slice (``slice_pieces``).
    step_mm : float
        Slice spacing, mm.
    min_mm : float
        Shortest stretch (mm) of one piece and of two.

    Returns
    -------
    score : float
        The best step's score, 0 when no step leaves ``min_mm`` on both sides.
    step : int
        Slices before the step.
    trunk_first : bool
        True when the one-piece side comes first (lower slice indices).
    """
    one, two = np.cumsum(counts == 1), np.cumsum(counts == 2)
    total, step = len(counts), np.arange(1, len(counts))
    before, after = step, total - step
    if not len(step):
        return 0.0, 0, True
    one_two = np.minimum(one[:-1] / before, (two[-1] - two[:-1]) / after)  # one piece before the step, two after
    two_one = np.minimum(two[:-1] / before, (one[-1] - one[:-1]) / after)
    room = (before * step_mm >= min_mm) & (after * step_mm >= min_mm)
    scores = np.where(room, np.maximum(one_two, two_one), 0.0)
    best = int(np.argmax(scores))
    return float(scores[best]), int(step[best]), bool(one_two[best] >= two_one[best])


def fork_score(region: np.ndarray, spacing_kji, min_mm: float, min_area_mm2: float = 2.0) -> float:
    """How well a region reads as one tube forking into two, from its cross-sections along its longest axis.

    Each slice across that axis holds some pieces (``slice_pieces``).  A bifurcation is one piece up to some
    slice and two beyond it (or the reverse); the score is the best step's (``fork_step``): the smaller of the
    fraction of slices with one piece on the one side and with two on the other.  A straight tube scores 0, a
    clean fork about 1.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
    spacing_kji : array_like, shape (3,)
    min_mm : float
        Shortest stretch (mm) of one piece and of two.
    min_area_mm2 : float
        Smallest piece counted.

    Returns
    -------
    float
    """
    axis, _, counts = slice_pieces(region, spacing_kji, min_area_mm2)
    return fork_step(counts, float(np.asarray(spacing_kji, float)[axis]), min_mm)[0]


def fork_seeds(region: np.ndarray, spacing_kji, min_mm: float = 5.0, min_area_mm2: float = 2.0,
               tip_mm: float = 5.0, fork_fit: float = FORK_FIT) -> np.ndarray | None:
    """Seed points of a forking region: one in its trunk and one near the far end of each of its two branches.

    The region is split at its best fork step (``fork_step``).  The trunk's seed is its deepest voxel (the
    largest distance to the region's edge) among the one-piece slices; each branch is a connected part of the
    two-piece slices beyond the step (the two largest), and its seed is its deepest voxel within ``tip_mm`` of
    its far end.  Seeds so placed start the evolution in every branch, as a user's one seed per branch does,
    so the seeded segmentation (and its exclusion of touching veins and chambers) runs without a user.

    Parameters
    ----------
    region : ndarray of bool, shape (nk, nj, ni)
        The seedless start (``automatic_region``).
    spacing_kji : array_like, shape (3,)
    min_mm, min_area_mm2 : float
        As in ``fork_score``.
    tip_mm : float
        Length (mm) of a branch's end in which its seed is placed.
    fork_fit : float
        Smallest score of the fork step (``fork_step``): the one ``automatic_region`` asks of a forking start,
        so that a start taken because nothing forked gets no branch seeds.

    Returns
    -------
    ndarray, shape (3, 3), float, or None
        Array indices (k, j, i) of the trunk's seed and the two branches', or None when the region does not
        fork (a step scoring below ``fork_fit``, or fewer than two branches beyond it).
    """
    spacing = np.asarray(spacing_kji, float)
    axis, _, counts = slice_pieces(region, spacing, min_area_mm2)
    score, step, trunk_first = fork_step(counts, float(spacing[axis]), min_mm)
    if score <= 0 or score < fork_fit:
        return None
    position = np.arange(region.shape[axis]).reshape([-1 if a == axis else 1 for a in range(3)])
    trunk_side = position < step if trunk_first else position >= step
    depth = ndimage.distance_transform_edt(region, sampling=spacing)
    trunk = region & trunk_side & (counts == 1)[position]
    branches, n = ndimage.label(region & ~trunk_side & (counts == 2)[position])
    if not trunk.any() or n < 2:
        return None
    sizes = ndimage.sum_labels(np.ones(branches.shape, np.float32), branches, np.arange(1, n + 1))
    seeds = [np.unravel_index(np.argmax(np.where(trunk, depth, 0.0)), region.shape)]
    distal = position if trunk_first else -position
    tip = int(np.ceil(tip_mm / spacing[axis]))
    for label in np.argsort(sizes)[::-1][:2] + 1:
        branch = branches == label
        end = np.max(np.where(branch, distal, np.iinfo(np.int64).min))
        seeds.append(np.unravel_index(np.argmax(np.where(branch & (distal > end - tip), depth, 0.0)), region.shape))
    return np.array(seeds, float)
