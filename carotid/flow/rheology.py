"""Generalised-Newtonian blood: the viscosity as a function of the local shear rate.

The apparent viscosity mu(gamma_dot) of each element is taken from its P1 velocity gradient,
``gamma_dot = sqrt(2 D:D)`` with ``D = (G + G^T)/2`` (constant per element), and enters the CBS scheme as an
element viscosity (:class:`carotid.flow.cbs.CBSSolver`, ``rheology``).  Models (mu in Pa s, gamma_dot in 1/s):

* Newtonian: ``mu``;
* Carreau-Yasuda: ``mu = mu_inf + (mu_0 - mu_inf) [1 + (lambda gamma_dot)^a]^((n - 1)/a)``, with the blood
  parameters of Cho & Kensey (1991, Biorheology 28:241) as the default: mu_0 = 0.056, mu_inf = 0.00345 Pa s,
  lambda = 3.313 s, n = 0.3568, a = 2 (the Carreau model; Johnston et al. 2004, J Biomech 37:709, use the same);
* Casson: ``mu = (sqrt(tau_y / gamma_dot) + sqrt(eta))^2``, yield stress tau_y and the high-shear viscosity
  eta; defaults tau_y = 0.005 Pa (whole blood at normal haematocrit lies at 4-15 mPa: Merrill 1969, Physiol Rev
  49:863; Kim et al. 2000 measured 13.8 mPa) and eta = 0.0035 Pa s;
* power law: ``mu = K gamma_dot^(n - 1)`` (for verification against its exact pipe flow).

The Casson and power-law viscosities are unbounded as gamma_dot -> 0; they are evaluated at
``max(gamma_dot, gamma_min)`` (``gamma_min`` = 0.01 1/s by default, a cap of 0.6 Pa s for the Casson blood
above), the usual regularisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carotid.errors import CarotidError

MODELS = ("newtonian", "carreau", "casson", "power")


@dataclass(frozen=True)
class Rheology:
    """A viscosity law; parameters in SI (Pa s, s, Pa) as in the module docstring.

    Attributes
    ----------
    model : {"newtonian", "carreau", "casson", "power"}
    mu : float
        Newtonian viscosity, Pa s.
    mu_0, mu_inf, lam, n, a : float
        Carreau-Yasuda parameters (``n`` is also the power-law index).
    tau_y, eta : float
        Casson yield stress (Pa) and high-shear viscosity (Pa s).
    k : float
        Power-law consistency, Pa s^n.
    gamma_min : float
        Shear rate below which the Casson and power-law viscosities are held, 1/s.
    """

    model: str = "newtonian"
    mu: float = 3.5e-3
    mu_0: float = 0.056
    mu_inf: float = 0.00345
    lam: float = 3.313
    n: float = 0.3568
    a: float = 2.0
    tau_y: float = 0.005
    eta: float = 0.0035
    k: float = 0.035
    gamma_min: float = 0.01

    def __post_init__(self):
        if self.model not in MODELS:
            raise CarotidError(f"unknown rheology {self.model!r} ({', '.join(MODELS)})")
        values = (self.mu, self.mu_0, self.mu_inf, self.lam, self.n, self.a, self.eta, self.k, self.gamma_min)
        if not all(np.isfinite(v) and v > 0 for v in values) or not self.tau_y >= 0:
            raise CarotidError("rheology parameters must be positive (the yield stress >= 0)")

    def viscosity(self, shear_rate: np.ndarray) -> np.ndarray:
        """Dynamic viscosity (Pa s) at shear rates ``shear_rate`` (1/s), same shape."""
        g = np.asarray(shear_rate, dtype=float)
        if self.model == "newtonian":
            return np.full_like(g, self.mu)
        if self.model == "carreau":
            return self.mu_inf + (self.mu_0 - self.mu_inf) * (1.0 + (self.lam * g) ** self.a) ** ((self.n - 1.0) / self.a)
        g = np.maximum(g, self.gamma_min)
        if self.model == "casson":
            return (np.sqrt(self.tau_y / g) + np.sqrt(self.eta)) ** 2
        return self.k * g ** (self.n - 1.0)

    @property
    def newtonian(self) -> bool:
        return self.model == "newtonian"


def shear_rate(gradients: np.ndarray) -> np.ndarray:
    """``sqrt(2 D:D)`` (1/s) of velocity gradients ``gradients`` (m, 3, 3) in 1/s, shape (m,)."""
    d = 0.5 * (gradients + gradients.transpose(0, 2, 1))
    return np.sqrt(2.0 * np.einsum("eij,eij->e", d, d))
