"""Grid convergence index (carotid.flow.convergence) against the published example and exact sequences."""

import numpy as np
import pytest

from carotid.errors import CarotidError
from carotid.flow.convergence import (DIVERGENT, INDETERMINATE, MONOTONIC, OSCILLATORY, grid_convergence,
                                      representative_size)


def test_celik_table1_reattachment_length():
    # Celik et al. 2008, J. Fluids Eng. 130:078001, table 1, first column: 2-D grids of 18000, 8000 and 4500
    # cells (so h = N^-1/2, r21 = 1.5, r32 = 1.333), dimensionless reattachment length 6.063, 5.972, 5.863;
    # published p = 1.53, phi_ext21 = 6.1685, e_a21 = 1.5 %, e_ext21 = 1.7 %, GCI_fine21 = 2.2 %.
    h = np.array([18000.0, 8000.0, 4500.0]) ** -0.5
    r = grid_convergence(h, [6.063, 5.972, 5.863])
    assert r["r21"] == pytest.approx(1.5) and r["r32"] == pytest.approx(4 / 3)
    assert r["p"] == pytest.approx(1.53, abs=0.005)
    assert r["phi_ext21"] == pytest.approx(6.1685, abs=5e-5)
    assert r["e_a21"] == pytest.approx(0.015, abs=5e-4)
    assert r["e_ext21"] == pytest.approx(0.017, abs=5e-4)
    assert r["gci_fine21"] == pytest.approx(0.022, abs=5e-4)
    assert r["status"] == MONOTONIC


def test_manufactured_sequences_unequal_ratios_vectorised():
    # phi(h) = phi0 + C h^p on h = 1, 1.7, 2.3 (r21 = 1.7, r32 = 1.353): p and phi0 recovered exactly, and the
    # GCI is Fs |phi1 - phi2| / |phi1| / (r21^p - 1); several quantities at once, meshes given in any order.
    p_true = np.array([[0.8, 1.0], [2.0, 2.7]])
    phi0 = np.array([[1.5, -3.0], [0.2, 10.0]])
    c = np.array([[0.3, 2.0], [-0.05, 1.0]])
    h = np.array([2.3, 1.0, 1.7])
    phi = phi0 + c * h[:, None, None] ** p_true
    r = grid_convergence(h, phi)
    np.testing.assert_allclose(r["p"], p_true, rtol=0, atol=1e-8)
    np.testing.assert_allclose(r["phi_ext21"], phi0, rtol=0, atol=1e-8)
    phi1, phi2 = phi0 + c, phi0 + c * 1.7 ** p_true
    np.testing.assert_allclose(r["gci_fine21"], 1.25 * np.abs((phi1 - phi2) / phi1) / (1.7 ** p_true - 1), rtol=1e-8)
    np.testing.assert_allclose(r["e_ext21"], np.abs(c / phi0), rtol=1e-8)
    assert np.all(r["status"] == MONOTONIC)


def test_oscillatory_divergent_and_indeterminate_are_flagged():
    # phi_i = phi0 + (-1)^i C h_i^p: eq. 2 with s = -1 recovers p exactly (h = 1, 1.5, 2.4)
    h = np.array([1.0, 1.5, 2.4])
    osc = 4.0 + np.array([-1.0, 1.0, -1.0]) * 0.2 * h ** 1.6
    # error growing as h shrinks (p = -1), and a quantity that does not change between the two finest meshes
    div = 4.0 + 0.2 * h ** -1.0
    flat = np.array([2.0, 2.0, 2.5])
    r = grid_convergence(h, np.stack([osc, div, flat], axis=1))
    assert r["p"][0] == pytest.approx(1.6, abs=1e-8)
    assert r["status"].tolist() == [OSCILLATORY, DIVERGENT, INDETERMINATE]
    assert np.isfinite(r["gci_fine21"][0]) and np.all(np.isnan(r["gci_fine21"][1:]))


