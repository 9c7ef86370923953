"""The geometric potential G of the GPF deformable model (paper, eqs. 2-5).

Two implementations of the same quantity:

``gpf_potential`` (the paper's contribution, used by the segmentation)
    One scalar convolution ``G = I * K`` with the kernel of eq. (5),
    ``K(x) = |x|^-4`` for ``x != 0`` (windowed, see Support) and ``K(0) = -S`` (S the sum of all other
    taps), distances in mm so anisotropic voxels are right, and each tap
    weighted by the voxel volume so that the sum approximates the integral of
    eq. (2) and G does not depend on the resolution.  Written out,
    ``G(x) = sum_x' (I(x') - I(x)) |x - x'|^-4``: negative inside a bright
    object, positive just outside it.  ``K`` is a discrete fractional
    Laplacian, ``-(-Delta)^(1/2)``, whose Fourier symbol grows like ``|k|``;
    an optional Gaussian pre-smoothing is folded into the same spectrum, so
    denoising costs no extra pass.

``gpf_potential_vector`` (reference)
    The original vector-kernel form of eq. (2): ``G = -(grad I * K_vec)`` with
    ``K_vec(x) = x / |x|^4``, one FFT per gradient and kernel component.  Since
    ``div K_vec = -|x|^-4`` away from 0, it equals the scalar form; the minus
    sign makes both negative inside bright objects.

Why this is written here and not taken from a library: no maintained package
provides the GPF kernel.  The FFTs are scipy.fft's.

Memory.  The kernel is even in every axis, so its spectrum is real and has
octant symmetry: it is computed by one type-I DCT of one octant of the kernel
(N/8 real values for a padded volume of N voxels) and applied through
reflected views.  The image spectrum is built slab by slab (padding, real FFT
along the last axis and FFT along the middle axis per slab, then one in-place
FFT along the first axis), so the padded real volume is never stored; the
inverse runs the same way and writes only the cropped output.  Peak extra
memory is about one complex half-spectrum (~N float32) plus the output.

Support.  Both kernels are cut off smoothly: the vector kernel is multiplied
by a window ``w(r)`` (1 up to R/2, a cosine-squared fall to 0 at R) and the
scalar kernel is its exact divergence, ``(w - r w') / r^4``, so the two forms
remain the same operator.  A hard cut at R would not: the vector form would
pick up a surface term ``(4 pi / R)(<I>_sphere(R) - I(x))``.

Padding is reflective ("symmetric") and at least the kernel radius wide on
every side, so the circular convolution never wraps around, and the image
border is not seen as an edge (zero padding would make it one).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft

DEFAULT_RADIUS_MM = 10.0
DEFAULT_SIGMA_MM = 0.6
_SLAB = 16


def padded_shape(shape: tuple[int, ...], spacing_kji, radius_mm: float) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """FFT grid and leading pad for a volume, so that a kernel of ``radius_mm`` never wraps.

    Parameters
    ----------
    shape : tuple of 3 int
        Volume shape (nk, nj, ni).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    radius_mm : float
        Kernel support radius in mm.

    Returns
    -------
    grid : tuple of 3 int
        Even, FFT-friendly padded shape, at least ``shape + 2 * pad``.
    pad : tuple of 3 int
        Voxels of padding before the volume along each axis (the rest goes after).
    """
    pad = tuple(int(np.ceil(radius_mm / h)) for h in spacing_kji)
    grid = []
    for n, p in zip(shape, pad):
        m = sfft.next_fast_len(n + 2 * p, real=True)
        while m % 2:
            m = sfft.next_fast_len(m + 1, real=True)
        grid.append(m)
    return tuple(grid), pad


def _half_axis_mm(n: int, h: float) -> np.ndarray:
    """Distances (mm) of the non-negative half of an even, wrapped FFT axis: 0..n/2."""
    return np.arange(n // 2 + 1, dtype=np.float64) * h


def window(r: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Kernel window ``w(r)`` and ``r w'(r)``: 1 up to R/2, cosine-squared to 0 at R, 0 beyond."""
    half = 0.5 * radius_mm
    u = np.clip((r - half) / half, 0.0, 1.0)
    w = np.cos(0.5 * np.pi * u) ** 2
    r_dw = np.where((u > 0) & (u < 1), -r * np.pi / (2 * half) * np.sin(np.pi * u), 0.0)
    return w, r_dw


