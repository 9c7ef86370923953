"""The blur model of the segmentation against closed-form images: measured blur, calcium edge, refined wall.

Each image is a lumen (and a calcification) blurred by a known Gaussian, so every answer is known exactly;
each test also runs the step with its mechanism switched off and checks that the answer is then wrong.
"""

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage, special

from carotid.io import Volume
from carotid.segment import SegmentParameters, calcium, deblur, segment, segmentation
from carotid.segment.calcium import hyperdense_edge
from carotid.segment.deblur import normal_background, refine
from carotid.segment.intensity import (IntensityModel, edge_blur, local_level, local_linear_level,
                                      through_plane_variance, wide_gaussian)
from carotid.segment.levelset import signed_distance

B, A, P = 40.0, 300.0, 1000.0  # tissue, lumen and calcium levels (HU)
FAT = -100.0
SPACING = np.array([0.3, 0.25, 0.25])  # (k, j, i) mm, anisotropic


def grid(shape, spacing=SPACING):
    """Voxel centres (mm) of a (k, j, i) grid centred on the origin, as three arrays."""
    axes = [(np.arange(n) - (n - 1) / 2) * h for n, h in zip(shape, spacing)]
    return np.meshgrid(*axes, indexing="ij")


def occupancy(sdf, spacing=SPACING):
    """Partial-volume occupancy of each voxel from a signed distance (mm): a ramp one voxel wide."""
    return np.clip(0.5 - sdf / float(np.mean(spacing)), 0.0, 1.0).astype(np.float32)


def blurred(fraction, sigma_mm, spacing=SPACING):
    return ndimage.gaussian_filter(fraction, sigma_mm / np.asarray(spacing))


def tube_sdf(shape, radius):
    """Signed distance (mm) of a straight tube of ``radius`` along k."""
    _, y, x = grid(shape)
    return np.hypot(x, y) - radius


def fat_lobules(shape, spacing, sigma_kji, noise, seed=0):
    """Fat lobules in muscle (a smoothed random field cut at a level, edges facing every way), sampled at the
    voxel centres after a Gaussian blur of standard deviations ``sigma_kji`` (mm), with noise (HU)."""
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.standard_normal(shape), 3.0 / np.asarray(spacing))
    fat = np.clip(0.5 + (field / field.std() - 0.7) / 0.25, 0.0, 1.0)
    image = ndimage.gaussian_filter(B + (FAT - B) * fat, np.asarray(sigma_kji) / np.asarray(spacing))
    return (image + rng.normal(0.0, noise, shape)).astype(np.float32)


@pytest.mark.parametrize("sigma_k", [0.6, 0.95])
def test_the_blur_along_the_slices_is_measured_on_tissue_edges(sigma_k):
    """0.9 mm slices of 0.45 mm pixels, blurred by 0.6 mm within the slices and ``sigma_k`` across them: the
    variance the slice axis adds is measured within 0.06 mm^2 (sigma_k within about 3 %), zero included.  Read
    along a wrong axis, or without the slices' share of the interpolation's widening (+0.10 mm^2), it is not."""
    spacing = np.array([0.9, 0.45, 0.45])
    image = fat_lobules((48, 96, 96), spacing, (sigma_k, 0.6, 0.6), noise=20.0)
    measured = through_plane_variance(image, (slice(None),) * 3, 200.0, spacing)
    assert measured == pytest.approx(sigma_k ** 2 - 0.6 ** 2, abs=0.06)


def test_no_tissue_edges_no_slice_blur():
    """A lumen in uniform tissue has one tissue class below its half level: no estimate rather than a wrong one."""
    shape = (40, 64, 64)
    image = (B + (A - B) * blurred(occupancy(tube_sdf(shape, 4.0)), 0.6)
             + np.random.default_rng(2).normal(0, 20, shape)).astype(np.float32)
    assert through_plane_variance(image, (slice(None),) * 3, 0.5 * (A + B), SPACING) is None


@pytest.mark.parametrize("sigma", [0.4, 0.6, 0.8])
def test_edge_blur_measures_the_blur_of_a_noisy_tube(sigma):
    shape = (40, 64, 64)
    sdf = tube_sdf(shape, 4.0)
    rng = np.random.default_rng(1)
    image = (B + (A - B) * blurred(occupancy(sdf), sigma) + rng.normal(0, 20, shape)).astype(np.float32)
    bright = ndimage.gaussian_filter(image, 1) > 0.5 * (A + B)
    estimate = edge_blur(image, (slice(None),) * 3, bright, 0.5 * (A + B), SPACING)
    # The voxel ramp adds its own width (h / sqrt(12) ~ 0.08 mm) in quadrature.
    assert estimate == pytest.approx(np.hypot(sigma, 0.08), abs=0.06)


def test_edge_blur_needs_a_clean_edge():
    """A region without plateaus around its edge (a thin wire) gives no estimate rather than a wrong one."""
    shape = (30, 40, 40)
    image = (B + (A - B) * blurred(occupancy(tube_sdf(shape, 0.6)), 0.6)).astype(np.float32)
    assert edge_blur(image, (slice(None),) * 3, image > 0.5 * (A + B), 0.5 * (A + B), SPACING) is None


def noisy_tube(tilt_deg, noise, sigma_kji, spacing, seed=1, shape=(48, 80, 80)):
    """A tube of radius 3 mm whose axis leans ``tilt_deg`` from k towards i, blurred by ``sigma_kji`` (mm) and
    with Gaussian noise (HU); the image and the blur ``edge_blur`` should read within the slices (the in-plane
    Gaussian and the voxel ramp in quadrature)."""
    k, j, i = grid(shape, spacing)
    t = np.deg2rad(tilt_deg)
    along = k * np.cos(t) + i * np.sin(t)
    sdf = np.sqrt(np.maximum(k ** 2 + j ** 2 + i ** 2 - along ** 2, 0.0)) - 3.0
    image = B + (A - B) * ndimage.gaussian_filter(occupancy(sdf, spacing), np.asarray(sigma_kji) / spacing)
    image += np.random.default_rng(seed).normal(0.0, noise, shape)
    return image.astype(np.float32), float(np.hypot(sigma_kji[1], np.mean(spacing) / np.sqrt(12)))


def measured_blur(image, spacing, **options):
    bright = ndimage.gaussian_filter(image, 1) > 0.5 * (A + B)
    return edge_blur(image, (slice(None),) * 3, bright, 0.5 * (A + B), spacing, **options)


@pytest.mark.parametrize("seed", [1, 2])
def test_edge_blur_is_not_sharpened_by_noise_nor_widened_by_interpolation(seed):
    """0.8 mm slices of 0.45 mm pixels, a contrast of 7.4 noise SDs: the blur within 2.5 %.  Edges located on
    the lightly smoothed image align the profiles on the noise (3-5 % too sharp when centred on the isosurface,
    1-3 % when centred on their own half levels); linear interpolation of the profiles widens them (4-6 %)."""
    spacing = np.array([0.8, 0.45, 0.45])
    image, truth = noisy_tube(0.0, 35.0, (0.95, 0.6, 0.6), spacing, seed)
    assert measured_blur(image, spacing) == pytest.approx(truth, rel=0.025)
    assert measured_blur(image, spacing, locate_mm=None, own_levels=False) < 0.975 * truth
    assert measured_blur(image, spacing, order=1) > 1.025 * truth


