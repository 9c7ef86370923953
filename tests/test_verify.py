"""`carotid verify` fails on a wrong solver: mutation tests, and the analytic references it relies on.

Each mutant changes the solver in memory (monkeypatch), then the verification's flow cases run lazily
(:func:`carotid.flow.verify.solver_cases`, quick meshes) until one fails; the test asserts that one does.
The straight-pipe cases cannot see the convective and characteristic terms (they vanish there), so those
two mutants are caught by the entrance-length case.
"""

import numpy as np
import pytest

from carotid.errors import CarotidError
from carotid.flow import assembly
from carotid.flow.cbs import CBSSolver
from carotid.flow.verify import durst_development_length, solver_cases
from carotid.flow.womersley import womersley_pressure_gradient


def _scaled_viscosity(factor):
    def patch(monkeypatch):
        init = CBSSolver.__init__

        def wrong_nu(self, mesh, inlet_speed, nu, *args, **kwargs):
            init(self, mesh, inlet_speed, factor * nu, *args, **kwargs)

        monkeypatch.setattr(CBSSolver, "__init__", wrong_nu)
    return patch


def _residual(transform):
    """Replace the explicit momentum residual by ``transform(kernel, tets, grads, volumes, u, nu_e, half_dt,
    out)``; ``kernel`` is the original (convection + viscosity + characteristic term)."""
    def patch(monkeypatch):
        kernel = assembly.momentum_residual
        monkeypatch.setattr(assembly, "momentum_residual",
                            lambda *args: transform(kernel, *args))
    return patch


def _no_convection(kernel, tets, grads, volumes, u, nu_e, half_dt, out):
    # viscous term only: the full residual without characteristic term minus the pure convection C(u)u
    convection = np.empty_like(out)
    kernel(tets, grads, volumes, u, np.zeros_like(nu_e), 0.0, convection)
    kernel(tets, grads, volumes, u, nu_e, 0.0, out)
    out -= convection


def _flipped_characteristic(kernel, tets, grads, volumes, u, nu_e, half_dt, out):
    kernel(tets, grads, volumes, u, nu_e, -half_dt, out)


def _idle_step(monkeypatch):
    step = CBSSolver.step

    def idle(self, max_dt=None):  # the clock advances, the fields do not
        u, p = self.u, self.p
        info = step(self, max_dt)
        self.u, self.p = u, p
        return info

    monkeypatch.setattr(CBSSolver, "step", idle)


MUTANTS = {
    "viscosity x1.5": (_scaled_viscosity(1.5), "explicit"),
    "viscosity x0.67": (_scaled_viscosity(0.67), "implicit"),
    "idle step": (_idle_step, "explicit"),
    "no convection": (_residual(_no_convection), "implicit"),
    "flipped characteristic term": (_residual(_flipped_characteristic), "implicit"),
}


@pytest.mark.parametrize("mutant", list(MUTANTS))
def test_every_mutant_fails_a_verify_case(mutant, monkeypatch):
    patch, viscous = MUTANTS[mutant]
    patch(monkeypatch)
    failed = None
    try:
        for name, passed, text, _ in solver_cases(viscous, quick=True):
            if not passed:
                failed = f"{name}: {text}"
                break
    except CarotidError as error:  # a solver that breaks down fails too
        failed = str(error)
    assert failed is not None, f"{mutant}: every quick case passed"


def test_womersley_pressure_gradient_balances_the_flow_and_the_wall_shear():
    # section-integrated momentum: pi R^2 A(t) = dQ/dt + 2 pi R tau_w(t) / rho, with tau_w from the
    # independent closed form of carotid.flow.womersley (validation.md)
    from carotid.flow.waveform import carotid_waveform, fourier_flow
    from carotid.flow.womersley import womersley_wss

    wave, nu, rho, r, n = carotid_waveform(), 3.3e-6, 1060.0, 3.25e-3, 10
    t = np.linspace(0.0, wave.period_s, 50)
    h = 1e-6
    q = wave.harmonics(n)
    dqdt = (fourier_flow(q, wave.omega, t + h) - fourier_flow(q, wave.omega, t - h)) / (2 * h)
    balance = (dqdt + 2 * np.pi * r * womersley_wss(t, r, wave, rho * nu, nu, n) / rho) / (np.pi * r**2)
    a = womersley_pressure_gradient(t, r, wave, nu, n)
    assert np.abs(a - balance).max() <= 1e-6 * np.abs(balance).max()
    # steady limit: Poiseuille, 8 nu Q / (pi R^4)
    assert womersley_pressure_gradient(t, r, wave, nu, 0) == pytest.approx(8 * nu * q[0].real / (np.pi * r**4))


