"""``carotid surface --from-surface``: the external surface's own flat caps and extent are kept, unless --reclip."""

import argparse
import json

import numpy as np
import pytest
import pyvista as pv
from conftest import FLUID_STL, needs_fluid_stl

from carotid.errors import CarotidError
from carotid.mesh.boundary import label_flat_caps
from carotid.surface.clip import cap_info
from carotid.surface.command import register
from carotid.surface.mesh import from_polydata, signed_volume
from carotid.surface.quality import surface_quality


def _run(*argv: str) -> int:
    """``carotid surface`` with the given arguments."""
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["surface", *argv])
    return args.func(args)


def _volume(poly: pv.PolyData) -> float:
    """Enclosed volume of a closed surface, mm^3."""
    points, faces, _ = from_polydata(poly.triangulate())
    return abs(signed_volume(points, faces))


@pytest.fixture(scope="module")
def fluid_caps():
    """Volume of fluid.stl and its flat caps (``cap_info``, largest first)."""
    labelled = label_flat_caps(pv.read(FLUID_STL))
    n_caps = int(np.asarray(labelled.cell_data["CellEntityIds"]).max()) - 1
    return _volume(labelled), cap_info(labelled, [""] * n_caps)


@needs_fluid_stl
def test_from_surface_keeps_caps_and_volume(tmp_path, fluid_caps):
    pytest.importorskip("carotid.centerline.extract")
    volume, caps_in = fluid_caps
    case = tmp_path / "case"
    assert _run("--from-surface", str(FLUID_STL), "-o", str(case)) == 0
    out = pv.read(case / "surface.vtp")
    assert abs(_volume(out) / volume - 1.0) < 0.005
    _, _, labels = from_polydata(out)
    assert sorted(np.unique(labels)) == [1, 2, 3, 4]
    caps = json.loads((case / "geometry.json").read_text())["caps"]
    assert [c["id"] for c in caps] == [2, 3, 4] and [c["name"] for c in caps] == ["CCA", "ICA", "ECA"]
    centres_in = np.array([c["centre"] for c in caps_in])
    centres_out = np.array([c["centre"] for c in caps])
    gap = np.linalg.norm(centres_out[:, None] - centres_in[None], axis=2)
    assert len(caps_in) == 3 and np.all(gap.min(axis=1) < 0.5) and len(set(gap.argmin(axis=1))) == 3
    assert gap[0, 0] < 0.5  # the inlet is the largest flat cap, on the CCA
    for cap in caps:  # in the plane of the input's cap
        before = caps_in[int(gap[cap["id"] - 2].argmin())]
        assert np.dot(cap["normal"], before["normal"]) > 1.0 - 1e-9 and cap["planarity"] < 1e-4
        assert abs(np.subtract(cap["centre"], before["centre"]) @ np.asarray(before["normal"])) < 1e-4
    q = surface_quality(out)
    assert q["watertight"] and q["consistently_oriented"] and q["self_intersections"] == 0
    assert q["min_angle_deg"]["fraction_ge_30"] >= 0.95


@needs_fluid_stl
def test_reclip_cuts_the_ends(tmp_path, fluid_caps):
    pytest.importorskip("carotid.centerline.extract")
    volume, caps_in = fluid_caps
    case = tmp_path / "case"
    assert _run("--from-surface", str(FLUID_STL), "-o", str(case), "--reclip") == 0
    assert _volume(pv.read(case / "surface.vtp")) / volume < 0.95
    caps = json.loads((case / "geometry.json").read_text())["caps"]
    centres_in = np.array([c["centre"] for c in caps_in])
    gap = np.linalg.norm(np.array([c["centre"] for c in caps])[:, None] - centres_in[None], axis=2)
    assert np.all(gap.min(axis=1) > 1.0)


@needs_fluid_stl
def test_flow_extensions_move_the_kept_caps(tmp_path, fluid_caps):
    pytest.importorskip("carotid.centerline.extract")
    _, caps_in = fluid_caps
    case = tmp_path / "case"
    assert _run("--from-surface", str(FLUID_STL), "-o", str(case), "--flow-extensions", "2") == 0
    caps = json.loads((case / "geometry.json").read_text())["caps"]
    for cap in caps:  # each cap is 2 of its radii further along its normal, in the input cap's direction
        before = min(caps_in, key=lambda c: np.linalg.norm(np.subtract(c["centre"], cap["centre"])))
        shift = np.subtract(cap["centre"], before["centre"])
        assert np.dot(cap["normal"], before["normal"]) > 0.9999
        assert shift @ np.asarray(before["normal"]) == pytest.approx(2.0 * before["equivalent_radius"], rel=0.02)


def test_reclip_needs_from_surface(tmp_path):
    with pytest.raises(CarotidError, match="--reclip"):
        _run(str(tmp_path), "--reclip")
