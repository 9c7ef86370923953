"""GPF segmentation accuracy against the phantoms' ground truth, from three kinds of initialisation."""

import numpy as np
import pytest
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.phantom import LABELS, make_phantom, sample_family
from carotid.segment import SegmentParameters, segment
from carotid.segment.init import FORK_FIT, automatic_region, fork_score, fork_seeds, seed_levelset
from carotid.segment.intensity import local_level, lumen_noise
from carotid.segment.metrics import dice, surface_distances, topology
from conftest import ACCURACY_CASES, phantom


def cross_boundary_region(p):
    """A 5 mm sphere centred 3.5 mm off the CCA axis, on the side away from the vein: it straddles the wall."""
    seed = np.array(p.info["seeds_mm"]["CCA"])
    vein = np.argwhere(p.labels.array == LABELS["vein"])
    away = seed - p.image.index_to_world(vein.mean(axis=0))
    away[2] = 0.0
    centre = seed + 3.5 * away / np.linalg.norm(away)
    region = seed_levelset(p.image, [centre], 5.0) < 0
    truth = p.mask.array > 0
    assert 0.2 < np.count_nonzero(region & truth) / np.count_nonzero(region) < 0.8  # really crosses the wall
    return region


def initialisation(p, how):
    if how == "seed":
        return {"seeds_xyz": [p.info["seeds_mm"]["CCA"]]}
    if how == "cross-boundary":
        return {"init_mask": cross_boundary_region(p)}
    return {}


@pytest.mark.parametrize("how", ["seed", "cross-boundary", "automatic"])
@pytest.mark.parametrize("case", ACCURACY_CASES, ids=[f"st{s}-n{n:.0f}-s{r}" for s, n, r in ACCURACY_CASES])
def test_accuracy_against_truth(case, how):
    p = phantom(*case)
    result = segment(p.image, params=SegmentParameters(), **initialisation(p, how))
    seg = result.mask.array > 0
    truth = p.mask.array > 0
    distances = surface_distances(result.levelset.array, p.sdf.array, p.image.spacing_kji)
    leaked = np.count_nonzero(seg & (p.labels.array >= LABELS["vein"]))
    assert dice(seg, truth) >= 0.95
    assert distances["mean"] <= 0.25
    assert leaked < 0.02 * np.count_nonzero(truth)
    assert result.report["converged"] and result.report["initialisation"] == how.replace("cross-boundary", "region")


def test_outputs_are_a_signed_distance_and_a_report():
    p = phantom()
    result = segment(p.image, seeds_xyz=[p.info["seeds_mm"]["CCA"]])
    phi = result.levelset.array
    assert phi.dtype == np.float32 and result.mask.array.dtype == np.uint8
    assert np.array_equal(result.mask.array > 0, phi < 0)
    grad = np.linalg.norm(np.gradient(phi, *p.image.spacing_kji), axis=0)
    near = np.abs(phi) < 1.5
    assert np.median(np.abs(grad[near] - 1)) < 0.05
    # The deepest point of the CCA lies about one radius inside.
    assert abs(-phi.min() - p.branches[0].radii[0]) < 0.5
    report = result.report
    assert report["lumen_volume_mm3"] == pytest.approx(np.count_nonzero(phi < 0) * np.prod(p.image.spacing_kji))
    assert set(report["seconds"]) >= {"potential_s", "evolution_s", "total_s"}
    assert report["topology"] == {"components": 1, "handles": 0}
    assert report["cavities_filled"] == {"count": 0, "volume_mm3": 0.0}
    quality = report["intensity"]
    assert quality["noise"] == pytest.approx(p.info["noise"], rel=0.1)
    assert quality["contrast_to_noise"] == pytest.approx(quality["contrast"] / quality["noise"])


def test_lumen_noise_is_the_noise_about_the_followed_level():
    # A tube whose level fades by a third of its contrast along z, under noise of 20: the spread about one level
    # holds the fade too, the spread about the followed level only the noise.
    rng = np.random.default_rng(3)
    spacing = (0.5, 0.5, 0.5)
    k, j, i = np.mgrid[:120, :40, :40]
    fade = 400.0 - 120.0 * k / 119.0
    inside = (j - 19.5) ** 2 + (i - 19.5) ** 2 < 12.0 ** 2
    image = np.where(inside, fade, 40.0) + rng.normal(0.0, 20.0, inside.shape)
    core = (j - 19.5) ** 2 + (i - 19.5) ** 2 < 8.0 ** 2
    followed = local_level(image.astype(np.float32), core, spacing, 10.0, 400.0)
    assert lumen_noise(image, core, followed) == pytest.approx(20.0, rel=0.05)
    assert lumen_noise(image, core, float(np.median(image[core]))) > 1.4 * 20.0
    assert lumen_noise(image, core & (k == 0) & (j == 19), followed) is None  # too few voxels


