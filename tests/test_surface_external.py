"""``carotid surface --from-surface``: the external surface's own flat caps and extent are kept, unless --reclip."""

import argparse
import json

import numpy as np
import pytest
import pyvista as pv
from conftest import FLUID_STL, needs_fluid_stl

from carotid.centerline.model import Branch, Centerlines
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.mesh.boundary import label_flat_caps
from carotid.mesh.testing import labelled_tube
from carotid.surface.clip import cap_info
from carotid.surface.command import register
from carotid.surface.external import load_external_surface
from carotid.surface.mesh import from_polydata, signed_volume
from carotid.surface.pipeline import _size_target, check_centerlines_match, estimated_triangles
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


# -------------------------------------------------------------------------------------------------- bad input

def _tube_levelset(length: float = 40.0, radius: float = 3.0) -> Volume:
    """Signed distance (mm) of a straight tube along z that leaves the 0.5 mm grid through both its z faces."""
    k, j, i = np.meshgrid(np.arange(int(length / 0.5) + 1), np.arange(25), np.arange(25), indexing="ij")
    phi = np.hypot(i * 0.5 - 6.0, j * 0.5 - 6.0) - radius
    return Volume(phi.astype(np.float32), (0.5, 0.5, 0.5), (0.0, 0.0, 0.0))


def _axis(z0: float, z1: float, x: float = 6.0, radius: float = 3.0) -> Centerlines:
    """A straight CCA centerline along z from z0 to z1 (mm) at (x, 6) mm."""
    z = np.linspace(z0, z1, 41)
    points = np.column_stack([np.full_like(z, x), np.full_like(z, 6.0), z])
    return Centerlines([Branch("CCA", points, np.full(len(z), radius))], np.full(3, np.nan), {})


def test_centerlines_must_lie_in_the_lumen_and_reach_its_open_ends():
    levelset = _tube_levelset()
    check_centerlines_match(levelset, _axis(0.0, 40.0))
    with pytest.raises(CarotidError, match="do not match this segmentation .41 of 41 centerline points lie outside"):
        check_centerlines_match(levelset, _axis(0.0, 40.0, x=14.0))  # another case's axis, beside this lumen
    with pytest.raises(CarotidError, match=r"leaves the image at \[6.0, 6.0, 40.0\] mm, where no centerline ends"):
        check_centerlines_match(levelset, _axis(0.0, 20.0))  # an axis that stops halfway


def test_edge_lengths_giving_too_many_triangles_are_refused_at_once():
    axis = _axis(0.0, 40.0)
    triangles, area = estimated_triangles(axis, 0.3, flow_extension_radii=5.0)
    assert area == pytest.approx(2 * np.pi * 3.0 * (40.0 + len(axis.ends()) * 5.0 * 3.0))  # 15 mm extensions
    assert triangles == pytest.approx(area / (np.sqrt(3) / 4 * 0.3**2))
    with pytest.raises(CarotidError, match=r"about 6e\+06 triangles.*over the 5e\+06 limit: use edges 1\.1 times"):
        _size_target(_axis(0.0, 40.0), 0.02, None, (0.15, 1.0), flow_extension_radii=5.0)  # extensions count too
    _size_target(axis, 0.022, None, (0.15, 1.0), flow_extension_radii=5.0)  # the edge the message asks for
    with pytest.raises(CarotidError, match="triangles"):
        _size_target(_axis(0.0, 80.0), 0.02, None, (0.15, 1.0))


@pytest.mark.parametrize("option, value", [("--flow-extensions", "1000"), ("--flow-extensions", "nan"),
                                           ("--target-edge", "0.001"), ("--edge-radius-ratio", "100")])
def test_command_line_sizes_are_held_to_the_config_ranges(tmp_path, option, value):
    with pytest.raises(CarotidError, match="bad surface parameter"):
        _run(str(tmp_path), option, value)


@pytest.mark.parametrize("content, message", [(b"", "not a readable surface file"),
                                              (None, "non-finite coordinates")])
