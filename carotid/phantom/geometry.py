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


def tube_sdf(points: np.ndarray, axis: np.ndarray, radius: float, far: float = 10.0) -> np.ndarray:
    """Signed distance (mm, negative inside) to a tube of constant ``radius`` (mm) around a densely
    sampled ``axis`` (m, 3), i.e. to the union of the spheres on the samples: exact up to the sampling
    (an error below 0.001 mm at the ``STEP`` spacing).  Points (n, 3) farther than ``far`` from the
    wall get ``far``.  Returns float32, shape (n,)."""
    d, _ = cKDTree(axis).query(points, k=1, distance_upper_bound=radius + far, workers=-1)
    return np.minimum(d - radius, far).astype(np.float32)


def integrate_tangents(start: np.ndarray, tangents: np.ndarray, step: float = STEP) -> np.ndarray:
    """Axis samples (n, 3) after ``start`` (3,), each ``step`` mm from the previous one along the unit
    tangent (n, 3) evaluated at the middle of that step."""
    return start + np.cumsum(step * tangents, axis=0)


def frame(t: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit vector ``t`` to a right-handed orthonormal frame, the
    first as close as possible to ``towards``."""
    u = perpendicular(t, towards)
    return u, np.cross(t, u)


def kink_tangents(t0: np.ndarray, bend: np.ndarray, angle: float, r1: float, straight: float, r2: float,
                  step: float = STEP) -> np.ndarray:
    """Unit tangents (n, 3) of a kinked segment: a sharp bend of ``angle`` (rad) with radius ``r1`` (mm)
    towards the unit vector ``bend`` (perpendicular to ``t0``), ``straight`` mm straight on, then a
    gentler bend of radius ``r2`` back to the original direction ``t0``."""
    l1, l3 = angle * r1, angle * r2
    s = np.arange(0.5 * step, l1 + straight + l3, step)
    psi = np.where(s < l1, s / r1, np.where(s < l1 + straight, angle, angle - (s - l1 - straight) / r2))
    psi = np.clip(psi, 0.0, angle)[:, None]
    return np.cos(psi) * t0 + np.sin(psi) * bend


def coil_tangents(t0: np.ndarray, u1: np.ndarray, handed: float, r_bend: float, r_coil: float, pitch: float,
                  step: float = STEP) -> np.ndarray:
    """Unit tangents (n, 3) of a coil: the axis leaves the direction ``t0`` bending (radius ``r_bend``,
    mm) towards the unit vector ``u1`` (perpendicular to ``t0``) until it climbs at the helix angle,
    makes one full helical turn of radius ``r_coil`` (mm) about ``t0`` rising ``pitch`` mm (``handed``
    = +1 or -1 sets the sense), and bends back to ``t0`` in the plane of ``t0`` and ``u1``."""
    u2 = np.cross(t0, u1)
    e_h = np.arctan2(pitch, 2.0 * np.pi * r_coil)
    l_a = (0.5 * np.pi - e_h) * r_bend
    l_b = 2.0 * np.pi * r_coil / np.cos(e_h)
    s = np.arange(0.5 * step, 2 * l_a + l_b, step)
    elev = np.where(s < l_a, 0.5 * np.pi - s / r_bend,
                    np.where(s < l_a + l_b, e_h, e_h + (s - l_a - l_b) / r_bend))
    elev = np.clip(elev, e_h, 0.5 * np.pi)[:, None]
    azim = (handed * 2.0 * np.pi * np.clip((s - l_a) / l_b, 0.0, 1.0))[:, None]
    return np.sin(elev) * t0 + np.cos(elev) * (np.cos(azim) * u1 + np.sin(azim) * u2)


def tube_gap(centres: np.ndarray, radii: np.ndarray, axis: np.ndarray, radius: float) -> tuple[float, int, int]:
    """Smallest wall-to-wall gap (mm; negative: overlap) between a union of spheres (centres (n, 3),
    radii (n,)) and a tube of constant ``radius`` around the densely sampled ``axis`` (m, 3).

    Returns
    -------
    gap : float
    i, j : int
        The sphere and the axis sample realising it.
    """
    d, j = cKDTree(axis).query(centres, k=1, workers=-1)
    i = int(np.argmin(d - radii))
    return float(d[i] - radii[i] - radius), i, int(j[i])


def bias_field(shape: tuple[int, int, int], rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """A smooth random multiplicative field (float32, ``shape`` in array order) of the form
    ``1 + amplitude * P`` with P a random polynomial of degree <= 2 in the normalised array
    coordinates, scaled so that the field spans exactly ``[1 - amplitude, 1 + amplitude]``."""
    k, j, i = (np.linspace(-1.0, 1.0, n, dtype=np.float32) for n in shape)
    k, j, i = k[:, None, None], j[None, :, None], i[None, None, :]
    terms = [k, j, i, k * k - 1 / 3, j * j - 1 / 3, i * i - 1 / 3, k * j, k * i, j * i]
    c = rng.standard_normal(len(terms))
    c[:3] *= 1.5  # mostly a gradient across the field of view, some curvature
    p = sum(float(ci) * t for ci, t in zip(c, terms))
    p = np.broadcast_to(p, shape).astype(np.float32)
    lo, hi = float(p.min()), float(p.max())
    p = (2.0 * p - (lo + hi)) / max(hi - lo, 1e-9)
    return (1.0 + amplitude * p).astype(np.float32)
