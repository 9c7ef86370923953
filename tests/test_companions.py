"""Companions: a bright vessel beside the seeded one behind a gap the blur nearly fills, told from a vessel
that follows it beyond a throat (``barrier.companion_basins``, ``barrier.tube_axes``), on blurred tubes whose
geometry is known in closed form."""

import numpy as np
import pytest
from scipy import ndimage

from carotid.segment.barrier import companion_basins, tube_axes

SPACING = np.array([0.8, 0.4, 0.4])  # k (z), j (y), i (x), mm: anisotropic, as a CT angiogram's
SHAPE = (50, 64, 64)
BLUR = np.array([0.75, 0.6, 0.6])  # mm per axis


def grid_mm():
    """World coordinates (z, y, x) in mm of the voxel centres, origin at the grid's centre."""
    return [(np.arange(n) - (n - 1) / 2) * h for n, h in zip(SHAPE, SPACING)]


def blurred(indicator: np.ndarray, noise: float = 0.02, seed: int = 0) -> np.ndarray:
    """The indicator (lumen contrast per voxel) blurred by ``BLUR`` with Gaussian noise, float32."""
    image = ndimage.gaussian_filter(indicator.astype(np.float32), BLUR / SPACING)
    return (image + noise * np.random.default_rng(seed).standard_normal(SHAPE)).astype(np.float32)


def cylinder(x0: float, radius: float, level: float = 1.0, radius_along=None) -> np.ndarray:
    """A cylinder along z through (x0, 0), its radius a function of z (``radius_along``) or constant, sampled
    with 4 x 4 sub-samples per voxel in plane (partial volume)."""
    z, y, x = grid_mm()
    sub = (np.arange(4) - 1.5) / 4
    ys = (y[:, None] + sub[None] * SPACING[1]).ravel()
    xs = (x[:, None] + sub[None] * SPACING[2]).ravel()
    r = np.full(len(z), radius) if radius_along is None else radius_along(z)
    d2 = (ys[None, :, None] ** 2 + (xs[None, None, :] - x0) ** 2)
    inside = (d2 < r[:, None, None] ** 2).astype(np.float32)
    return level * inside.reshape(len(z), len(y), 4, len(x), 4).mean(axis=(2, 4))


def seed_at(x0: float, z: float = 0.0) -> np.ndarray:
    """Continuous array index of the point (z, 0, x0)."""
    return np.array([[(z / SPACING[0]) + (SHAPE[0] - 1) / 2, (SHAPE[1] - 1) / 2, x0 / SPACING[2] + (SHAPE[2] - 1) / 2]])


def test_tube_axes_follow_a_tilted_tube():
    """A tube tilted 25 degrees from z: the axis read at its voxels lies within 10 degrees of its direction."""
    z, y, x = np.meshgrid(*grid_mm(), indexing="ij")
    direction = np.array([np.cos(np.radians(25)), 0.0, np.sin(np.radians(25))])  # (z, y, x)
    points = np.stack([z, y, x], axis=-1)
    radial = points - (points @ direction)[..., None] * direction
    image = blurred(np.linalg.norm(radial, axis=-1) < 3.0)
    read = tube_axes(image, SPACING, 2.0, np.nonzero(np.linalg.norm(radial, axis=-1) < 2.0))
    assert np.allclose(np.linalg.norm(read, axis=1), 1.0, atol=1e-5)
    assert np.median(np.abs(read @ direction)) > np.cos(np.radians(10))


