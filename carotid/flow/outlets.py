"""Lumped-parameter outlet models: resistance and three-element Windkessel (RCR), and their calibration.

Each outlet j relates its pressure P_j to its volume flow Q_j (SI: Pa, m^3/s):

* resistance: ``P_j = R_j Q_j + P_d``;
* RCR (Westerhof et al. 2009, "The arterial Windkessel", Med Biol Eng Comput 47:131): a proximal resistance
  R_p in series with a compliance C parallel to a distal resistance R_d::

      P_j = R_p Q_j + P_c,     C dP_c/dt = Q_j - (P_c - P_d) / R_d.

The CBS step couples them implicitly (:class:`carotid.flow.cbs.CBSSolver`): the outlet fluxes are affine in
the outlet pressures, ``q = q0 + F c``, and the backward-Euler update of ``P_c`` makes each law affine in
its flux, ``P = R_eff Q + b`` (:meth:`OutletModel.affine`), so one small linear system per step gives
pressures and fluxes that satisfy both at the new time level, as in the implicit coupling of
Vignon-Clementel et al. (2006, Comput Methods Appl Mech Eng 195:3776).  The state ``P_c`` is then
advanced with the flux of the step (:meth:`OutletModel.advance`).

Calibration (:func:`tune_rcr`) follows the usual two-step recipe for carotid and cerebral outlets: the
total resistance of each outlet from a target mean pressure and its target share of the mean flow,
``R_T = (P_mean - P_d) / (s_j Q_mean)``, split into ``R_p = f R_T`` (the characteristic impedance is 5-10 %
of the peripheral resistance, Westerhof et al. 2009) and ``R_d = R_T - R_p``; then one time constant
``tau = R_d C`` for all outlets, chosen so that the 0D model driven by the inflow waveform reproduces a
target pulse pressure (the pulse-pressure method of Stergiopulos et al. 1995, Am J Physiol 268:H1540).
The resistances of the 3D domain are left out of the calibration on purpose: a stenosis then lowers
its branch's share, which a fixed split cannot do.

Written here because no maintained Python package couples 0D outlets to a P1 CBS solver; the formulas are
the textbook ones above.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from carotid.errors import CarotidError

MMHG = 133.322387415
"""Pa per mmHg."""


@dataclass
class OutletModel:
    """Resistance or RCR outlets, one entry per outlet (ascending label 3, 4, ...), SI units.

    Attributes
    ----------
    rp : ndarray, shape (m,)
        Proximal (resistance model: the only) resistance, Pa s/m^3.
    c : ndarray, shape (m,)
        Compliance, m^3/Pa; 0 for a pure resistance.
    rd : ndarray, shape (m,)
        Distal resistance, Pa s/m^3 (unused where ``c`` is 0).
    pd : float
        Distal (venous) pressure, Pa.
    pc : ndarray, shape (m,)
        Compliance pressure, Pa: the state, advanced every step.
    """

    rp: np.ndarray
    c: np.ndarray
    rd: np.ndarray
    pd: float = 0.0
    pc: np.ndarray = field(default=None)

    def __post_init__(self):
        self.rp, self.c, self.rd = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (self.rp, self.c, self.rd))
        if not (self.rp.shape == self.c.shape == self.rd.shape) or self.rp.ndim != 1:
            raise CarotidError("the outlet model needs one R_p, C and R_d per outlet")
        if np.any(~np.isfinite(self.rp)) or np.any(self.rp < 0) or np.any(self.c < 0) or np.any(
                (self.c > 0) & ~(self.rd > 0)):
            raise CarotidError("outlet resistances and compliances must be finite and >= 0 (R_d > 0 with C > 0)")
        if np.any((self.c == 0) & ~(self.rp > 0)):
            raise CarotidError("a resistance outlet needs a positive resistance")
        self.pd = float(self.pd)
        if self.pc is None:
            self.pc = np.full(len(self.rp), self.pd)
        self.pc = np.asarray(self.pc, dtype=float)

    @classmethod
    def resistance(cls, r, pd: float = 0.0) -> OutletModel:
        """Pure resistances ``r`` (m,), Pa s/m^3, to the distal pressure ``pd`` (Pa)."""
        r = np.atleast_1d(np.asarray(r, dtype=float))
        return cls(r, np.zeros_like(r), np.zeros_like(r), pd)

    @property
    def n_outlets(self) -> int:
        return len(self.rp)

    def affine(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """``(R_eff, b)`` with ``P = R_eff Q + b`` at the end of a step of ``dt`` s (backward Euler), SI."""
        rcr = self.c > 0
        a = np.ones_like(self.rp)
        a[rcr] = 1.0 / (1.0 + dt / (self.rd[rcr] * self.c[rcr]))
        r_eff = self.rp.copy()
        b = np.full_like(self.rp, self.pd)
        r_eff[rcr] += a[rcr] * dt / self.c[rcr]
        b[rcr] = a[rcr] * (self.pc[rcr] + dt * self.pd / (self.rd[rcr] * self.c[rcr]))
        return r_eff, b

    def advance(self, q: np.ndarray, dt: float) -> None:
        """Advance ``P_c`` over a step of ``dt`` s with the outlet flows ``q`` (m,), m^3/s (backward Euler)."""
        rcr = self.c > 0
        a = 1.0 / (1.0 + dt / (self.rd[rcr] * self.c[rcr]))
        self.pc[rcr] = a * (self.pc[rcr] + dt * (q[rcr] + self.pd / self.rd[rcr]) / self.c[rcr])

    def pressures(self, q: np.ndarray) -> np.ndarray:
        """Outlet pressures (m,), Pa, for the flows ``q`` (m,) with the current ``P_c`` (after :meth:`advance`)."""
        return np.where(self.c > 0, self.rp * q + self.pc, self.rp * q + self.pd)

    def impedance(self, omega: np.ndarray) -> np.ndarray:
        """Input impedance ``Z(omega)`` (m, k) of each outlet at angular frequencies ``omega`` (k,), rad/s,
        Pa s/m^3: ``R_p + R_d / (1 + i omega R_d C)`` (``R_p`` for a resistance)."""
        w = np.atleast_1d(np.asarray(omega, dtype=float))[None]
        rd, c = self.rd[:, None], self.c[:, None]
        return self.rp[:, None] + np.where(c > 0, rd / (1.0 + 1j * w * rd * c), 0.0)

    def as_dict(self) -> dict:
        """Parameters in SI and in the clinical units, for summary.json."""
        return {"rp_pa_s_m3": self.rp.tolist(), "c_m3_pa": self.c.tolist(), "rd_pa_s_m3": self.rd.tolist(),
                "pd_pa": self.pd, "time_constant_s": np.where(self.c > 0, self.rd * self.c, 0.0).tolist(),
                "total_resistance_mmhg_s_ml": ((self.rp + np.where(self.c > 0, self.rd, 0.0)) / MMHG * 1e-6).tolist()}


def zero_d_pressure(model: OutletModel, waveform, share: np.ndarray, samples: int = 512,
                    n_harmonics: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Periodic pressure of each outlet when it receives ``share`` (m,) of the inflow ``waveform``, Pa.

    The steady periodic solution of the 0D law by Fourier series: ``P_k = Z(k omega) share Q_k`` for the
    first ``n_harmonics`` harmonics of the waveform (:meth:`Waveform.harmonics`).

    Returns
    -------
    t : ndarray, shape (samples,)
        s, over one period.
    p : ndarray, shape (m, samples)
        Pa.
    """
    from carotid.flow.waveform import fourier_flow

    q = waveform.harmonics(n_harmonics)  # complex amplitudes: Q(t) = sum_k Re(q_k e^{i k omega t})
    t = np.linspace(0.0, waveform.period_s, samples, endpoint=False)
    z = model.impedance(waveform.omega * np.arange(len(q)))
    p = np.array([fourier_flow(z[j] * share[j] * q, waveform.omega, t) for j in range(model.n_outlets)])
    return t, p + model.pd