def test_topology_counts_components_and_handles_not_cavities():
    z, y, x = np.mgrid[-20:21, -20:21, -20:21]
    r = np.sqrt(x ** 2 + y ** 2 + z ** 2)
    torus = np.hypot(np.hypot(x, y) - 10, z) < 4
    assert topology(torus) == {"components": 1, "handles": 1}
    assert topology(r < 10) == {"components": 1, "handles": 0}
    assert topology((r < 10) & (r > 5)) == {"components": 1, "handles": 0}  # a cavity is no handle
    rods = (np.abs(y) < 3) & (np.abs(np.abs(x) - 10) < 3)
    assert topology(rods) == {"components": 2, "handles": 0}
    # Two rods joined at both ends: a loop, one handle; touching diagonally (26-connected) still joins.
    ring = rods | ((np.abs(y) < 3) & (np.abs(np.abs(z) - 15) < 2) & (np.abs(x) < 13))
    assert topology(ring) == {"components": 1, "handles": 1}
    assert topology(np.zeros((4, 4, 4), bool)) == {"components": 0, "handles": 0}


def test_seed_outside_the_image_is_refused():
    p = phantom()
    with pytest.raises(CarotidError, match="outside the image"):
        segment(p.image, seeds_xyz=[[0.0, 0.0, 500.0]])


def test_unusable_images_are_refused():
    p = phantom()
    for spacing in ((1e-6, 1e-6, 1e-6), (0.5, 0.5, 500.0)):  # metres or micrometres written as mm
        wrong = Volume(p.image.array, spacing=spacing, origin=p.image.origin, direction=p.image.direction)
        with pytest.raises(CarotidError, match="voxel size .* mm is outside 0.01-20 mm"):
            segment(wrong, seeds_xyz=[p.image.origin])
    constant = p.image.with_array(np.full(p.image.array.shape, 40.0, np.float32))
    with pytest.raises(CarotidError, match="constant"):
        segment(constant, seeds_xyz=[p.info["seeds_mm"]["CCA"]])
    holes = p.image.array.copy()
    holes[3, 4, 5] = np.nan
    with pytest.raises(CarotidError, match="NaN"):
        segment(p.image.with_array(holes))
    with pytest.raises(CarotidError, match="alpha"):
        segment(p.image, params=SegmentParameters(alpha=1.5))


@pytest.mark.parametrize("field, value", [("deblur_iterations", 10 ** 8), ("deblur_gain", 1e6), ("tolerance", 5.0),
                                          ("seed_radius_mm", 1000.0), ("slice_thickness_mm", 1000.0)])
def test_values_past_any_scan_are_refused(field, value):
    """Values that hung the refinement for hours (10^8 steps) or gave a wrong lumen without a word (a 1 m seed,
    a tolerance of 500 % that stops the front at once) are refused; the largest meaningful value passes."""
    with pytest.raises(CarotidError, match=field):
        SegmentParameters(**{field: value}).validate()
    limits = {"deblur_iterations": 1000, "deblur_gain": 10.0, "tolerance": 0.5, "seed_radius_mm": 20.0,
              "slice_thickness_mm": 10.0}
    SegmentParameters(**{field: limits[field]}).validate()


def test_an_initial_region_that_fills_the_image_is_refused():
    p = phantom()
    with pytest.raises(CarotidError, match="covers 100 % of the image"):
        segment(p.image, init_mask=np.ones(p.image.array.shape, bool))


def test_kept_components_follow_the_seeds():
    """A seed inside a component keeps it; a seed the front left keeps the component within reach of it,
    and not the largest one; a seed far from everything falls back to the largest."""
    from carotid.segment.segmentation import keep_components

    inside = np.zeros((20, 20, 60), bool)
    inside[5:15, 5:15, 2:10] = True  # small, near the seeds
    inside[5:15, 5:15, 30:58] = True  # large
    spacing = np.array([0.5, 0.5, 0.5])
    small = inside.copy()
    small[..., 20:] = False
    assert np.array_equal(keep_components(inside, np.array([[10.0, 10.0, 5.0]]), spacing), small)
    # 4 voxels (2 mm) beyond the small block's face: within 5 mm of it.
    assert np.array_equal(keep_components(inside, np.array([[10.0, 10.0, 13.0]]), spacing), small)
    assert np.array_equal(keep_components(inside, np.array([[10.0, 10.0, 20.0]]), spacing, reach_mm=1.0),
                          inside & ~small)


