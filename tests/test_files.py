"""The files a case leaves for other tools: the flow series in SI (coordinates in metres) and the boundary
groups of the mesh files named by branch (issue 14)."""

import json

import meshio
import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from carotid.flow.verify import TubeSpec, tube_mesh
from carotid.mesh import write_mesh
from carotid.mesh.core import gmsh_session

TINY = TubeSpec(n_square=2, n_core=2, n_layers=2, first_layer=0.1, growth=1.3, n_axial=2, length=3.0)


def _demo_case(demo_run):
    """The demo's case folder, once its flow stage has finished (the later report stage is not needed)."""
    proc, out = demo_run
    assert (out / "case" / "flow" / "summary.json").is_file(), proc.stderr[-2000:]
    return out / "case"


def _last_step(path):
    """Points (n, 3), cells of the first block, point data and cell data of the last step of an XDMF series."""
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        _, point_data, cell_data = reader.read_data(reader.num_steps - 1)
    return points, cells[0].data, point_data, cell_data


def test_flow_series_coordinates_are_metres(demo_run):
    case = _demo_case(demo_run)
    mesh_mm = pv.read(case / "mesh.vtu").points
    points, tets, point_data, _ = _last_step(case / "flow" / "fields.xdmf")
    np.testing.assert_allclose(points, mesh_mm / 1000.0, rtol=1e-12)
    assert 0.01 < np.ptp(points, axis=0).max() < 0.2  # a carotid bifurcation is a few cm long
    assert len(tets) == np.sum(pv.read(case / "mesh.vtu").celltypes == pv.CellType.TETRA)
    assert point_data["velocity"].shape == points.shape
    wall_points, _, _, _ = _last_step(case / "flow" / "wall.xdmf")
    distance, _ = cKDTree(points).query(wall_points)
    assert distance.max() == 0.0  # the wall nodes are volume nodes, in the same unit


def test_wall_shear_from_the_series_gradients_is_in_pascal(demo_run):
    """mu (grad u + grad u^T) n computed by a user from the XDMF (P1 gradient of the wall tetrahedron) is
    the solver's WSS_face (Pa) up to the solver's extrapolation to the wall, not 1000 times smaller."""
    case = _demo_case(demo_run)
    mu = json.loads((case / "flow" / "summary.json").read_text())["settings"]["mu"]
    points, tets, point_data, _ = _last_step(case / "flow" / "fields.xdmf")
    wall_points, wall_triangles, _, wall_cells = _last_step(case / "flow" / "wall.xdmf")
    u = point_data["velocity"]
    # element gradients: the edge vectors E (rows) and velocity differences dU (rows) satisfy dU = E grad^T
    edges = points[tets[:, 1:]] - points[tets[:, :1]]
    grad = np.linalg.solve(edges, u[tets[:, 1:]] - u[tets[:, :1]]).transpose(0, 2, 1)
    # the tetrahedron owning each wall triangle, by a sorted-vertex key
    tri = cKDTree(points).query(wall_points)[1][wall_triangles]
    n = len(points)
    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    keys = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
    tri_sorted = np.sort(tri, axis=1)
    order = np.argsort(keys)
    pos = np.searchsorted(keys[order], (tri_sorted[:, 0] * n + tri_sorted[:, 1]) * n + tri_sorted[:, 2])
    owner = order[pos] // 4
    assert np.array_equal(faces[order[pos]], tri_sorted)
    normal = np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inward = np.einsum("fi,fi->f", points[tets[owner]].mean(axis=1) - points[tri].mean(axis=1), normal)
    normal *= np.sign(inward)[:, None]
    g = grad[owner]
    tau = mu * np.einsum("fij,fj->fi", g + g.transpose(0, 2, 1), normal)
    tau -= np.einsum("fi,fi->f", tau, normal)[:, None] * normal
    stored = wall_cells["WSS_face"][0]
    strong = np.linalg.norm(stored, axis=1) > np.median(np.linalg.norm(stored, axis=1))
    ratio = np.linalg.norm(tau[strong], axis=1) / np.linalg.norm(stored[strong], axis=1)
    cosine = np.einsum("fi,fi->f", tau[strong], stored[strong]) / np.linalg.norm(tau[strong], axis=1) \
        / np.linalg.norm(stored[strong], axis=1)
    assert 0.8 < np.median(ratio) < 1.1
    assert np.median(cosine) > 0.99


