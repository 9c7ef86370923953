"""Probes, the virtual duplex and the Doppler-calibrated inflow, against exact answers, with their mutants.

* probes: a field linear in space is recovered exactly at random interior points; points outside are refused;
  permuted barycentric weights fail it;
* gates: the carotid waveform (period 0.5 s, alpha 3.9) with its Womersley inlet in a straight tube: a gate on
  the axis reads the analytic Womersley centreline velocity at the systolic peak and at end diastole within 3 %;
  a gate off the axis, or one that averages its sample volume instead of taking its largest speed, misses;
* calibration: the inlet's Womersley centreline velocity reaches the targets exactly; a calibration that
  assumes u_centre = 2 q / A misses at alpha 4.3;
* SRU consensus grading at the boundaries of each criterion.
"""

import numpy as np
import pytest

from carotid.errors import CarotidError
from carotid.flow import duplex, probes
from carotid.flow.duplex import (calibrate_inflow, inlet_centreline, peak_and_end_diastole, sru_category,
                                 sru_grade)
from carotid.flow.probes import PointLocator, ProbeRecorder, ProbeSet, ProbeSpec
from carotid.flow.verify import NU, TubeSpec, developed_start, disc_mesh, section_profile, tube_mesh
from carotid.flow.waveform import ML, Waveform, carotid_waveform
from carotid.flow.womersley import inlet_profile, womersley_number, womersley_velocity

PROBE_TUBE = TubeSpec(radius=2.0, length=6.0, n_square=4, n_core=2, n_layers=2, first_layer=0.2, growth=1.3,
                      n_axial=6)
GATE_TUBE = TubeSpec(radius=2.0, length=12.0, n_square=8, n_core=4, n_layers=4, first_layer=0.075, growth=1.3 ** 0.75,
                     n_axial=16)


# ------------------------------------------------------------------------------------------------ probes
def _linear_recovery_error(mesh, points_mm) -> float:
    """Largest relative error of the probes' interpolation of u = A x + c, p = b . x + d at ``points_mm``."""
    rng = np.random.default_rng(1)
    a, c, b, d = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=3), rng.normal()
    x = mesh.points / 1e-3  # mm: the field varies by its own size over the tube
    u, p = x @ a.T + c, x @ b + d
    probe_set = ProbeSet(mesh, [ProbeSpec(f"p{k}", point) for k, point in enumerate(points_mm)])
    sample = probe_set.sample(u, p)
    xs = points_mm
    exact_u, exact_p = xs @ a.T + c, xs @ b + d
    return max(np.abs(sample[:, :3] - exact_u).max() / np.abs(exact_u).max(),
               np.abs(sample[:, 3] - np.linalg.norm(exact_u, axis=1)).max() / np.abs(exact_u).max(),
               np.abs(sample[:, 4] - exact_p).max() / np.abs(exact_p).max())


@pytest.fixture(scope="module")
def probe_tube():
    mesh = tube_mesh(PROBE_TUBE)
    rng = np.random.default_rng(0)
    r = PROBE_TUBE.radius * 0.95 * np.sqrt(rng.uniform(size=200))
    phi = rng.uniform(0, 2 * np.pi, size=200)
    points = np.column_stack([r * np.cos(phi), r * np.sin(phi), rng.uniform(0, PROBE_TUBE.length, size=200)])
    return mesh, points


def test_a_linear_field_is_recovered_exactly_at_interior_points(probe_tube):
    mesh, points = probe_tube
    assert _linear_recovery_error(mesh, points) < 1e-12


def test_points_the_nearest_centroids_miss_are_found_by_the_box_search(probe_tube, monkeypatch):
    mesh, points = probe_tube
    monkeypatch.setattr(probes, "CANDIDATES", (1,))  # most points are not in the element of the nearest centroid
    assert _linear_recovery_error(mesh, points) < 1e-12


def test_permuted_barycentric_weights_fail_the_linear_recovery(probe_tube, monkeypatch):
    mesh, points = probe_tube
    right = probes.barycentric
    monkeypatch.setattr(probes, "barycentric", lambda vertices, x: np.roll(right(vertices, x), 1, axis=-1))
    assert _linear_recovery_error(mesh, points) > 1e-2


