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


def test_convergence_study_plumbing_on_a_tiny_tube(tmp_path):
    # end to end on a capped tube (wall, inlet, outlet) split into two "branches" along its axis: three meshes,
    # three short runs, per-branch and per-node GCI written; the GCI itself is verified above
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
    params = FlowParameters(cycles=0.1, waveform=Waveform(0.02, t, np.full(6, 0.2e-6)), output_every=2)
    result = run_convergence(tmp_path, params, refinement=1.5)

    recorded = json.loads((tmp_path / "mesh_quality.json").read_text())["parameters"]
    finest = coarsened_mesh_parameters(recorded, 1.5 ** -2)
    assert finest["size"] == pytest.approx(0.3 / 2.25) and finest["layers"] == 7  # round(3 * 2.25)
    assert finest["ratio"] ** 7 == pytest.approx(1.2 ** 3)  # same grading span
    h = [level["h_mm"] for level in result["levels"]]
    assert h[0] < h[1] < h[2]
    assert set(result["branches"]["TAWSS"]) == {"CCA", "ICA", "whole wall"}
    for row in result["branches"]["TAWSS"].values():
        assert len(row["phi_fine_to_coarse"]) == 3 and row["status"] in ("monotonic", "oscillatory", "divergent",
                                                                         "indeterminate")
    gci_map = pv.read(tmp_path / "flow" / "convergence.vtp")
    assert {"TAWSS_GCI", "OSI_ext", "RRT_p", "branch"} <= set(gci_map.point_data.keys())
    assert json.loads((tmp_path / "flow" / "convergence.json").read_text())["refinement"] == 1.5