def test_representative_size_and_bad_input():
    assert representative_size(8000.0, 1000) == pytest.approx(2.0)
    with pytest.raises(CarotidError):
        grid_convergence([1.0, 1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(CarotidError):
        grid_convergence([1.0, 2.0], [1.0, 2.0])


def test_coarsened_surface_scales_the_wall_and_keeps_the_caps():
    # the convergence levels' walls: edges factor times as long (shorter for factor < 1), same labels, caps in
    # their planes, the same lumen (volume within 3 %: the chords of 0.68 mm edges on a 1.5 mm radius cut 2 %)
    from carotid.mesh.boundary import check_surface
    from carotid.mesh.mesher import median_edge
    from carotid.mesh.testing import labelled_tube
    from carotid.surface.mesh import from_polydata, signed_volume
    from carotid.surface.remesh import coarsened_surface, local_edge_length

    surface = labelled_tube(radius=1.5, length=4.0, size=0.3)
    points, faces, labels = from_polydata(surface)
    edge = median_edge(check_surface(surface))
    assert np.median(local_edge_length(points, faces)) == pytest.approx(edge, rel=0.1)
    for factor in (1.5, 2.25, 1 / 1.5):
        coarse = coarsened_surface(surface, factor)
        p, f, lab = from_polydata(coarse)
        assert median_edge(check_surface(coarse)) == pytest.approx(factor * edge, rel=0.15)
        assert set(np.unique(lab)) == {1, 2, 3}
        np.testing.assert_allclose(p[np.unique(f[lab == 2]), 2], 0.0, atol=1e-9)
        np.testing.assert_allclose(p[np.unique(f[lab == 3]), 2], 4.0, atol=1e-9)
        assert signed_volume(p, f) == pytest.approx(signed_volume(points, faces), rel=0.03)


def test_wall_interpolation_reproduces_a_linear_field():
    # coarse-level indices are carried to the case wall's nodes linearly: exact for a linear field on a plane,
    # from one triangulation to another
    import pyvista as pv

    from carotid.flow.convergence import wall_interpolation

    coarse = pv.Plane(i_size=2.0, j_size=2.0, i_resolution=3, j_resolution=4).triangulate()
    fine = pv.Plane(i_size=2.0, j_size=2.0, i_resolution=11, j_resolution=7).triangulate()
    query = np.asarray(fine.points) + np.array([0.0, 0.0, 0.05])  # off the plane: the closest point is used
    vertices, weights = wall_interpolation(coarse, query)
    field = np.asarray(coarse.points) @ np.array([1.5, -0.7, 0.0]) + 2.0
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert weights.min() >= -1e-12
    np.testing.assert_allclose((field[vertices] * weights).sum(axis=1),
                               np.asarray(fine.points) @ np.array([1.5, -0.7, 0.0]) + 2.0, atol=1e-12)


def test_convergence_options():
    from carotid.flow.command import build_parser

    args = build_parser().parse_args(["simulate", "case", "--convergence"])
    assert (args.cycles, args.time_levels, args.workers, args.refinement, args.case_mesh) == (None, True, 2, 1.5, True)
    args = build_parser().parse_args(["simulate", "case", "--convergence", "--no-time-levels", "--workers", "1",
                                      "--no-case-mesh"])
    assert (args.time_levels, args.workers, args.case_mesh) == (False, 1, False)


def test_convergence_study_on_a_tiny_tube(tmp_path):
    # end to end on a capped tube (wall, inlet, outlet) split into two "branches" along its axis, in two worker
    # processes: the case mesh is level 0 and levels 1, 2 are meshed from the surface remeshed with longer edges
    # (the wall is coarsened too), the coarsest runs again at 1/2 and 1/4 of its step; per-branch and per-node
    # GCI written, in space and in time.  The GCI itself is verified above.
    import json

    import pyvista as pv

    from carotid.centerline import Branch, Centerlines, write_centerlines
    from carotid.flow.convergence import coarsened_mesh_parameters, run_convergence
    from carotid.flow.simulate import FlowParameters
    from carotid.flow.waveform import Waveform
    from carotid.mesh.io import write_mesh
    from carotid.mesh.mesher import build_mesh
    from carotid.mesh.testing import labelled_tube

    surface = labelled_tube(radius=1.5, length=3.0, size=0.3, sections=7)
    surface.save(tmp_path / "surface.vtp")
    mesh, quality = build_mesh(surface, layers=3, ratio=1.2, size=0.3)
    write_mesh(mesh, tmp_path, quality)
    z = np.linspace(0.0, 3.0, 7)[:, None] * np.array([0.0, 0.0, 1.0])
    write_centerlines(Centerlines([Branch("CCA", z[:4], np.ones(4)), Branch("ICA", z[3:], np.ones(4))], z[3]),
                      tmp_path)
    t = np.linspace(0.0, 0.02, 6, endpoint=False)
    params = FlowParameters(cycles=0.5, waveform=Waveform(0.02, t, np.full(6, 0.2e-6)), output_every=2)
    seen = []
    result = run_convergence(tmp_path, params, refinement=1.5, workers=2, progress=seen.append)

    recorded = json.loads((tmp_path / "mesh_quality.json").read_text())["parameters"]
    coarsest = coarsened_mesh_parameters(recorded, 1.5 ** 2)
    assert coarsest["size"] == pytest.approx(0.3 * 2.25) and coarsest["layers"] == 2  # max(2, round(3 / 2.25))
    assert coarsest["ratio"] ** 2 == pytest.approx(1.2 ** 3)  # same grading span
    levels = result["levels"]
    assert levels[0]["tetrahedra"] == quality["elements"]["tetrahedra"]  # level 0 is the case mesh itself
    assert [level["edge_factor"] for level in levels] == pytest.approx([1.0, 1.5, 2.25])
    h = [level["h_mm"] for level in levels]
    assert h[0] < h[1] < h[2]
    walls = [level["wall_triangles"] for level in levels]
    assert walls[0] > 1.8 * walls[1] and walls[1] > 1.8 * walls[2]  # about 1.5^2 fewer wall triangles per level
    edges = [level["wall_edge_mm"] for level in levels]
    assert edges[1] / edges[0] == pytest.approx(1.5, rel=0.15) and edges[2] / edges[1] == pytest.approx(1.5, rel=0.15)
    assert set(result["branches"]["TAWSS"]) == {"CCA", "ICA", "whole wall"}
    for row in result["branches"]["TAWSS"].values():
        assert len(row["phi_fine_to_coarse"]) == 3 and row["status"] in ("monotonic", "oscillatory", "divergent",
                                                                         "indeterminate")
    temporal = result["time"]
    assert [level["name"] for level in temporal["levels"]] == ["level2", "level2_dt2", "level2_dt4"]
    steps = [level["steps"] for level in temporal["levels"]]
    assert steps[0] < steps[1] < steps[2] and temporal["levels"][0]["steps"] == levels[2]["steps"]
    assert set(temporal["branches"]["TAWSS"]) == {"CCA", "ICA", "whole wall"}
    gci_map = pv.read(tmp_path / "flow" / "convergence.vtp")
    assert gci_map.n_points == pv.read(tmp_path / "flow" / "convergence" / "level0" / "flow" / "indices.vtp").n_points
    assert {"TAWSS_GCI", "OSI_ext", "RRT_p", "branch"} <= set(gci_map.point_data.keys())
    written = json.loads((tmp_path / "flow" / "convergence.json").read_text())
    assert written["refinement"] == 1.5 and written["time"]["mesh_level"] == 2
    assert seen and seen[-1]["fraction"] == pytest.approx(1.0)
    assert set(seen[-1]["runs"]) == {"level0", "level1", "level2", "level2_dt2", "level2_dt4"}

    # without the case mesh: the levels are the case mesh coarsened by 1.5, 1.5^2 and 1.5^3 (rebuilt identically)
    coarser = run_convergence(tmp_path, params, refinement=1.5, time_levels=False, workers=1, case_mesh=False)
    assert [level["edge_factor"] for level in coarser["levels"]] == pytest.approx([1.5, 2.25, 3.375])
    assert coarser["levels"][0]["tetrahedra"] == levels[1]["tetrahedra"] and coarser["time"] is None
    assert coarser["case_level"] is None and result["case_level"] == 0
