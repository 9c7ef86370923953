"""Calcium at a graded stenosis: the distance from the lumen's wall to the hyperdense voxels, checked against a
brute-force distance in world coordinates, and carried to geometry.json, the summary and the report."""

import json

import numpy as np
import pytest
from conftest import ACCURACY_CASES, phantom
from scipy.spatial import cKDTree

from carotid.centerline import plaque
from carotid.centerline.command import register
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.report.html import verdict_html

# An oblique LPS frame and anisotropic voxels: a distance computed with the axes or the spacings mixed up
# differs from the world's.
SPACING_XYZ = (0.45, 0.3, 0.7)
DIRECTION = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
SHAPE = (36, 40, 32)


def tube(radius=2.0):
    """A straight lumen of ``radius`` mm along world y through the grid's centre: its level set (mm), the
    world coordinates (n, 3) of the voxels, and the centre (x, y, z)."""
    vol = Volume(np.zeros(SHAPE, np.float32), SPACING_XYZ, (3.0, -2.0, 5.0), DIRECTION)
    xyz = vol.index_to_world(np.indices(SHAPE).reshape(3, -1).T)
    centre = vol.index_to_world((np.array(SHAPE) - 1) / 2.0)
    d = xyz - centre
    phi = (np.hypot(d[:, 0], d[:, 2]) - radius).reshape(SHAPE).astype(np.float32)
    return vol.with_array(phi), xyz, centre


def block(xyz, centre, x_range, half_y=1.5, half_z=1.0):
    """A calcium block (uint8 (k, j, i)) spanning ``x_range`` (mm from the centre) beside the tube."""
    d = xyz - centre
    inside = (d[:, 0] >= x_range[0]) & (d[:, 0] <= x_range[1]) & (np.abs(d[:, 1]) <= half_y) & (
        np.abs(d[:, 2]) <= half_z)
    return inside.reshape(SHAPE).astype(np.uint8)


def brute_force(levelset, calcium, xyz, centre, reach):
    """The same distance from world coordinates alone: wall voxels within ``reach`` of the centre, nearest
    calcium voxel centre by a k-d tree."""
    h = max(SPACING_XYZ)
    phi = levelset.array.ravel()
    wall = (np.abs(phi) <= 0.5 * h) & (np.linalg.norm(xyz - centre, axis=1) <= reach)
    return float(cKDTree(xyz[calcium.array.ravel() > 0]).query(xyz[wall])[0].min())


@pytest.mark.parametrize("gap", [0.0, 0.6, 1.5])
def test_the_calcium_distance_is_the_world_distance_from_the_wall(gap):
    levelset, xyz, centre = tube()
    calcium = levelset.with_array(block(xyz, centre, (2.0 + gap, 4.0 + gap)))
    found = plaque.calcium_distance(centre, 4.0, levelset, calcium)
    expected = brute_force(levelset, calcium, xyz, centre, 2.0 + plaque.SEARCH_MM)
    assert found == pytest.approx(expected, abs=1e-6)
    # And it is the gap, to the wall band's half voxel and a voxel's sampling of the block.
    assert gap - 0.5 * max(SPACING_XYZ) - 0.05 <= found <= gap + max(SPACING_XYZ)
    assert plaque.calcified({"calcium_mm": found}) == (gap <= plaque.CALCIFIED_MM)


def test_no_calcium_near_the_throat_gives_no_distance():
    levelset, xyz, centre = tube()
    assert plaque.calcium_distance(centre, 4.0, levelset, levelset.with_array(np.zeros(SHAPE, np.uint8))) is None
    # Calcium against the tube 6 mm along it: a distance, but not a calcified throat.
    aside = block(xyz - np.array([0.0, 6.0, 0.0]), centre, (2.0, 4.0))
    distance = plaque.calcium_distance(centre, 4.0, levelset, levelset.with_array(aside))
    assert distance > plaque.CALCIFIED_MM
    # 11 mm along it, beyond twice the reach of the throat: none.
    far = block(xyz - np.array([0.0, 11.0, 0.0]), centre, (2.0, 4.0))
    assert far.any()
    assert plaque.calcium_distance(centre, 4.0, levelset, levelset.with_array(far)) is None
    assert not plaque.calcified({"calcium_mm": None}) and not plaque.calcified({})


def _parse(argv):
    import argparse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(argv)


def test_the_graded_stenosis_carries_its_calcium_to_geometry_summary_and_report(tmp_path, capsys):
    from carotid.segment.segmentation import Segmentation, write_segmentation

    ph = phantom(*ACCURACY_CASES[1])
    write_segmentation(Segmentation(ph.sdf, ph.mask, {}), tmp_path / "soft")
    args = _parse(["centerlines", str(tmp_path / "soft")])
    assert args.func(args) == 0
    soft = json.loads((tmp_path / "soft" / "geometry.json").read_text())["stenosis"]
    assert "calcium_mm" not in soft and "Calcified" not in capsys.readouterr().out
    assert "Calcified" not in verdict_html({"stenosis": soft})

    # Calcium against the wall at the graded throat: the voxels just outside the wall within 1.5 mm of it.
    xyz = ph.sdf.index_to_world(np.indices(ph.sdf.array.shape).reshape(3, -1).T)
    near = np.linalg.norm(xyz - np.asarray(soft["location_mm"]), axis=1) <= 0.5 * soft["min_diameter_mm"] + 1.5
    shell = near.reshape(ph.sdf.array.shape) & (ph.sdf.array > 0) & (ph.sdf.array < 1.0)
    calcium = ph.sdf.with_array(shell.astype(np.uint8))
    write_segmentation(Segmentation(ph.sdf, ph.mask, {}, calcium=calcium), tmp_path / "calcified")
    args = _parse(["centerlines", str(tmp_path / "calcified")])
    assert args.func(args) == 0
    grade = json.loads((tmp_path / "calcified" / "geometry.json").read_text())["stenosis"]
    assert grade["calcium_mm"] <= 0.5 * max(ph.sdf.spacing)
    assert "Calcified" in capsys.readouterr().out
    page = verdict_html({"stenosis": grade})
    assert "Calcified stenosis" in page and "the lumen at the stenosis" in page

    # A mask on another grid is refused, not read in the wrong place.
    moved = Volume(calcium.array, calcium.spacing, np.asarray(calcium.origin) + 1.0, calcium.direction)
    write_segmentation(Segmentation(ph.sdf, ph.mask, {}, calcium=moved), tmp_path / "moved")
    args = _parse(["centerlines", str(tmp_path / "moved")])
    with pytest.raises(CarotidError, match="not on the grid"):
        args.func(args)
