"""Outer-wall stage: a thrombosed vessel phantom with an eccentric lumen, a contrast-filled vein and a side branch."""

import numpy as np
import pytest
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume, read_image
from carotid.segment import SegmentParameters, segment, write_segmentation
from carotid.segment.metrics import dice
from carotid.segment.wall import ball_closing, ball_opening, trunk, trunk_axis, wall_level

SPACING = (0.9, 0.9, 1.2)  # i, j, k in mm
SHAPE = (40, 72, 72)  # k, j, i
OUTER_R, LUMEN_R, LUMEN_SHIFT = 10.0, 4.0, 5.0  # mm
VEIN_R, BRANCH_R = 4.0, 2.5  # mm


def world_grid():
    """(z, y, x) in mm of every voxel, origin at the centre of the volume's xy-plane."""
    k, j, i = np.indices(SHAPE, dtype=np.float32)
    return k * SPACING[2], (j - SHAPE[1] / 2) * SPACING[1], (i - SHAPE[2] / 2) * SPACING[0]


def thrombosed_vessel(branch: bool = False, seed: int = 0) -> dict:
    """CT (HU) of a vessel along z: a 10 mm thrombus (60 HU) around an eccentric 4 mm lumen (420 HU) in fat.

    A vein full of contrast (1000 HU) touches the vessel on the -y side.  With ``branch``, a 2.5 mm artery
    leaves the lumen along +x and runs 15 mm beyond the vessel.  Blur 0.8 mm, noise 15 HU.
    """
    z, y, x = world_grid()
    outer = x ** 2 + y ** 2 <= OUTER_R ** 2
    lumen = (x - LUMEN_SHIFT) ** 2 + y ** 2 <= LUMEN_R ** 2
    vein = x ** 2 + (y + OUTER_R + VEIN_R) ** 2 <= VEIN_R ** 2
    hu = np.full(SHAPE, -100.0, np.float32)
    hu[outer] = 60.0
    hu[vein] = 1000.0
    arteries = lumen.copy()
    if branch:
        arteries |= (y ** 2 + (z - z.mean()) ** 2 <= BRANCH_R ** 2) & (x > 0) & (x < OUTER_R + 15.0)
    hu[arteries] = 420.0
    hu = ndimage.gaussian_filter(hu, 0.8 / np.array(SPACING[::-1]))
    hu += np.random.default_rng(seed).normal(0.0, 15.0, SHAPE).astype(np.float32)
    image = Volume(hu.astype(np.float32), spacing=SPACING)
    centre = image.index_to_world(np.array([SHAPE[0] / 2, SHAPE[1] / 2, SHAPE[2] / 2 + LUMEN_SHIFT / SPACING[0]]))
    return {"image": image, "outer": outer, "lumen": lumen, "vein": vein, "arteries": arteries, "seed": centre}


PARAMS = dict(wall=True)


def test_wall_stage_recovers_the_thrombus_and_leaves_the_lumen_alone(tmp_path):
    case = thrombosed_vessel()
    with_wall = segment(case["image"], seeds_xyz=[case["seed"]], params=SegmentParameters(**PARAMS))
    lumen_only = segment(case["image"], seeds_xyz=[case["seed"]], params=SegmentParameters(**{**PARAMS, "wall": False}))
    wall = with_wall.wall.array > 0
    assert np.array_equal(with_wall.mask.array, lumen_only.mask.array) and lumen_only.wall is None
    assert dice(with_wall.mask.array > 0, case["lumen"]) >= 0.95
    assert dice(wall, case["outer"]) >= 0.9
    assert with_wall.report["wall"]["thrombus_level_hu"] == pytest.approx(60.0, abs=25.0)
    assert dice(lumen_only.mask.array > 0, case["outer"]) < 0.4
    assert np.count_nonzero(wall & case["vein"]) < 0.01 * np.count_nonzero(case["outer"])  # contrast neighbour kept out
    assert np.all(wall[with_wall.mask.array > 0])
    report = with_wall.report["wall"]
    assert report["converged"]
    assert report["volume_mm3"] == pytest.approx(np.count_nonzero(wall) * np.prod(SPACING))
    out = write_segmentation(with_wall, tmp_path)
    assert np.array_equal(read_image(out / "wall_mask.nii.gz", dtype=np.uint8).array, with_wall.wall.array)


