"""Pre-processing of CT angiograms before the GPF potential.

* ``window_hu``: maps intensities to [0, 1] over the lumen's window (from
  ``intensity.IntensityModel``, possibly varying along the vessel); values
  brighter than the window (calcium, cortical bone) are folded back down, so a
  calcified plaque touching the lumen appears dark and forms an edge instead of
  looking like more contrast.
* ``denoise``: edge-preserving curvature anisotropic diffusion (SimpleITK).
* ``edge_stopping``: ``g = 1 / (1 + |grad I| / beta)`` of eq. (1).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from carotid.io import Volume, to_sitk


def window_hu(hu: np.ndarray, low=-100.0, high=550.0, fold: float = 3.0) -> np.ndarray:
    """Window intensities to [0, 1], folding values above ``high`` back down.

    Parameters
    ----------
    hu : ndarray, shape (nk, nj, ni)
        Intensities (HU for CT, the scanner's units for MR).
    low, high : float or ndarray broadcastable to ``hu``
        Window; ``low`` maps to 0 and ``high`` to 1.  Arrays give a window that
        follows the lumen level along the vessel.
    fold : float
        Slope of the fold above ``high``: ``high + d`` maps like ``high - fold * d``
        (0 clips instead of folding).

    Returns
    -------
    ndarray, float32, same shape
    """
    v = np.asarray(hu, np.float32)
    low = np.asarray(low, np.float32)
    high = np.asarray(high, np.float32)
    if fold > 0:
        v = np.where(v > high, high - np.float32(fold) * (v - high), v)
    out = (np.clip(v, low, high) - low) / (high - low)
    return out.astype(np.float32, copy=False)


def denoise(volume: Volume, iterations: int = 5, conductance: float = 1.0, time_step: float | None = None) -> Volume:
    """Curvature anisotropic diffusion (SimpleITK), which smooths noise but keeps edges.

    Parameters
    ----------
    volume : Volume
        Image (any units), float32 array.
    iterations : int
        Diffusion iterations.
    conductance : float
        Edge sensitivity (lower keeps more edges), in ITK's normalised units.
    time_step : float, optional
        Diffusion step in mm; defaults to ITK's stable bound ``min(spacing) / 2**(3+1)``.
    """
    image = to_sitk(volume.with_array(np.asarray(volume.array, np.float32)))
    step = time_step if time_step is not None else min(volume.spacing) / 16.0
    out = sitk.CurvatureAnisotropicDiffusion(image, timeStep=step, conductanceParameter=conductance,
                                             numberOfIterations=int(iterations))
    return volume.with_array(sitk.GetArrayFromImage(out).astype(np.float32))


def edge_stopping(image: np.ndarray, spacing_kji, beta: float = 0.1, sigma_mm: float = 0.6) -> np.ndarray:
    """Edge-stopping function ``g = 1 / (1 + |grad I| / beta)`` of eq. (1).

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
        Windowed image in [0, 1].
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    beta : float
        Gradient scale in 1/mm (window units per mm).
    sigma_mm : float
        Gaussian derivative scale in mm.

    Returns
    -------
    ndarray, float32, same shape, values in (0, 1]
    """
    spacing_kji = np.asarray(spacing_kji, float)
    sigma = sigma_mm / spacing_kji
    sq = np.zeros(image.shape, np.float32)
    for axis in range(3):
        order = [0, 0, 0]
        order[axis] = 1
        d = ndimage.gaussian_filter(image, sigma, order=order, output=np.float32)
        d /= np.float32(spacing_kji[axis])
        sq += d * d
    return (1.0 / (1.0 + np.sqrt(sq) / np.float32(beta))).astype(np.float32)
