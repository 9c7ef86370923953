"""Inlet waveforms, the analytic Womersley solution and the generalised (non-circular) Womersley inlet."""

import math

import numpy as np
import pytest
from scipy.spatial import Delaunay

from carotid.errors import CarotidError
from carotid.flow.waveform import Waveform, carotid_waveform, fourier_flow, read_waveform_csv
from carotid.flow.womersley import (
    inlet_profile,
    womersley_lambdas,
    womersley_number,
    womersley_shape,
    womersley_velocity,
    womersley_wall_factor,
    womersley_wss,
)

NU = 3.3e-6  # m^2/s
MU = 3.5e-3  # Pa s
ML = 1e-6
CAROTID = carotid_waveform()
R_ALPHA4 = 4.0 / womersley_number(1.0, CAROTID.period_s, NU)  # radius (m) giving alpha = 4: ~2.78 mm
NORMAL = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])


# ---------------------------------------------------------------------------------------------------- meshes

def disc_mesh(radius: float, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay triangulation of concentric rings (6 i nodes on ring i, alternate rings rotated half a step).

    Returns the 2D points (p, 2) and the triangles (t, 3); rim nodes lie exactly on the circle.
    """
    pts = [np.zeros((1, 2))]
    for i in range(1, rings + 1):
        theta = 2 * np.pi * (np.arange(6 * i) + 0.5 * (i % 2)) / (6 * i)
        pts.append(radius * i / rings * np.column_stack([np.cos(theta), np.sin(theta)]))
    xy = np.vstack(pts)
    return xy, Delaunay(xy).simplices


def embed(xy: np.ndarray, normal: np.ndarray = NORMAL, centre=(0.01, -0.02, 0.05)) -> np.ndarray:
    """Place 2D points in the plane through ``centre`` normal to ``normal`` (a tilted inlet), shape (p, 3)."""
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return np.asarray(centre) + xy[:, :1] * e1 + xy[:, 1:] * e2


def consistent_mass_norm(xy, tri, values):
    """P1 L2 norm of nodal values on a planar triangulation."""
    p = xy[tri]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    v = values[tri]
    # int (sum v_i phi_i)^2 = area/12 (sum v_i^2 + (sum v_i)^2)
    return math.sqrt(np.sum(area / 12.0 * ((v**2).sum(axis=1) + v.sum(axis=1) ** 2)))


# ---------------------------------------------------------------------------------------------------- waveform

def test_carotid_waveform_features():
    t = np.linspace(0.0, CAROTID.period_s, 20000, endpoint=False)
    q = CAROTID.flow(t) / ML
    assert CAROTID.period_s == 0.917
    assert abs(CAROTID.mean_m3s / ML - 6.0) < 1e-6
    assert abs(q.mean() - 6.0) < 1e-6  # the sampled mean agrees with the exact spline integral
    assert 23.0 <= q.max() <= 26.0
    assert 0.12 <= t[q.argmax()] <= 0.17
    assert q.min() > 0.0  # no reversal at the CCA


@pytest.mark.parametrize("n", [10, 15, 20])
def test_carotid_harmonics_reproduce_waveform(n):
    t = np.linspace(0.0, CAROTID.period_s, 2001)
    q = CAROTID.flow(t)
    assert np.max(np.abs(fourier_flow(CAROTID.harmonics(n), CAROTID.omega, t) - q)) < 0.01 * q.max()


def test_harmonics_convention_and_periodicity():
    """Q = 1 + 0.5 cos(w t) + 0.2 sin(2 w t) has Q_0 = 1, Q_1 = 0.5, Q_2 = -0.2 i (Q = Re sum Q_k e^{ikwt})."""
    period = 0.8
    w = 2 * np.pi / period
    t = np.linspace(0.0, period, 65)
    wave = Waveform(period, t, 1 + 0.5 * np.cos(w * t) + 0.2 * np.sin(2 * w * t))  # closing sample dropped
    assert len(wave.times_s) == 64
    np.testing.assert_allclose(wave.harmonics(3), [1.0, 0.5, -0.2j, 0.0], atol=1e-6)
    assert wave.flow(0.3 + 5 * period) == pytest.approx(wave.flow(0.3), rel=1e-12)
    doubled = wave.scaled(2.0)
    assert doubled.mean_m3s == pytest.approx(2.0, rel=1e-12)
    np.testing.assert_allclose(doubled.flow(t), 2 * wave.flow(t), rtol=1e-12)


def test_csv_round_trip(tmp_path):
    path = tmp_path / "wave.csv"
    t = np.r_[CAROTID.times_s, CAROTID.period_s]
    q = np.r_[CAROTID.flow_m3s, CAROTID.flow_m3s[0]] / ML
    path.write_text("time_s,flow_mL_s\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(t, q)))
    back = read_waveform_csv(path)
    assert back.period_s == pytest.approx(CAROTID.period_s, rel=1e-14)
    probe = np.linspace(-1.0, 2.0, 301)
    np.testing.assert_allclose(back.flow(probe), CAROTID.flow(probe), rtol=1e-12, atol=1e-18)
    # Without the closing row, with an explicit period; white-space separated, no header.
    path.write_text("".join(f"{float(a)!r} {float(b)!r}\n" for a, b in zip(t[:-1], q[:-1])))
    np.testing.assert_allclose(read_waveform_csv(path, period=0.917).flow(probe), CAROTID.flow(probe), rtol=1e-12)


@pytest.mark.parametrize("text, line", [
    ("t,q\n0,1\n0.1,2\n0.2,abc\n0.3,1.5\n0.4,1\n", 4),   # non-numeric
    ("0,1\n0.1,2\n0.2,nan\n0.3,1.5\n0.4,1\n", 3),         # NaN
    ("0,1\n0.1,2\n0.1,3\n0.3,1.5\n0.4,1\n", 3),           # time does not increase
    ("0,1\n0.1,2\n0.2,3,4\n0.3,1.5\n0.4,1\n", 3),         # three fields
    ("0,1\n0.1,2\n0.2,3\n0.3,1.5\n0.4,1.2\n", 5),         # last flow differs from the first: unknown period
])
def test_csv_bad_rows_name_the_line(tmp_path, text, line):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(CarotidError, match=f"line {line}:"):
        read_waveform_csv(path)


def test_csv_too_short_or_missing(tmp_path):
    path = tmp_path / "short.csv"
    path.write_text("time,flow\n0,1\n0.5,2\n1.0,1\n")
    with pytest.raises(CarotidError, match="at least 4 rows"):
        read_waveform_csv(path)
    with pytest.raises(CarotidError, match="cannot read"):
        read_waveform_csv(tmp_path / "missing.csv")


# ---------------------------------------------------------------------------------------------------- analytic

@pytest.mark.parametrize("alpha, wall", [(1, 1.0009 + 0.0416j), (2, 1.0136 + 0.1649j), (4, 1.1714 + 0.5785j),
                                         (10, 2.1758 + 1.7297j)])
def test_womersley_wall_check_values(alpha, wall):
    assert abs(womersley_wall_factor(womersley_lambdas(alpha, 1))[0] - wall) < 1e-3


@pytest.mark.parametrize("alpha, centre", [(2, 1.9729 - 0.1624j), (4, 1.6822 - 0.4627j)])
def test_womersley_centreline_check_values(alpha, centre):
    assert abs(womersley_shape(np.array(0.0), womersley_lambdas(alpha, 1))[0] - centre) < 1e-3


def test_womersley_wss_single_harmonic():
    """Through the public API: Q = Q0 + A cos(w t) at alpha = 4 gives the alpha = 4 check value."""
    period, radius = 1.0, 3e-3
    nu = (radius / 4.0) ** 2 * 2 * np.pi / period
    t = np.linspace(0, period, 200, endpoint=False)
    wave = Waveform(period, t, 5e-6 + 3e-6 * np.cos(2 * np.pi * t / period))
    scale = 4 * MU / (np.pi * radius**3)
    for time in (0.0, 0.2, 0.45, 0.7):
        expected = scale * (5e-6 + np.real(3e-6 * (1.1714 + 0.5785j) * np.exp(2j * np.pi * time / period)))
        assert womersley_wss(time, radius, wave, MU, nu, n_harmonics=3) == pytest.approx(expected, rel=2e-4)


def test_womersley_tends_to_poiseuille_as_alpha_vanishes():
    radius = 3e-3
    nu = (radius / 1e-3) ** 2 * CAROTID.omega  # alpha = 1e-3
    r = np.linspace(0, radius, 50)
    for t in (0.0, 0.15, 0.5):
        q = CAROTID.flow(t)
        poiseuille = 2 * q / (np.pi * radius**2) * (1 - (r / radius) ** 2)
        np.testing.assert_allclose(womersley_velocity(r, t, radius, CAROTID, nu), poiseuille,
                                   atol=1e-5 * poiseuille.max())
        assert womersley_wss(t, radius, CAROTID, MU, nu) == pytest.approx(4 * MU * q / (np.pi * radius**3),
                                                                         rel=1e-5)


def test_womersley_velocity_integrates_to_the_flow():
    x, wgt = np.polynomial.legendre.leggauss(60)
    r = 0.5 * R_ALPHA4 * (x + 1)
    for t in np.linspace(0, CAROTID.period_s, 7):
        flux = np.sum(0.5 * R_ALPHA4 * wgt * 2 * np.pi * r * womersley_velocity(r, t, R_ALPHA4, CAROTID, NU))
        assert flux == pytest.approx(CAROTID.flow(t), rel=1e-10)
        assert womersley_velocity(R_ALPHA4, t, R_ALPHA4, CAROTID, NU) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(CarotidError, match=r"\[0, R\]"):
        womersley_velocity(1.1 * R_ALPHA4, 0.0, R_ALPHA4, CAROTID, NU)


# ---------------------------------------------------------------------------------------------------- generalised

def test_generalised_inlet_matches_analytic_on_a_circle():
    xy, tri = disc_mesh(R_ALPHA4, 20)
    profile = inlet_profile(embed(xy), tri, -3 * NORMAL, CAROTID, NU)
    r = np.minimum(np.linalg.norm(xy, axis=1), R_ALPHA4)
    assert np.all(profile.velocity(0.3)[profile.rim] == 0) and profile.rim.sum() == 120
    for t in np.linspace(0, CAROTID.period_s, 9):
        exact = womersley_velocity(r, t, R_ALPHA4, CAROTID, NU)
        assert np.max(np.abs(profile.velocity(t) - exact)) < 0.01 * np.max(np.abs(exact))


def test_generalised_inlet_flux_is_exact():
    xy, tri = disc_mesh(R_ALPHA4, 8)
    profile = inlet_profile(embed(xy), tri, NORMAL, CAROTID, NU)
    t = np.linspace(0, 2 * CAROTID.period_s, 101)
    np.testing.assert_allclose(profile.flux(t), profile.flow(t), rtol=1e-10)
    np.testing.assert_allclose(profile.flow(t), CAROTID.flow(t), rtol=1e-6)  # the built-in is band-limited
    assert profile.mass.sum() == pytest.approx(np.pi * R_ALPHA4**2, rel=0.02)  # inscribed polygon


def ellipse_error(stretch: float, rings: int = 16) -> tuple[float, float]:
    """Max error (relative to the peak) against the circular analytic profile of an equal-area ellipse with
    semi-axes R s and R / s, and the worst relative flux error over the cycle."""
    xy, tri = disc_mesh(R_ALPHA4, rings)
    profile = inlet_profile(embed(xy * [stretch, 1 / stretch]), tri, NORMAL, CAROTID, NU)
    r = np.minimum(np.linalg.norm(xy, axis=1), R_ALPHA4)  # the node's radius before stretching
    times = np.linspace(0, CAROTID.period_s, 12, endpoint=False)
    exact = np.array([womersley_velocity(r, t, R_ALPHA4, CAROTID, NU) for t in times])
    error = np.max(np.abs(profile.velocity(times) - exact)) / np.max(np.abs(exact))
    flux_error = np.max(np.abs(profile.flux(times) - CAROTID.flow(times)) / CAROTID.flow(times))
    return error, flux_error


def test_ellipse_carries_the_flux_and_tends_to_the_circle():
    errors = []
    for stretch in (2.0, 1.5, 1.25, 1.1, 1.03, 1.0):
        error, flux_error = ellipse_error(stretch)
        assert flux_error < 1e-6
        errors.append(error)
    assert np.all(np.diff(errors) < 0), errors
    assert errors[0] > 0.1 and errors[-1] < 0.01


def test_ellipse_steady_mode_is_elliptic_poiseuille():
    """k = 0 on an ellipse (a, b): u = 2 Q0 / (pi a b) (1 - x^2/a^2 - y^2/b^2)."""
    a, b = 2 * R_ALPHA4, 0.5 * R_ALPHA4
    xy, tri = disc_mesh(1.0, 20)
    profile = inlet_profile(embed(xy * [a, b]), tri, NORMAL, CAROTID, NU, n_harmonics=0)
    exact = 2 * CAROTID.mean_m3s / (np.pi * a * b) * (1 - np.sum(xy**2, axis=1))
    assert np.max(np.abs(profile.modes[0].real - exact)) < 0.01 * exact.max()


def test_generalised_inlet_converges_at_second_order():
    errors, sizes = [], []
    t = 0.15
    for rings in (5, 10, 20):
        xy, tri = disc_mesh(R_ALPHA4, rings)
        profile = inlet_profile(embed(xy), tri, NORMAL, CAROTID, NU)
        exact = womersley_velocity(np.minimum(np.linalg.norm(xy, axis=1), R_ALPHA4), t, R_ALPHA4, CAROTID, NU)
        errors.append(consistent_mass_norm(xy, tri, profile.velocity(t) - exact)
                      / consistent_mass_norm(xy, tri, exact))
        sizes.append(R_ALPHA4 / rings)
    orders = np.diff(np.log(errors)) / np.diff(np.log(sizes))
    print(f"generalised inlet L2 errors {errors}, observed orders {orders}")
    assert np.all(orders > 1.8)


def test_inlet_profile_rejects_bad_faces():
    xy, tri = disc_mesh(1e-3, 3)
    points = embed(xy)
    x = xy[:, 0]
    folded = np.column_stack([np.where(x > 0, -0.5 * x, x), xy[:, 1], np.maximum(x, 0)])  # right half bent back
    with pytest.raises(CarotidError, match="folds over"):
        inlet_profile(folded, tri, [0, 0, 1], CAROTID, NU)
    with pytest.raises(CarotidError, match="degenerate"):
        inlet_profile(points, tri, np.cross(NORMAL, [0, 0, 1]), CAROTID, NU)  # the normal lies in the face
    with pytest.raises(CarotidError, match="no interior nodes"):
        inlet_profile(points[:3], np.array([[0, 1, 2]]), NORMAL, CAROTID, NU)
    with pytest.raises(CarotidError, match="do not exist"):
        inlet_profile(points, tri + 1000, NORMAL, CAROTID, NU)
    with pytest.raises(CarotidError, match="non-zero"):
        inlet_profile(points, tri, [0, 0, 0], CAROTID, NU)
