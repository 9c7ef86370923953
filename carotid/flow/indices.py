"""Haemodynamic wall indices of one cardiac cycle of wall shear stress (WSS) vectors.

From the WSS vector tau(t) at each wall node over one period T (validation.md):

* TAWSS = (1/T) int |tau| dt                                  (Pa)
* OSI = 0.5 [1 - |int tau dt| / int |tau| dt]                 (0 to 0.5)
* RRT = 1 / [(1 - 2 OSI) TAWSS] = 1 / |mean tau|              (1/Pa)
* ECAP = OSI / TAWSS                                          (1/Pa)
* transWSS = (1/T) int |tau . (n x m)| dt, m = mean tau / |mean tau|   (Pa; Peiffer et al. 2013)
* TWSSG, the *temporal* WSS gradient (1/T) int |d tau / dt| dt        (Pa/s)
* optionally TWSSG_spatial, the time-averaged spatial WSS gradient of Lei et al. (1995),
  (1/T) int sqrt((d tau_m / dm)^2 + (d tau_p / dp)^2) dt, with m the direction of the mean WSS and
  p = n x m                                                   (Pa/m)

No maintained Python library computes these from arrays (VMTK and SimVascular do it inside their own
pipelines), and each is one vectorised line, so they are written here.
"""

from __future__ import annotations

import numpy as np

from carotid.errors import CarotidError

UNDEFINED_DIRECTION = 1e-12
"""|mean tau| at or below this fraction of TAWSS counts as no mean direction (pure reversal)."""

LOW_TAWSS_PA = 0.4
"""TAWSS below which the wall counts as exposed to low shear, Pa (the report and cohort.csv)."""

HIGH_OSI = 0.2
"""OSI above which the wall counts as exposed to oscillating shear (the report and cohort.csv)."""


def trapezoid_weights(times: np.ndarray) -> np.ndarray:
    """Weights w (k,) such that ``w @ f`` is the trapezoidal integral of samples f over ``times``, s."""
    dt = np.diff(times)
    return 0.5 * (np.r_[dt, 0.0] + np.r_[0.0, dt])


def _check(times, wss, normals, gradient):
    times = np.asarray(times, dtype=float)
    wss = np.asarray(wss, dtype=float)
    normals = np.asarray(normals, dtype=float)
    if times.ndim != 1 or times.size < 2 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise CarotidError("WSS sample times must be at least 2 finite, strictly increasing values")
    if wss.ndim != 3 or wss.shape[0] != times.size or wss.shape[2] != 3:
        raise CarotidError(f"WSS must have shape (times={times.size}, nodes, 3), got {wss.shape}")
    if normals.shape != (wss.shape[1], 3):
        raise CarotidError(f"wall normals must have shape ({wss.shape[1]}, 3), got {normals.shape}")
    length = np.linalg.norm(normals, axis=1)
    if not (np.all(np.isfinite(wss)) and np.all(np.isfinite(normals)) and np.all(length > 0)):
        raise CarotidError("WSS vectors and wall normals must be finite, and the normals non-zero")
    if gradient is not None:
        gradient = np.asarray(gradient, dtype=float)
        if gradient.shape != wss.shape + (3,) or not np.all(np.isfinite(gradient)):
            raise CarotidError(f"the WSS gradient must be finite with shape {wss.shape + (3,)}, got {gradient.shape}")
    return times, wss, normals / length[:, None], gradient


