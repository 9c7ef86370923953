"""Handles of a lumen mask removed by the thinnest cut or fill, on shapes whose answer is known by construction."""

import numpy as np
from scipy import ndimage
from skimage.measure import euler_number

from carotid.segment.handles import cavities, euler_changes, remove_handles
from carotid.segment.metrics import topology

SPACING = np.array([0.6, 0.4, 0.4])  # anisotropic, array order (k, j, i)


def grid(extent_mm=(36.0, 24.0, 24.0)):
    """World coordinates (z, y, x) in mm of a grid of ``SPACING`` centred on the origin."""
    axes = [(np.arange(int(e / h)) - (int(e / h) - 1) / 2) * h for e, h in zip(extent_mm, SPACING)]
    return np.meshgrid(*axes, indexing="ij")


def rod(points, a, b, radius):
    """Voxels within ``radius`` (mm) of the segment from ``a`` to ``b`` (z, y, x in mm)."""
    p = np.stack(points, axis=-1)
    a, b = np.asarray(a, float), np.asarray(b, float)
    t = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1) <= radius


def looped_vessel(points):
    """Two limbs of radius 2 mm, 3 mm apart wall to wall, joined at the top: a looped artery without a handle."""
    return (rod(points, (-12, 0, -3.5), (12, 0, -3.5), 2.0) | rod(points, (-12, 0, 3.5), (12, 0, 3.5), 2.0)
            | rod(points, (12, 0, -3.5), (12, 0, 3.5), 2.0))


def test_a_bridge_between_two_limbs_is_cut_and_nothing_else():
    points = grid()
    loop = looped_vessel(points)
    bridge = rod(points, (-4, 0, -3.5), (-4, 0, 3.5), 0.5)
    assert topology(loop) == {"components": 1, "handles": 0}
    assert topology(loop | bridge) == {"components": 1, "handles": 1}
    out, changes = remove_handles(loop | bridge, SPACING, 1.5)
    assert topology(out) == {"components": 1, "handles": 0}
    assert [c["kind"] for c in changes] == ["cut"] and changes[0]["scale_mm"] <= 1.0
    removed = (loop | bridge) & ~out
    assert not (out & ~(loop | bridge)).any()
    # Only the bridge goes, and only its part between the limbs' walls (a voxel of slack at the wall).
    assert removed.any() and not (removed & ~rod(points, (-4, 0, -3.5), (-4, 0, 3.5), 0.5 + 0.4)).any()
    assert not (removed & rod(points, (-12, 0, -3.5), (12, 0, -3.5), 2.0 - 0.6)).any()
    assert np.allclose(changes[0]["centre_kji"][1:], (np.array(out.shape[1:]) - 1) / 2, atol=1.0)


def test_a_tunnel_through_the_lumen_is_filled_and_nothing_else():
    """A 1 mm tunnel through a 4 mm tube is filled.  A pocket opening through a 0.8 mm neck is no handle, and
    its neck stays open (filling it would enclose a cavity)."""
    points = grid()
    z, y, x = points
    hole = rod(points, (0, -5, 0), (0, 5, 0), 0.5)
    pocket = rod(points, (8, 0, 0), (8, 0, 0.01), 2.0) | rod(points, (8, 0, 0), (8, 0, 5), 0.4)
    lumen = (np.hypot(y, x) <= 4.0) & ~hole & ~pocket
    assert topology(lumen) == {"components": 1, "handles": 1}
    out, changes = remove_handles(lumen, SPACING, 1.5)
    assert topology(out) == {"components": 1, "handles": 0}
    assert [c["kind"] for c in changes] == ["fill"]
    added = out & ~lumen
    assert added.any() and not (added & ~hole).any() and not (lumen & ~out).any()


def test_no_part_of_the_lumen_is_dropped_to_remove_a_handle():
    """A bridge one voxel thin that is also the only link to a side branch: any cut that opens the loop also
    drops the branch, so the handle stays."""
    points = grid()
    lumen = looped_vessel(points)
    k, j, i = (np.array(lumen.shape) - 1) // 2
    lumen[k, j, :] |= np.abs(points[2][k, j, :]) <= 3.5  # the bridge, along x between the limbs' axes
    lumen[k, j:j + 15, i] = True  # a stalk 6 mm long, along y from the bridge's middle
    tip = [points[0][k, j, i], points[1][k, j + 14, i] + 2.4, points[2][k, j, i]]
    lumen |= np.linalg.norm(np.stack(points, -1) - tip, axis=-1) <= 2.5  # its branch, a ball
    assert topology(lumen) == {"components": 1, "handles": 1}
    out, changes = remove_handles(lumen, SPACING, 1.5)
    assert changes == [] and np.array_equal(out, lumen)


def test_stenoses_and_loops_wider_than_the_limit_are_left_alone():
    points = grid()
    z, y, x = points
    radius = np.where(np.abs(z) < 2.0, 0.5, 2.5)  # a throat 1 mm wide
    stenosed = np.hypot(y, x) <= radius
    out, changes = remove_handles(stenosed, SPACING, 1.5)
    assert out is stenosed and changes == []
    ring = np.hypot(np.hypot(z / 1.5, y) - 7.0, x) <= 2.5  # a loop 5 mm thick: no bridge of a blurred gap
    out, changes = remove_handles(ring, SPACING, 1.5)
    assert changes == [] and topology(out) == {"components": 1, "handles": 1}
    out, changes = remove_handles(looped_vessel(points) | rod(points, (-4, 0, -3.5), (-4, 0, 3.5), 0.5),
                                  SPACING, 0.0)
    assert changes == [] and topology(out)["handles"] == 1


def test_the_euler_characteristic_of_each_piece_matches_scikit_image():
    rng = np.random.default_rng(3)
    for _ in range(40):
        mask = rng.random((9, 11, 10)) < rng.uniform(0.2, 0.8)
        labels, n = ndimage.label(rng.random(mask.shape) < 0.12, structure=np.ones((3, 3, 3), bool))
        change = euler_changes(mask, labels, n)
        base = euler_number(mask, connectivity=3)
        assert all(change[i] == euler_number(mask ^ (labels == i), connectivity=3) - base for i in range(1, n + 1))


def test_cavities_are_the_enclosed_voids_and_not_the_pockets():
    """A tube running out of the image with a void at its axis and a pocket open through a 0.8 mm neck: the void
    is a cavity, the pocket and the background at the image's ends are not."""
    points = grid()
    _, y, x = points
    void = rod(points, (0, 0, 0), (0, 0, 0.01), 0.7)
    pocket = rod(points, (8, 0, 0), (8, 0, 0.01), 2.0) | rod(points, (8, 0, 0), (8, 0, 5), 0.4)
    tube = np.hypot(y, x) <= 4.0
    assert tube[0].any() and tube[-1].any()
    lumen = tube & ~void & ~pocket
    assert np.array_equal(cavities(lumen, SPACING), void)
    assert not cavities(tube, SPACING).any()