def test_durst_correlation_limits():
    assert durst_development_length(0.0) == pytest.approx(0.619)
    assert durst_development_length(1000.0) == pytest.approx(56.7, rel=1e-3)
    assert durst_development_length(50.0) == pytest.approx(2.99, abs=0.01)


def test_entrance_length_and_generalised_inlet():
    from carotid.flow.verify import entrance, inlet_profiles

    e = entrance(viscous="implicit")  # Re 50: Durst 2.99 D; measured 3.01 D
    assert abs(e["length_error"]) <= 0.1 and e["residual"] < 1e-3
    assert np.all(np.diff(e["centreline"]["u_over_mean"]) > -1e-3)  # the core accelerates monotonically
    g = inlet_profiles()  # measured 0.8 % (48-gon) and 0.6 %
    assert g["circle_error"] <= 0.02 and g["ellipse_error"] <= 0.02


def test_ethier_steinman_solves_the_navier_stokes_equations():
    """The reference itself, by central differences: div u = 0 and u_t + (u.grad)u + grad p - nu Lap u = 0."""
    from carotid.flow.exact import EthierSteinman

    es = EthierSteinman(length=3e-3, speed=0.02, nu=3.3e-6, centre=(0.0, 0.0, 3e-3))
    x = np.random.default_rng(0).uniform(-3e-3, 3e-3, (50, 3)) + np.array([0.0, 0.0, 3e-3])
    t, h, k = 0.1, 1e-5 * 3e-3, 1e-4
    e = np.eye(3) * h
    grad = es.velocity_gradient(x, t)
    lap = sum(es.velocity(x + e[c], t) - 2 * es.velocity(x, t) + es.velocity(x - e[c], t) for c in range(3)) / h**2
    grad_p = np.column_stack([(es.pressure(x + e[c], t) - es.pressure(x - e[c], t)) / (2 * h) for c in range(3)])
    u_t = (es.velocity(x, t + k) - es.velocity(x, t - k)) / (2 * k)
    u = es.velocity(x, t)
    residual = u_t + np.einsum("krc,kc->kr", grad, u) + grad_p - es.nu * lap
    scale = np.abs(np.einsum("krc,kc->kr", grad, u)).max()  # the convective term, balanced by grad p
    assert np.abs(np.trace(grad, axis1=1, axis2=2)).max() <= 1e-6 * np.abs(grad).max()
    assert np.abs(residual).max() <= 1e-4 * scale
    # with a wrong pressure (half of it) the balance fails: the check can fail
    assert np.abs(u_t + np.einsum("krc,kc->kr", grad, u) + 0.5 * grad_p - es.nu * lap).max() > 0.1 * scale


def test_convective_case_converges_at_the_expected_orders():
    """Ethier-Steinman on the mesh stage's boundary-layer meshes: velocity order 2, gradient order 1 in space,
    at least first order in time (measured: 2.51, 2.27; 1.13, 1.03; in time 2.60 and 1.37 for the pressure)."""
    from carotid.flow.verify import convective_cases

    space, time = list(convective_cases("implicit", quick=True))
    assert space[1] and time[1], space[2] + " | " + time[2]
    orders = space[3]["orders"]
    assert min(orders["velocity_error"]) >= 1.8 and min(orders["gradient_error"]) >= 0.9
    assert min(time[3]["orders"]["pressure_error"]) >= 0.9


@pytest.mark.parametrize("mutant", ["viscosity x1.5", "viscosity x0.67", "idle step", "no convection"])
def test_convective_case_fails_on_a_wrong_solver(mutant, monkeypatch):
    """The convective case alone catches every mutant but the flipped characteristic term (an O(dt) term that
    the small steps of its space study make negligible; the entrance case catches that one)."""
    from carotid.flow.verify import convective_cases

    MUTANTS[mutant][0](monkeypatch)
    name, passed, text, _ = next(convective_cases("implicit", quick=True))
    assert not passed, text


def _rcr_without_compliance(monkeypatch):
    from carotid.flow.outlets import OutletModel

    affine = OutletModel.affine
    monkeypatch.setattr(OutletModel, "affine", lambda self, dt: (self.rp + self.rd, affine(self, dt)[1] * 0))


def _rcr_frozen_state(monkeypatch):
    from carotid.flow.outlets import OutletModel

    monkeypatch.setattr(OutletModel, "advance", lambda self, q, dt: None)


