"""Outer-wall stage: the whole vessel (lumen, non-enhancing thrombus and wall) around a segmented lumen.

A contrast-lumen model stops, rightly, at the lumen.  In an aortic dissection
(a thrombosed false lumen) or an aneurysm (mural thrombus) users also need the
vessel's outer boundary: thrombus volume, the whole aorta.  This stage runs the
same GPF evolution (eq. 1, ``levelset.evolve``) a second time, started from the
lumen, on an image built for that boundary:

* an HU window from ``wall_hu_low`` (fat, lung: dark) to the thrombus and wall
  level, clipped, with the lumen set bright: thrombus, wall and lumen look
  alike, and the vessel's outer boundary is the only edge left.  The level is
  ``wall_hu_high`` if set, else measured in a ring 1.5-4.5 mm outside the lumen:
  its local mean within a Gaussian of ``wall_level_mm`` (a false lumen can be
  thrombosed in one segment of the aorta and partly enhancing in the next), or
  the ring's median with ``wall_level_mm = 0``;
* voxels outside the lumen brighter than ``wall_contrast_hu`` (other
  contrast-filled structures: veins carrying the injected bolus, bone) are set
  dark, so the front does not cross into them where they touch the vessel;
* the potential is set to push the front back (``Ghat = +1``) farther than
  ``wall_max_mm`` from the lumen, which bounds the thickness of thrombus and
  wall where nothing else stops the front (soft tissue touching the vessel).

Two optional morphological steps follow, by balls in mm (Euclidean distance
transforms, so anisotropic voxels are exact): a closing of radius
``wall_close_mm`` fills the internal layers of a partly thrombosed lumen that
the front could not cross (a dependent layer of contrast under clot makes an
edge inside the vessel), and an opening of radius ``wall_open_mm`` cuts side
branches and leaks narrower than the ball.  Both are off by default; for the
aorta about half its radius serves.

For a single trunk such as the aorta, ``trunk`` keeps the part of the vessel
within ``wall_trunk_mm`` of a tube of inscribed balls along its main axis: it
cuts side branches (TotalSegmentator, for one, labels the arch branches apart
from the aorta) and leaks into soft tissue that touches the vessel, which
neither the image nor an opening can tell apart from it.  The axis is the path
between the two ends of the skeleton farthest apart when each step counts its
inscribed radius squared, so a long but thin branch or leak weighs less than
the thick trunk; the ball radii are a running median along it.

Why written here: the evolution and the potential are the package's own; the
rest is a few numpy/scipy operations on the package's skeleton graph
(``carotid.centerline``); no maintained library fits a trunk tube to a mask.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from carotid.centerline.graph import voxel_adjacency
from carotid.centerline.skeleton import skeletonize_lumen
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.segment.init import mask_levelset
from carotid.segment.levelset import evolve
from carotid.segment.preprocess import window_hu


def ring(hu: np.ndarray, distance: np.ndarray, low: float, contrast: float,
         ring_mm: tuple[float, float] = (1.5, 4.5)) -> np.ndarray:
    """The voxels that sample thrombus and wall: ``ring_mm`` (from, to) outside the lumen, fat and contrast left out.

    ``distance`` is each voxel's distance to the lumen in mm (0 inside), shape of ``hu``.  The ring starts
    beyond the lumen's blurred edge; voxels at or below ``low`` (fat, lung) or at or above ``contrast`` are
    not thrombus.  Returns a boolean array of that shape.
    """
    return (distance > ring_mm[0]) & (distance <= ring_mm[1]) & (hu > low) & (hu < contrast)


def wall_level(hu: np.ndarray, sample: np.ndarray, sigma_mm: float, spacing_kji, low: float) -> np.ndarray:
    """The HU of thrombus and wall, from the ``sample`` voxels (``ring``): local, or one value.

    Parameters
    ----------
    hu : ndarray, shape (nk, nj, ni)
        CT intensities in HU.
    sample : ndarray of bool, same shape
        Where thrombus and wall are sampled.
    sigma_mm : float
        Gaussian (mm) of the local mean of ``hu`` over ``sample``; 0: the median of the whole sample.
        Far from every sample voxel the median stands in.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    low : float
        The level is kept at least 10 HU above this; an empty sample gives ``low + 100``.

    Returns
    -------
    ndarray, float32: shape of ``hu``, or () with ``sigma_mm = 0``
    """
    values = hu[sample]
    median = np.float32(np.median(values) if values.size else low + 100.0)
    if sigma_mm == 0 or not values.size:
        return np.maximum(median, np.float32(low + 10.0))
    sigma = sigma_mm / np.asarray(spacing_kji, float)
    weight = ndimage.gaussian_filter(sample.astype(np.float32), sigma)
    total = ndimage.gaussian_filter(np.where(sample, hu, 0).astype(np.float32), sigma)
    local = np.where(weight > 1e-3, total / np.maximum(weight, np.float32(1e-3)), median)
    return np.maximum(local, np.float32(low + 10.0)).astype(np.float32)


def wall_image(hu: np.ndarray, lumen: np.ndarray, low: float, high: float, contrast: float) -> np.ndarray:
    """The image the outer-wall potential sees, float32 in [0, 1].

    Parameters
    ----------
    hu : ndarray, shape (nk, nj, ni)
        CT intensities in HU.
    lumen : ndarray of bool, same shape
        The segmented lumen; it counts as bright whatever its HU.
    low : float
        Bottom of the HU window (fat, lung).
    high : float or ndarray, float32, same shape
        Top of the window, clipped (no fold): the thrombus and wall level (``wall_level``), so that they and
        the lumen look alike and the vessel's outer boundary is the only edge.
    contrast : float
        Voxels outside the lumen above this HU count as dark (other contrast-filled structures).

    Returns
    -------
    ndarray, float32, same shape
    """
    image = window_hu(np.where(hu > contrast, np.float32(low), hu), low, high, fold=0.0)
    image[lumen] = 1.0
    return image


def ball_closing(mask: np.ndarray, radius_mm: float, spacing_kji) -> np.ndarray:
    """Closing of a boolean mask by a ball of ``radius_mm`` (mm, exact for anisotropic voxels); keeps ``mask``."""
    dilated = ndimage.distance_transform_edt(~mask, sampling=spacing_kji) <= radius_mm
    return (ndimage.distance_transform_edt(dilated, sampling=spacing_kji) > radius_mm) | mask


def ball_opening(mask: np.ndarray, radius_mm: float, spacing_kji) -> np.ndarray:
    """Opening of a boolean mask by a ball of ``radius_mm``: the union of the balls that fit inside it."""
    centres = ndimage.distance_transform_edt(mask, sampling=spacing_kji) > radius_mm
    return (ndimage.distance_transform_edt(~centres, sampling=spacing_kji) <= radius_mm) & mask


def close_and_open(mask: np.ndarray, close_mm: float, open_mm: float, spacing_kji) -> np.ndarray:
    """``mask`` closed by a ball of ``close_mm``, then opened by one of ``open_mm`` (mm; 0 skips either step)."""
    if close_mm > 0:
        mask = ball_closing(mask, close_mm, spacing_kji)
    if open_mm > 0:
        mask = ball_opening(mask, open_mm, spacing_kji)
    return mask


def outer_wall(volume: Volume, lumen: np.ndarray, ghat_g, params, progress=None) -> tuple[np.ndarray, dict]:
    """The vessel's outer boundary grown from its lumen (module docstring).

    Parameters
    ----------
    volume : Volume
        CT image in HU.
    lumen : ndarray of bool, shape volume.array.shape
        The segmented lumen, not empty.
    ghat_g : callable
        ``ghat_g(image01) -> (Ghat, g)``: the normalised potential (kernel ``wall_kernel_mm``) and
        edge-stopping function of a [0, 1] image (``segmentation.speed_fields``).
    params : SegmentParameters
        ``wall_*`` fields and ``cfl``, ``max_iterations``, ``tolerance``.
    progress : callable, optional
        Passed to ``evolve``.

    Returns
    -------
    wall : ndarray of bool, same shape
        Lumen, thrombus and wall (the lumen whole, unless ``wall_open_mm`` cuts a side branch); before
        component selection.
    report : dict
        Thrombus level (median and 5th-95th percentiles over the ring, HU), iterations, convergence
        and seconds of the stage.
    """
    t0 = time.perf_counter()
    spacing = volume.spacing_kji
    distance = ndimage.distance_transform_edt(~lumen, sampling=spacing)
    low, contrast = params.wall_hu_low, params.wall_contrast_hu
    sample = ring(volume.array, distance, low, contrast)
    if params.wall_hu_high:
        level = np.float32(params.wall_hu_high)
    else:
        level = wall_level(volume.array, sample, params.wall_level_mm, spacing, low)
    level_range = np.percentile(level[sample] if level.ndim else level.reshape(1), [5, 50, 95])
    ghat, g = ghat_g(wall_image(volume.array, lumen, low, level, contrast))
    ghat[distance > params.wall_max_mm] = 1.0
    del distance, sample, level
    result = evolve(mask_levelset(lumen, spacing), ghat, g, spacing, alpha=params.wall_alpha, cfl=params.cfl,
                    max_iterations=params.max_iterations, tolerance=params.tolerance, progress=progress)
    del ghat, g
    # The whole vessel holds its lumen: where the front fell back inside it (the curvature term narrows a
    # carotid a few millimetres across that no thrombus surrounds), the lumen is kept.
    wall = close_and_open((result.phi < 0) | lumen, params.wall_close_mm, params.wall_open_mm, spacing)
    if params.wall_open_mm > 0 and not wall.any():
        raise CarotidError(f"no ball of radius wall_open_mm = {params.wall_open_mm:g} mm fits in the vessel: "
                           "choose a smaller one")
    report = {"thrombus_level_hu": float(level_range[1]),
              "thrombus_level_range_hu": [float(level_range[0]), float(level_range[2])],
              "iterations": result.iterations, "converged": result.converged, "seconds": time.perf_counter() - t0}
    return wall, report


TRUNK_MEDIAN_MM = 20.0  # length of the running median of the trunk's inscribed radius, mm


def trunk_axis(mask: np.ndarray, spacing_kji) -> tuple[np.ndarray, np.ndarray]:
    """The main axis of a vessel mask: skeleton voxels from one end of the trunk to the other (module docstring).

    Parameters
    ----------
    mask : ndarray of bool, shape (nk, nj, ni)
        One connected vessel, not empty.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.

    Returns
    -------
    points : ndarray of int, shape (n, 3)
        Voxel indices (k, j, i) along the axis, in order; none for a mask too small to thin.
    radii : ndarray, shape (n,)
        Radius of the largest ball inside ``mask`` at each point, mm.
    """
    spacing = np.asarray(spacing_kji, float)
    depth = ndimage.distance_transform_edt(mask, sampling=spacing)
    kji, adjacency = voxel_adjacency(skeletonize_lumen(mask, spacing, extend_mm=2.0 * float(depth.max())))
    radii = depth[tuple(kji.T)]
    if not len(kji):
        return kji, radii
    edges = sparse.triu(adjacency, format="coo")
    step = np.linalg.norm((kji[edges.row] - kji[edges.col]) * spacing, axis=1)

    def graph(w):
        return sparse.csr_matrix((w, (edges.row, edges.col)), shape=adjacency.shape)

    weighted = graph(step * (0.5 * (radii[edges.row] + radii[edges.col])) ** 2 + 1e-6)

    def farthest(start):
        reach = csgraph.dijkstra(weighted, directed=False, indices=start)
        return int(np.argmax(np.where(np.isfinite(reach), reach, -1.0)))

    first = farthest(int(np.argmax(radii)))
    last = farthest(first)
    lengths = csgraph.dijkstra(graph(step), directed=False, indices=[first, last])
    on_path = np.flatnonzero(np.isclose(lengths.sum(axis=0), lengths[0, last]))
    order = on_path[np.argsort(lengths[0, on_path])]
    return kji[order], radii[order]


def trunk(mask: np.ndarray, spacing_kji, margin_mm: float) -> np.ndarray:
    """The part of ``mask`` within ``margin_mm`` of the balls along its main axis (``trunk_axis``).

    ``mask`` and ``spacing_kji`` as for ``trunk_axis``; ``margin_mm`` is added to the running median
    (over ``TRUNK_MEDIAN_MM``) of the inscribed radius along the axis.  Returns a boolean array of the
    shape of ``mask``: all of it when it is too small to thin.
    """
    spacing = np.asarray(spacing_kji, float)
    points, radii = trunk_axis(mask, spacing)
    if not len(points):
        return mask.copy()
    steps = np.linalg.norm(np.diff(points * spacing, axis=0), axis=1)
    window = 2 * int(TRUNK_MEDIAN_MM / (2.0 * (float(steps.mean()) if steps.size else 1.0))) + 1
    reach = ndimage.median_filter(radii, size=window, mode="nearest") + margin_mm
    voxels = np.argwhere(mask)
    pairs = cKDTree(voxels * spacing).sparse_distance_matrix(cKDTree(points * spacing), float(reach.max()),
                                                            output_type="ndarray")
    covered = pairs["i"][pairs["v"] <= reach[pairs["j"]]]
    out = np.zeros(mask.shape, bool)
    out[tuple(voxels[covered].T)] = True
    return out
