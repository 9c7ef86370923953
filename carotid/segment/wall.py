"""Outer-wall stage: the whole vessel (lumen, non-enhancing thrombus and wall) around a segmented lumen.

A contrast-lumen model stops, rightly, at the lumen.  In an aortic dissection
(a thrombosed false lumen) or an aneurysm (mural thrombus) users also need the
vessel's outer boundary: thrombus volume, the whole aorta.  This stage runs the
same GPF evolution (eq. 1, ``levelset.evolve``) a second time, started from the
lumen, on an image built for that boundary:

* an HU window from ``wall_hu_low`` (fat, lung: dark) to the thrombus and wall
  level (``wall_hu_high``, by default the median HU of a ring 1.5-4.5 mm
  outside the lumen), clipped, with the lumen set bright: thrombus, wall and lumen
  look alike, and the vessel's outer boundary is the only edge left;
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

Why written here: the evolution and the potential are the package's own; the
rest is a few numpy/scipy.ndimage operations.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.segment.init import mask_levelset
from carotid.segment.levelset import evolve
from carotid.segment.preprocess import window_hu


def wall_level(hu: np.ndarray, distance: np.ndarray, low: float, contrast: float,
               ring_mm: tuple[float, float] = (1.5, 4.5)) -> float:
    """The HU of thrombus and wall: the median of the ring ``ring_mm`` (from, to) outside the lumen.

    ``distance`` is each voxel's distance to the lumen in mm (0 inside), shape of ``hu``.  The ring
    starts beyond the lumen's blurred edge.  Voxels at or below ``low`` (fat, lung) and above
    ``contrast`` are left out of the median; without any, the level is ``low + 100``.
    """
    ring = (distance > ring_mm[0]) & (distance <= ring_mm[1])
    values = hu[ring & (hu > low) & (hu < contrast)]
    return float(np.median(values)) if values.size else low + 100.0


def wall_image(hu: np.ndarray, lumen: np.ndarray, low: float, high: float, contrast: float) -> np.ndarray:
    """The image the outer-wall potential sees, float32 in [0, 1].

    Parameters
    ----------
    hu : ndarray, shape (nk, nj, ni)
        CT intensities in HU.
    lumen : ndarray of bool, same shape
        The segmented lumen; it counts as bright whatever its HU.
    low, high : float
        HU window, clipped (no fold): ``high`` is the thrombus and wall level, so that they and the lumen
        look alike and the vessel's outer boundary is the only edge.
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
        Lumen, thrombus and wall; before component selection.
    report : dict
        Iterations, convergence and seconds of the stage.
    """
    t0 = time.perf_counter()
    spacing = volume.spacing_kji
    distance = ndimage.distance_transform_edt(~lumen, sampling=spacing)
    low, contrast = params.wall_hu_low, params.wall_contrast_hu
    level = params.wall_hu_high or max(wall_level(volume.array, distance, low, contrast), low + 10.0)
    ghat, g = ghat_g(wall_image(volume.array, lumen, low, level, contrast))
    ghat[distance > params.wall_max_mm] = 1.0
    del distance
    result = evolve(mask_levelset(lumen, spacing), ghat, g, spacing, alpha=params.wall_alpha, cfl=params.cfl,
                    max_iterations=params.max_iterations, tolerance=params.tolerance, progress=progress)
    del ghat, g
    wall = close_and_open(result.phi < 0, params.wall_close_mm, params.wall_open_mm, spacing)
    if params.wall_open_mm > 0 and not wall.any():
        raise CarotidError(f"no ball of radius wall_open_mm = {params.wall_open_mm:g} mm fits in the vessel: "
                           "choose a smaller one")
    report = {"thrombus_level_hu": level, "iterations": result.iterations, "converged": result.converged,
              "seconds": time.perf_counter() - t0}
    return wall, report
