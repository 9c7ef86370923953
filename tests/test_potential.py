"""The GPF potential: the scalar kernel of eq. (5) against a direct sum, its sign and padding,
and the paper's claim that it equals the vector-kernel form at a third of the memory."""

import tracemalloc

import numpy as np
import pytest
from scipy import ndimage

from carotid.segment.potential import gpf_potential, gpf_potential_vector

SPACING = np.array([0.625, 0.45, 0.45])  # (k, j, i) mm


def direct_potential(image, spacing, radius):
    """sum_x' K(x - x') (I(x') - I(x)) with K = (w - r w') / r^4 dV, symmetric padding, written naively."""
    half = [int(np.ceil(radius / h)) for h in spacing]
    padded = np.pad(image.astype(float), [(p, p) for p in half], mode="symmetric")
    out = np.zeros(image.shape)
    for offset in np.ndindex(*[2 * p + 1 for p in half]):
        d = (np.array(offset) - half) * spacing
        r = np.linalg.norm(d)
        if r == 0 or r >= radius:
            continue
        u = np.clip((r - radius / 2) / (radius / 2), 0, 1)
        weight = (np.cos(np.pi * u / 2) ** 2 + np.pi * r / radius * np.sin(np.pi * u)) / r**4 * np.prod(spacing)
        window = tuple(slice(o, o + n) for o, n in zip(offset, image.shape))
        out += weight * (padded[window] - image)
    return out


def ball(shape, spacing, centre_mm, radius_mm, inside=400.0, outside=40.0, blur_mm=0.4):
    grids = np.meshgrid(*[np.arange(n) * h for n, h in zip(shape, spacing)], indexing="ij")
    r = np.sqrt(sum((g - c) ** 2 for g, c in zip(grids, centre_mm)))
    image = np.where(r < radius_mm, inside, outside).astype(np.float32)
    return ndimage.gaussian_filter(image, blur_mm / spacing), r


def test_scalar_kernel_equals_direct_sum():
    image = np.random.default_rng(0).normal(size=(14, 16, 15)).astype(np.float32)
    ours = gpf_potential(image, SPACING, radius_mm=2.5, sigma_mm=0.0)
    ref = direct_potential(image, SPACING, 2.5)
    assert np.abs(ours - ref).max() <= 1e-5 * np.abs(ref).max()


def test_sign_negative_inside_bright_positive_outside():
    shape = (48, 64, 64)
    image, r = ball(shape, SPACING, (15.0, 14.4, 14.4), 3.0)
    g = gpf_potential(image, SPACING)
    assert (g[r < 2.5] < 0).all()
    shell = (r > 3.6) & (r < 5.0)
    assert (g[shell] > 0).mean() > 0.99


def test_reflective_padding_sees_no_edge_at_the_border():
    # A constant image has no edge anywhere; zero padding would make its border one.
    g = gpf_potential(np.full((20, 30, 30), 40.0, np.float32), SPACING)
    assert np.abs(g).max() < 1e-3
    # A vessel leaving the volume keeps a negative potential up to the border.
    image, r = ball((40, 40, 40), SPACING, (0.0, 9.0, 9.0), 3.0)
    g = gpf_potential(image, SPACING)
    axis_line = g[:, 20, 20]
    assert (axis_line[:3] < 0).all()


def test_physical_units_make_anisotropic_sampling_consistent():
    # The same ball sampled isotropically and anisotropically gives the same potential (mm units),
    # compared along a line both grids sample: z = 11.25 mm (k = 25 and 18), y = 13.5 mm (j = 30).
    iso = np.array([0.45, 0.45, 0.45])
    a_img, _ = ball((50, 60, 60), iso, (11.25, 13.5, 13.5), 3.0)
    b_img, _ = ball((36, 60, 60), SPACING, (11.25, 13.5, 13.5), 3.0)
    line_a = gpf_potential(a_img, iso)[25, 30, :]
    line_b = gpf_potential(b_img, SPACING)[18, 30, :]
    assert np.corrcoef(line_a, line_b)[0, 1] > 0.99
    assert np.abs(line_a - line_b).max() < 0.1 * np.abs(line_a).max()


def test_scalar_and_vector_kernels_agree():
    image, _ = ball((48, 64, 64), SPACING, (15.0, 14.4, 14.4), 4.0)
    image += np.random.default_rng(1).normal(0, 20, image.shape).astype(np.float32)
    s = gpf_potential(image, SPACING)
    v = gpf_potential_vector(image, SPACING)
    correlation = np.mean((s - s.mean()) * (v - v.mean())) / (s.std() * v.std())
    assert correlation >= 0.99


@pytest.mark.parametrize("sigma", [0.0, 0.6])
def test_scalar_kernel_needs_a_third_of_the_memory(sigma):
    image, _ = ball((64, 80, 80), SPACING, (20.0, 18.0, 18.0), 4.0)
    peaks = {}
    for name, fn in (("scalar", gpf_potential), ("vector", gpf_potential_vector)):
        tracemalloc.start()
        fn(image, SPACING, sigma_mm=sigma)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks["scalar"] <= peaks["vector"] / 3


def test_gaussian_in_the_spectrum_equals_smoothing_first():
    image, _ = ball((40, 48, 48), SPACING, (12.0, 10.8, 10.8), 3.0, blur_mm=0.01)
    folded = gpf_potential(image, SPACING, sigma_mm=0.6)
    smoothed = ndimage.gaussian_filter(image, 0.6 / SPACING, mode="reflect", truncate=6)
    explicit = gpf_potential(smoothed, SPACING, sigma_mm=0.0)
    inner = (slice(8, -8),) * 3
    assert np.abs(folded - explicit)[inner].max() < 0.02 * np.abs(explicit).max()