def test_points_outside_the_fluid_are_refused(probe_tube):
    mesh, _ = probe_tube
    outside = np.array([[2.1, 0.0, 3.0], [0.0, 0.0, -0.2], [0.0, 0.0, 6.3], [1.5, 1.5, 3.0]])
    tet, _ = PointLocator(mesh.points, mesh.tets).locate(outside * 1e-3)
    assert np.all(tet < 0)
    with pytest.raises(CarotidError, match=r"probe 'wall side' at \(2.1, 0, 3\) mm LPS is outside the fluid"):
        ProbeSet(mesh, [ProbeSpec("inside", np.array([0.0, 0.0, 3.0])), ProbeSpec("wall side", outside[0])])
    # a gate's sample volume may reach past the wall: those samples are dropped, the gate stays
    gate = ProbeSet(mesh, [ProbeSpec("gate", np.array([1.6, 0.0, 3.0]), 0.9, "gate")])
    assert 1 < gate.sample_counts[0] < 43


def test_probe_csv_rows_and_errors(tmp_path):
    path = tmp_path / "probes.csv"
    path.write_text("x,y,z,name\n1,2,3,bulb\n# a comment\n4,5,6\n")
    assert probes.read_probe_csv(path) == [("bulb", (1.0, 2.0, 3.0)), ("probe2", (4.0, 5.0, 6.0))]
    path.write_text("1,2,3\n4,five,6\n")
    with pytest.raises(CarotidError, match=r"probes.csv: line 2: expected 'x, y, z\[, name\]'"):
        probes.read_probe_csv(path)


# ------------------------------------------------------------------------------------------------ gates
class MeanGates(ProbeSet):
    """A mutant: a gate that reads the mean speed of its sample volume instead of its largest."""

    def sample(self, u, p):
        vel = np.einsum("sj,sjd->sd", self.weights, u[self.nodes])
        mean = np.bincount(self.group, np.linalg.norm(vel, axis=1)) / np.bincount(self.group)
        return np.column_stack([vel[self.first], mean, mean])


@pytest.fixture(scope="module")
def womersley_gates():
    """One cycle of the carotid waveform (0.5 s, mean 1 mL/s) in a 2 mm tube started developed at t = -0.1 s;
    the gate readings of the last cycle and the analytic centreline velocity."""
    from carotid.flow.cbs import CBSSolver
    from carotid.flow.simulate import stabilisation_velocity

    base, period = carotid_waveform(), 0.5
    wave = Waveform(period, base.times_s * period / base.period_s, base.flow_m3s / 6.0)
    mesh = tube_mesh(GATE_TUBE)
    profile = section_profile(mesh, wave, 10)
    solver = CBSSolver(mesh, profile.velocity, NU, safety=0.8, viscous="implicit",
                       velocity_scale=stabilisation_velocity(wave, mesh.face_area(2)))
    solver.reset(developed_start(mesh, profile), t0=-0.1)
    r, mid = GATE_TUBE.radius, 0.5 * GATE_TUBE.length
    gate = duplex.gate_radius_mm(r)
    specs = [ProbeSpec("axis", np.array([0.0, 0.0, mid]), gate, "gate"),
             ProbeSpec("off axis", np.array([0.7 * r, 0.0, mid]), 0.2 * r, "gate")]
    recorders = [ProbeRecorder(ProbeSet(mesh, specs), period), ProbeRecorder(MeanGates(mesh, specs[:1]), period)]
    while solver.t < period * (1 - 1e-12):
        solver.step(max_dt=(0.0 if solver.t < 0 else period) - solver.t)
        for recorder in recorders:
            if solver.t >= -1e-12:
                recorder.record(solver.t, solver.u, 1060.0 * solver.p)
    times = np.linspace(0.0, period, 2000, endpoint=False)
    exact = np.array([womersley_velocity(np.zeros(1), t, r * 1e-3, wave, NU)[0] for t in times])
    peak, end = peak_and_end_diastole(times, exact, period)
    readings = {}
    for recorder in recorders:
        t, values = recorder.arrays(0.0)
        for k, name in enumerate(recorder.probes.names):
            key = name if recorder is recorders[0] else f"{name} (mean)"
            i, j = peak_and_end_diastole(t, values[:, k, 3], period)
            readings[key] = (values[i, k, 3] / exact[peak] - 1, values[j, k, 3] / exact[end] - 1)
    return readings, womersley_number(r * 1e-3, period, NU)


def test_an_axial_gate_reads_the_womersley_centreline_psv_and_edv(womersley_gates):
    readings, alpha = womersley_gates
    assert 3.5 < alpha < 4.5
    psv_error, edv_error = readings["axis"]
    assert abs(psv_error) < 0.03 and abs(edv_error) < 0.03, readings


@pytest.mark.parametrize("mutant", ["off axis", "axis (mean)"])
def test_an_off_axis_or_averaging_gate_misses(womersley_gates, mutant):
    readings, _ = womersley_gates
    assert max(abs(e) for e in readings[mutant]) > 0.03, readings