def test_lumen_levelset_holds_out_neighbours_keeps_the_seeded_tree_and_cuts_a_bridge():
    """segment's clean-up of a refined front that overlaps a held-out vein, holds a blob apart from the
    artery and a bridge between two limbs of a loop: the vein and the blob go, the bridge is cut, and the
    level set is the signed distance of the looped artery that is left."""

    from carotid.segment.segmentation import lumen_levelset
    from test_handles import SPACING, grid, looped_vessel, rod

    points = grid()
    loop = looped_vessel(points)
    bridge = rod(points, (-4, 0, -3.5), (-4, 0, 3.5), 0.5)
    vein = rod(points, (-12, 0, -7.0), (0, 0, -7.0), 2.0) & ~loop  # touching the left limb's outer wall
    blob = rod(points, (-12, 0, 9.0), (-10, 0, 9.0), 1.0)
    front = loop | bridge | vein | blob
    phi = (ndimage.distance_transform_edt(~front, sampling=SPACING)
           - ndimage.distance_transform_edt(front, sampling=SPACING)).astype(np.float32)
    seed = np.argwhere(rod(points, (7.9, 0, -3.5), (8.1, 0, -3.5), 0.3)).mean(axis=0)[None]
    out, mask, changes, _ = lumen_levelset(phi, vein, seed, SPACING, SegmentParameters())
    assert np.array_equal(mask > 0, out < 0)
    assert topology(mask > 0) == {"components": 1, "handles": 0}
    assert [c["kind"] for c in changes] == ["cut"]
    assert not (mask > 0)[vein | blob].any()
    assert (mask > 0)[loop].mean() > 0.995
    # A signed distance: about -2 mm near a limb's axis (radius 2 mm; within a voxel), and at the dropped blob's
    # centre the 3.5 mm to the limb's wall (x = 5.5 mm), clamped to far_mm.
    assert -2.2 < out[tuple(np.round(seed[0]).astype(int))] < -1.4
    centre = np.argwhere(rod(points, (-11.1, 0, 9.0), (-10.9, 0, 9.0), 0.3)).mean(axis=0).round().astype(int)
    assert abs(out[tuple(centre)] - min(3.5, SegmentParameters().far_mm)) < 0.4


def test_lumen_levelset_fills_the_cavities_a_front_or_a_held_out_pit_leaves():
    """A front grown around a dark voxel at a tube's axis, and a voxel at the axis held out as a neighbour (a
    noise pit taken for an under-enhanced plateau), leave voids inside the lumen: both are filled, so that the
    level set at the axis is the tube's radius and not the distance to the void (which the inscribed radius of
    the centerlines and the stenosis grading read as a throat)."""
    from carotid.segment.segmentation import lumen_levelset
    from test_handles import SPACING, grid, rod

    points = grid()
    tube = rod(points, (-16, 0, 0), (16, 0, 0), 3.0)
    position = np.stack(points, axis=-1)
    pit, held, seed = (np.unravel_index(np.argmin(np.linalg.norm(position - [z, 0, 0], axis=-1)), tube.shape)
                       for z in (0.0, 3.0, -8.0))
    front = tube.copy()
    front[pit] = False
    phi = -ndimage.distance_transform_edt(front, sampling=SPACING).astype(np.float32)
    phi[~front] = 0.3
    stopped = np.zeros(tube.shape, bool)
    stopped[held] = True
    out, mask, changes, filled = lumen_levelset(phi, stopped, np.array([seed], float), SPACING, SegmentParameters())
    assert filled["count"] == 2 and filled["volume_mm3"] == pytest.approx(2 * np.prod(SPACING))
    assert np.array_equal(mask > 0, tube) and changes == []
    assert topology(mask > 0) == {"components": 1, "handles": 0}
    for voxel in (pit, held):
        assert out[voxel] == pytest.approx(-3.0, abs=0.45)