def test_edge_blur_reads_the_blur_within_the_slices_on_a_tube_across_them():
    """A tube leaning 65 degrees out of the slices, blurred by 0.95 mm along k and 0.6 mm within the slices:
    the in-plane blur within 8 %, not the 15 % and more its edges facing along k read (all of them, or those
    facing within 0.3 of the i axis instead of the k axis: 17 %)."""
    spacing = np.array([0.8, 0.45, 0.45])
    image, truth = noisy_tube(65.0, 15.0, (0.95, 0.6, 0.6), spacing)
    assert measured_blur(image, spacing) == pytest.approx(truth, rel=0.08)
    assert measured_blur(image, spacing, max_tilt=1.0) > 1.15 * truth


def fading_tube(fade, seed=1, sigma=0.6):
    """A tube of radius 3 mm along k whose contrast falls linearly by ``fade`` from one end to the other (a
    fading bolus), blurred by ``sigma`` (mm), with 10 HU noise; the image, the blur ``edge_blur`` should read
    and the spacing."""
    spacing = np.array([0.5, 0.45, 0.45])
    k, j, i = grid((64, 64, 64), spacing)
    lumen = blurred(occupancy(np.hypot(j, i) - 3.0, spacing), sigma, spacing)
    image = B + (A - B) * (1.0 - fade * (k - k.min()) / np.ptp(k)) * lumen
    image += np.random.default_rng(seed).normal(0.0, 10.0, k.shape)
    return image.astype(np.float32), float(np.hypot(sigma, np.mean(spacing) / np.sqrt(12))), spacing


def test_edge_blur_reads_each_profile_between_its_own_levels():
    """A bolus fading by half along the tube: each profile centred on its own half level, the blur within 4 %
    (the wall's curvature adds 2 %).  Centred on the seed's half level, the dimmer profiles are shifted
    outward and the median step reads 7 % wider than the blur."""
    image, truth, spacing = fading_tube(0.5)
    assert measured_blur(image, spacing) == pytest.approx(truth, rel=0.04)
    assert measured_blur(image, spacing, own_levels=False) > 1.05 * truth


def test_edge_blur_leaves_out_a_bright_structure_without_a_plateau():
    """A 300 HU lumen beside a vertebra (a 1.6 mm cortex at 1000 HU around 250 HU marrow, both above the
    lumen's half level, 2.5 mm away): the bone's edges have no flat bright side and are left out, the blur
    within 4 %.  Taken with them it reads 27 % too sharp."""
    spacing = np.array([0.5, 0.45, 0.45])
    k, j, i = grid((48, 96, 96), spacing)
    bone = np.hypot(j, i - 5.0) - 7.5
    image = B + (A - B) * occupancy(np.hypot(j, i + 8.0) - 3.0, spacing)
    image += (1000.0 - image) * occupancy(bone, spacing)
    image += (250.0 - image) * occupancy(bone + 1.6, spacing)
    image = blurred(image, 0.6, spacing) + np.random.default_rng(1).normal(0.0, 10.0, k.shape)
    truth = float(np.hypot(0.6, np.mean(spacing) / np.sqrt(12)))
    assert measured_blur(image.astype(np.float32), spacing) == pytest.approx(truth, rel=0.04)
    assert measured_blur(image.astype(np.float32), spacing, own_levels=False) < 0.8 * truth


def calcified_tube(sigma, radius=1.5):
    """A tube of radius 3 mm whose wall holds a calcium sphere (``radius``, mm) reaching 1 mm into the lumen.

    Returns the image and the lumen alone blurred (no calcium).  On the line from the axis to the sphere's
    centre (along +i) the lumen ends where the calcium begins, 2 mm from the axis.
    """
    shape = (48, 64, 64)
    k, j, i = grid(shape)
    sphere = np.sqrt(k ** 2 + j ** 2 + (i - 2.0 - radius) ** 2) - radius
    lumen = np.maximum(tube_sdf(shape, 3.0), -sphere)
    lumen_only = B + (A - B) * blurred(occupancy(lumen), sigma)
    image = lumen_only + (P - B) * blurred(occupancy(sphere), sigma)
    return image.astype(np.float32), lumen_only.astype(np.float32)


def crossing(profile, positions, level):
    """First position where ``profile`` falls below ``level`` (linear interpolation)."""
    below = np.flatnonzero(profile < level)[0]
    x0, x1, y0, y1 = positions[below - 1], positions[below], profile[below - 1], profile[below]
    return x0 + (y0 - level) / (y0 - y1) * (x1 - x0)


def edge_towards_calcium(image):
    """Half-level crossing (mm from the axis) of ``image`` on the axis-to-calcium line."""
    centre = (np.array(image.shape) - 1) / 2
    positions = np.arange(0.0, 3.0, 0.02)
    coords = np.stack([np.full_like(positions, centre[0]), np.full_like(positions, centre[1]),
                       centre[2] + positions / SPACING[2]])
    return crossing(ndimage.map_coordinates(image, coords, order=1), positions, 0.5 * (A + B))


def calcium_edge_error(image, sigma, balls=False, depth_cap=False):
    """Where the corrected image puts the lumen's edge next to the calcium, minus where it is (mm)."""
    corrected, _, info = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, sigma, balls=balls,
                                         depth_cap=depth_cap)
    assert info["structures"] == 1
    return edge_towards_calcium(corrected) - 2.0


@pytest.mark.parametrize("depth_cap", [False, True])
@pytest.mark.parametrize("sigma", [0.45, 0.6])
def test_calcium_and_its_blur_leave_the_lumen_edge_where_it_is(sigma, depth_cap, monkeypatch):
    image, lumen_only = calcified_tube(sigma)
    error = calcium_edge_error(image, sigma, depth_cap=depth_cap)
    assert abs(error) < 0.15
    # The calcium's blur is gone around it: the tissue beyond it is back at the tissue level.
    corrected, _, _ = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, sigma)
    beyond = (24, 32, int(round(31.5 + 5.6 / SPACING[2])))
    assert abs(corrected[beyond] - B) < 0.1 * (A - B) < abs(image[beyond] - B)
    # Mutation: without the subtraction of its blur, the calcium's blur stays in the tissue (a lumen-like shell
    # the front follows).
    kept, _, _ = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, None)
    assert abs(kept[beyond] - B) > 0.5 * abs(image[beyond] - B)
    # Mutations that put the lumen's edge 0.25 mm or more further into the calcification: its extent to the
    # voxel (no sub-voxel edge); the sub-voxel edge without its curvature term.
    monkeypatch.setattr(calcium, "edge_fraction", lambda image, extent, *args, **kwargs: extent.astype(np.float32))
    assert calcium_edge_error(image, sigma, depth_cap=depth_cap) - error > 0.25
    monkeypatch.undo()
    exact = calcium.edge_fraction
    monkeypatch.setattr(calcium, "edge_fraction",
                        lambda image, extent, near, spacing, blur, s, **kwargs: exact(image, extent, near, spacing,
                                                                                     blur, s, curvature=False))
    assert calcium_edge_error(image, sigma, depth_cap=depth_cap) - error > 0.25