def wall_indices(times, wss, normals, *, tangential_gradient=None) -> dict[str, np.ndarray]:
    """TAWSS, OSI, RRT, ECAP, transWSS and TWSSG at every wall node over one cardiac cycle.

    Parameters
    ----------
    times : array_like, shape (k,)
        Sample times, s, strictly increasing, not necessarily uniform.  They must cover exactly one
        period: T = times[-1] - times[0], with both t_0 and t_0 + T included (for a periodic solution
        the first and last samples coincide; they are not required to).  Integrals in time use the
        trapezoidal rule over these samples.
    wss : array_like, shape (k, n, 3)
        WSS vectors, Pa, at each time and node (tangential to the wall).
    normals : array_like, shape (n, 3)
        Wall normals at the nodes (any length, either sign).
    tangential_gradient : array_like, shape (k, n, 3, 3), optional
        Surface gradient of the WSS vector, ``[..., i, j] = d tau_i / d x_j``, Pa/m.  When given, the
        spatial TWSSG of Lei et al. (1995) is added as ``"TWSSG_spatial"``.

    Returns
    -------
    dict of str to ndarray, each shape (n,)
        ``"TAWSS"`` (Pa), ``"OSI"`` (in [0, 0.5]), ``"RRT"`` (1/Pa), ``"ECAP"`` (1/Pa),
        ``"transWSS"`` (Pa), ``"TWSSG"`` (temporal, Pa/s), and ``"TWSSG_spatial"`` (Pa/m) if asked.

    Notes
    -----
    Guards, all documented values rather than errors:

    * |mean tau| <= 1e-12 TAWSS (a purely reversing WSS; rounding decides the rest): OSI = 0.5,
      RRT = +inf, and transWSS and TWSSG_spatial, which need the mean direction, are NaN.
    * TAWSS = 0 (no shear at all over the cycle): OSI = 0, ECAP = 0, RRT = +inf, transWSS = 0
      (and TWSSG_spatial = 0).
    * Otherwise OSI is clipped to [0, 0.5] against rounding and RRT = 1 / |mean tau| (finite, but large
      where OSI is near 0.5); writers that cannot store inf should cap RRT themselves.

    The temporal TWSSG integrates the derivative of the piecewise-linear interpolant of the samples:
    ``sum_j |tau_{j+1} - tau_j| / T``, the length of the WSS vector's path over the cycle divided by T.
    """
    times, wss, normals, gradient = _check(times, wss, normals, tangential_gradient)
    period = times[-1] - times[0]
    weights = trapezoid_weights(times) / period
    magnitude = np.linalg.norm(wss, axis=2)
    tawss = weights @ magnitude
    mean = np.tensordot(weights, wss, axes=(0, 0))
    mean_norm = np.linalg.norm(mean, axis=1)
    sheared = tawss > 0
    directed = mean_norm > UNDEFINED_DIRECTION * tawss
    ratio = np.divide(mean_norm, tawss, out=np.ones_like(tawss), where=sheared)
    osi = np.where(directed | ~sheared, np.clip(0.5 * (1.0 - ratio), 0.0, 0.5), 0.5)
    with np.errstate(divide="ignore"):
        rrt = np.where(directed, 1.0 / np.where(directed, mean_norm, 1.0), np.inf)
    ecap = np.divide(osi, tawss, out=np.zeros_like(tawss), where=sheared)

    tangent_mean = mean - np.sum(mean * normals, axis=1, keepdims=True) * normals
    tangent_norm = np.linalg.norm(tangent_mean, axis=1, keepdims=True)
    direction = np.divide(tangent_mean, tangent_norm, out=np.zeros_like(mean), where=tangent_norm > 0)
    across = np.cross(normals, direction)
    transwss = weights @ np.abs(np.einsum("knd,nd->kn", wss, across))
    transwss[sheared & ~directed] = np.nan

    result = {"TAWSS": tawss, "OSI": osi, "RRT": rrt, "ECAP": ecap, "transWSS": transwss,
              "TWSSG": np.linalg.norm(np.diff(wss, axis=0), axis=2).sum(axis=0) / period}
    if gradient is not None:
        along = np.einsum("ni,knij,nj->kn", direction, gradient, direction)
        normal_part = np.einsum("ni,knij,nj->kn", across, gradient, across)
        spatial = weights @ np.hypot(along, normal_part)
        spatial[sheared & ~directed] = np.nan
        result["TWSSG_spatial"] = spatial
    return result


def area_fraction(values, areas, threshold: float) -> float:
    """Fraction of the wall area where ``values > threshold``, e.g. the OSI > 0.1 area fraction.

    Parameters
    ----------
    values : array_like, shape (n,)
        Nodal (or cell) index values; NaN counts as not above the threshold.
    areas : array_like, shape (n,)
        Area attached to each node (or cell), any unit, non-negative.
    threshold : float
        Same unit as ``values``.

    Returns
    -------
    float
        In [0, 1].
    """
    values = np.asarray(values, dtype=float)
    areas = np.asarray(areas, dtype=float)
    if values.shape != areas.shape or values.ndim != 1:
        raise CarotidError(f"values and areas must be 1-D arrays of one length, got {values.shape}, {areas.shape}")
    if not np.all(np.isfinite(areas)) or np.any(areas < 0) or areas.sum() <= 0:
        raise CarotidError("areas must be finite, non-negative and not all zero")
    return float(areas[values > threshold].sum() / areas.sum())


def node_areas(points, triangles) -> np.ndarray:
    """Wall area attached to each node of a triangle surface: a third of each adjacent triangle.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Node coordinates (mm, or any length unit).
    triangles : array_like of int, shape (f, 3)

    Returns
    -------
    ndarray, shape (n,)
        Areas in the square of the points' unit.
    """
    points, triangles = np.asarray(points, dtype=float), np.asarray(triangles)
    p = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    return np.bincount(triangles.ravel(), np.repeat(area / 3.0, 3), minlength=len(points))