def test_unreadable_surface_file_is_one_error_without_vtk_output(tmp_path, capfd, content, message):
    path = tmp_path / "bad.stl"
    if content is None:  # a binary STL of one triangle with a NaN corner
        corners = np.array([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]], "<f4")
        path.write_bytes(b"\0" * 80 + np.uint32(1).tobytes() + np.zeros(3, "<f4").tobytes() + corners.tobytes()
                         + b"\0\0")
    else:
        path.write_bytes(content)
    with pytest.raises(CarotidError, match=message):
        _run("--from-surface", str(path), "-o", str(tmp_path / "case"))
    assert capfd.readouterr().err == ""


def test_junk_centerlines_are_one_error_without_vtk_output(tmp_path, capfd):
    (tmp_path / "segmentation").mkdir()
    (tmp_path / "segmentation" / "levelset.nii.gz").write_bytes(b"")
    (tmp_path / "centerlines.vtp").write_text("<VTKFile junk")
    with pytest.raises(CarotidError, match="centerlines.vtp: not a readable centerline file"):
        _run(str(tmp_path))
    assert capfd.readouterr().err == ""


def test_surfaces_in_micrometres_or_flat_are_refused(tmp_path):
    tube = labelled_tube(radius=3.0, length=20.0, size=1.0)
    pv.PolyData(np.asarray(tube.points) * 1000.0, tube.faces).save(tmp_path / "um.stl")
    with pytest.raises(CarotidError, match="looks like micrometres, pass --scale 0.001"):
        load_external_surface(tmp_path / "um.stl")
    flat = np.asarray(tube.points) * [1.0, 0.0, 1.0]
    pv.PolyData(flat, tube.faces).save(tmp_path / "flat.stl")
    with pytest.raises(CarotidError, match="the surface is flat"):
        load_external_surface(tmp_path / "flat.stl")


def test_specks_beside_the_lumen_are_dropped_and_a_second_vessel_is_refused(tmp_path):
    """``main_piece``: a speck (a 0.5 mm sphere beside the tube) is dropped with a warning and the tube read
    as alone; a second tube as large as the first is refused (keeping either would be a guess), as it was
    read before as the first tube with two unexplained end caps."""
    from carotid.errors import CarotidWarning

    tube = labelled_tube(radius=3.0, length=20.0, size=1.0)
    alone, _ = load_external_surface(_save(tmp_path / "tube.stl", tube))
    speck = pv.Sphere(radius=0.5, center=(12.0, 0.0, 10.0)).triangulate()
    with pytest.warns(CarotidWarning, match=r"1 small separate piece dropped \(0.\d+ % of the surface's area\)"):
        kept, _ = load_external_surface(_save(tmp_path / "speck.stl", tube + speck))
    assert kept.n_cells == alone.n_cells and abs(kept.volume - alone.volume) < 1e-9 * alone.volume
    second = tube.copy()
    second.points = np.asarray(second.points) + [20.0, 0.0, 0.0]
    with pytest.raises(CarotidError, match="2 separate pieces, the next largest 100 % of the largest one's area; a "
                                           "lumen is one"):
        load_external_surface(_save(tmp_path / "two.stl", tube + second))
    specks = tube.copy()  # 40 specks of 2 % of its area each: together more than a tenth of the area is not debris
    for k in range(40):
        specks = specks + pv.Sphere(radius=0.75, center=(12.0 + 2.0 * (k % 8), 2.0 * (k // 8), 0.0)).triangulate()
    with pytest.raises(CarotidError, match=r"41 separate pieces, the next largest 2, 2, 2, \.\.\. %"):
        load_external_surface(_save(tmp_path / "specks.stl", specks))
    with pytest.raises(CarotidError, match="2 separate pieces"):
        _run("--from-surface", str(tmp_path / "two.stl"), "-o", str(tmp_path / "case"))


def _save(path, surface: pv.PolyData):
    pv.PolyData(np.asarray(surface.points), surface.faces).save(path)
    return path