def test_the_whole_vessel_holds_a_carotid_lumen_with_no_thrombus():
    """On a carotid phantom (no thrombus, tissue around the wall) the wall's front, its curvature term strong
    on vessels a few millimetres across, fell back inside the lumen: the whole vessel held half of it.  The
    whole vessel holds its lumen."""
    from carotid.phantom import make_phantom

    p = make_phantom(extent=(30, 30, 64), spacing=(0.7, 0.7, 0.9), noise=15)
    seeds = [p.info["seeds_mm"][b] for b in ("CCA", "ICA", "ECA")]
    result = segment(p.image, seeds_xyz=seeds, params=SegmentParameters(**PARAMS))
    lumen, wall = result.mask.array > 0, result.wall.array > 0
    assert np.all(wall[lumen])
    assert result.report["wall"]["volume_mm3"] >= result.report["lumen_volume_mm3"]


@pytest.mark.parametrize("cut", [{"wall_open_mm": 4.0}, {"wall_trunk_mm": 3.0}])
def test_opening_or_trunk_cuts_a_side_branch_but_keeps_the_vessel(cut):
    case = thrombosed_vessel(branch=True, seed=1)
    beyond = case["arteries"] & ~case["outer"]
    results = {}
    for name, extra in (("plain", {}), ("cut", cut)):
        params = SegmentParameters(**PARAMS, **extra)
        results[name] = segment(case["image"], seeds_xyz=[case["seed"]], params=params).wall.array > 0
    assert np.count_nonzero(results["plain"] & beyond) > 0.8 * np.count_nonzero(beyond)
    # The trunk keeps what lies within its margin (3-4 mm) of the vessel: up to a fifth of the 15 mm branch beyond
    # the outer wall (the opening cuts it closer to the wall).
    assert np.count_nonzero(results["cut"] & beyond) < 0.25 * np.count_nonzero(beyond)
    assert dice(results["cut"], case["outer"]) >= 0.9


def test_local_level_follows_the_thrombus_along_the_vessel():
    """Thrombus of 60 HU in the lower half and 150 HU (partly enhancing) in the upper: each half gets its own."""
    z, y, x = world_grid()
    radius = np.hypot(x, y)
    sample = (radius > 6.0) & (radius <= 9.0)
    upper = z >= z.mean()
    hu = np.where(upper, 150.0, 60.0) + np.random.default_rng(3).normal(0.0, 15.0, SHAPE)
    hu = hu.astype(np.float32)
    level = wall_level(hu, sample, 5.0, SPACING[::-1], low=0.0)
    far = np.abs(z - z.mean()) > 15.0  # three Gaussians from the change
    assert level.shape == SHAPE and level.dtype == np.float32
    assert np.abs(level[sample & far & ~upper] - 60.0).max() < 10.0
    assert np.abs(level[sample & far & upper] - 150.0).max() < 10.0
    assert float(wall_level(hu, sample, 0.0, SPACING[::-1], low=0.0)) == pytest.approx(np.median(hu[sample]))
    assert float(wall_level(hu, np.zeros(SHAPE, bool), 5.0, SPACING[::-1], low=0.0)) == 100.0  # nothing sampled


