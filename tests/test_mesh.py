"""Boundary-layer volume mesh: conformity, exact volume, the requested layers measured back, core quality,
stenosis, bad inputs, smoothing, file outputs and the command line."""

import argparse
import itertools
import json
import warnings

import meshio
import numpy as np
import pytest
import pyvista as pv

from conftest import FLUID_STL, needs_fluid_stl

from carotid.errors import CarotidError, CarotidWarning
from carotid.mesh import build_mesh, cap_open_ends, check_surface, label_flat_caps, write_mesh
from carotid.mesh.boundary import LABELS, cap_planes
from carotid.mesh.command import register
from carotid.mesh.core import boundary_faces, face_keys
from carotid.mesh.io import split_cells
from carotid.mesh.layers import MAX_LEAN_DEG, build_layers, split_prisms, tet_volumes, triangle_min_angles
from carotid.mesh.mesher import CORE_MIN_DIHEDRAL
from carotid.mesh.quality import dihedral_angles, min_dihedral, prism_measures
from carotid.mesh.smooth import lloyd_smooth
from carotid.mesh.testing import labelled_bifurcation, labelled_tube
from carotid.surface.mesh import signed_volume

R, T, N, F = 3.0, 0.6, 10, 1.2  # tube radius, layer thickness (mm), sub-layers, growth ratio


@pytest.fixture(scope="module")
def tube():
    return labelled_tube(radius=R, length=12.0, size=0.6)


@pytest.fixture(scope="module")
def tube_mesh(tube):
    return build_mesh(tube, layers=N, ratio=F, thickness=T)


@pytest.fixture(scope="module")
def bifurcation_mesh():
    surface = labelled_bifurcation(size=0.6)
    return (surface, *build_mesh(surface))


@pytest.fixture(scope="module")
def stenosis_mesh():
    surface = labelled_tube(radius=R, length=16.0, size=0.5, stenosis=0.8)
    return (surface, *build_mesh(surface, layers=N, ratio=F, thickness_ratio=0.3))


def face_counts(tets):
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]])
    return np.unique(face_keys(faces), return_counts=True)[1]


def coordinate_keys(points, triangles):
    """Order-independent keys of triangles by their vertex coordinates (rounded to 1e-9 mm)."""
    coords = np.round(points[triangles], 9)
    return {tuple(sorted(map(tuple, tri))) for tri in coords}


def check_valid(surface, mesh):
    """Assertions shared by every mesh: positive, conforming, exact volume, boundary = input wall + caps."""
    points = np.asarray(mesh.points)
    tets, region, triangles, labels = split_cells(mesh)
    volumes = tet_volumes(points, tets)
    assert volumes.min() > 0
    counts = face_counts(tets)
    assert counts.max() == 2  # every face is shared by at most two tetrahedra ...
    assert np.sum(counts == 1) == len(triangles)  # ... and the faces used once are exactly the boundary
    surf = check_surface(surface)
    enclosed = signed_volume(surf.points, surf.triangles)
    assert abs(volumes.sum() - enclosed) <= 1e-6 * enclosed
    wall_in = surf.triangles[surf.labels == 1]
    assert coordinate_keys(points, triangles[labels == 1]) == coordinate_keys(surf.points, wall_in)
    for label, (centre, normal) in cap_planes(surf).items():
        cap_out = triangles[labels == label]
        assert np.abs((points[cap_out] - centre) @ normal).max() < 1e-9 * R
        area_in = np.linalg.norm(np.cross(*(surf.points[surf.triangles[surf.labels == label]][:, 1:]
                                            - surf.points[surf.triangles[surf.labels == label]][:, :1]
                                            ).transpose(1, 0, 2)), axis=1).sum()
        area_out = np.linalg.norm(np.cross(*(points[cap_out][:, 1:] - points[cap_out][:, :1]).transpose(1, 0, 2)),
                                  axis=1).sum()
        assert area_out == pytest.approx(area_in, rel=1e-9)
    assert set(np.unique(labels)) == set(np.unique(surf.labels))
    return points, tets, region


