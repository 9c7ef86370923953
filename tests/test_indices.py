"""Wall shear stress indices on synthetic WSS histories with closed-form values."""

import numpy as np
import pytest
from scipy.special import ellipe

from carotid.errors import CarotidError
from carotid.flow.indices import area_fraction, wall_indices

T = 0.917
OMEGA = 2 * np.pi / T
EX, EY, EZ = np.eye(3)


def history(vectors_of_t, samples: int = 2001, t0: float = 1.3):
    """Times covering one period (both ends included) and WSS (k, n, 3) from per-node functions of time."""
    times = t0 + np.linspace(0.0, T, samples)
    phase = OMEGA * (times - t0)
    wss = np.stack([f(phase) for f in vectors_of_t], axis=1)
    return times, wss, np.tile(EZ, (len(vectors_of_t), 1))


def along(direction, scalar_of_phase):
    """A per-node function of the phase: scalar(phase) * direction, shape (k, 3)."""
    return lambda phase: scalar_of_phase(phase)[:, None] * direction


def test_constant_vector():
    tau = 1.7 * EX - 0.4 * EY
    times, wss, normals = history([lambda phase: np.tile(tau, (len(phase), 1))], samples=7)
    out = wall_indices(times, wss, normals)
    mag = np.linalg.norm(tau)
    assert out["TAWSS"][0] == pytest.approx(mag, rel=1e-14)
    assert out["OSI"][0] == pytest.approx(0.0, abs=1e-15)  # |mean vector| = mean |vector| up to rounding
    assert out["RRT"][0] == pytest.approx(1 / mag, rel=1e-14)
    assert out["ECAP"][0] == pytest.approx(0.0, abs=1e-15)
    assert out["transWSS"][0] == pytest.approx(0.0, abs=1e-14)
    assert out["TWSSG"][0] == 0.0


def test_pure_reversal():
    """tau = a cos(w t) e_x: TAWSS 2a/pi, OSI 0.5, RRT inf, ECAP pi/(4a), TWSSG 2 a w / pi, transWSS undefined."""
    a = 2.0
    times, wss, normals = history([along(EX, lambda p: a * np.cos(p))], samples=2001)
    out = wall_indices(times, wss, normals)
    assert out["TAWSS"][0] == pytest.approx(2 * a / np.pi, rel=1e-5)
    assert out["OSI"][0] == 0.5
    assert out["RRT"][0] == np.inf
    assert out["ECAP"][0] == pytest.approx(np.pi / (4 * a), rel=1e-5)
    assert out["TWSSG"][0] == pytest.approx(2 * a * OMEGA / np.pi, rel=1e-12)  # samples hit the extrema
    assert np.isnan(out["transWSS"][0])


@pytest.mark.parametrize("a, b", [(3.0, 1.0), (3.0, -2.5), (1.0, 2.0), (0.5, 3.0)])
def test_pulsatile_along_one_direction(a, b):
    """tau = (a + b cos w t) e_x: OSI 0 when |b| < a; with reversal (|b| > a), theta0 = arccos(-a/|b|),
    TAWSS = [a (2 theta0 - pi) + 2 |b| sin theta0] / pi and OSI = (1 - a / TAWSS) / 2."""
    times, wss, normals = history([along(EX, lambda p: a + b * np.cos(p))], samples=4001)
    out = wall_indices(times, wss, normals)
    if abs(b) < a:
        tawss = a
    else:
        theta0 = np.arccos(-a / abs(b))
        tawss = (a * (2 * theta0 - np.pi) + 2 * abs(b) * np.sin(theta0)) / np.pi
    assert out["TAWSS"][0] == pytest.approx(tawss, rel=1e-6)
    assert out["OSI"][0] == pytest.approx(0.5 * (1 - a / tawss), abs=1e-7)
    assert out["RRT"][0] == pytest.approx(1 / a, rel=1e-10)
    assert out["ECAP"][0] == pytest.approx(out["OSI"][0] / out["TAWSS"][0], rel=1e-12)
    assert out["transWSS"][0] == pytest.approx(0.0, abs=1e-14)
    assert out["TWSSG"][0] == pytest.approx(2 * abs(b) * OMEGA / np.pi, rel=1e-12)


def test_rotating_vector_with_a_mean():
    """tau = a e_x + b (cos wt e_x + sin wt e_y) on a wall with normal e_z.

    Mean a e_x, so transWSS = mean |b sin| = 2b/pi; TAWSS = (1/2pi) int sqrt(a^2 + b^2 + 2ab cos) =
    2 (a + b) E(4ab / (a + b)^2) / pi; RRT = 1/a; TWSSG = |d tau/dt| = b w.
    """
    a, b = 1.2, 2.0
    def rotating(phase):
        return a * EX + b * (np.cos(phase)[:, None] * EX + np.sin(phase)[:, None] * EY)
    times, wss, normals = history([rotating], samples=4001)
    out = wall_indices(times, wss, -3 * normals)  # normal length and sign do not matter
    tawss = 2 * (a + b) * ellipe(4 * a * b / (a + b) ** 2) / np.pi
    assert out["TAWSS"][0] == pytest.approx(tawss, rel=1e-10)
    assert out["OSI"][0] == pytest.approx(0.5 * (1 - a / tawss), rel=1e-9)
    assert out["RRT"][0] == pytest.approx(1 / a, rel=1e-10)
    assert out["transWSS"][0] == pytest.approx(2 * b / np.pi, rel=1e-6)
    assert out["TWSSG"][0] == pytest.approx(b * OMEGA, rel=1e-6)  # chords of a 4000-gon