def scalar_kernel_octant(grid, spacing_kji, radius_mm: float = DEFAULT_RADIUS_MM) -> np.ndarray:
    """One octant of the eq. (5) kernel on an even FFT grid.

    Returns
    -------
    ndarray, shape (n0/2+1, n1/2+1, n2/2+1), float64
        ``|x|^-4 dV`` (x in mm, dV the voxel volume in mm^3) times the
        window factor ``w - r w'``, and ``-S``
        at the origin so that the full kernel sums to zero.
    """
    z, y, x = (_half_axis_mm(n, h) for n, h in zip(grid, spacing_kji))
    r = np.sqrt(z[:, None, None] ** 2 + y[None, :, None] ** 2 + x[None, None, :] ** 2)
    w, r_dw = window(r, radius_mm)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(r > 0, (w - r_dw) / r**4, 0.0)
    k *= float(np.prod(spacing_kji))  # voxel volume: the sum approximates the integral, G in units/mm
    # Each octant tap stands for 2 per axis where it is neither 0 nor the Nyquist plane.
    mult = [np.where((np.arange(n // 2 + 1) == 0) | (np.arange(n // 2 + 1) == n // 2), 1.0, 2.0) for n in grid]
    weight = mult[0][:, None, None] * mult[1][None, :, None] * mult[2][None, None, :]
    k[0, 0, 0] = -float(np.sum(k * weight))
    return k


def _gaussian_octant(grid, spacing_kji, sigma_mm: float) -> np.ndarray:
    """Fourier transform of a unit-mass Gaussian (sigma in mm) on the octant of frequencies."""
    factors = []
    for n, h in zip(grid, spacing_kji):
        k = 2.0 * np.pi * np.arange(n // 2 + 1) / (n * h)
        factors.append(np.exp(-0.5 * (sigma_mm * k) ** 2))
    return factors[0][:, None, None] * factors[1][None, :, None] * factors[2][None, None, :]


def kernel_spectrum_octant(grid, spacing_kji, radius_mm: float = DEFAULT_RADIUS_MM,
                           sigma_mm: float = DEFAULT_SIGMA_MM) -> np.ndarray:
    """Real spectrum of the eq. (5) kernel (times a Gaussian of ``sigma_mm``) on one octant.

    The DFT of an even sequence of even length n equals the type-I DCT of its
    first n/2+1 samples, axis by axis.

    Returns
    -------
    ndarray, shape (n0/2+1, n1/2+1, n2/2+1), float32
    """
    spec = sfft.dctn(scalar_kernel_octant(grid, spacing_kji, radius_mm), type=1)
    if sigma_mm > 0:
        spec *= _gaussian_octant(grid, spacing_kji, sigma_mm)
    return spec.astype(np.float32)


def _reflect_index(n: int, pad: int, m: int) -> np.ndarray:
    """Source indices (m,) for a symmetric padding of an axis of length n by ``pad`` before."""
    idx = np.arange(m) - pad
    period = 2 * n
    idx = np.mod(idx, period)
    return np.where(idx < n, idx, period - 1 - idx)


def _forward_spectrum(image: np.ndarray, grid, pad, workers) -> np.ndarray:
    """Half spectrum (n0, n1, n2/2+1) complex64 of the symmetrically padded image, slab by slab."""
    n0, n1, n2 = grid
    src = [_reflect_index(n, p, m) for n, p, m in zip(image.shape, pad, grid)]
    spec = np.empty((n0, n1, n2 // 2 + 1), np.complex64)
    for a in range(0, n0, _SLAB):
        block = image[src[0][a:a + _SLAB]][:, src[1]][:, :, src[2]].astype(np.float32, copy=False)
        part = sfft.rfft(block, axis=2, workers=workers)
        spec[a:a + _SLAB] = sfft.fft(part, axis=1, overwrite_x=True, workers=workers)
    return sfft.fft(spec, axis=0, overwrite_x=True, workers=workers)


def _inverse_cropped(spec: np.ndarray, grid, pad, shape, workers) -> np.ndarray:
    """Inverse of ``_forward_spectrum`` (overwrites ``spec``), returning only the unpadded region."""
    spec = sfft.ifft(spec, axis=0, overwrite_x=True, workers=workers)
    out = np.empty(shape, np.float32)
    k0 = pad[0]
    for a in range(k0, k0 + shape[0], _SLAB):
        b = min(a + _SLAB, k0 + shape[0])
        part = sfft.ifft(spec[a:b], axis=1, workers=workers)[:, pad[1]:pad[1] + shape[1]]
        out[a - k0:b - k0] = sfft.irfft(part, n=grid[2], axis=2, workers=workers)[:, :, pad[2]:pad[2] + shape[2]]
    return out


def _apply_octant(spec: np.ndarray, octant: np.ndarray) -> None:
    """Multiply a half spectrum (n0, n1, n2/2+1) in place by an even real spectrum given on its octant."""
    n0, n1 = spec.shape[:2]
    h0, h1 = n0 // 2, n1 // 2
    rows = ((slice(0, h0 + 1), slice(0, h0 + 1)), (slice(h0 + 1, n0), slice(h0 - 1, 0, -1)))
    cols = ((slice(0, h1 + 1), slice(0, h1 + 1)), (slice(h1 + 1, n1), slice(h1 - 1, 0, -1)))
    for dst0, src0 in rows:
        for dst1, src1 in cols:
            spec[dst0, dst1] *= octant[src0, src1]


def gpf_potential(image: np.ndarray, spacing_kji, radius_mm: float = DEFAULT_RADIUS_MM,
                  sigma_mm: float = DEFAULT_SIGMA_MM, workers: int = -1) -> np.ndarray:
    """GPF potential by the scalar kernel of eq. (5), one FFT convolution.

    Parameters
    ----------
    image : ndarray, shape (nk, nj, ni)
        Grey levels (any real dtype; float32 internally).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    radius_mm : float
        Support radius of the kernel in mm; the padding is at least this wide.
    sigma_mm : float
        Gaussian pre-smoothing in mm, folded into the kernel spectrum (0: none).
    workers : int
        Threads for scipy.fft (-1: all cores).

    Returns
    -------
    ndarray, shape (nk, nj, ni), float32
        G in image units per mm: negative inside bright objects, positive outside.
    """
    image = np.asarray(image)
    grid, pad = padded_shape(image.shape, spacing_kji, radius_mm)
    octant = kernel_spectrum_octant(grid, spacing_kji, radius_mm, sigma_mm)
    spec = _forward_spectrum(image, grid, pad, workers)
    _apply_octant(spec, octant)
    del octant
    return _inverse_cropped(spec, grid, pad, image.shape, workers)


def gpf_potential_vector(image: np.ndarray, spacing_kji, radius_mm: float = DEFAULT_RADIUS_MM,
                         sigma_mm: float = DEFAULT_SIGMA_MM, workers: int = -1) -> np.ndarray:
    """Reference GPF potential by the original vector kernel of eq. (2).

    Stores the three gradient components, the three kernel components and their
    spectra, as the original method does; same padding and pre-smoothing as
    ``gpf_potential``, and the same sign convention.

    Returns
    -------
    ndarray, shape (nk, nj, ni), float32
    """
    image = np.asarray(image, np.float32)
    grid, pad = padded_shape(image.shape, spacing_kji, radius_mm)
    widths = [(p, m - n - p) for n, p, m in zip(image.shape, pad, grid)]
    padded = np.pad(image, widths, mode="symmetric")
    grads = np.gradient(padded, *spacing_kji)
    del padded
    coords = [np.fft.fftfreq(n, 1.0 / n).astype(np.float32) * np.float32(h) for n, h in zip(grid, spacing_kji)]
    r = np.sqrt(coords[0][:, None, None] ** 2 + coords[1][None, :, None] ** 2 + coords[2][None, None, :] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_r4 = np.where(r > 0, window(r, radius_mm)[0] / r**4, 0.0) * float(np.prod(spacing_kji))
    inv_r4 = inv_r4.astype(np.float32)
    del r
    total = None
    for axis, grad in enumerate(grads):
        shape = [1, 1, 1]
        shape[axis] = -1
        component = coords[axis].reshape(shape) * inv_r4
        term = sfft.rfftn(grad, workers=workers) * sfft.rfftn(component, workers=workers)
        total = term if total is None else total + term
    del grads, inv_r4
    if sigma_mm > 0:
        full = [np.fft.fftfreq(n, h) * 2 * np.pi for n, h in zip(grid, spacing_kji)]
        full[2] = full[2][: grid[2] // 2 + 1]
        total *= np.exp(-0.5 * sigma_mm**2 * (full[0][:, None, None] ** 2 + full[1][None, :, None] ** 2
                                               + full[2][None, None, :] ** 2)).astype(np.float32)
    out = -sfft.irfftn(total, s=grid, workers=workers)
    crop = tuple(slice(p, p + n) for p, n in zip(pad, image.shape))
    return np.ascontiguousarray(out[crop], dtype=np.float32)