def test_end_diastole_is_the_foot_of_the_upstroke_not_the_cycle_end():
    wave = carotid_waveform()
    times = np.linspace(0.0, wave.period_s, 1000, endpoint=False)
    peak, end = peak_and_end_diastole(times, wave.flow(times), wave.period_s)
    assert 0.14 < times[peak] < 0.17 and 0.03 < times[end] < 0.08  # the foot at ~55 ms, the last sample at 917
    rolled = np.roll(np.arange(1000), -300)  # the same cycle sampled from another start: same samples found
    p2, e2 = peak_and_end_diastole(times[rolled], wave.flow(times)[rolled], wave.period_s)
    assert rolled[p2] == peak and rolled[e2] == end


# ------------------------------------------------------------------------------------------------ calibration
@pytest.fixture(scope="module")
def inlet_face():
    spec = TubeSpec(radius=3.0, n_square=10, n_core=5, n_layers=4, first_layer=0.08, growth=1.3)
    xy, tri, _ = disc_mesh(spec)
    d1, d2 = xy[tri[:, 1]] - xy[tri[:, 0]], xy[tri[:, 2]] - xy[tri[:, 0]]
    tri = np.where((d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0)[:, None], tri, tri[:, ::-1])
    return np.column_stack([xy * 1e-3, np.zeros(len(xy))]), tri, spec.radius * 1e-3


def _calibrated_centreline(face, psv, edv):
    points, tri, _ = face
    wave, profile, record = calibrate_inflow(carotid_waveform(), points, tri, [0, 0, 1], NU, 10, psv, edv)
    times = np.arange(2048) * wave.period_s / 2048
    u, _ = inlet_centreline(inlet_profile(points, tri, [0, 0, 1], wave, NU, 10), times)  # the real one
    peak, end = peak_and_end_diastole(times, u, wave.period_s)
    return u[peak], u[end], record


def test_calibrated_inflow_reaches_the_measured_cca_velocities(inlet_face):
    assert 4.0 < womersley_number(inlet_face[2], carotid_waveform().period_s, NU) < 4.6
    psv, edv, record = _calibrated_centreline(inlet_face, 0.9, 0.2)
    assert psv == pytest.approx(0.9, rel=1e-6) and edv == pytest.approx(0.2, rel=1e-6)
    assert record["inlet_psv_cm_s"] == pytest.approx(90.0, rel=1e-6) and record["target_edv_cm_s"] == 20.0
    assert record["a"] > 0 and record["mean_flow_ml_s"] > 0
    # the flow is the affine map of the built-in waveform
    base = carotid_waveform()
    assert record["mean_flow_ml_s"] == pytest.approx(record["a"] * base.mean_m3s / ML + record["b_ml_s"], rel=1e-9)


def test_a_poiseuille_calibration_misses_at_womersley_four(inlet_face, monkeypatch):
    area = np.pi * inlet_face[2] ** 2
    monkeypatch.setattr(duplex, "inlet_centreline",
                        lambda profile, times: (2.0 * profile.flow(times) / area, 2.0 / area))
    psv, edv, _ = _calibrated_centreline(inlet_face, 0.9, 0.2)
    monkeypatch.undo()
    assert abs(psv / 0.9 - 1) > 0.01 or abs(edv / 0.2 - 1) > 0.01


@pytest.mark.parametrize("psv, edv, message", [(50.0, 60.0, "below the peak systolic"), (50.0, 50.0, "below"),
                                               (80.0, -1.0, "at least 0"), (500.0, 20.0, "implausible"),
                                               (5.0, 1.0, "implausible")])
def test_implausible_doppler_values_are_refused(inlet_face, psv, edv, message):
    points, tri, _ = inlet_face
    with pytest.raises(CarotidError, match=message):
        calibrate_inflow(carotid_waveform(), points, tri, [0, 0, 1], NU, 10, psv / 100, edv / 100)


# ------------------------------------------------------------------------------------------------ SRU grade
@pytest.mark.parametrize("value, bounds, category", [
    (124.99, duplex.SRU_PSV_CM_S, "<50 %"), (125.0, duplex.SRU_PSV_CM_S, "50-69 %"),
    (230.0, duplex.SRU_PSV_CM_S, "50-69 %"), (230.01, duplex.SRU_PSV_CM_S, ">=70 %"),
    (1.99, duplex.SRU_RATIO, "<50 %"), (2.0, duplex.SRU_RATIO, "50-69 %"), (4.0, duplex.SRU_RATIO, "50-69 %"),
    (4.01, duplex.SRU_RATIO, ">=70 %"), (39.9, duplex.SRU_EDV_CM_S, "<50 %"), (40.0, duplex.SRU_EDV_CM_S, "50-69 %"),
    (100.0, duplex.SRU_EDV_CM_S, "50-69 %"), (100.1, duplex.SRU_EDV_CM_S, ">=70 %")])