def test_nodes_are_independent_and_samples_may_be_non_uniform():
    """Several nodes at once; a non-uniform sampling of the same history gives the same indices."""
    funcs = [along(EX, lambda p: 3 + np.cos(p)), along(EY, lambda p: np.cos(p)),
             lambda p: 1.2 * EX + 2 * (np.cos(p)[:, None] * EX + np.sin(p)[:, None] * EY)]
    times, wss, normals = history(funcs, samples=4001)
    uniform = wall_indices(times, wss, normals)
    s = np.linspace(0, 1, 6001)
    warped = np.r_[0.0, np.sort(s[1:-1] + 0.08 * np.sin(2 * np.pi * s[1:-1]) / (2 * np.pi)), 1.0]
    times2 = 1.3 + T * warped
    wss2 = np.stack([f(OMEGA * (times2 - 1.3)) for f in funcs], axis=1)
    other = wall_indices(times2, wss2, normals)
    for key in ("TAWSS", "OSI", "TWSSG"):
        np.testing.assert_allclose(other[key], uniform[key], rtol=1e-5)
    # Node 1 reverses purely: its mean direction (RRT, transWSS) is at the mercy of quadrature errors.
    for key in ("RRT", "transWSS"):
        np.testing.assert_allclose(other[key][[0, 2]], uniform[key][[0, 2]], rtol=1e-5, atol=1e-12)
    assert uniform["OSI"][0] == 0 and uniform["OSI"][1] == 0.5


def test_spatial_twssg_of_lei():
    """d tau/dx = diag(g cos wt, h, 0) with the mean WSS along e_x: (1/T) int sqrt((g cos)^2 + h^2) dt;
    with h = 0 that is 2g/pi."""
    g = 40.0
    times, wss, normals = history([lambda p: np.tile(EX, (len(p), 1))], samples=2001)
    grad = np.zeros(wss.shape + (3,))
    grad[:, 0, 0, 0] = g * np.cos(OMEGA * (times - times[0]))
    out = wall_indices(times, wss, normals, tangential_gradient=grad)
    assert out["TWSSG_spatial"][0] == pytest.approx(2 * g / np.pi, rel=1e-5)
    grad[:, 0, 0, 0] = 0.0
    grad[:, 0, 1, 1] = 7.0  # d tau_y / dy: the p = n x m component
    assert wall_indices(times, wss, normals, tangential_gradient=grad)["TWSSG_spatial"][0] == pytest.approx(7.0)


def test_no_shear_is_finite_where_defined():
    times, wss, normals = history([lambda p: np.zeros((len(p), 3))], samples=5)
    out = wall_indices(times, wss, normals)
    assert out["TAWSS"][0] == 0 and out["OSI"][0] == 0 and out["ECAP"][0] == 0 and out["RRT"][0] == np.inf


def test_area_fraction():
    osi = np.array([0.0, 0.05, 0.2, 0.3, np.nan])
    areas = np.array([1.0, 1.0, 2.0, 4.0, 2.0])
    assert area_fraction(osi, areas, 0.1) == pytest.approx(0.6)
    with pytest.raises(CarotidError):
        area_fraction(osi, np.zeros(5), 0.1)


@pytest.mark.parametrize("times, wss, normals", [
    (np.array([0.0, 1.0, 1.0]), np.zeros((3, 2, 3)), np.tile(EZ, (2, 1))),     # repeated time
    (np.array([0.0, 1.0]), np.zeros((3, 2, 3)), np.tile(EZ, (2, 1))),          # time count mismatch
    (np.array([0.0, 1.0]), np.zeros((2, 2, 3)), np.tile(EZ, (3, 1))),          # normals count mismatch
    (np.array([0.0, 1.0]), np.zeros((2, 2, 3)), np.zeros((2, 3))),             # zero normal
    (np.array([0.0, 1.0]), np.full((2, 2, 3), np.nan), np.tile(EZ, (2, 1))),   # NaN WSS
])
def test_bad_inputs(times, wss, normals):
    with pytest.raises(CarotidError):
        wall_indices(times, wss, normals)


def test_node_areas_share_each_triangle_in_thirds():
    from carotid.flow.indices import node_areas

    points = np.array([[0.0, 0, 0], [2, 0, 0], [2, 3, 0], [0, 3, 0], [5, 5, 5]])  # the last node is unused
    areas = node_areas(points, np.array([[0, 1, 2], [0, 2, 3]]))
    np.testing.assert_allclose(areas, [2.0, 1.0, 2.0, 1.0, 0.0])  # two triangles of 3 mm^2
