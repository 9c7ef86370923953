"""Bad inputs of the flow stage: one line on stderr and exit 2 (or one warning line), never a traceback, a VTK
error dump or a run that means nothing."""

import numpy as np
import pytest

from carotid.cli import main
from carotid.errors import CarotidError, CarotidWarning
from carotid.flow.verify import TubeSpec, tube_mesh

TINY = TubeSpec(n_square=4, n_core=3, n_layers=2, first_layer=0.1, growth=1.4, n_axial=3, length=3.0)


@pytest.fixture
def tube_case(tmp_path):
    tube_mesh(TINY).to_pyvista().save(tmp_path / "mesh.vtu")
    return tmp_path


def _params(**kw):
    from carotid.flow.simulate import FlowParameters

    return FlowParameters(**{"cycles": 0.003, "output_every": 10, "checkpoint_every": 20, "n_harmonics": 4, **kw})


def _one_error(capfd, argv) -> str:
    """The CLI's stderr for ``argv``, asserting exit 2 and a single line."""
    code = main([str(a) for a in argv])
    err = capfd.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith("carotid: error: "), err
    return err


def test_a_mesh_node_with_non_finite_coordinates_is_refused_when_read(tube_case, capfd):
    grid = tube_mesh(TINY).to_pyvista()
    grid.points[5] = np.nan
    grid.save(tube_case / "mesh.vtu")
    err = _one_error(capfd, ["simulate", tube_case, "--cycles", "0.01"])
    assert "mesh.vtu: non-finite coordinates" in err


@pytest.mark.parametrize("name, what", [("mesh.vtu", "mesh file"), ("centerlines.vtp", "centerline file")])
def test_a_junk_vtk_file_is_one_line_without_vtk_output(tube_case, capfd, name, what):
    (tube_case / name).write_text("this is not VTK\n")
    err = _one_error(capfd, ["simulate", tube_case, "--cycles", "0.01"])
    assert f"{name}: not a readable {what} (Error parsing XML" in err


@pytest.mark.parametrize("text, reason", [("{x", "not valid JSON"), ("[1, 2, 3]", "not a JSON object")])
def test_an_unreadable_geometry_record_is_named(tube_case, capfd, text, reason):
    from carotid.centerline import Branch, Centerlines, write_centerlines

    z = np.linspace(0.0, 3.0, 7)[:, None] * np.array([0.0, 0.0, 1.0])
    write_centerlines(Centerlines([Branch("CCA", z, np.ones(7))], z[-1]), tube_case)
    (tube_case / "geometry.json").write_text(text)
    err = _one_error(capfd, ["simulate", tube_case, "--cycles", "0.01"])
    assert f"geometry.json: {reason}" in err and "rerun `carotid centerlines`" in err


def test_centerlines_of_another_case_skip_the_duplex_with_a_warning(tube_case):
    from carotid.centerline import Branch, Centerlines, write_centerlines
    from carotid.flow.duplex import case_probes
    from carotid.flow.mesh import FlowMesh

    z = np.linspace(0.0, 3.0, 7)[:, None] * np.array([0.0, 0.0, 1.0]) + [20.0, 0.0, 0.0]  # beside the tube
    write_centerlines(Centerlines([Branch("CCA", z[:4], np.ones(4)), Branch("ICA", z[3:], np.ones(4))], z[3]),
                      tube_case)
    with pytest.warns(CarotidWarning, match="no virtual duplex: the centerlines do not match the mesh: 0 %"):
        probes, meta = case_probes(tube_case, FlowMesh.from_vtu(tube_case / "mesh.vtu"))
    assert not len(probes) and "do not match" in meta["reason"]


def test_a_corrupt_checkpoint_stops_resume_and_is_set_aside_by_auto(tube_case):
    from carotid.flow.simulate import simulate

    ckpt = tube_case / "flow" / "checkpoint.npz"
    ckpt.parent.mkdir()
    ckpt.write_bytes(b"junk, not an archive")
    with pytest.raises(CarotidError, match="checkpoint.npz: not a readable checkpoint .*delete it to start from t = 0"):
        simulate(tube_case / "mesh.vtu", tube_case, _params(), resume=True)
    with pytest.warns(CarotidWarning, match="not a readable checkpoint .*moved to checkpoint.npz.corrupt"):
        summary = simulate(tube_case / "mesh.vtu", tube_case, _params(), resume="auto")
    assert summary["steps"] > 0 and ckpt.is_file()
    assert (ckpt.parent / "checkpoint.npz.corrupt").read_bytes() == b"junk, not an archive"


@pytest.mark.parametrize("rows, message", [
    ("0,5e-9\n0.25,8e-9\n0.5,6e-9\n0.75,5e-9\n1,5e-9\n", "mean flow of 6e-09 mL/s is below 0.01 mL/s"),
    ("0,5\n1e-9,8\n2e-9,6\n3e-9,5\n4e-9,5\n", "a cardiac period of 4e-09 s is outside 0.2-5 s"),
    ("0,-5\n0.25,-8\n0.5,-6\n0.75,-5\n1,-5\n", "blood must enter through the CCA inlet on average"),
])
def test_a_waveform_outside_physiology_is_refused(tmp_path, rows, message):
    from carotid.flow.waveform import read_waveform_csv

    path = tmp_path / "wave.csv"
    path.write_text("time,flow\n" + rows)
    with pytest.raises(CarotidError, match=message):
        read_waveform_csv(path)


@pytest.mark.parametrize("fields, message", [
    ({"flow_ml_s": 1e-12}, "flow_ml_s: a mean flow of 1e-12 mL/s is below 0.01 mL/s"),
    ({"split": [0.6, 0.4]}, "split .* needs outlets .* split, resistance or rcr"),
    ({"doppler_cca_psv": 80.0}, "doppler_cca_psv without doppler_cca_edv: give both"),
    ({"doppler_cca_edv": 20.0}, "doppler_cca_edv without doppler_cca_psv: give both"),
])
def test_contradictory_or_meaningless_simulate_parameters_are_refused(fields, message):
    from carotid.stages import FlowStageParameters

    with pytest.raises(CarotidError, match=message):
        FlowStageParameters(**fields).validate()


@pytest.mark.parametrize("argv, message", [
    (["--flow", "0"], "--flow 0: a steady inflow must be positive"),
    (["--outlets", "murray", "--split", "0.6:0.4"], "split (--split) needs outlets (--outlets) split"),
])
def test_contradictory_options_exit_2(tube_case, capfd, argv, message):
    assert message in _one_error(capfd, ["simulate", tube_case, *argv])
    assert not (tube_case / "flow").exists()


def test_a_waveform_given_through_the_api_must_carry_blood_in():
    """``FlowParameters.validate`` refuses a waveform whose mean flow leaves through the inlet, whatever its
    source; the physiological bounds of user input (``check_inflow``) are not imposed on the API, whose
    verification cases run small tubes on short periods."""
    from carotid.flow.simulate import FlowParameters
    from carotid.flow.waveform import constant_waveform

    with pytest.raises(CarotidError, match="mean flow is -6 mL/s: blood must enter through the CCA inlet"):
        FlowParameters(waveform=constant_waveform(-6e-6)).validate()
    FlowParameters(waveform=constant_waveform(0.2e-6, 0.05)).validate()