def _tube(shape, spacing, start, end, radius):
    """Voxels within ``radius`` (mm) of the segment from ``start`` to ``end`` (mm, k j i)."""
    points = np.stack(np.meshgrid(*[np.arange(n) * h for n, h in zip(shape, spacing)], indexing="ij"), axis=-1)
    a, b = np.asarray(start, float), np.asarray(end, float)
    t = np.clip(((points - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[..., None] * (b - a)), axis=-1) <= radius


def _regions():
    """A Y (trunk along k up to 30 mm, branches ending at k = 59 mm, i = 5 and 20 mm), a straight tube and
    two parallel tubes, on 0.5 mm voxels."""
    spacing, shape = np.array([0.5, 0.5, 0.5]), (120, 50, 50)
    trunk = _tube(shape, spacing, (0, 12.5, 12.5), (30, 12.5, 12.5), 3.0)
    fork = trunk | _tube(shape, spacing, (30, 12.5, 12.5), (59, 12.5, 5.0), 2.2) | _tube(
        shape, spacing, (30, 12.5, 12.5), (59, 12.5, 20.0), 1.8)
    straight = _tube(shape, spacing, (0, 12.5, 12.5), (59, 12.5, 12.5), 3.0)
    pair = _tube(shape, spacing, (0, 12.5, 5.0), (59, 12.5, 5.0), 2.0) | _tube(
        shape, spacing, (0, 12.5, 20.0), (59, 12.5, 20.0), 2.0)
    return spacing, fork, straight, pair


def test_a_fork_scores_near_one_a_single_or_double_tube_near_zero():
    spacing, fork, straight, pair = _regions()
    assert fork_score(fork, spacing, 5.0) > 0.8
    assert fork_score(fork[::-1], spacing, 5.0) > 0.8  # the fork at the bottom
    assert fork_score(straight, spacing, 5.0) == 0.0
    assert fork_score(pair, spacing, 5.0) == 0.0


@pytest.mark.parametrize("flip", [False, True])
def test_fork_seeds_lie_in_the_trunk_and_near_the_end_of_each_branch(flip):
    spacing, fork, straight, pair = _regions()
    seeds = fork_seeds(fork[::-1] if flip else fork, spacing) * spacing
    if flip:
        seeds[:, 0] = (fork.shape[0] - 1) * spacing[0] - seeds[:, 0]
    trunk, branches = seeds[0], seeds[1:][np.argsort(seeds[1:, 2])]
    assert trunk[0] <= 31.0 and abs(trunk[2] - 12.5) <= 1.0  # on the trunk's axis, before the branches part
    assert np.all(branches[:, 0] > 59.0 - 5.0)  # within 5 mm of the branches' ends
    assert np.allclose(branches[:, 2], [5.0 + 0.7, 20.0 - 0.5], atol=1.5)  # one on each branch's axis
    assert fork_seeds(straight, spacing) is None and fork_seeds(pair, spacing) is None


def test_a_start_that_barely_forks_gets_no_branch_seeds():
    """A tube that splits into two arms for 20 mm and joins again (one piece, then two, then one again for 19
    mm) scores below ``FORK_FIT``: ``automatic_region`` would not take it as a fork, and ``fork_seeds`` places
    no branch seeds in it (the arms are not branches: they end where they join)."""
    spacing, shape = np.array([0.5, 0.5, 0.5]), (120, 50, 50)
    region = _tube(shape, spacing, (0, 12.5, 12.5), (20, 12.5, 12.5), 3.0) | _tube(
        shape, spacing, (40, 12.5, 12.5), (59, 12.5, 12.5), 3.0)
    for side in (5.0, 20.0):
        region |= _tube(shape, spacing, (20, 12.5, 12.5), (30, 12.5, side), 1.8) | _tube(
            shape, spacing, (30, 12.5, side), (40, 12.5, 12.5), 1.8)
    assert 0.0 < fork_score(region, spacing, 5.0) < FORK_FIT
    assert fork_seeds(region, spacing) is None
    assert fork_seeds(region, spacing, fork_fit=0.0) is not None  # the threshold, not the shape, refuses it


def test_a_fork_whose_thin_branch_has_no_deep_core_is_still_found():
    """A Y whose thinner branch (1.4 mm radius) keeps no core of 2 mm^2 a millimetre deep, beside a brighter
    straight tube: at the full depth nothing forks and the tube would be taken; at half the depth the Y forks."""
    spacing, shape = np.array([0.5, 0.5, 0.5]), (120, 50, 90)
    artery = _tube(shape, spacing, (0, 12.5, 12.5), (30, 12.5, 12.5), 3.0) | _tube(
        shape, spacing, (30, 12.5, 12.5), (59, 12.5, 5.0), 2.2) | _tube(shape, spacing, (30, 12.5, 12.5),
                                                                       (59, 12.5, 22.0), 1.4)
    decoy = _tube(shape, spacing, (0, 12.5, 36.0), (59, 12.5, 36.0), 3.0)
    image01 = np.where(decoy, 1.0, np.where(artery, 0.8, 0.0)).astype(np.float32)
    ghat = np.where(artery | decoy, -1.0, 1.0).astype(np.float32)
    region = automatic_region(image01, ghat, spacing)
    assert not (region & decoy).any() and fork_seeds(region, spacing) is not None


@pytest.mark.parametrize("seed, decoy", [(1, "bone"), (18, "vein")])
def test_automatic_initialisation_finds_the_forking_artery_not_a_brighter_tube(seed, decoy):
    """Family 1 (CT): a bone below the window's top is brighter than the lumen; family 18 (MR): under the bias
    field the jugular vein is.  Without seeds the start is the structure that forks (before: the decoy, Dice 0)."""
    p = make_phantom(**sample_family(seed))
    result = segment(p.image, params=SegmentParameters())
    seg, truth = result.mask.array > 0, p.mask.array > 0
    assert result.report["initialisation"] == "automatic"
    assert dice(seg, truth) >= 0.92
    assert np.count_nonzero(seg & (p.labels.array == LABELS[decoy])) < 0.02 * np.count_nonzero(truth)
