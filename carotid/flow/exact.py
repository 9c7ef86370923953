"""The Ethier-Steinman exact solution of the unsteady 3D Navier-Stokes equations, for solver verification.

Ethier & Steinman (1994, "Exact fully 3D Navier-Stokes solutions for benchmarking", Int. J. Numer. Methods
Fluids 19:369-375) give, in coordinates ``(x, y, z)``, with viscosity ``nu`` and constants ``a``, ``d``::

    u = -a [e^{ax} sin(ay + dz) + e^{az} cos(ax + dy)] e^{-nu d^2 t}
    v = -a [e^{ay} sin(az + dx) + e^{ax} cos(ay + dz)] e^{-nu d^2 t}
    w = -a [e^{az} sin(ax + dy) + e^{ay} cos(az + dx)] e^{-nu d^2 t}
    p = -a^2/2 [e^{2ax} + e^{2ay} + e^{2az} + 2 sin(ax + dy) cos(az + dx) e^{a(y+z)}
                + 2 sin(ay + dz) cos(ax + dy) e^{a(z+x)} + 2 sin(az + dx) cos(ay + dz) e^{a(x+y)}] e^{-2 nu d^2 t}

(kinematic pressure).  It is a Beltrami flow (vorticity parallel to velocity): the convective term
``(u.grad) u = grad |u|^2/2`` is balanced by the pressure, and ``Lap u = -d^2 u`` gives the viscous decay.
Scaled to a domain of size L and a velocity scale U (``xi = (x - c)/L``, ``u = U u(xi)``, ``p = U^2 p(xi)``)
it solves the equations with viscosity ``nu`` for any U, with the decay ``exp(-nu d^2 t / L^2)``; the
Reynolds number ``U L / nu`` sets how much the pressure (convection) matters against the decay
(viscosity).  The formulas are written out here because
no maintained Python package provides them; ``tests/test_verify.py`` checks them by finite differences
against the Navier-Stokes equations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

A, D = np.pi / 4, np.pi / 2
"""The constants a and d of Ethier & Steinman's test case (their domain is the cube [-1, 1]^3)."""


@dataclass(frozen=True)
class EthierSteinman:
    """The Ethier-Steinman solution scaled to a domain.

    Parameters
    ----------
    length : float
        Length scale, m (``xi = (x - centre) / length``).
    speed : float
        Velocity scale U, m/s.
    nu : float
        Kinematic viscosity, m^2/s.
    centre : tuple of float
        Point mapped to ``xi = 0``, m.
    """

    length: float
    speed: float
    nu: float
    centre: tuple = (0.0, 0.0, 0.0)

    def decay(self, t: float) -> float:
        """Velocity decay factor ``exp(-nu d^2 t / length^2)`` at time ``t`` (s)."""
        return float(np.exp(-self.nu * D**2 * t / self.length**2))

    def _xi(self, x: np.ndarray) -> np.ndarray:
        return ((np.asarray(x, dtype=float) - np.asarray(self.centre)) / self.length).T

    def velocity(self, x: np.ndarray, t: float) -> np.ndarray:
        """Velocity at points ``x`` (k, 3) in m and time ``t`` in s, m/s, shape (k, 3)."""
        x_, y, z = self._xi(x)
        u = np.exp(A * x_) * np.sin(A * y + D * z) + np.exp(A * z) * np.cos(A * x_ + D * y)
        v = np.exp(A * y) * np.sin(A * z + D * x_) + np.exp(A * x_) * np.cos(A * y + D * z)
        w = np.exp(A * z) * np.sin(A * x_ + D * y) + np.exp(A * y) * np.cos(A * z + D * x_)
        return (-A * self.speed * self.decay(t)) * np.column_stack([u, v, w])

    def pressure(self, x: np.ndarray, t: float) -> np.ndarray:
        """Kinematic pressure p / rho at points ``x`` (k, 3) in m and time ``t`` in s, m^2/s^2, shape (k,)."""
        x_, y, z = self._xi(x)
        p = (np.exp(2 * A * x_) + np.exp(2 * A * y) + np.exp(2 * A * z)
             + 2 * np.sin(A * x_ + D * y) * np.cos(A * z + D * x_) * np.exp(A * (y + z))
             + 2 * np.sin(A * y + D * z) * np.cos(A * x_ + D * y) * np.exp(A * (z + x_))
             + 2 * np.sin(A * z + D * x_) * np.cos(A * y + D * z) * np.exp(A * (x_ + y)))
        return (-0.5 * A**2 * self.speed**2 * self.decay(t) ** 2) * p

    def velocity_gradient(self, x: np.ndarray, t: float, step: float = 1e-6) -> np.ndarray:
        """``G[k, r, c] = d u_r / d x_c`` at points ``x`` (k, 3), 1/s, shape (k, 3, 3), by central differences
        with a step of ``step * length`` (the solution is smooth; the truncation error is ~1e-12 relative)."""
        h = step * self.length
        x = np.asarray(x, dtype=float)
        cols = [(self.velocity(x + h * e, t) - self.velocity(x - h * e, t)) / (2 * h) for e in np.eye(3)]
        return np.stack(cols, axis=-1)