@pytest.mark.parametrize("sigma", [0.45, 0.6])
def test_a_small_calcification_keeps_the_lumen_edge_with_the_blurred_ball_model(sigma):
    # A 1 mm nodule is about one and a half blur widths across: the curvature shift, right for structures much
    # wider than the blur, puts its edge 0.4-0.65 mm into the lumen; the blurred ball's own steepest point
    # and ridge put it where it is.  The 1.5 mm nodule stays where it was.
    small, _ = calcified_tube(sigma, radius=1.0)
    assert abs(calcium_edge_error(small, sigma, balls=True)) < 0.15
    assert calcium_edge_error(small, sigma) < -0.3
    large, _ = calcified_tube(sigma)
    assert abs(calcium_edge_error(large, sigma, balls=True)) < 0.15


def walled_nodule(sigma, gap, radius=1.0, density=1400.0):
    """A tube of radius 3 mm and, ``gap`` mm outside its wall, a calcified nodule (``radius``, mm; ``density``,
    HU), blurred by ``sigma``.  Returns the image and the nodule's signed distance (mm)."""
    shape = (48, 64, 64)
    k, j, i = grid(shape)
    ball = np.sqrt(k ** 2 + j ** 2 + (i - 3.0 - gap - radius) ** 2) - radius
    image = (B + (A - B) * blurred(occupancy(tube_sdf(shape, 3.0)), sigma)
             + (density - B) * blurred(occupancy(ball), sigma))
    return image.astype(np.float32), ball


@pytest.mark.parametrize("sigma, gap", [(0.6, 0.0), (0.6, 0.3), (0.75, 0.0), (0.75, 0.3)])
def test_a_nodule_in_the_wall_keeps_no_more_of_the_lumen_than_its_blur_leaves(sigma, gap):
    # A nodule 2 mm across is about three blur widths: the blur fitted on its tissue side takes less off its
    # core than it spread there.  What remains inside it may be the lumen's blur, which at its centre, a
    # millimetre or more from the lumen, is below 5 % of the contrast; kept up to the lumen's half level
    # throughout (without the depth cap), the nodule reads as a pocket of lumen-like intensity.
    image, ball = walled_nodule(sigma, gap)
    centre = ball == ball.min()
    corrected, extent, info = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, sigma, depth_cap=True)
    assert info["structures"] == 1 and extent[ball < -0.5].all()
    assert np.all(corrected[centre] - B < 0.2 * (A - B))
    held, _, _ = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, sigma)
    assert np.all(held[centre] - B > 0.25 * (A - B))


def shelled_tube(sigma, density=700.0, thickness=0.8, half_angle_deg=50.0, length=4.0):
    """A tube of radius 3 mm along k and, against its wall, a calcified shell (``density`` HU, ``thickness``
    mm, ``half_angle_deg`` either side of +i, ``length`` mm along k) in tissue at ``B``, blurred by ``sigma``."""
    shape = (48, 64, 64)
    k, j, i = grid(shape)
    rho = np.hypot(i, j)
    across = np.maximum(3.0 - rho, rho - 3.0 - thickness)
    around = 3.0 * (np.abs(np.arctan2(j, i)) - np.radians(half_angle_deg))
    shell = np.maximum(np.maximum(across, around), np.abs(k) - length / 2)
    image = B + (A - B) * blurred(occupancy(tube_sdf(shape, 3.0)), sigma) + (density - B) * blurred(
        occupancy(shell), sigma)
    return image.astype(np.float32)


def test_the_blur_amplitude_with_the_tissue_level_is_exact_whatever_the_background():
    # A 1.5 mm ball's blur of amplitude 500 HU on tissue at B: fitted with the tissue level, the amplitude is
    # exact whether the background passed is B or 60 HU below it (the neck's level, pulled down by fat).
    # Without it, the 60 HU are taken for blur: the amplitude comes out more than 10 % too large.
    shape = (40, 48, 48)
    k, j, i = grid(shape)
    ball = np.sqrt(k ** 2 + j ** 2 + i ** 2) - 1.5
    fraction = occupancy(ball)
    labels = (fraction > 0).astype(np.int32)
    image = (B + 500.0 * blurred(fraction, 0.6)).astype(np.float32)
    owner = ((ball > 0.3) & (ball < 3.0)).astype(np.int32)
    for background in (B, B - 60.0):
        _, amplitude = calcium.structure_blur(image, labels, 1, fraction, owner, background, SPACING, 0.6,
                                              tissue_offset=True)
        assert amplitude[0] == pytest.approx(500.0, rel=1e-3)
    _, plain = calcium.structure_blur(image, labels, 1, fraction, owner, B - 60.0, SPACING, 0.6)
    assert plain[0] > 1.1 * 500.0


@pytest.mark.parametrize("sigma", [0.45, 0.6])
@pytest.mark.parametrize("density, thickness", [(700.0, 0.8), (1000.0, 0.6)])
def test_with_the_tissue_level_the_lumen_beside_a_shell_does_not_follow_the_background(sigma, density,
                                                                                        thickness):
    # A thin calcified shell against the wall.  The background level the image gives (one for the whole
    # neck) lies a quarter of the contrast below the tissue around the shell.  Without the tissue level the
    # difference is fitted as the shell's blur and subtracted from the lumen beside it too: its edge moves
    # 0.2 mm or more into the lumen.  With it the lumen's edge is where the true background would put it.
    # (Where that is, 0.4-0.9 mm inside the true wall for these shells thinner than two blur widths, is the
    # shell's extent: benchmarks/README.md, bench_second_generator.)
    image = shelled_tube(sigma, density, thickness)
    top = A + 0.3 * (A - B)

    def edge(background, tissue_level):
        corrected, _, info = hyperdense_edge(image, top, A, background, SPACING, sigma,
                                             tissue_offset=tissue_level)
        assert info["structures"] == 1
        return edge_towards_calcium(corrected)

    low = B - 0.25 * (A - B)
    assert abs(edge(low, True) - edge(B, True)) < 0.03
    assert edge(low, True) - edge(low, False) > 0.2


def test_segment_passes_the_tissue_level_to_the_calcium_step(monkeypatch):
    seen = []

    def recording(*args, **kwargs):
        seen.append(kwargs["tissue_offset"])
        return hyperdense_edge(*args, **kwargs)

    monkeypatch.setattr(segmentation, "hyperdense_edge", recording)
    volume = Volume(shelled_tube(0.6), spacing=tuple(SPACING[::-1]))
    seeds = volume.index_to_world(np.array([[6.0, 31.5, 31.5], [41.0, 31.5, 31.5]]))
    for level in (False, True):
        segment(volume, seeds_xyz=seeds, params=SegmentParameters(calcium_tissue_level=level))
    assert seen == [False, True]


def test_the_lumen_blur_cap_is_half_the_contrast_at_the_edge_and_a_gaussian_tail_behind_it():
    spacing = np.array([0.8, 0.4, 0.4])
    depth = np.array([0.4, 0.8, 1.0, 1.6, 10.0], np.float32)  # the first: an outermost voxel
    cap = calcium.lumen_blur_cap(depth, A, B, 0.6, spacing)
    behind = np.maximum(depth - 0.4, 0.0) / 0.6
    np.testing.assert_allclose(cap, B + (A - B) * 0.5 * (1 + np.vectorize(math.erf)(-behind / math.sqrt(2))),
                               rtol=1e-5)
    assert cap[0] == pytest.approx(0.5 * (A + B)) and cap[-1] == pytest.approx(B)


