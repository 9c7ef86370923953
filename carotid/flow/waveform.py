"""Inlet flow waveforms: a periodic flow rate Q(t), its Fourier harmonics, the built-in common carotid
waveform and user waveforms read from CSV.

A :class:`Waveform` holds one period of samples; it is evaluated between samples by a periodic cubic
spline (``scipy.interpolate.CubicSpline``, ``bc_type="periodic"``), so Q(t) is C2 and periodic.  Its
harmonics follow the convention of validation.md (Womersley 1957)::

    Q(t) = Re sum_{k>=0} Q_k exp(i k omega t),   Q_0 = mean,   Q_k = (2/T) int_0^T Q(t) exp(-i k omega t) dt.

Units: time in s, flow in m^3/s inside the package; CSV files give flow in mL/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline, PchipInterpolator

from carotid.errors import CarotidError

ML = 1e-6
"""One millilitre in m^3."""

FFT_SAMPLES = 4096
"""Points per period of the FFT that computes the harmonics of the spline (aliasing error ~1e-14)."""

# Holdsworth et al. 1999 (Physiol. Meas. 20:219), spatial-peak velocity feature points of the common carotid
# waveform, t s : v cm/s (validation.md).  Shape only: the flow is scaled to CAROTID_MEAN_ML / CAROTID_PEAK_ML.
CAROTID_PERIOD_S = 0.917
CAROTID_FEATURES = ((0.0, 25.9), (0.055, 20.9), (0.110, 47.7), (0.116, 64.6), (0.153, 108.2),
                    (0.219, 64.6), (0.398, 19.4), (0.917, 25.9))
CAROTID_MEAN_ML = 6.0
CAROTID_PEAK_ML = 25.0
CAROTID_HARMONICS = 10
CAROTID_SAMPLES = 512

PERIOD_RANGE_S = (0.2, 5.0)
"""Cardiac periods a user waveform may have, s: heart rates of 12 to 300 beats a minute."""
MIN_MEAN_FLOW_ML = 0.01
"""Smallest mean inflow of a user waveform or steady flow, mL/s.  A carotid carries 2-20 mL/s; below this the
adaptive time step, set by the inflow speed, spans a whole cycle, so the run resolves nothing."""


def check_inflow_sign(mean_ml_s: float, source: str) -> None:
    """Raise CarotidError unless the mean flow (mL/s) enters through the inlet; ``source`` names the input."""
    if not mean_ml_s > 0:
        raise CarotidError(f"{source}: the mean flow is {mean_ml_s:.3g} mL/s: blood must enter through the CCA "
                           "inlet on average (check the sign of the flow column)")


def check_inflow(period_s: float, mean_ml_s: float, source: str) -> None:
    """Raise CarotidError unless the period (s) lies in ``PERIOD_RANGE_S`` and the mean flow (mL/s) enters
    (:func:`check_inflow_sign`) and is at least ``MIN_MEAN_FLOW_ML``; ``source`` names the input in the
    message."""
    low, high = PERIOD_RANGE_S
    if not low <= period_s <= high:
        raise CarotidError(f"{source}: a cardiac period of {period_s:g} s is outside {low:g}-{high:g} s (heart rates "
                           "of 12-300 per minute): check the time column, which is in seconds")
    check_inflow_sign(mean_ml_s, source)
    if not mean_ml_s >= MIN_MEAN_FLOW_ML:
        raise CarotidError(f"{source}: a mean flow of {mean_ml_s:.3g} mL/s is below {MIN_MEAN_FLOW_ML:g} mL/s (a "
                           "carotid carries 2-20 mL/s; the adaptive time step would span the whole cycle): check the "
                           "flow, which is in mL/s")


@dataclass(frozen=True, eq=False)
class Waveform:
    """A periodic volumetric flow rate given by samples over one period.

    Attributes
    ----------
    period_s : float
        Period T, s.
    times_s : ndarray, shape (m,)
        Strictly increasing sample times, s, with ``times_s[-1] - times_s[0] <= period_s``.  When the span
        equals the period the last sample repeats the first one and is dropped (its flow must match).
    flow_m3s : ndarray, shape (m,)
        Flow rate at the sample times, m^3/s.

    Notes
    -----
    Between samples Q(t) is the periodic cubic spline through them; ``flow`` wraps any t into the period.
    At least 4 distinct samples per period are required.
    """

    period_s: float
    times_s: np.ndarray
    flow_m3s: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.times_s, dtype=float).ravel()
        q = np.asarray(self.flow_m3s, dtype=float).ravel()
        period = float(self.period_s)
        if not (math.isfinite(period) and period > 0):
            raise CarotidError(f"waveform period must be a positive number of seconds, got {self.period_s}")
        if t.shape != q.shape:
            raise CarotidError(f"waveform has {t.size} times but {q.size} flow values")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
            raise CarotidError("waveform times and flows must be finite numbers")
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise CarotidError("waveform times must be strictly increasing")
        if t.size and t[-1] - t[0] > period * (1 + 1e-12):
            raise CarotidError(f"waveform samples span {t[-1] - t[0]:g} s, more than the period {period:g} s")
        if t.size and t[-1] - t[0] >= period * (1 - 1e-12):
            if not math.isclose(q[-1], q[0], rel_tol=1e-6, abs_tol=1e-9 * max(np.abs(q).max(), 1e-300)):
                raise CarotidError("the waveform's last sample ends the period but its flow differs from the first")
            t, q = t[:-1], q[:-1]
        if t.size < 4:
            raise CarotidError(f"a waveform needs at least 4 samples per period, got {t.size}")
        object.__setattr__(self, "period_s", period)
        object.__setattr__(self, "times_s", t)
        object.__setattr__(self, "flow_m3s", q)
        spline = CubicSpline(np.r_[t, t[0] + period], np.r_[q, q[0]], bc_type="periodic")
        object.__setattr__(self, "_spline", spline)

    @property
    def omega(self) -> float:
        """Angular frequency 2 pi / T, rad/s."""
        return 2.0 * math.pi / self.period_s

    @property
    def mean_m3s(self) -> float:
        """Time-averaged flow Q_0, m^3/s (exact integral of the spline)."""
        t0 = self.times_s[0]
        return float(self._spline.integrate(t0, t0 + self.period_s)) / self.period_s

    def flow(self, t):
        """Flow rate at time(s) ``t`` (s, any real, wrapped into the period), m^3/s; float for a scalar t."""
        t0 = self.times_s[0]
        out = self._spline(t0 + np.mod(np.asarray(t, dtype=float) - t0, self.period_s))
        return float(out) if np.ndim(out) == 0 else out

    def harmonics(self, n: int) -> np.ndarray:
        """Complex Fourier coefficients Q_0 ... Q_n, m^3/s, shape (n + 1,).

        ``Q(t) = Re sum_k Q_k exp(i k omega t)`` with t measured from 0 (not from ``times_s[0]``);
        Q_0 is the (real) mean.  Computed by an FFT of the spline on ``FFT_SAMPLES`` points.
        """
        n = int(n)
        if n < 0 or n >= FFT_SAMPLES // 2:
            raise CarotidError(f"number of harmonics must be in [0, {FFT_SAMPLES // 2 - 1}], got {n}")
        t = np.arange(FFT_SAMPLES) * (self.period_s / FFT_SAMPLES)
        coeffs = np.fft.rfft(self.flow(t))[: n + 1] / FFT_SAMPLES
        coeffs[1:] *= 2.0
        coeffs[0] = self.mean_m3s
        return coeffs

    def scaled(self, mean_m3s: float) -> Waveform:
        """The same shape multiplied by a constant so that its mean is ``mean_m3s`` (m^3/s)."""
        mean = self.mean_m3s
        if not (math.isfinite(mean_m3s) and mean_m3s > 0):
            raise CarotidError(f"target mean flow must be positive, got {mean_m3s} m^3/s")
        if mean <= 0:
            raise CarotidError(f"cannot scale a waveform whose mean flow is {mean:g} m^3/s to a positive mean")
        return self.affine(mean_m3s / mean, 0.0)

    def affine(self, a: float, b: float) -> Waveform:
        """The waveform ``a Q(t) + b`` (``b`` in m^3/s): its spline and harmonics are those of Q mapped the same
        way, since both are linear in the samples and reproduce a constant."""
        return Waveform(self.period_s, self.times_s, a * self.flow_m3s + b)


def fourier_flow(coeffs: np.ndarray, omega: float, t) -> np.ndarray:
    """Evaluate ``Re sum_k coeffs[k] exp(i k omega t)`` at time(s) ``t``; shape of ``t``."""
    t = np.asarray(t, dtype=float)
    k = np.arange(len(coeffs))
    return np.real(np.exp(1j * omega * t[..., None] * k) @ coeffs)


def constant_waveform(q_m3s: float, period_s: float = 1.0) -> Waveform:
    """A steady flow rate as a waveform of period ``period_s`` (s; the "cycle" of a steady run).

    Parameters
    ----------
    q_m3s : float
        Flow rate, m^3/s.
    period_s : float
        Period, s.
    """
    return Waveform(period_s, np.linspace(0.0, period_s, 9)[:-1], np.full(8, float(q_m3s)))


def carotid_waveform() -> Waveform:
    """The built-in common carotid artery flow waveform: T = 0.917 s, mean 6.0 mL/s, peak 25.0 mL/s.

    Built from the shape of Holdsworth et al. (1999, Physiol. Meas. 20:219), whose archetypal waveform is not
    public as a table, so this is an approximation:

    1. the spatial-peak velocity feature points (``CAROTID_FEATURES``: t = 0, 0.055, 0.110, 0.116, 0.153,
       0.219, 0.398, 0.917 s; 25.9 ... 108.2 cm/s) are joined by a monotone piecewise-cubic (PCHIP)
       interpolant, made periodic by wrapping one feature point around each end;
    2. that curve is sampled on 4096 points per period and truncated to its first 10 harmonics (FFT), which
       smooths the kink of the systolic upstroke at 0.110-0.116 s (largest shape change there, ~8% of the
       peak) and leaves a band-limited waveform that a 10-harmonic Womersley inlet carries exactly;
    3. the truncated shape s(t) is mapped affinely, Q = a + b s, with a and b chosen so that the mean is
       exactly 6.0 mL/s and the maximum exactly 25.0 mL/s (Holdsworth: mean ~6.0, peak ~23-25 mL/s).
       The peak falls at ~0.158 s, the minimum (end of diastole) is ~2.2 mL/s, so flow never reverses.

    Treating the centreline velocity shape as the flow shape is itself an approximation (the profile
    flattens in systole).  The result is stored as 512 uniform samples (spline error ~1e-9 of the peak).

    Returns
    -------
    Waveform
    """
    tf, vf = np.array(CAROTID_FEATURES).T
    period = CAROTID_PERIOD_S
    pchip = PchipInterpolator(np.r_[tf[-2] - period, tf, period + tf[1]], np.r_[vf[-2], vf, vf[1]])
    shape = np.fft.rfft(pchip(np.arange(FFT_SAMPLES) * (period / FFT_SAMPLES)))[: CAROTID_HARMONICS + 1]
    shape = shape * np.where(np.arange(CAROTID_HARMONICS + 1) == 0, 1.0, 2.0) / FFT_SAMPLES
    omega = 2.0 * math.pi / period
    fine = fourier_flow(shape, omega, np.arange(FFT_SAMPLES) * (period / FFT_SAMPLES))
    b = (CAROTID_PEAK_ML - CAROTID_MEAN_ML) / (fine.max() - shape[0].real)
    coeffs = b * shape
    coeffs[0] = CAROTID_MEAN_ML
    times = np.arange(CAROTID_SAMPLES) * (period / CAROTID_SAMPLES)
    return Waveform(period, times, ML * fourier_flow(coeffs, omega, times))


def _parse_row(text: str, lineno: int, path: Path, header_allowed: bool) -> tuple[float, float] | None:
    """(time, flow) of one CSV line, None for a header line; CarotidError naming the line otherwise."""
    fields = text.replace(";", ",").split(",") if ("," in text or ";" in text) else text.split()
    fields = [f.strip() for f in fields]
    numbers = []
    for field in fields:
        try:
            numbers.append(float(field))
        except ValueError:
            numbers.append(None)
    if header_allowed and all(x is None for x in numbers):
        return None
    if len(numbers) != 2 or None in numbers:
        raise CarotidError(f"{path}: line {lineno}: expected two numbers 'time_s, flow_mL_s', got {text!r}")
    if not all(math.isfinite(x) for x in numbers):
        raise CarotidError(f"{path}: line {lineno}: time and flow must be finite numbers, got {text!r}")
    return numbers[0], numbers[1]


def read_waveform_csv(path, period: float | None = None) -> Waveform:
    """Read a waveform from a CSV file of two columns: time (s) and flow (mL/s).

    Parameters
    ----------
    path : str or Path
        Text file; fields separated by commas, semicolons or white space; an optional header line before the data;
        blank lines and lines starting with ``#`` are skipped.  At least 4 rows, strictly increasing times.
    period : float, optional
        Period in s.  Without it the last row must close the period: its flow must equal the first row's
        (relative 1e-6), and ``T = t_last - t_first``.  With it, the rows span at most ``period``.

    Returns
    -------
    Waveform
        Flow converted to m^3/s.

    Raises
    ------
    CarotidError
        Missing file, a non-numeric, NaN or infinite field, a non-increasing time (the message names the
        line), fewer than 4 rows, an open period without ``period``, or a period or mean flow outside the
        bounds of :func:`check_inflow`.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CarotidError(f"cannot read waveform file {path}: {exc}") from None
    rows, linenos, seen_header = [], [], False
    for lineno, text in enumerate(lines, start=1):
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        row = _parse_row(text, lineno, path, header_allowed=not rows and not seen_header)
        if row is None:
            seen_header = True
            continue
        if rows and row[0] <= rows[-1][0]:
            raise CarotidError(f"{path}: line {lineno}: time {row[0]:g} s does not increase "
                               f"(previous row has {rows[-1][0]:g} s)")
        rows.append(row)
        linenos.append(lineno)
    if len(rows) < 4:
        raise CarotidError(f"{path}: a waveform needs at least 4 rows of 'time_s, flow_mL_s', found {len(rows)}")
    t, q = np.array(rows).T
    if period is None:
        if not math.isclose(q[-1], q[0], rel_tol=1e-6, abs_tol=1e-12):
            raise CarotidError(f"{path}: line {linenos[-1]}: the last flow ({q[-1]:g} mL/s) differs from the "
                               f"first ({q[0]:g} mL/s), so the period is unknown: repeat the first flow at t = T "
                               f"or give the period")
        period = t[-1] - t[0]
    elif t[-1] - t[0] > period * (1 + 1e-12):
        raise CarotidError(f"{path}: line {linenos[-1]}: rows span {t[-1] - t[0]:g} s, more than the "
                           f"period {period:g} s")
    try:
        waveform = Waveform(period, t, q * ML)
    except CarotidError as exc:
        raise CarotidError(f"{path}: {exc}") from None
    check_inflow(waveform.period_s, waveform.mean_m3s / ML, str(path))
    return waveform