def arch_with_branch_and_leak():
    """An aortic arch in the x-z plane: two 40 mm legs (radius 8 mm) joined by a half circle of 25 mm, a 100 mm
    branch (radius 3 mm) leaving its top, a leak (a 10 mm ball) bulging from one leg.  Voxels 0.8 x 0.8 x 1.2 mm.

    Returns the mask, its parts (trunk, branch, leak) and the spacing in array order.
    """
    spacing = np.array([1.2, 0.8, 0.8])
    shape = (150, 30, 130)
    k, j, i = np.indices(shape, dtype=np.float32)
    z, y, x = k * spacing[0], (j - shape[1] / 2) * spacing[1], (i - shape[2] / 2) * spacing[2]
    legs = (z <= 40.0) & (np.minimum(np.hypot(x - 25.0, y), np.hypot(x + 25.0, y)) <= 8.0)
    arch = (z > 40.0) & (np.hypot(np.hypot(x, z - 40.0) - 25.0, y) <= 8.0)
    branch = (np.hypot(x, y) <= 3.0) & (z > 60.0) & (z <= 165.0)
    leak = np.hypot(np.hypot(x - 40.0, y), z - 20.0) <= 10.0
    trunk_part = legs | arch
    return trunk_part | branch | leak, trunk_part, branch & ~trunk_part, leak & ~trunk_part, spacing


def test_trunk_follows_the_thick_axis_not_the_longest():
    mask, trunk_part, branch, leak, spacing = arch_with_branch_and_leak()
    points, radii = trunk_axis(mask, spacing)
    ends = points[[0, -1]] * spacing
    assert np.all(ends[:, 0] < 15.0)  # both ends in the legs (z < 40 mm), neither at the branch's far end
    assert np.all(np.linalg.norm(np.diff(points, axis=0), axis=1) < 2.0)  # one connected voxel path
    assert np.median(radii) == pytest.approx(8.0, abs=1.0)
    kept = trunk(mask, spacing, 2.0)
    assert np.all(kept <= mask)
    assert np.count_nonzero(kept & trunk_part) > 0.98 * np.count_nonzero(trunk_part)
    assert np.count_nonzero(kept & branch) < 0.1 * np.count_nonzero(branch)
    assert np.count_nonzero(kept & leak) < 0.4 * np.count_nonzero(leak)


def test_ball_closing_and_opening_in_mm_on_anisotropic_voxels():
    z, y, x = world_grid()
    sphere = (z - 24.0) ** 2 + y ** 2 + x ** 2 <= 8.0 ** 2
    rod = (y - 15.0) ** 2 + x ** 2 <= 2.0 ** 2
    spacing = np.array(SPACING[::-1])
    opened = ball_opening(sphere | rod, 3.0, spacing)
    assert not np.any(opened & rod) and np.all(opened <= sphere | rod)  # no 3 mm ball fits in the 2 mm rod
    assert dice(opened, sphere) > 0.98  # the 8 mm sphere holds one everywhere
    slit = sphere & ~(np.abs(x) <= 1.0)  # a 2 mm cut through the sphere
    closed = ball_closing(slit, 3.0, spacing)
    assert np.all(closed >= slit) and np.all(closed[sphere & (np.abs(z - 24.0) < 4.0) & (np.abs(y) < 4.0)])


def test_an_opening_wider_than_the_vessel_is_refused():
    case = thrombosed_vessel()
    with pytest.raises(CarotidError, match="wall_open_mm"):
        segment(case["image"], seeds_xyz=[case["seed"]], params=SegmentParameters(**PARAMS, wall_open_mm=12.0))


@pytest.mark.parametrize("bad", [{"wall_alpha": 1.2}, {"wall_hu_low": 800.0}, {"wall_contrast_hu": -10.0},
                                 {"wall_max_mm": 0.0}, {"wall_kernel_mm": 0.0}, {"wall_open_mm": -1.0},
                                 {"wall_level_mm": -1.0}, {"wall_trunk_mm": -2.0},
                                 {"wall": False, "wall_trunk_mm": 5.0}, {"wall": False, "wall_open_mm": 2.0}])
def test_bad_wall_parameters_are_refused(bad):
    with pytest.raises(CarotidError, match="wall"):
        SegmentParameters(**bad).validate()