def test_the_blurred_balls_are_steepest_where_their_closed_forms_say():
    radii, steepest = calcium.ball_flanks()
    # A vanishing ball is steepest at the Gaussian's inflection; a wide one at its radius less (n - 1) / (2 R).
    np.testing.assert_allclose(steepest[:, 0], 1.0, atol=0.01)
    wide = radii == 5.0
    np.testing.assert_allclose(steepest[:, wide].ravel(), [5.0, 5.0 - 1 / 10, 5.0 - 2 / 10], atol=0.01)
    # A plate of half-thickness R (1-D) is steepest where its two edges' Gaussians balance:
    # (r + R) g(r + R) = (r - R) g(r - R), checked at R = 1.
    r = steepest[0, radii == 1.0][0]
    assert (r + 1) * np.exp(-0.5 * (r + 1) ** 2) == pytest.approx((r - 1) * np.exp(-0.5 * (r - 1) ** 2), abs=2e-3)
    # The radius from the steepest point inverts the table, for each dimension and between them.
    np.testing.assert_allclose(calcium.ball_radius(steepest[2, 40:60], np.full(20, 2.0)), radii[40:60], atol=1e-6)
    # For the same steepest point a rod is wider than a plate, and a shape between them lies between.
    plate, between, rod = (calcium.ball_radius(np.array([2.0]), np.array([m]))[0] for m in (0.0, 0.5, 1.0))
    assert plate < between < rod


def test_nothing_hyperdense_leaves_the_image_alone():
    _, lumen_only = calcified_tube(0.6)
    corrected, extent, info = hyperdense_edge(lumen_only, A + 0.3 * (A - B), A, B, SPACING, 0.6)
    assert info["structures"] == 0 and not extent.any()
    np.testing.assert_array_equal(corrected, lumen_only)


def ray_radii(phi, spacing=SPACING):
    """Radius (mm) of the zero level of ``phi`` on 36 rays from the tube's axis in the middle section; ray
    ``a`` points at angle ``10 a`` degrees from +i towards +j."""
    centre = (np.array(phi.shape) - 1) / 2
    angles = np.radians(np.arange(0, 360, 10))
    r = np.arange(0.0, 3.5, 0.01)
    coords = np.stack([np.full((36, r.size), centre[0]),
                       centre[1] + np.outer(np.sin(angles), r) / spacing[1],
                       centre[2] + np.outer(np.cos(angles), r) / spacing[2]]).reshape(3, -1)
    values = ndimage.map_coordinates(phi, coords, order=1).reshape(36, r.size)
    return np.array([crossing(-v, r, 0.0) for v in values])


def radius_of(phi, spacing=SPACING):
    """Mean radius (mm) of the zero level of ``phi`` on rays from the tube's axis in the middle section."""
    return float(np.mean(ray_radii(phi, spacing)))


@pytest.mark.parametrize("radius,sigma", [(1.2, 0.7), (2.5, 0.5)])
def test_refinement_moves_an_edge_front_to_the_true_wall(radius, sigma):
    """A blurred tube's half-level contour lies sigma^2 / (2 R) inside its wall; the refinement removes that."""
    shape = (24, 64, 64)
    rng = np.random.default_rng(3)
    image = (B + (A - B) * blurred(occupancy(tube_sdf(shape, radius)), sigma)
             + rng.normal(0, 15, shape)).astype(np.float32)
    half = ndimage.gaussian_filter(image, 0.5 / SPACING) > 0.5 * (A + B)
    start = (ndimage.distance_transform_edt(~half, sampling=SPACING)
             - ndimage.distance_transform_edt(half, sampling=SPACING)).astype(np.float32)
    before = radius_of(start)
    assert radius - before > 0.5 * sigma ** 2 / (2 * radius)  # premise: the edge front is too narrow
    after = radius_of(refine(image, start, SPACING, A, B, sigma))
    assert after == pytest.approx(radius, abs=0.06)
    # Mutation: no descent steps leaves the front where it was.
    assert radius_of(refine(image, start, SPACING, A, B, sigma, iterations=0)) == pytest.approx(before, abs=1e-6)


def test_refinement_narrows_a_front_that_is_too_wide_and_stays_within_a_blur_width():
    shape = (24, 64, 64)
    sdf = tube_sdf(shape, 2.0)
    image = (B + (A - B) * blurred(occupancy(sdf), 0.6)).astype(np.float32)
    assert radius_of(refine(image, (sdf - 0.35).astype(np.float32), SPACING, A, B, 0.6)) == pytest.approx(2.0, abs=0.06)
    # A front 2 mm too wide may move by one blur width only: the refinement corrects, it does not re-segment.
    far = refine(image, (sdf - 2.0).astype(np.float32), SPACING, A, B, 0.6)
    assert radius_of(far) >= 4.0 - 0.6 - 0.02


def test_the_lumen_level_is_read_on_a_core_with_the_blur_taken_out(monkeypatch):
    """A 4 mm tube blurred by 0.8 mm: two blur widths inside its wall the blur still darkens the core by 4 % of
    the contrast, so a model built on the core's plain mean is too dark and moves the true wall 0.08 mm out.
    The level is followed from the core (``level_mm``) from a default 50 HU too low; with the blur taken out
    of the core the wall stays where it is."""
    shape = (24, 64, 64)
    sdf = tube_sdf(shape, 2.0).astype(np.float32)
    image = (B + (A - B) * blurred(occupancy(sdf), 0.8)
             + np.random.default_rng(3).normal(0, 15, shape)).astype(np.float32)
    assert radius_of(refine(image, sdf, SPACING, A - 50.0, B, 0.8, level_mm=10.0)) == pytest.approx(2.0, abs=0.02)
    # Mutation: the core's plain mean.
    monkeypatch.setattr(deblur, "lumen_level", lambda image, tissue, phi, core, spacing, blur, ramp, scale, default,
                        linear: local_level(image, core, spacing, scale, default))
    assert radius_of(refine(image, sdf, SPACING, A - 50.0, B, 0.8, level_mm=10.0)) > 2.05


def bulb_and_branch(fade_per_mm: float, spacing=np.array([0.5, 0.3, 0.3])):
    """A 3.5 mm bulb (z < -6 mm) going on into a 1.5 mm branch along k, whose lumen level fades by
    ``fade_per_mm`` HU per mm along the vessel, blurred by 0.6 mm, 10 HU noise.  Returns the image, the
    spacing, the true signed distance, the true level and the k coordinates (mm)."""
    shape = (64, 48, 48)
    z, y, x = grid(shape, spacing)
    sdf = (np.hypot(x, y) - np.where(z < -6.0, 3.5, 1.5)).astype(np.float32)
    level = (A - fade_per_mm * (z - z.min())).astype(np.float32)
    image = B + (level - B) * blurred(occupancy(sdf, spacing), 0.6, spacing)
    image += np.random.default_rng(4).normal(0, 10, shape)
    return image.astype(np.float32), spacing, sdf, level, z