def test_test_surfaces_are_closed_labelled_and_planar_capped(tube):
    for surface, labels in [(tube, {1, 2, 3}), (labelled_bifurcation(size=1.0), {1, 2, 3, 4})]:
        surf = check_surface(surface)
        assert set(np.unique(surf.labels)) == labels
        assert signed_volume(surf.points, surf.triangles) > 0
    area_volume = signed_volume(*(lambda s: (s.points, s.triangles))(check_surface(tube)))
    assert area_volume == pytest.approx(np.pi * R**2 * 12.0, rel=0.01)  # polygonal cross-sections


def test_prism_split_is_positive_and_index_consistent_for_every_numbering():
    bottom = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    points = np.vstack([bottom, bottom + [0.1, 0.2, 0.5]])  # sheared prism, tet (0, 1, 2, 3) positive
    for perm in itertools.permutations(range(6)):
        perm = np.array(perm)
        pts = np.empty_like(points)
        pts[perm] = points  # global index perm[i] sits at prism corner i
        tets = split_prisms(perm[None, :])
        assert tets.shape == (3, 4) and tet_volumes(pts, tets).min() > 0
        # each quad face is cut along the diagonal from its smallest index
        edges = {frozenset(e) for t in tets for e in itertools.combinations(t, 2)}
        for quad in ([0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]):
            q = perm[quad]
            start = int(np.argmin(q))
            assert frozenset((q[start], q[(start + 2) % 4])) in edges
            assert frozenset((q[(start + 1) % 4], q[(start + 3) % 4])) not in edges


def test_tube_mesh_is_conforming_positive_and_fills_the_surface(tube, tube_mesh):
    mesh, quality = tube_mesh
    points, tets, region = check_valid(tube, mesh)
    assert quality["volume"]["relative_error"] < 1e-9
    assert quality["elements"]["layer"] == 3 * N * np.sum(np.asarray(tube.cell_data[LABELS]) == 1)


def test_layers_measured_back_along_the_normals(tube_mesh):
    """On a straight cylinder the wall normal is radial: the depths of the mesh nodes below the
    wall cluster at N + 1 levels whose spacings are the requested heights."""
    mesh, quality = tube_mesh
    points = np.asarray(mesh.points)
    depth = R - np.linalg.norm(points[:, :2], axis=1)
    inner = depth[(depth < T * 1.01)]
    levels = np.sort(inner)
    gaps = np.flatnonzero(np.diff(levels) > 0.2 * T * (F - 1) / (F**N - 1))
    clusters = np.split(levels, gaps + 1)
    # the cylinder is a polygon: vertices sit at radius R exactly; allow the sagitta of the chords
    assert len(clusters) == N + 1
    means = np.array([c.mean() for c in clusters])
    heights = np.diff(means)
    first = T * (F - 1) / (F**N - 1)
    assert heights[0] == pytest.approx(first, rel=2e-3)
    np.testing.assert_allclose(heights[1:] / heights[:-1], F, rtol=2e-3)
    assert means[-1] == pytest.approx(T, rel=2e-3)
    assert max(np.ptp(c) for c in clusters) < 1e-3 * T  # every vertex of a level at the same depth
    profile = quality["boundary_layer"]
    assert profile["growth_ratio"]["max_abs_error"] < 1e-9
    assert profile["first_height_rel_error"]["max"] < 1e-9
    assert profile["reduced_fraction"] == 0.0
    walked = profile["read_back_from_mesh"]  # from the final mesh alone, along mesh edges
    assert walked["layers_found"]["min"] == N
    assert walked["growth_ratio_abs_error"]["max"] < 1e-3
    assert walked["first_height_rel_error"]["max"] < 1e-3


def test_core_quality_bounds(tube_mesh, bifurcation_mesh):
    for mesh, quality in (tube_mesh, bifurcation_mesh[1:]):
        points, tets, region = np.asarray(mesh.points), *split_cells(mesh)[:2]
        core = min_dihedral(points, tets[region == 1])
        assert core.min() >= 10.0
        assert np.mean(core >= 20.0) >= 0.99
        assert quality["core"]["min_dihedral"]["min_deg"] == pytest.approx(core.min())