def _physical_groups(path):
    """``{name: (dim, tag, number of elements)}`` of a Gmsh file, read with gmsh's API."""
    with gmsh_session() as gmsh:
        gmsh.open(str(path))
        groups = {}
        for dim, tag in gmsh.model.getPhysicalGroups():
            count = sum(len(gmsh.model.mesh.getElements(dim, int(entity))[1][0])
                        for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag))
            groups[gmsh.model.getPhysicalName(dim, tag)] = (dim, tag, count)
    return groups


def test_mesh_outlet_groups_are_named_by_branch(demo_run):
    case = _demo_case(demo_run)
    caps = {c["name"]: c["id"] for c in json.loads((case / "geometry.json").read_text())["caps"]}
    expected = {"wall": 1, "inlet": 2, "outlet_ICA": caps["ICA"], "outlet_ECA": caps["ECA"]}
    grid = pv.read(case / "mesh.vtu")
    ids = np.asarray(grid.cell_data["CellEntityIds"])[grid.celltypes == pv.CellType.TRIANGLE]
    groups = _physical_groups(case / "mesh.msh")
    assert {name: tag for name, (dim, tag, _) in groups.items() if dim == 2} == expected
    assert groups["fluid"][:2] == (3, 1)
    for name, tag in expected.items():  # each group holds exactly the triangles of its CellEntityIds
        assert groups[name][2] == np.sum(ids == tag) > 0
    assert {k: v.tolist() for k, v in meshio.read(case / "mesh.msh").field_data.items()} == \
        {**{name: [tag, 2] for name, tag in expected.items()}, "fluid": [1, 3]}
    facets = meshio.read(case / "mesh_facets.xdmf")
    assert {k: v.tolist() for k, v in facets.field_data.items()} == {n: [t, 2] for n, t in expected.items()}
    assert json.loads((case / "mesh_quality.json").read_text())["groups"] == expected


def test_outlets_fall_back_to_numbers_without_a_matching_record(tmp_path):
    grid = tube_mesh(TINY, split_outlet=True).to_pyvista()  # outlets 3 (x < 0) and 4 (x > 0), mm
    grid.cell_data["Region"] = np.where(grid.celltypes == pv.CellType.TETRA, 1, -1).astype(np.int32)
    labels = np.asarray(grid.cell_data["CellEntityIds"])
    caps = []
    for label, name in ((3, "ICA"), (4, "ECA")):
        cells = grid.extract_cells(labels == label)
        area = cells.compute_cell_sizes(length=False, volume=False)["Area"]
        caps.append({"id": label, "name": name, "centre": cells.cell_centers().points.T @ area / area.sum(),
                     "equivalent_radius": float(np.sqrt(area.sum() / np.pi))})
    swapped = [{**caps[0], "centre": caps[1]["centre"]}, {**caps[1], "centre": caps[0]["centre"]}]
    numbered = {"wall": 1, "inlet": 2, "outlet_1": 3, "outlet_2": 4}
    named = {"wall": 1, "inlet": 2, "outlet_ICA": 3, "outlet_ECA": 4}
    for folder, record, expected in (("none", None, numbered), ("other_surface", swapped, numbered),
                                     ("this_surface", caps, named)):
        case = tmp_path / folder
        case.mkdir()
        if record is not None:
            (case / "geometry.json").write_text(json.dumps(
                {"caps": [{**c, "centre": np.asarray(c["centre"]).tolist()} for c in record]}))
        write_mesh(grid, case, {})
        groups = _physical_groups(case / "mesh.msh")
        assert {name: tag for name, (dim, tag, _) in groups.items() if dim == 2} == expected
        facets = meshio.read(case / "mesh_facets.xdmf")
        assert {k: v.tolist() for k, v in facets.field_data.items()} == {n: [t, 2] for n, t in expected.items()}
        assert json.loads((case / "mesh_quality.json").read_text())["groups"] == expected