def test_sru_thresholds_at_their_boundaries(value, bounds, category):
    assert sru_category(value, bounds) == category


def test_sru_grade_follows_the_psv_with_plaque_and_near_occlusion():
    assert sru_grade(124.9, 30.0, 1.5, plaque=False, near_occlusion=False)["grade"] == "normal"
    assert sru_grade(124.9, 30.0, 1.5, plaque=True, near_occlusion=False)["grade"] == "<50 %"
    graded = sru_grade(125.0, 30.0, 4.5, plaque=True, near_occlusion=False)
    assert graded == {"grade": "50-69 %", "by_psv": "50-69 %", "by_ratio": ">=70 %", "by_edv": "<50 %",
                      "concordant": False}
    assert sru_grade(231.0, 101.0, 4.1, plaque=True, near_occlusion=False)["concordant"]
    assert sru_grade(80.0, 10.0, 1.0, plaque=True, near_occlusion=True)["grade"] == "near occlusion"


def test_start_up_samples_are_not_end_diastole_unless_nothing_else_is_there():
    """A first cycle from rest: zero velocity at its start, systole at 0.15 s, late diastole falling to 0.3 at
    its end; the start-up is left out, so the end diastole is read at the cycle's end."""
    times = np.linspace(0.0, 1.0, 101)
    values = np.r_[np.zeros(5), np.linspace(0.5, 1.0, 11), np.linspace(0.95, 0.3, 85)]
    assert times[peak_and_end_diastole(times, values, 1.0)[1]] == 0.0  # without it: the rest state
    peak, end = peak_and_end_diastole(times, values, 1.0, settled=0.1)
    assert times[peak] == pytest.approx(0.15) and times[end] == pytest.approx(1.0)
    short = slice(0, 8)  # a run shorter than the start-up: its samples are all there is
    assert peak_and_end_diastole(times[short], values[short], 1.0, settled=0.1)[1] == 0


def test_gates_follow_the_centerlines_inside_the_mesh():
    """A straight tube (z 0-30 mm, radius 2 mm) read as a CCA up to z = 12 mm and an ICA beyond, narrowed at
    z = 20 mm, each centerline running 2 mm beyond its cap as a clipped surface's does: the ICA gate sits at the
    narrowest section, the CCA gate as far up the CCA as the mesh allows (20 mm is beyond its inlet: one diameter
    from the inlet cap), the distal pressure point one diameter before the outlet; a narrowest section outside
    the mesh gives no gates."""
    from carotid.centerline.model import Branch, Centerlines

    mesh = tube_mesh(TubeSpec(radius=2.0, length=30.0, n_square=4, n_core=2, n_layers=2, first_layer=0.2,
                              growth=1.3, n_axial=15))
    z = np.linspace(-2.0, 32.0, 341)
    axis = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    radius = np.where(np.abs(z - 20.0) < 0.5, 1.2, 2.0)
    cca, ica = z <= 12.0, z >= 12.0
    cl = Centerlines([Branch("CCA", axis[cca], radius[cca]), Branch("ICA", axis[ica], radius[ica])],
                     np.array([0.0, 0.0, 12.0]))
    grade = {"branch": "ICA", "location_mm": [0.0, 0.0, 20.0], "extent_from_bifurcation_mm": [7.5, 8.5],
             "distal_diameter_mm": 4.0, "nascet": 0.4, "ecst": 0.4, "min_diameter_mm": 2.4}
    locator = PointLocator(mesh.points, mesh.tets)
    specs, meta = duplex.duplex_probes(cl, {"stenoses": [grade]}, locator)
    found = {spec.name: spec for spec in specs}
    assert np.allclose(found["ICA_gate"].centre_mm, [0, 0, 20.0]) and found["ICA_gate"].radius_mm == pytest.approx(0.6)
    assert found["CCA_gate"].centre_mm[2] == pytest.approx(4.0, abs=0.11)
    assert found["CCA_gate"].info["arclength_from_bifurcation_mm"] == pytest.approx(8.0, abs=0.11)
    assert found["ICA_distal"].centre_mm[2] == pytest.approx(26.0, abs=0.11)  # 3 diameters beyond is past the end
    ProbeSet(mesh, specs, locator)  # all inside
    grade["location_mm"] = [0.0, 0.0, 13.0]  # at the ICA's origin: the bifurcation end is no cap, it is graded
    assert np.allclose(duplex.duplex_probes(cl, {"stenoses": [grade]}, locator)[0][0].centre_mm, [0, 0, 13.0])
    grade["location_mm"] = [0.0, 0.0, 31.0]
    assert duplex.duplex_probes(cl, {"stenoses": [grade]}, locator)[0] == []