def test_prism_measures_of_right_and_sheared_prisms():
    base = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(0.75), 0.0]])
    shift = np.array([0.3, 0.0, 0.1])  # a sheared prism: skew atan(0.3 / 0.1)
    points = np.vstack([base, base + [0.0, 0.0, 0.1], base + shift])
    prisms = np.array([[0, 1, 2, 3, 4, 5], [0, 1, 2, 6, 7, 8]])
    m = prism_measures(points, prisms, np.array([0.1, 0.2]))
    np.testing.assert_allclose(m["base_min_angle_deg"], 60.0)
    np.testing.assert_allclose(m["base_max_angle_deg"], 60.0)
    np.testing.assert_allclose(m["skew_deg"], [0.0, np.degrees(np.arctan(3.0))], atol=1e-9)
    np.testing.assert_allclose(m["height_mm"], 0.1)
    np.testing.assert_allclose(m["height_ratio"], [1.0, 0.5])


def test_layer_quality_is_reported_by_prisms_on_the_tube(tube, tube_mesh):
    """Straight tube, uniform layer: prism bases are the wall triangles, barely shrunk; right prisms."""
    mesh, quality = tube_mesh
    prisms = quality["layer_prisms"]
    surf = check_surface(tube)
    wall_angle = triangle_min_angles(surf.points, surf.triangles[surf.labels == 1]).min()
    assert prisms["count"] == N * np.sum(surf.labels == 1)
    assert 0.75 * wall_angle <= prisms["base_min_angle_deg"]["min"] <= wall_angle + 1e-9
    assert prisms["skew_deg"]["max"] < 5.0  # vertex normals against face normals of a 0.6 mm / R 3 mm tube
    assert 0.99 < prisms["height_ratio"]["min"] <= prisms["height_ratio"]["max"] < 1.0 + 1e-9
    assert prisms["degenerate"]["count"] == 0
    assert quality["layer"]["elements"] == "split-prism tetrahedra"
    whole = quality["mesh"]
    assert whole["core"] == {"floor_deg": CORE_MIN_DIHEDRAL, "below_floor": 0,
                             "worst_deg": quality["core"]["min_dihedral"]["min_deg"]}
    assert whole["min_dihedral_deg"] == min(quality["core"]["min_dihedral"]["min_deg"],
                                            quality["layer"]["min_dihedral"]["min_deg"])


def test_bifurcation_mesh_is_valid(bifurcation_mesh):
    surface, mesh, quality = bifurcation_mesh
    check_valid(surface, mesh)
    assert quality["boundary_layer"]["growth_ratio"]["max_abs_error"] < 1e-9
    # every column found again by an edge walk from the wall, beside the flow divider too
    assert quality["boundary_layer"]["read_back_from_mesh"]["layers_found"]["min"] == N


def test_layer_columns_stay_near_the_wall_normal_and_the_radius_is_the_walls():
    """At the Y bifurcation's divider the smoothed directions lean by up to 47 degrees from the normal.  They
    must stay within MAX_LEAN_DEG of it, and the local radius (which sets the thickness) is a property of the
    wall: the same however much the directions are smoothed."""
    surface = check_surface(labelled_bifurcation(size=0.6))
    wall_tris = surface.triangles[surface.labels == 1]
    smooth, rough = (build_layers(surface, layers=2, smoothing=s) for s in (10, 3))
    wall = smooth.wall_vertices
    area = np.cross(surface.points[wall_tris[:, 1]] - surface.points[wall_tris[:, 0]],
                    surface.points[wall_tris[:, 2]] - surface.points[wall_tris[:, 0]])
    normal = np.zeros((len(surface.points), 3))
    for k in range(3):
        np.add.at(normal, wall_tris[:, k], -area)
    normal = normal[wall] / np.linalg.norm(normal[wall], axis=1, keepdims=True)
    rim = np.isin(wall, surface.triangles[surface.labels != 1])  # projected onto the cap plane there
    lean = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", smooth.directions, normal), -1.0, 1.0)))
    assert lean[~rim].max() <= MAX_LEAN_DEG + 1e-6
    assert lean[~rim].max() > 0.9 * MAX_LEAN_DEG  # the divider reaches the cone: the bound acts
    np.testing.assert_array_equal(smooth.local_radius, rough.local_radius)
    trunk = (surface.points[wall, 2] > -12.0) & (surface.points[wall, 2] < -5.0)  # a cylinder of radius 3 mm
    assert np.median(smooth.local_radius[trunk]) == pytest.approx(3.0, rel=0.02)
    np.testing.assert_allclose(smooth.local_radius[trunk], 3.0, rtol=0.1)  # vertex normals of 0.6 mm facets