def tune_rcr(waveform, share, mean_pressure: float = 93.0 * MMHG, pulse_pressure: float = 40.0 * MMHG,
             proximal_fraction: float = 0.09, distal_pressure: float = 0.0) -> OutletModel:
    """RCR outlets that give ``mean_pressure`` and ``pulse_pressure`` (Pa) with the flow shares ``share``.

    Parameters
    ----------
    waveform : Waveform
        Inflow, m^3/s.
    share : array_like, shape (m,)
        Target fraction of the mean inflow through each outlet (sums to 1).
    mean_pressure, pulse_pressure : float
        Targets, Pa (defaults 93 mmHg and 40 mmHg: 120/80 mmHg).
    proximal_fraction : float
        ``R_p / (R_p + R_d)``.
    distal_pressure : float
        Pa.

    Returns
    -------
    OutletModel
        The shares and the mean pressure are met exactly by the 0D model (the 3D domain left out); the pulse
        pressure to 1e-6 relative when reachable, else the nearest reachable value (the RCR's pulse pressure
        lies between that of ``R_p`` alone and that of ``R_p + R_d``), with a CarotidError when the target is
        out of that range.
    """
    share = np.atleast_1d(np.asarray(share, dtype=float))
    if not mean_pressure > distal_pressure:
        raise CarotidError("the target mean pressure must exceed the distal pressure")
    if not (0 < proximal_fraction < 1) or not pulse_pressure > 0:
        raise CarotidError("the RCR tuning needs 0 < R_p fraction < 1 and a positive pulse pressure")
    r_total = (mean_pressure - distal_pressure) / (share * waveform.mean_m3s)
    rp, rd = proximal_fraction * r_total, (1.0 - proximal_fraction) * r_total

    def pulse(log_tau: float) -> float:
        model = OutletModel(rp, np.exp(log_tau) / rd, rd, distal_pressure)
        p = zero_d_pressure(model, waveform, share)[1][0]
        return float(p.max() - p.min()) - pulse_pressure

    low, high = np.log(1e-4 * waveform.period_s), np.log(1e3 * waveform.period_s)
    if pulse(low) < 0 or pulse(high) > 0:
        raise CarotidError(f"a pulse pressure of {pulse_pressure / MMHG:.0f} mmHg cannot be reached with this inflow "
                           f"and R_p fraction (range {(pulse(high) + pulse_pressure) / MMHG:.0f}-"
                           f"{(pulse(low) + pulse_pressure) / MMHG:.0f} mmHg)")
    tau = np.exp(optimize.brentq(pulse, low, high, xtol=1e-10))
    return OutletModel(rp, tau / rd, rd, distal_pressure)