def test_the_followed_lumen_level_does_not_lean_towards_a_wider_bulb():
    """The bolus fades by 1.5 HU/mm (0.6 % of the contrast) along a bulb and its 1.5 mm branch.  Near the bulb
    the branch's few core voxels are outweighed by the bulb's many, so a local mean reads the branch's level
    10-17 HU too bright and a refinement on it narrows the branch by 0.07 mm; the local linear fit follows the
    fade, and the wall stays."""
    image, spacing, sdf, level, z = bulb_and_branch(1.5)
    core, near = sdf < -1.0, sdf < 1.0
    branch = near & (z > -4.0)
    fitted = local_linear_level(level, core, spacing, 10.0, A, near)
    assert np.abs(fitted - level)[branch].max() < 1.0
    assert np.abs(local_level(level, core, spacing, 10.0, A) - level)[branch].min() > 9.0
    # Mutation: a ridge so strong the slope vanishes, i.e. the local mean.
    assert np.abs(local_linear_level(level, core, spacing, 10.0, A, near, ridge=1e6) - level)[branch].min() > 9.0
    # The middle section lies 6 mm into the branch.
    linear = refine(image, sdf, spacing, A, B, 0.6, level_mm=10.0, linear_level=True)
    assert radius_of(linear, spacing) == pytest.approx(1.5, abs=0.02)
    assert radius_of(refine(image, sdf, spacing, A, B, 0.6, level_mm=10.0), spacing) < 1.5 - 0.05