def _fans(count: int, spokes: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """``count`` separate fans of ``spokes`` triangles around a centre vertex (index ``f * (spokes + 1)``), their
    rims at random radii (0.3-1.5) and heights (-2.5 to 2.5): steep creases and saddles, like a coarse wall at a
    tight throat.  Triangles wind counter-clockwise seen from +z."""
    theta = np.sort(rng.uniform(0.0, 2.0 * np.pi, (count, spokes)), axis=1)
    radius, height = rng.uniform(0.3, 1.5, (count, spokes)), rng.uniform(-2.5, 2.5, (count, spokes))
    rim = np.stack([radius * np.cos(theta), radius * np.sin(theta), height], axis=-1)
    points = np.concatenate([np.zeros((count, 1, 3)), rim], axis=1) + 10.0 * np.arange(count)[:, None, None] * [1, 0, 0]
    centre = np.arange(count)[:, None] * (spokes + 1)
    k = np.arange(spokes)
    triangles = np.stack([np.broadcast_to(centre, (count, spokes)), centre + 1 + k, centre + 1 + (k + 1) % spokes],
                         axis=-1).reshape(-1, 3)
    return points.reshape(-1, 3), triangles


def test_layer_directions_see_every_face_wherever_a_direction_can():
    """The maximin direction of a vertex's faces (``_most_visible``) is at least as good as the best of 20 000
    directions sampled on the sphere; on 150 random fans the layer's direction at the centre sees all its faces
    (the first prism is upright) on every fan where some direction sees them by more than a degree (142).  The
    Laplacian-smoothed normals with their pushes alone leave 124 of those with an inverted first prism at any
    thickness."""
    from carotid.mesh.layers import _adjacency, _directions, _face_normals, _inward_normals, _most_visible, _unit

    rng = np.random.default_rng(7)
    count, spokes = 150, 9
    points, triangles = _fans(count, spokes, rng)
    inward_faces = -_unit(_face_normals(points, triangles)).reshape(count, spokes, 3)
    best, seen = _most_visible(inward_faces, np.zeros((count, 3)))
    sphere = _unit(rng.normal(size=(20000, 3)))
    sampled = np.einsum("si,fki->fsk", sphere, inward_faces).min(axis=2).max(axis=1)
    feasible = sampled > 0.0
    assert np.all(seen[feasible] >= sampled[feasible] - 1e-9)
    assert np.allclose(np.einsum("fki,fi->fk", inward_faces, best).min(axis=1), seen)
    n = len(points)
    directions = _directions(points, triangles, _inward_normals(points, triangles, triangles, n), triangles,
                             np.zeros((n, 3)), _adjacency(triangles, n), 10)
    centre_sees = np.einsum("fki,fi->fk", inward_faces, directions[::spokes + 1]).min(axis=1)
    clear = seen > np.sin(np.radians(1.0))
    assert clear.sum() >= count // 2 and np.all(centre_sees[clear] > 0.0)
    # a direction kept in a cap's plane (a rim vertex) stays in it
    plane = _unit(rng.normal(size=(count, 3)))
    in_plane, _ = _most_visible(inward_faces, plane)
    assert np.abs(np.einsum("fi,fi->f", in_plane, plane)).max() < 1e-9


def test_severe_stenosis_meshes_validly_with_a_thinner_layer_in_the_throat(stenosis_mesh):
    surface, mesh, quality = stenosis_mesh
    points, tets, region = check_valid(surface, mesh)
    assert quality["boundary_layer"]["thickness_mm"]["min"] <= 0.5 * 0.2 * R  # throat radius 0.6 mm
    assert quality["boundary_layer"]["thickness_mm"]["max"] >= 0.25 * R
    core = min_dihedral(points, tets[region == 1])
    assert core.min() >= 10.0


def test_tetgen_core_keeps_the_boundary_and_the_layer(tube):
    """TetGen's slivers (below the core floor here) are reported, and the layer is not thinned chasing them."""
    mesh, quality = build_mesh(tube, layers=3, ratio=1.3, thickness=0.5, core="tetgen", lloyd_iterations=1)
    check_valid(tube, mesh)
    assert quality["parameters"]["core"] == "tetgen"
    assert quality["mesh"]["core"]["below_floor"] > 0
    assert quality["boundary_layer"]["thinned_against_core_slivers"] == {"rounds": 0, "wall_vertices": 0}
    assert quality["boundary_layer"]["reduced_fraction"] == 0.0


def test_too_thick_layer_is_reduced_with_a_warning(tube):
    with pytest.warns(UserWarning, match="reduced"):
        mesh, quality = build_mesh(tube, layers=4, thickness=2.5, lloyd_iterations=0)
    check_valid(tube, mesh)
    assert quality["boundary_layer"]["thickness_mm"]["max"] <= 0.5 * R * 1.001


def test_lloyd_never_inverts_never_moves_fixed_nodes_and_improves(tube_mesh):
    mesh, _ = tube_mesh
    points, (tets, region) = np.asarray(mesh.points), split_cells(mesh)[:2]
    core = tets[region == 1]
    free = np.zeros(len(points), bool)
    free[np.unique(core)] = True
    free[np.unique(tets[region == 0])] = False
    free[boundary_faces(core).ravel()] = False
    rng = np.random.default_rng(0)
    noisy = points.copy()
    noisy[free] += rng.normal(scale=0.05, size=(free.sum(), 3))
    assert tet_volumes(noisy, core).min() > 0
    before = min_dihedral(noisy, core)
    smoothed, info = lloyd_smooth(noisy, core, free, iterations=5)
    after = min_dihedral(smoothed, core)
    assert tet_volumes(smoothed, core).min() > 0
    np.testing.assert_array_equal(smoothed[~free], noisy[~free])
    assert after.min() >= min(before.min(), 20.0) - 1e-9
    assert np.mean(dihedral_angles(smoothed, core).min(axis=1)) > np.mean(before) + 1.0
    assert info["moved"][0] > 0.5 * free.sum()


@pytest.mark.filterwarnings("ignore:boundary layer reduced")
def test_bad_surfaces_are_rejected_with_a_clear_error(tube):
    open_tube = tube.extract_cells(np.asarray(tube.cell_data[LABELS]) == 1).extract_surface(
        algorithm="dataset_surface")
    with pytest.raises(CarotidError, match="open"):
        build_mesh(open_tube)
    unlabelled = pv.PolyData(tube.points, tube.faces)
    with pytest.raises(CarotidError, match="CellEntityIds"):
        build_mesh(unlabelled)
    no_wall = tube.copy()
    no_wall.cell_data[LABELS] = np.full(tube.n_cells, 2, dtype=np.int32)
    with pytest.raises(CarotidError, match="wall"):
        build_mesh(no_wall)
    bent_cap = tube.copy()
    pts = np.asarray(bent_cap.points).copy()
    cap = np.unique(bent_cap.regular_faces[np.asarray(bent_cap.cell_data[LABELS]) == 3])
    inner_cap = cap[np.linalg.norm(pts[cap, :2], axis=1) < 1.0]
    pts[inner_cap, 2] += 0.3
    bent_cap.points = pts
    with pytest.raises(CarotidError, match="planar"):
        build_mesh(bent_cap)
    # two overlapping closed tubes: closed and manifold, but self-intersecting
    other = tube.copy()
    other.points = np.asarray(tube.points) + [1.5, 0.0, 3.0]
    other.cell_data[LABELS] = np.where(other.cell_data[LABELS] == 1, 1, other.cell_data[LABELS] + 2)
    crossing = tube.merge(other)
    with pytest.raises(CarotidError, match="intersect"):
        build_mesh(crossing, layers=2, thickness=0.3, lloyd_iterations=0)


def test_cap_open_ends_and_flat_cap_detection_restore_the_volume(tube):
    closed = check_surface(tube)
    expected = signed_volume(closed.points, closed.triangles)
    open_tube = tube.extract_cells(np.asarray(tube.cell_data[LABELS]) == 1).extract_surface(
        algorithm="dataset_surface")
    capped = check_surface(cap_open_ends(open_tube))
    assert signed_volume(capped.points, capped.triangles) == pytest.approx(expected, rel=1e-12)
    assert sorted(np.unique(capped.labels)) == [1, 2, 3]
    relabelled = check_surface(label_flat_caps(pv.PolyData(tube.points, tube.faces)))
    np.testing.assert_array_equal(np.bincount(relabelled.labels), np.bincount(closed.labels))
    with pytest.raises(CarotidError, match="flat end caps"):
        label_flat_caps(pv.Sphere(radius=3.0))


def test_a_small_open_end_is_capped_with_a_warning_that_it_may_be_a_hole(tube):
    """Two triangles taken out of the wall leave a loop of about 2 mm beside ends of 2 pi R: capped as an
    outlet all the same (a cut small branch looks alike), with a warning; the tube's own two ends give none."""
    wall = tube.extract_cells(np.asarray(tube.cell_data[LABELS]) == 1).extract_surface(algorithm="dataset_surface")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cap_open_ends(wall)
    centres = wall.cell_centers().points
    middle = np.argsort(np.abs(centres[:, 2] - 6.0))[:1]
    neighbour = np.flatnonzero(np.isin(wall.regular_faces, wall.regular_faces[middle]).sum(axis=1) == 2)[:1]
    holed = wall.remove_cells(np.r_[middle, neighbour]).extract_surface(algorithm="dataset_surface")
    with pytest.warns(CarotidWarning, match=r"1 open end\(s\) of perimeter .* capped as outlets"):
        capped = cap_open_ends(holed)
    assert sorted(np.unique(capped.cell_data[LABELS])) == [1, 2, 3, 4]


def test_write_mesh_outputs(tmp_path, tube_mesh):
    mesh, quality = tube_mesh
    write_mesh(mesh, tmp_path, quality)
    vtu = pv.read(tmp_path / "mesh.vtu")
    assert vtu.n_cells == mesh.n_cells
    ids = np.asarray(vtu.cell_data[LABELS])
    assert np.all(ids[vtu.celltypes == pv.CellType.TETRA] == 0)
    assert set(np.unique(ids[vtu.celltypes == pv.CellType.TRIANGLE])) == {1, 2, 3}
    msh = meshio.read(tmp_path / "mesh.msh")
    assert {"wall", "inlet", "outlet_1", "fluid"} <= set(msh.field_data)
    assert sum(len(b.data) for b in msh.cells if b.type == "tetra") == quality["elements"]["tetrahedra"]
    header = (tmp_path / "mesh.msh").read_bytes()[:40]
    assert b"4.1" in header
    xdmf = meshio.read(tmp_path / "mesh.xdmf")
    assert len(xdmf.cells_dict["tetra"]) == quality["elements"]["tetrahedra"]
    facets = meshio.read(tmp_path / "mesh_facets.xdmf")
    assert set(np.unique(facets.cell_data[LABELS][0])) == {1, 2, 3}
    report = json.loads((tmp_path / "mesh_quality.json").read_text())
    assert report["elements"]["tetrahedra"] == quality["elements"]["tetrahedra"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["mesh.vtu", "mesh.msh", "mesh.xdmf", "mesh.h5", "mesh_facets.xdmf", "mesh_facets.h5", "mesh_quality.json"])


def test_write_mesh_leaves_nothing_half_written(tmp_path, tube_mesh, monkeypatch):
    import carotid.mesh.io as mesh_io

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(mesh_io, "write_xdmf", broken)
    with pytest.raises(OSError):
        write_mesh(tube_mesh[0], tmp_path, tube_mesh[1])
    assert list(tmp_path.iterdir()) == []


def _parser():
    parser = argparse.ArgumentParser(prog="carotid")
    register(parser.add_subparsers(dest="command"))
    return parser


def test_command_line(tmp_path, capsys):
    parser = _parser()
    case = tmp_path / "case"
    args = parser.parse_args(["mesh", str(case)])
    with pytest.raises(CarotidError, match="carotid surface"):
        args.func(args)
    case.mkdir()
    labelled_tube(radius=2.0, length=6.0, size=0.7).save(case / "surface.vtp")
    args = parser.parse_args(["mesh", str(case), "--layers", "3", "--ratio", "1.3", "--thickness", "0.3",
                              "--core", "tetgen", "--lloyd", "1"])
    assert args.func(args) == 0
    assert "tetrahedra" in capsys.readouterr().out
    report = json.loads((case / "mesh_quality.json").read_text())
    assert report["parameters"]["layers"] == 3 and report["parameters"]["core"] == "tetgen"
    # an external open surface: its ends are capped
    tube = labelled_tube(radius=2.0, length=6.0, size=0.7)
    tube.extract_cells(np.asarray(tube.cell_data[LABELS]) == 1).extract_surface(
        algorithm="dataset_surface").save(tmp_path / "open.stl")
    args = parser.parse_args(["mesh", "--from-surface", str(tmp_path / "open.stl"), "-o", str(tmp_path / "ext"),
                              "--layers", "2", "--thickness-ratio", "0.2", "--lloyd", "0"])
    assert args.func(args) == 0
    assert set(json.loads((tmp_path / "ext" / "mesh_quality.json").read_text())["elements"]
               ["boundary_triangles"]) == {"1", "2", "3"}
    pv.Sphere().save(tmp_path / "sphere.stl")
    args = parser.parse_args(["mesh", "--from-surface", str(tmp_path / "sphere.stl"), "-o", str(tmp_path / "s")])
    with pytest.raises(CarotidError, match="flat end caps"):
        args.func(args)
    assert not (tmp_path / "s").exists()
    with pytest.raises(SystemExit):
        parser.parse_args(["mesh", str(case), "--thickness", "0.3", "--thickness-ratio", "0.2"])


@needs_fluid_stl
def test_real_carotid_surface_meshes_with_ten_layers():
    """fluid.stl (SPHinXsys) through carotid's own external-surface path (level set, centerlines,
    clipped and remeshed surface), then meshed with 10 layers."""
    from carotid.centerline import compute_centerlines
    from carotid.surface.external import levelset_from_surface, load_external_surface
    from carotid.surface.pipeline import build_surface

    closed, _ = load_external_surface(FLUID_STL)
    levelset = levelset_from_surface(closed, spacing=0.3)
    surface, caps, _ = build_surface(levelset, compute_centerlines(levelset), target_edge_mm=0.5)
    assert sorted(np.unique(surface.cell_data[LABELS])) == [1, 2, 3, 4]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh, quality = build_mesh(surface, layers=10)
    points, tets = np.asarray(mesh.points), split_cells(mesh)[0]
    assert tet_volumes(points, tets).min() > 0
    assert face_counts(tets).max() == 2
    assert quality["volume"]["relative_error"] < 1e-6
    assert quality["boundary_layer"]["layers"] == 10
    assert quality["core"]["min_dihedral"]["fraction_ge_20deg"] >= 0.99


def test_retriangulated_inner_caps_and_no_layer_meshes_are_valid(tube, monkeypatch):
    import carotid.mesh.layers as layers

    monkeypatch.setattr(layers._inner_caps, "__defaults__", (180.0,))  # force the Delaunay re-triangulation
    mesh, quality = build_mesh(tube, layers=3, thickness=0.5, lloyd_iterations=1)
    points, tets, region = check_valid(tube, mesh)
    assert len(np.unique(tets)) == len(points)  # the unused cap vertices were dropped
    monkeypatch.undo()
    mesh, quality = build_mesh(tube, layers=0, lloyd_iterations=1)
    points, tets, region = check_valid(tube, mesh)
    assert np.all(region == 1) and "boundary_layer" not in quality
    triangles, labels = split_cells(mesh)[2:]
    surf = check_surface(tube)
    assert coordinate_keys(points, triangles) == coordinate_keys(surf.points, surf.triangles)


def test_a_single_sub_layer_meshes_and_reports_no_growth_ratio(tube):
    mesh, quality = build_mesh(tube, layers=1, thickness=0.4, lloyd_iterations=0)
    points, tets, region = check_valid(tube, mesh)
    layer = quality["boundary_layer"]
    assert layer["layers"] == 1 and layer["growth_ratio"] is None
    assert layer["first_height_mm"]["max"] == pytest.approx(0.4, rel=0.05)
    assert np.count_nonzero(region == 0) > 0
