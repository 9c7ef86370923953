"""Analytic geometry of the synthetic carotid bifurcation.

Each vessel branch is a smooth axis sampled every ``STEP`` mm with a radius at
every sample; the lumen is the union of the spheres centred on the samples, so
its signed distance is ``min_i(|x - c_i| - r_i)`` (exact for a constant radius,
and within a few micrometres of the swept tube for the slowly varying radii
used here).  The jugular vein and the vertebra are straight analytic solids.
All lengths are in mm in the world (LPS) frame; z points superiorly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

STEP = 0.15  # mm between axis samples


@dataclass
class Branch:
    """A vessel branch: axis samples (n, 3) in mm and the lumen radius (n,) in mm."""

    name: str
    points: np.ndarray
    radii: np.ndarray

    @property
    def arclength(self) -> np.ndarray:
        """Arc length (n,) in mm from the first sample."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))])


def spline_axis(control: np.ndarray, step: float = STEP) -> np.ndarray:
    """Resample a cubic spline through control points (m, 3) every ``step`` mm of arc length."""
    control = np.asarray(control, float)
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(control, axis=0), axis=1))])
    spline = CubicSpline(chord, control, bc_type="natural")
    fine_t = np.linspace(0.0, chord[-1], int(chord[-1] / step * 10) + 2)
    fine = spline(fine_t)
    fine_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(fine, axis=0), axis=1))])
    s = np.arange(0.0, fine_s[-1], step)
    return spline(np.interp(s, fine_s, fine_t))


def raised_cosine(s: np.ndarray, centre: float, half_width: float) -> np.ndarray:
    """1 at ``centre`` falling smoothly to 0 at ``centre +- half_width`` (mm)."""
    u = np.clip(np.abs(s - centre) / half_width, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * u))


def union_of_spheres_sdf(points: np.ndarray, branches: list[Branch], neighbours: int = 32,
                         far: float = 10.0) -> np.ndarray:
    """Signed distance (mm, negative inside) of query points to a union of branch tubes.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Query points in mm.
    branches : list of Branch
    neighbours : int
        Axis samples searched per point; enough to cover the radius variation.
    far : float
        Value (mm) returned for points farther than ``far`` from every tube.

    Returns
    -------
    ndarray, shape (n,), float32
    """
    centres = np.concatenate([b.points for b in branches])
    radii = np.concatenate([b.radii for b in branches])
    tree = cKDTree(centres)
    bound = radii.max() + far
    d1, _ = tree.query(points, k=1, distance_upper_bound=bound, workers=-1)
    out = np.full(len(points), far, np.float32)
    near = np.flatnonzero(np.isfinite(d1))
    d, idx = tree.query(points[near], k=neighbours, distance_upper_bound=bound, workers=-1)
    valid = np.isfinite(d)
    sdf = np.where(valid, d - radii[np.minimum(idx, len(radii) - 1)], np.inf).min(axis=1)
    out[near] = np.minimum(sdf, far)
    return out


def cylinder_sdf(points: np.ndarray, centre_xy: np.ndarray, tilt_xy: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (mm) to an infinite vertical-ish cylinder whose axis passes through
    ``centre_xy`` at z = 0 and moves by ``tilt_xy`` mm per mm of z (small tilts only)."""
    axis_xy = centre_xy[None, :] + points[:, 2:3] * tilt_xy[None, :]
    return np.linalg.norm(points[:, :2] - axis_xy, axis=1) - radius


def ellipsoid_sdf(points: np.ndarray, centre: np.ndarray, axes: np.ndarray, semi: np.ndarray) -> np.ndarray:
    """Approximate signed distance (mm) to an ellipsoid with orthonormal ``axes`` (3, 3, rows)
    and semi-axis lengths ``semi`` (3,); exact on the principal axes, first order elsewhere."""
    local = (points - centre) @ axes.T
    q = np.linalg.norm(local / semi, axis=1)
    grad = np.linalg.norm(local / semi**2, axis=1)
    return (q * (q - 1.0) / np.maximum(grad, 1e-9)).astype(np.float32)


def perpendicular(t: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """Unit vector perpendicular to the unit vector ``t`` and as close as possible to ``towards``."""
    u = towards - np.dot(towards, t) * t
    return u / np.linalg.norm(u)
