"""Cycle-to-cycle periodicity of the TAWSS in simulate(), and the partial-cycle flag of summary.json."""

import numpy as np
import pytest

from carotid.flow.simulate import FlowParameters, simulate
from carotid.flow.verify import TubeSpec, tube_mesh
from carotid.flow.waveform import Waveform

PERIOD = 0.05  # s: a 1 mm radius tube settles within a few such cycles (viscous time R^2 / nu = 0.3 s)


@pytest.fixture(scope="module")
def tube():
    spec = TubeSpec(radius=1.0, length=3.0, n_square=4, n_core=2, n_layers=2, first_layer=0.08, growth=1.3,
                    n_axial=4)
    t = np.linspace(0.0, PERIOD, 8, endpoint=False)
    return tube_mesh(spec), Waveform(PERIOD, t, 0.2e-6 * (1 + 0.5 * np.sin(2 * np.pi * t / PERIOD)))


def test_periodic_run_stops_at_the_first_cycle_within_tolerance(tube, tmp_path):
    mesh, waveform = tube
    summary = simulate(mesh, tmp_path, FlowParameters(cycles=6, waveform=waveform, periodic_tol=0.02,
                                                      output_every=5))
    entries = summary["periodicity"]
    changes = [e["relative_change"] for e in entries]
    # from rest the first cycle differs; the run ends on the first cycle end where the change is below 2 %
    assert changes[0] is None and all(c >= 0.02 for c in changes[1:-1]) and changes[-1] < 0.02
    assert len(entries) < 6 and summary["time_s"] == pytest.approx(len(entries) * PERIOD, rel=1e-9)
    assert summary["periodic"]["status"] == "periodic" and not summary["partial"]
    assert summary["indices_cycle_fraction"] == pytest.approx(1.0)
    # every cycle end is an output, so each cycle's TAWSS integrates exactly over [(k-1) T, k T]
    from carotid.flow.output import load_checkpoint

    times = np.array([r["time"] for r in load_checkpoint(tmp_path / "flow" / "checkpoint.npz")[1]["records"]])
    for k in range(len(entries) + 1):
        assert np.min(np.abs(times - k * PERIOD)) < 1e-12

    # resuming a shorter run with the tolerance reproduces the same cycles and stops at the same one
    short = tmp_path / "resumed"
    simulate(mesh, short, FlowParameters(cycles=2, waveform=waveform, output_every=5))
    again = simulate(mesh, short, FlowParameters(cycles=6, waveform=waveform, periodic_tol=0.02, output_every=5),
                     resume=True)
    resumed = [e["relative_change"] for e in again["periodicity"]]
    assert resumed[0] is None and resumed[1:] == pytest.approx(changes[1:], rel=1e-9)


def test_too_small_tolerance_runs_to_the_maximum_and_says_not_periodic(tube, tmp_path):
    mesh, waveform = tube
    summary = simulate(mesh, tmp_path, FlowParameters(cycles=3, waveform=waveform, periodic_tol=1e-12,
                                                      output_every=5))
    assert summary["time_s"] == pytest.approx(3 * PERIOD, rel=1e-9) and len(summary["periodicity"]) == 3
    assert summary["periodic"]["status"] == "not periodic"
    assert summary["periodic"]["last_relative_change"] > 1e-12


def test_partial_cycle_is_flagged(tube, tmp_path):
    mesh, waveform = tube
    summary = simulate(mesh, tmp_path, FlowParameters(cycles=0.3, waveform=waveform, output_every=2))
    assert summary["partial"] is True and summary["indices_cycle_fraction"] == pytest.approx(0.3)
    assert "PARTIAL" in summary["indices_note"] and summary["periodicity"] == []
    assert summary["periodic"]["status"] == "not assessed"


def test_periodic_tolerance_and_convergence_options_reach_the_solver():
    from carotid.errors import CarotidError
    from carotid.flow.command import build_parser
    from carotid.stages import FlowStageParameters

    args = build_parser().parse_args(["simulate", "case", "--periodic-tol", "0.01", "--convergence",
                                      "--refinement", "1.3"])
    assert (args.periodic_tol, args.convergence, args.refinement) == (0.01, True, 1.3)
    assert FlowStageParameters(periodic_tol=0.01).validate().flow_parameters().periodic_tol == 0.01
    with pytest.raises(CarotidError):
        FlowStageParameters(periodic_tol=0.6).validate()
