"""`carotid mesh --from-surface` on surfaces from other tools: end caps of a stenotic nozzle (never its
sudden-expansion annulus), the layer in its throat, units, repeatability, and the real carotid fluid.stl
(self-intersecting, needle triangles) meshed with its extent and volume kept."""

import json

import numpy as np
import pytest
import pyvista as pv

from conftest import FLUID_STL, needs_fluid_stl

from carotid.cli import main
from carotid.mesh import build_mesh
from carotid.mesh.io import split_cells
from carotid.mesh.layers import tet_volumes
from carotid.mesh.mesher import CORE_MIN_DIHEDRAL
from carotid.mesh.quality import min_dihedral
from carotid.mesh.testing import stenotic_nozzle

# The nozzle (mm): 12 mm pipe, 20-degree cone, 4 mm x 40 mm throat, sudden expansion back to 12 mm.
RADIUS, THROAT, INLET, OUTLET, THROAT_LENGTH = 6.0, 2.0, 10.0, 30.0, 40.0
CONE = (RADIUS - THROAT) / np.tan(np.radians(10.0))
STEP = INLET + CONE + THROAT_LENGTH  # z of the sudden expansion
LENGTH = STEP + OUTLET


@pytest.fixture(scope="module")
def nozzle():
    return stenotic_nozzle(radius=RADIUS, throat_radius=THROAT, cone_deg=20.0, throat_length=THROAT_LENGTH,
                           inlet_length=INLET, outlet_length=OUTLET, size=1.0)


@pytest.fixture(scope="module")
def nozzle_stl(nozzle, tmp_path_factory):
    """The nozzle as a plain STL: triangles only, no labels."""
    path = tmp_path_factory.mktemp("nozzle") / "nozzle.stl"
    pv.PolyData(nozzle.points, nozzle.faces).save(path)
    return path


@pytest.fixture(scope="module")
def nozzle_case(nozzle_stl, tmp_path_factory):
    case = tmp_path_factory.mktemp("nozzle_case") / "case"
    assert main(["mesh", "--from-surface", str(nozzle_stl), "-o", str(case), "--layers", "4", "--lloyd", "1"]) == 0
    return pv.read(case / "mesh.vtu"), json.loads((case / "mesh_quality.json").read_text())


def test_nozzle_has_one_inlet_and_one_outlet_at_its_ends_and_the_annulus_is_wall(nozzle_case):
    mesh, quality = nozzle_case
    points = np.asarray(mesh.points)
    _, _, triangles, labels = split_cells(mesh)
    assert sorted(quality["elements"]["boundary_triangles"]) == ["1", "2", "3"]
    z = points[triangles][:, :, 2]
    np.testing.assert_allclose(z[labels == 2], 0.0, atol=1e-6)  # the inlet is the z = 0 end ...
    np.testing.assert_allclose(z[labels == 3], LENGTH, atol=1e-6)  # ... the outlet the other end
    r = np.linalg.norm(points[triangles][:, :, :2], axis=2)
    annulus = np.all(np.abs(z - STEP) < 1e-6, axis=1) & np.all((r > THROAT + 0.1) & (r < RADIUS - 0.1), axis=1)
    assert annulus.sum() > 20
    assert np.all(labels[annulus] == 1)


def test_nozzle_layer_stays_thin_in_the_throat(nozzle_case):
    """Layer depth read from the mesh geometry: throat radius minus the radius of the deepest layer node."""
    mesh, quality = nozzle_case
    points = np.asarray(mesh.points)
    tets, region = split_cells(mesh)[:2]
    layer = np.unique(tets[region == 0])
    z, r = points[layer, 2], np.linalg.norm(points[layer, :2], axis=1)
    throat = (z > INLET + CONE + 3.0) & (z < STEP - 3.0)
    depth = THROAT - r[throat].min()
    assert 0.05 * THROAT < depth < THROAT / 3.0


def test_surface_in_metres_is_refused_unless_scaled(nozzle, tmp_path, capsys):
    small = tmp_path / "metres.stl"
    pv.PolyData(np.asarray(nozzle.points) * 1e-3, nozzle.faces).save(small)
    assert main(["mesh", "--from-surface", str(small), "-o", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "metres" in err and "--scale 1000" in err
    assert main(["mesh", "--from-surface", str(small), "-o", str(tmp_path / "m"), "--scale", "1000",
                 "--layers", "2", "--lloyd", "0"]) == 0
    volume = json.loads((tmp_path / "m" / "mesh_quality.json").read_text())["volume"]["mesh_mm3"]
    exact = np.pi * (RADIUS**2 * (INLET + OUTLET) + THROAT**2 * THROAT_LENGTH
                     + CONE * (RADIUS**2 + RADIUS * THROAT + THROAT**2) / 3.0)
    assert volume == pytest.approx(exact, rel=0.02)  # polygonal sections of 1 mm edges


def test_same_input_gives_the_same_mesh(nozzle):
    first, _ = build_mesh(nozzle, layers=2, lloyd_iterations=1)
    second, _ = build_mesh(nozzle, layers=2, lloyd_iterations=1)
    assert (first.n_points, first.n_cells) == (second.n_points, second.n_cells)
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.cell_connectivity, second.cell_connectivity)


@needs_fluid_stl
def test_real_carotid_stl_as_given_meshes_with_its_extent_and_volume(tmp_path, capsys):
    """fluid.stl straight to the mesher (3 self-intersecting pairs, needle triangles): repaired in place; no
    core sliver (the layer's inner surface has a crease near (4.5, 5.6, -12.6) mm where HXT left a 0.6-degree
    core tetrahedron on four inner-surface vertices: the layer is thinned there)."""
    assert main(["mesh", "--from-surface", str(FLUID_STL), "-o", str(tmp_path / "c"), "--layers", "4"]) == 0
    assert "remeshed in place" in capsys.readouterr().out
    stl = pv.read(FLUID_STL)
    mesh = pv.read(tmp_path / "c" / "mesh.vtu")
    points = np.asarray(mesh.points)
    tets, region, triangles, labels = split_cells(mesh)
    volumes = tet_volumes(points, tets)
    assert volumes.min() > 0
    assert volumes.sum() == pytest.approx(stl.volume, rel=0.005)
    np.testing.assert_allclose(mesh.bounds, stl.bounds, atol=0.05)
    assert sorted(np.unique(labels)) == [1, 2, 3, 4]
    quality = json.loads((tmp_path / "c" / "mesh_quality.json").read_text())
    assert quality["boundary_layer"]["layers"] == 4
    assert min_dihedral(points, tets[region == 1]).min() >= CORE_MIN_DIHEDRAL
    assert quality["mesh"]["core"]["below_floor"] == 0
    assert 3 * quality["layer_prisms"]["count"] == np.sum(region == 0)