def test_a_vein_beside_the_artery_is_a_companion():
    """An artery (radius 3 mm, contrast 1) and a vein beside it (3.5 mm, 0.9) 0.3 mm apart: blurred, the gap
    stays above 70 % of the contrast, so the captured region holds both; the vein's basin is the companion and
    the artery's the vessel."""
    artery, vein = cylinder(-3.3, 3.0), cylinder(3.5, 3.5, 0.9)
    image = blurred(np.maximum(artery, vein))
    gap = image[:, SHAPE[1] // 2, :][SHAPE[0] // 2]
    assert gap[(SHAPE[2] - 1) // 2 - 2:(SHAPE[2] - 1) // 2 + 3].min() > 0.7, "premise: the gap is above 70 %"
    captured = ndimage.gaussian_filter(image, 1.0) > 0.5
    assert ndimage.label(captured)[1] == 1, "premise: the captured region holds both"
    found = companion_basins(captured, image, seed_at(-3.3), SPACING)
    assert found is not None
    vessel, companions = found
    true_vein = vein > 0.5
    assert np.count_nonzero(companions & true_vein) > 0.8 * np.count_nonzero(companions)
    assert np.count_nonzero(vessel & (artery > 0.5)) > 0.8 * np.count_nonzero(vessel)


def test_a_vessel_beyond_a_throat_is_not_a_companion(monkeypatch):
    """One artery (radius 3 mm) narrowed to 1.2 mm over a 6 mm raised-cosine throat, seeded at one end: the
    blur dims the throat, which cuts the region into basins in a row along the vessel; none is a companion.
    With the direction test switched off (every touching basin taken), the vessel beyond the throat is."""
    def radius(z):
        return 3.0 - 1.8 * np.where(np.abs(z) < 3.0, 0.5 * (1 + np.cos(np.pi * z / 3.0)), 0.0)
    artery = cylinder(0.0, 3.0, radius_along=radius)
    image = blurred(artery)
    captured = ndimage.gaussian_filter(image, 1.0) > 0.4
    assert ndimage.label(captured)[1] == 1
    seed = seed_at(0.0, z=-15.0)
    assert companion_basins(captured, image, seed, SPACING) is None
    found = companion_basins(captured, image, seed, SPACING, across=1.01)
    assert found is not None, "premise: the throat sets basins apart (else the case proves nothing)"
    beyond = np.zeros(SHAPE, bool)
    beyond[int(SHAPE[0] / 2 + 6 / SPACING[0]):] = True
    assert np.count_nonzero(found[1] & beyond) > 0.5 * np.count_nonzero(found[1])


def two_throats(z):
    """Radius (mm) of an artery of 3 mm narrowed to 1.2 mm at two raised-cosine throats, z = -6 and +6 mm."""
    def bump(centre):
        return np.where(np.abs(z - centre) < 3.0, 0.5 * (1 + np.cos(np.pi * (z - centre) / 3.0)), 0.0)
    return 3.0 - 1.8 * (bump(-6.0) + bump(6.0))


def test_a_segment_between_two_seeds_is_not_a_companion():
    """The artery of ``two_throats``, seeded at both ends: the blur cuts it into three basins in a row.  With
    the direction test switched off (every touching basin taken, as when the axis is read across a kink), the
    middle segment joins the two seeds' basins and stays in the vessel.  Seeded at one end only, the same
    segment is taken: it is the link between seeds, not the direction, that keeps it."""
    image = blurred(cylinder(0.0, 3.0, radius_along=two_throats))
    captured = ndimage.gaussian_filter(image, 1.0) > 0.4
    assert ndimage.label(captured)[1] == 1
    seeds = np.vstack([seed_at(0.0, z=-15.0), seed_at(0.0, z=15.0)])
    middle = np.zeros(SHAPE, bool)
    middle[int(SHAPE[0] / 2 - 4 / SPACING[0]):int(SHAPE[0] / 2 + 4 / SPACING[0])] = True
    one = companion_basins(captured, image, seeds[:1], SPACING, across=1.01)
    assert one is not None, "premise: the middle segment is a basin of its own"
    assert np.count_nonzero(one[1] & middle) > 0.9 * np.count_nonzero(captured & middle)
    assert companion_basins(captured, image, seeds, SPACING, across=1.01) is None


def test_a_vein_beside_an_artery_seeded_at_both_ends_is_still_a_companion():
    """The vein of ``test_a_vein_beside_the_artery_is_a_companion`` with the artery seeded at both ends: the
    artery joins its seeds without the vein, so the vein links nothing and stays out."""
    artery, vein = cylinder(-3.3, 3.0), cylinder(3.5, 3.5, 0.9)
    image = blurred(np.maximum(artery, vein))
    captured = ndimage.gaussian_filter(image, 1.0) > 0.5
    seeds = np.vstack([seed_at(-3.3, z=-15.0), seed_at(-3.3, z=15.0)])
    found = companion_basins(captured, image, seeds, SPACING)
    assert found is not None
    assert np.count_nonzero(found[1] & (vein > 0.5)) > 0.8 * np.count_nonzero(found[1])


def test_companions_need_a_dip():
    """Without a dip between them (the two tubes fused, no gap), there is one basin and no companion."""
    fused = np.maximum(cylinder(-3.0, 3.0), cylinder(2.5, 3.5, 1.0))
    image = blurred(fused)
    captured = ndimage.gaussian_filter(image, 1.0) > 0.5
    assert companion_basins(captured, image, seed_at(-3.0), SPACING) is None


def test_segment_parameters_refuse_a_companion_depth_out_of_range():
    from carotid.errors import CarotidError
    from carotid.segment import SegmentParameters

    assert SegmentParameters(companion_depth=0.0).validate().companion_depth == 0.0
    with pytest.raises(CarotidError, match="companion_depth"):
        SegmentParameters(companion_depth=1.0).validate()