def throat_image(slices: int, h: float = 0.3, sigma: float = 0.6, length: float = 1.5, depth: float = 0.9,
                 step: int | None = None, nc: int = 15):
    """A tube along k, radius ``2 - depth exp(-z^2 / (2 length^2))`` mm (throat 1.1 mm at z = 0), blurred by
    ``sigma`` on an isotropic grid of ``h`` mm and integrated over slices ``slices`` grid planes thick (as a
    scanner's thick slice does), one every ``step`` planes (default ``slices``: contiguous; fewer overlap);
    10 HU noise.  Returns the image, its spacing and the true signed distance (``r - R(z)``) on its grid."""
    n, step = 64, step or slices
    assert slices % 2 == 1, "an odd number of planes puts each slice's centre on a plane"
    planes = (nc - 1) * step + slices
    zf = (np.arange(planes) - (planes - 1) / 2) * h
    zc = zf[slices // 2::step][:nc]
    xy = (np.arange(n) - (n - 1) / 2) * h

    def sdf(z):
        zz, y, x = np.meshgrid(z, xy, xy, indexing="ij")
        return np.hypot(x, y) - (2.0 - depth * np.exp(-zz ** 2 / (2 * length ** 2)))

    fine = blurred(np.clip(0.5 - sdf(zf) / h, 0, 1).astype(np.float32), sigma, np.full(3, h))
    image = B + (A - B) * ndimage.uniform_filter1d(fine, slices, axis=0)[slices // 2::step][:nc]
    image += np.random.default_rng(5).normal(0, 10, image.shape)
    return image.astype(np.float32), np.array([step * h, h, h]), sdf(zc).astype(np.float32)


def test_a_thick_slice_blurs_a_throat_along_the_vessel_and_the_model_does_too():
    """A 1.1 mm throat in 1.5 mm slices: the slice's boxcar fills the throat from the wider lumen on either
    side, and a model blurred along the vessel by the in-plane blur alone widens the throat to match."""
    image, spacing, sdf = throat_image(slices=5)
    blur = deblur.gaussian_part(float(np.hypot(0.6, 0.3 / np.sqrt(12))), spacing)  # from what edge_blur measures
    # The middle slice is the throat's.
    assert radius_of(refine(image, sdf, spacing, A, B, blur), spacing) == pytest.approx(1.1, abs=0.035)
    # Mutation: the in-plane blur along every axis.
    assert radius_of(refine(image, sdf, spacing, A, B, blur, slices=False), spacing) > 1.1 + 0.045
    np.testing.assert_allclose(deblur.axis_blur(0.6, spacing), [np.sqrt(0.36 + (1.5 ** 2 - 0.09) / 12), 0.6, 0.6])


def test_overlapping_slices_blur_a_throat_by_their_thickness_not_their_spacing():
    """2.1 mm slices every 0.6 mm (overlapping, as CT angiograms are reconstructed): each slice integrates
    2.1 mm of the vessel, so a model that takes the 0.6 mm spacing for the slice's extent is blurred too
    little along the vessel and widens the short 1.1 mm throat to match; given the thickness, it finds it."""
    image, spacing, sdf = throat_image(slices=7, step=2, nc=25, length=1.0)
    assert spacing[0] == pytest.approx(0.6)
    blur = deblur.gaussian_part(float(np.hypot(0.6, 0.3 / np.sqrt(12))), spacing)  # from what edge_blur measures
    assert radius_of(refine(image, sdf, spacing, A, B, blur, thickness_mm=2.1), spacing) == pytest.approx(
        1.1, abs=0.025)
    # Mutation: the slice spacing taken for the thickness.
    assert radius_of(refine(image, sdf, spacing, A, B, blur), spacing) > 1.1 + 0.04
    np.testing.assert_allclose(deblur.axis_blur(0.6, spacing, 2.1), [np.sqrt(0.36 + (2.1 ** 2 - 0.09) / 12), 0.6, 0.6])
    # Slices thinner than the pixels still integrate over their own thickness.
    np.testing.assert_allclose(deblur.axis_blur(0.05, [0.2, 0.5, 0.5], 0.2)[0], 0.2 / np.sqrt(12))
    assert deblur.reach_mm(0.6, spacing, 2.1) > deblur.reach_mm(0.6, spacing)


def test_the_wall_radius_is_the_throats_own_not_its_neighbours():
    """Beside a short 1.1 mm throat in a 2 mm tube the ray down the inward normal reaches the throat's axis: the
    wall there reads the throat's radius, and the tube's wall 6 mm away its own.  No voxel centre lies on the
    axis, where interpolation cuts the depth's peak: read as the peak's height rather than its place, the tube
    came out 0.14 mm narrow.  A ray shorter than the radius reads its own length."""
    _, spacing, sdf = throat_image(slices=1, h=0.3, sigma=0.6, length=1.0, nc=41)
    z = (np.arange(sdf.shape[0]) - (sdf.shape[0] - 1) / 2) * spacing[0]
    wall = np.abs(sdf) < 0.2
    radius = np.zeros(sdf.shape, np.float32)
    radius[wall] = deblur.wall_radius(sdf, spacing, wall, 4.0)
    throat, tube = wall & (np.abs(z) < 0.1)[:, None, None], wall & (np.abs(z) > 5.5)[:, None, None]
    # To a step of the ray and the grid's offset from the axis (the nearest voxel centres lie 0.2 mm off it).
    assert np.median(radius[throat]) == pytest.approx(1.1, abs=0.12)
    assert np.median(radius[tube]) == pytest.approx(2.0, abs=0.12)
    assert np.median(deblur.wall_radius(sdf, spacing, tube, 1.2)) == pytest.approx(1.2, abs=0.12)


def half_level_front(image, spacing):
    """The front an edge-based evolution leaves: the signed distance (mm) of the lightly smoothed image's half
    level between ``A`` and ``B``."""
    half = ndimage.gaussian_filter(image, 0.5) > 0.5 * (A + B)
    return signed_distance((ndimage.distance_transform_edt(~half, sampling=spacing)
                            - ndimage.distance_transform_edt(half, sampling=spacing)).astype(np.float32), spacing, 6.0)


def test_a_short_throat_is_refined_at_its_own_scale():
    """A 1.1 mm throat whose narrowing spans about a millimetre each way, blurred by 0.6 mm, from the front an
    edge-based evolution leaves (the blurred image's half level).  Smoothed over a millimetre, the wall's speed
    spreads the wider lumen's pull over the throat and the refinement widens it by 0.03 mm; smoothed over
    at most 0.4 of the radius beside the wall, the throat keeps its width."""
    image, spacing, sdf = throat_image(slices=1, h=0.3, sigma=0.6, length=1.0, nc=41)
    front = half_level_front(image, spacing)
    assert radius_of(refine(image, front, spacing, A, B, 0.6, smooth_radius=0.4), spacing) == pytest.approx(
        1.1, abs=0.015)
    # Mutation: the same smoothing everywhere.
    assert radius_of(refine(image, front, spacing, A, B, 0.6), spacing) > 1.1 + 0.025


def test_the_default_refinement_follows_the_level_and_corrects_a_throat_at_its_scale():
    """``segment``'s refinement with the default parameters (``segmentation.deblur``) keeps both walls that
    ``refine``'s options keep above: the 1.5 mm branch beyond a fading bulb, whose level a local mean reads too
    bright, and the short 1.1 mm throat, which a smoothing of a millimetre everywhere widens."""
    model = IntensityModel(lumen=A, spread=10.0, background=B, source="seeds", blur=0.6)

    def refined(image, phi, spacing, **overrides):
        return radius_of(segmentation.deblur(image, phi, spacing, model, SegmentParameters(**overrides), None,
                                             None)[0], spacing)

    image, spacing, sdf, _, _ = bulb_and_branch(1.5)
    assert refined(image, sdf, spacing) == pytest.approx(1.5, abs=0.03)
    # Mutation: the local mean.
    assert refined(image, sdf, spacing, deblur_linear_level=False) < 1.5 - 0.06
    image, spacing, _ = throat_image(slices=1, h=0.3, sigma=0.6, length=1.0, nc=41)
    front = half_level_front(image, spacing)
    assert refined(image, front, spacing) == pytest.approx(1.1, abs=0.015)
    # Mutation: the same smoothing everywhere.
    assert refined(image, front, spacing, deblur_smooth_radius=0.0) > 1.1 + 0.025


def ramped_step(x, ramp, sigma):
    """Closed form of the lumen indicator ``clip(0.5 - x / ramp, 0, 1)`` (a flat wall at ``x = 0``, lumen at
    negative ``x``, mm) blurred by a Gaussian of ``sigma`` mm: the difference of ``F(u) = u Phi(u / sigma) +
    sigma phi(u / sigma)`` across the ramp, over its width."""
    def antiderivative(u):
        return u * special.ndtr(u / sigma) + sigma * np.exp(-0.5 * (u / sigma) ** 2) / math.sqrt(2.0 * math.pi)
    return (antiderivative(0.5 * ramp - x) - antiderivative(-0.5 * ramp - x)) / ramp


@pytest.mark.parametrize("offset", [0.0, 0.2])
def test_the_blur_model_explains_the_closed_form_image_of_its_wall(offset):
    """A flat wall blurred by 0.6 mm, built from the closed form (``ramped_step``): the model
    (``deblur.blur_model``) of a level set at the true wall leaves a misfit below 0.5 % of the contrast (the
    tissue level is read along the normals where the lumen's blur has not quite died out: 0.4 % high), and
    of a level set ``offset`` too narrow the difference of the two closed forms.  Mutations: the model
    blurred by 20 % more, or its indicator's ramp reversed, leave a misfit at the true wall."""
    sigma, shape = 0.6, (10, 12, 48)
    _, _, x = grid(shape)
    ramp = deblur.ramp_width(SPACING)
    image = (B + (A - B) * ramped_step(x, ramp, sigma)).astype(np.float32)
    phi = (x + offset).astype(np.float32)  # the wall at x = -offset
    model = deblur.blur_model(image, phi, SPACING, A, B, sigma, slices=False)
    inner = (slice(None), slice(None), slice(12, -12))  # the band, clear of the box's ends
    misfit = deblur.model_misfit(model, model.phi0)[inner]
    expected = (A - B) * (ramped_step(x, ramp, sigma) - ramped_step(x + offset, ramp, sigma))[model.box][inner]
    weight = model.weight[inner]
    assert weight.sum() > 500
    assert np.max(np.abs(misfit - np.where(weight, expected, 0.0))) < 0.005 * (A - B)
    if offset == 0.0:
        wider = deblur.blur_model(image, phi, SPACING, A, B, 1.2 * sigma, slices=False)
        assert np.max(np.abs(deblur.model_misfit(wider, wider.phi0)[inner])) > 0.02 * (A - B)
        reversed_ramp = dataclasses.replace(model, ramp=-model.ramp)
        assert np.max(np.abs(deblur.model_misfit(reversed_ramp, model.phi0)[inner])) > 0.2 * (A - B)


def test_the_model_does_not_count_the_voxel_twice():
    """A 1.1 mm throat in 0.5 mm voxels: the image's edges hold the voxel's boxcar as well as the scanner's
    Gaussian, and ``edge_blur`` measures both; the model's lumen indicator carries that boxcar as its
    partial-volume ramp, so its Gaussian is the measured blur less the ramp's variance.  Blurred by the whole
    measured width, the model's throat is filled more than the image's, and it is matched with a wider wall."""
    image, spacing, sdf = throat_image(slices=1, h=0.5, sigma=0.4, length=1.0, nc=24)
    measured = float(np.hypot(0.4, 0.5 / np.sqrt(12)))  # edge_blur's reading (test_edge_blur_measures...)
    assert deblur.gaussian_part(measured, spacing) == pytest.approx(0.4)
    assert radius_of(refine(image, sdf, spacing, A, B, deblur.gaussian_part(measured, spacing)),
                     spacing) == pytest.approx(1.1, abs=0.008)
    # Mutation: the model blurred by the measured width, its ramp counted twice.
    assert radius_of(refine(image, sdf, spacing, A, B, measured), spacing) > 1.1 + 0.012
    # A reading narrower than the voxel's own boxcar keeps half of itself.
    assert deblur.gaussian_part(0.1, [1.0, 1.0, 1.0]) == pytest.approx(0.05)


def test_the_refinement_reads_its_level_set_only_within_its_reach():
    """A level set clamped at ``reach_mm`` refines to the same wall, bit for bit, as the exact distance."""
    image, spacing, sdf = throat_image(slices=3)
    blur = 0.6
    reach = deblur.reach_mm(blur, spacing)
    assert 0 < reach < np.abs(sdf).max()
    exact = refine(image, sdf, spacing, A, B, blur, level_mm=10.0)

    def clamped(at):
        return refine(image, np.clip(sdf, -at, at), spacing, A, B, blur, level_mm=10.0)

    near = np.abs(exact) < 1.0
    at_reach = clamped(reach)
    np.testing.assert_array_equal(at_reach[near], exact[near])
    np.testing.assert_array_equal(at_reach < 0, exact < 0)
    # Mutation: clamped well within the model's reach (the bound is about twice what this case needs), the
    # wall moves.
    assert not np.array_equal(clamped(0.3 * reach)[near], exact[near])


@pytest.mark.parametrize("sigma", [0.6, 0.8])
@pytest.mark.parametrize("offset", [-0.3, 0.3])
def test_fat_on_one_side_of_the_wall_neither_dents_nor_bulges_it(sigma, offset):
    """A tube with fat (-90 HU) against one half of its wall and muscle (+50 HU) against the other: the tissue
    level taken along each normal puts both halves on the true wall; the shell's smoothed mean, which averages
    the two tissues, pulls the fat side in and pushes the muscle side out by about 0.1 mm."""
    shape = (24, 80, 80)
    sdf = tube_sdf(shape, 2.0)
    _, _, x = grid(shape)
    tissue = np.where(x < 0, -90.0, 50.0)
    fraction = occupancy(sdf)
    image = blurred(A * fraction + tissue * (1 - fraction), sigma)
    image = (image + np.random.default_rng(1).normal(0, 10, shape)).astype(np.float32)
    start = (sdf + offset).astype(np.float32)  # a front 0.3 mm too narrow or too wide
    fat_side, muscle_side = np.arange(12, 25), np.r_[0:7, 30:36]
    radii = ray_radii(refine(image, start, SPACING, A, 0.0, sigma))
    assert radii[fat_side].mean() == pytest.approx(2.0, abs=0.03)
    assert radii[muscle_side].mean() == pytest.approx(2.0, abs=0.03)
    # Mutation: the shell's smoothed mean alone.
    shell = ray_radii(refine(image, start, SPACING, A, 0.0, sigma, normal=False))
    assert shell[fat_side].mean() < 1.95 and shell[muscle_side].mean() > 2.04


def test_the_tissue_along_a_normal_is_never_read_in_a_neighbouring_branch():
    """Two parallel lumens 1.2 mm apart, as at a flow divider: the normal of the wall facing the other lumen
    reaches into it within 2.5 blur widths; those samples are dropped and the tissue level stays the
    tissue's, not the lumen's."""
    shape = (24, 64, 96)
    _, y, x = grid(shape)
    sdf = np.minimum(np.hypot(x + 3.2, y), np.hypot(x - 3.2, y)) - 2.0  # walls 1.2 mm apart at x = 0
    image = blurred(B + (A - B) * occupancy(sdf), 0.6).astype(np.float32)
    level = normal_background(image, sdf.astype(np.float32), SPACING, 0.6, None,
                              np.full(shape, B, np.float32))
    facing = (np.abs(sdf) < 0.1) & (np.abs(x) < 1.5)
    assert facing.sum() > 50
    np.testing.assert_allclose(level[facing], B, atol=5.0)
    beyond = (np.abs(sdf) < 0.1) & (np.abs(x) > 4.5)  # walls facing away read the blurred-out tissue
    np.testing.assert_allclose(level[beyond], B, atol=5.0)


def test_the_tissue_along_a_normal_skips_what_is_excluded():
    """A vein (250 HU) 1.5-3.5 mm beyond one side of a tube's wall, held out of the lumen up to the darkest
    point between the two (as ``barrier.competing_region`` holds it): the normals on that side end in it,
    and the tissue level there stays at the fallback; read through it (the mutant), it is the vein's."""
    shape = (24, 64, 80)
    _, y, x = grid(shape)
    sdf = tube_sdf(shape, 2.0)
    vein = (x > 3.5) & (x < 5.5) & (np.abs(y) < 3.0)
    image = blurred(np.where(vein, 250.0, B) + (A - B) * occupancy(sdf), 0.6).astype(np.float32)
    fallback = np.full(shape, B, np.float32)
    facing = (np.abs(sdf) < 0.1) & (x > 1.8)
    held = (x > 2.75) & (np.abs(y) < 3.5)
    level = normal_background(image, sdf.astype(np.float32), SPACING, 0.6, held, fallback)
    np.testing.assert_allclose(level[facing], B, atol=0.1 * (250.0 - B))
    through = normal_background(image, sdf.astype(np.float32), SPACING, 0.6, None, fallback)
    assert np.median(through[facing]) > B + 0.5 * (250.0 - B)


@pytest.mark.parametrize("gap", [0.8, 1.2, 2.0])
def test_a_vein_beside_the_wall_does_not_pull_it_in(gap):
    """A jugular vein (75 % of the arterial contrast, radius 3 mm) ``gap`` mm beside a 2 mm tube, blurred by
    0.6 mm, held out of nothing: with ``neighbours`` the refinement takes a front 0.25 mm inside the wall to
    the wall on the side facing the vein (rays within 30 degrees).  Mutation (and the default): with the vein taken for tissue the normals end in it,
    the model's background is the vein's, and the wall stays 0.1 mm (vein 2 mm away) to 0.45 mm (0.8 mm
    away) inside."""
    shape = (24, 64, 96)
    _, y, x = grid(shape)
    sdf = tube_sdf(shape, 2.0).astype(np.float32)
    vein = np.hypot(x - (2.0 + gap + 3.0), y) - 3.0
    image = (B + (A - B) * blurred(occupancy(sdf) + 0.75 * occupancy(vein), 0.6)
             + np.random.default_rng(6).normal(0, 10, shape)).astype(np.float32)
    facing = [0, 1, 2, 34, 35]
    start = sdf + np.float32(0.25)  # a front 0.25 mm inside the wall
    kept = ray_radii(refine(image, start, SPACING, A, B, 0.6, neighbours=True))[facing]
    np.testing.assert_allclose(kept, 2.0, atol=0.06)
    pulled = ray_radii(refine(image, start, SPACING, A, B, 0.6))[facing]
    assert np.median(pulled) < 2.0 - 0.08


def test_a_bright_spot_inside_the_lumen_is_not_calcium(monkeypatch):
    """Contrast brighter than the window's top 4 mm from any wall (streaming, noise on a coarse scan) stays lumen."""
    shape = (40, 64, 64)
    k, j, i = grid(shape)
    spot = np.sqrt(k ** 2 + j ** 2 + i ** 2) - 0.8
    image = (B + (A - B) * blurred(occupancy(tube_sdf(shape, 6.0)), 0.6)
             + (P - A) * blurred(occupancy(spot), 0.6)).astype(np.float32)
    corrected, extent, _ = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, 0.6)
    assert not extent.any()
    np.testing.assert_array_equal(corrected, image)
    # Mutation: taken for calcium, the spot is cut out of the lumen, a hole no brighter than the half level.
    monkeypatch.setattr(calcium, "in_the_wall", lambda extent, *args: extent)
    cut, _, _ = hyperdense_edge(image, A + 0.3 * (A - B), A, B, SPACING, 0.6)
    assert cut[tuple(n // 2 for n in shape)] <= 0.5 * (A + B)


@pytest.mark.parametrize("sigma", [(12.0, 12.0, 8.0), (22.0, 6.0, 14.0)])
def test_wide_gaussian_matches_the_direct_filter(sigma):
    """The coarse-grid Gaussian of ``local_level`` against scipy's direct filter on a smooth field with a
    masked-out half (a lumen core ending inside the field of view)."""
    rng = np.random.default_rng(5)
    field = ndimage.gaussian_filter(rng.normal(0, 100, (90, 110, 70)).astype(np.float32), 3) + 300
    field[:, :, 40:] = 0
    direct = ndimage.gaussian_filter(field, sigma, mode="nearest")
    coarse = wide_gaussian(field, sigma)
    assert coarse.dtype == np.float32 and coarse.shape == field.shape
    assert np.abs(coarse - direct).max() < 0.01 * np.ptp(direct)


def test_separable_upsampling_and_label_maxima_match_scipy():
    """The coarse grid's upsampling equals ``ndimage.zoom`` (linear, block-aligned, held beyond the last block
    centre), a one-block axis included; the per-structure maxima equal ``ndimage.maximum``."""
    from carotid.segment.calcium import label_maximum
    from carotid.segment.intensity import _upsample_linear

    rng = np.random.default_rng(2)
    coarse = rng.random((5, 1, 7)).astype(np.float32)
    factor, shape = (3, 4, 5), (14, 4, 33)
    fine = coarse
    for axis in range(3):
        fine = _upsample_linear(fine, axis, factor[axis], shape[axis])
    zoomed = ndimage.zoom(coarse, factor, order=1, mode="nearest", grid_mode=True)[:14, :4, :33]
    assert fine.shape == shape and np.abs(fine - zoomed).max() < 1e-6
    labels = rng.integers(0, 6, 500)
    values = rng.normal(size=500)
    inside = labels > 0
    assert np.array_equal(label_maximum(values[inside], labels[inside], 5),
                          ndimage.maximum(values, labels, np.arange(1, 6)))


def test_slab_filters_equal_scipy_bit_for_bit(monkeypatch):
    """The Gaussian (orders 0 and 1, anisotropic, several boundary modes) and box maximum filters computed in
    two slabs on two threads give scipy's arrays exactly; a halo one voxel short of the kernel does not."""
    from carotid.segment import preprocess

    monkeypatch.setattr(preprocess, "SLAB_VOXELS", 1000)
    rng = np.random.default_rng(3)
    a = rng.random((41, 23, 17)).astype(np.float32)
    for sigma, order, options in (((1.3, 0.7, 2.0), 0, {}), ((2.2, 1.0, 1.0), (1, 0, 0), {"output": np.float32}),
                                  (1.5, 0, {"mode": "nearest", "truncate": 3.0})):
        assert np.array_equal(preprocess.gaussian_filter(a, sigma, order=order, **options),
                              ndimage.gaussian_filter(a, sigma, order=order, **options))
    for size in (5, (7, 3, 3)):
        assert np.array_equal(preprocess.maximum_filter(a, size), ndimage.maximum_filter(a, size=size))
    short = preprocess._in_slabs(lambda x: ndimage.gaussian_filter(x, 2.0), a, int(4.0 * 2.0 + 0.5) - 1)
    assert not np.array_equal(short, ndimage.gaussian_filter(a, 2.0))


@pytest.mark.parametrize("bad", [{"deblur_iterations": -1}, {"deblur_gain": 0.0}, {"deblur_smooth_mm": -0.5},
                                 {"deblur_smooth_radius": -0.5}])
def test_bad_refinement_parameters_are_refused(bad):
    from carotid.errors import CarotidError
    from carotid.segment import SegmentParameters

    with pytest.raises(CarotidError, match="deblur"):
        SegmentParameters(**bad).validate()


def test_segment_takes_the_slice_thickness_from_the_scan_or_the_parameter():
    """The thickness a scan records reaches the blur model (the throat of overlapping slices comes out
    narrower, nearer its 1.1 mm, than with the spacing taken for the thickness); the parameter overrides it,
    and the report says which was used."""
    image, spacing, sdf = throat_image(slices=7, step=2, nc=25, length=1.0)
    grid = dict(spacing=tuple(spacing[::-1]), origin=(-9.45, -9.45, -7.2))
    seeds = [[0.0, 0.0, -6.0], [0.0, 0.0, 6.0]]
    runs = {name: segment(Volume(image, **grid, slice_thickness=thickness), seeds_xyz=seeds,
                          params=SegmentParameters(slice_thickness_mm=parameter))
            for name, thickness, parameter in (("spacing", None, 0.0), ("image", 2.1, 0.0),
                                                ("parameter", 2.1, 0.6))}
    for name, run in runs.items():
        assert run.report["intensity"]["slice_thickness_source"] == {"spacing": "slice spacing"}.get(name, name)
    blur = runs["image"].report["intensity"]["blur_mm"]
    np.testing.assert_allclose(runs["image"].report["intensity"]["model_blur_kji_mm"],
                               deblur.axis_blur(deblur.gaussian_part(blur, spacing), spacing, 2.1))
    radius = {name: radius_of(run.levelset.array, spacing) for name, run in runs.items()}
    assert abs(radius["image"] - 1.1) < abs(radius["spacing"] - 1.1) - 0.02
    # A parameter equal to the spacing gives the spacing's wall.
    assert radius["parameter"] == pytest.approx(radius["spacing"], abs=1e-6)


def test_a_measured_slice_blur_reaches_the_model_and_the_report(monkeypatch):
    """``measure_slice_blur``: the measured variance ``v`` becomes the thickness whose boxcar adds ``v`` to the
    in-plane blur along k; a given thickness overrides it, and without tissue edges the spacing is kept."""
    image, spacing, _ = throat_image(slices=7, step=2, nc=25, length=1.0)
    volume = Volume(image, spacing=tuple(spacing[::-1]), origin=(-9.45, -9.45, -7.2))
    seeds = [[0.0, 0.0, -6.0], [0.0, 0.0, 6.0]]
    unmeasured = segment(volume, seeds_xyz=seeds, params=SegmentParameters(measure_slice_blur=True))
    assert unmeasured.report["intensity"]["slice_thickness_source"] == "slice spacing"
    monkeypatch.setattr(segmentation, "through_plane_variance", lambda *args: 0.25)
    runs = {parameter: segment(volume, seeds_xyz=seeds, params=SegmentParameters(
        measure_slice_blur=True, slice_thickness_mm=parameter)) for parameter in (0.0, 0.6)}
    measured = runs[0.0].report["intensity"]
    assert measured["slice_thickness_source"] == "measured"
    gaussian = deblur.gaussian_part(measured["blur_mm"], spacing)
    assert measured["model_blur_kji_mm"][0] == pytest.approx(np.hypot(gaussian, 0.5))
    assert runs[0.6].report["intensity"]["slice_thickness_source"] == "parameter"


def test_segment_passes_the_depth_cap_to_the_calcium_step(monkeypatch):
    """``calcium_depth_cap`` reaches ``hyperdense_edge``: with it the walled nodule's core leaves the image the
    front reads near the tissue level, without it near the lumen's half level."""
    image, ball = walled_nodule(0.75, 0.3)
    centre = ball == ball.min()
    seen = {}

    def recording(*args, **kwargs):
        corrected, extent, info = hyperdense_edge(*args, **kwargs)
        seen[kwargs["depth_cap"]] = float(np.max(corrected[centre]))
        return corrected, extent, info

    monkeypatch.setattr(segmentation, "hyperdense_edge", recording)
    volume = Volume(image, spacing=tuple(SPACING[::-1]))
    seeds = volume.index_to_world(np.array([[6.0, 31.5, 31.5], [41.0, 31.5, 31.5]]))
    for cap in (False, True):
        segment(volume, seeds_xyz=seeds, params=SegmentParameters(calcium_depth_cap=cap))
    assert set(seen) == {False, True}
    assert seen[True] - B < 0.2 * (A - B) < 0.25 * (A - B) < seen[False] - B