@pytest.mark.parametrize("mutant", [None, _rcr_without_compliance, _rcr_frozen_state])
def test_rcr_outlet_matches_the_0d_impedance_and_fails_when_wrong(mutant, monkeypatch):
    """Measured: mean -0.00005 %, amplitude -0.62 %, phase -38.85 deg for -39.29 (-1.1 %)."""
    from carotid.flow.verify import rcr_outlet

    if mutant is not None:
        mutant(monkeypatch)
    r = rcr_outlet()
    ok = max(abs(r["mean_error"]), abs(r["amplitude_error"]), abs(r["phase_error"])) <= 0.02
    assert ok == (mutant is None), r


def test_rcr_calibration_meets_its_targets():
    """The calibrated 0D model gives the target mean and pulse pressures and shares (checked by integrating its
    ODE in time, independently of the Fourier solution the calibration uses)."""
    from carotid.flow.outlets import MMHG, tune_rcr
    from carotid.flow.waveform import carotid_waveform

    from scipy.signal import lfilter

    wave, share = carotid_waveform(), np.array([0.3, 0.7])
    model = tune_rcr(wave, share)
    dt = wave.period_s / 4000
    q = share[:, None] * wave.flow(np.arange(8 * 4000) * dt)[None]  # (outlets, steps)
    a = 1 / (1 + dt / (model.rd * model.c))
    p = np.empty_like(q)
    for j in range(2):  # backward Euler of C dPc/dt = Q - Pc / Rd as a first-order filter, from the mean state
        pc0 = model.rd[j] * share[j] * wave.mean_m3s
        pc = lfilter([a[j] * dt / model.c[j]], [1, -a[j]], q[j], zi=[a[j] * pc0])[0]
        p[j] = model.rp[j] * q[j] + pc
    p = p.T
    last = p[-4000:] / MMHG
    assert np.allclose(last.mean(axis=0), 93.0, rtol=2e-3)
    assert np.allclose(last.max(axis=0) - last.min(axis=0), 40.0, rtol=1e-2)
    assert np.allclose(model.rp / (model.rp + model.rd), 0.09)


def test_power_law_case_fails_when_the_solver_ignores_the_viscosity_law(monkeypatch):
    """Landed: centreline +0.43 %, WSS +0.61 %, dp/dz +0.74 %; with a Newtonian solver 14.5 %, -8.4 %, -61 %."""
    from carotid.flow.verify import power_law

    good = power_law()
    assert max(abs(good[k]) for k in ("centreline_error", "wss_mean_error", "pressure_gradient_error")) <= 0.02
    monkeypatch.setattr(CBSSolver, "molecular_viscosity", lambda self: np.full(len(self.mesh.tets), self.nu))
    bad = power_law()
    assert max(abs(bad[k]) for k in ("centreline_error", "wss_mean_error", "pressure_gradient_error")) > 0.05


def test_viscosity_laws_and_the_reassembled_viscous_matrix():
    from carotid.flow.assembly import StiffnessBlock, element_geometry, stiffness_matrix
    from carotid.flow.rheology import Rheology, shear_rate
    from carotid.flow.verify import POISEUILLE, tube_mesh

    carreau = Rheology("carreau")
    assert carreau.viscosity(np.array([0.0]))[0] == pytest.approx(0.056)
    assert carreau.viscosity(np.array([1e7]))[0] == pytest.approx(0.00345, rel=1e-3)
    # Cho & Kensey's curve at 1 1/s: mu_inf + (mu_0 - mu_inf) (1 + 3.313^2)^((0.3568 - 1)/2)
    assert carreau.viscosity(np.array([1.0]))[0] == pytest.approx(0.00345 + 0.05255 * (1 + 3.313**2) ** -0.3216)
    casson = Rheology("casson")
    assert casson.viscosity(np.array([1e8]))[0] == pytest.approx(0.0035, rel=0.02)
    assert casson.viscosity(np.array([0.0]))[0] == casson.viscosity(np.array([0.01]))[0]  # regularised
    g = np.zeros((1, 3, 3))
    g[0, 2, 0] = 5.0  # simple shear du_z/dx = 5 1/s
    assert shear_rate(g)[0] == pytest.approx(5.0)
    mesh = tube_mesh(POISEUILLE)
    volumes, grads = element_geometry(mesh.points, mesh.tets)
    w = np.random.default_rng(1).uniform(1e-6, 1e-4, len(mesh.tets))
    rows, cols = np.arange(0, mesh.n_points, 2), np.arange(1, mesh.n_points, 3)
    block = StiffnessBlock(volumes, grads, mesh.tets, mesh.n_points, rows, cols)
    block.update(np.ones_like(w))
    block = block.update(w)  # re-assembled in place
    full = stiffness_matrix(volumes * w, grads, mesh.tets, mesh.n_points)
    assert abs(block - full[rows][:, cols]).max() <= 1e-12 * abs(full).max()
