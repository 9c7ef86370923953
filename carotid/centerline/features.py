"""Geometric features of the centerlines: lengths, radii, tortuosity, kinks and stenosis degrees.

Every branch's points run with the flow (CCA: inlet to bifurcation; the
others: bifurcation outward), so "distal" is "further along the points".

Stenosis grading, on the inscribed-sphere radius profile r(s) of a branch
(diameters are 2 r; the inscribed sphere measures the narrowest width of a
non-circular section, the quantity angiographic grading approximates):

* the original (healthy) radius at each point is estimated by linear
  interpolation between the widest sections within four median radii
  upstream and downstream of it (the sinus bulb, the recovered distal ICA);
* the lesion is where r(s) falls furthest below that estimate, away from the
  branch ends (one end radius is skipped at each end, where the radius
  reflects the junction or the cut);
* NASCET = 1 - d_min / d_distal, with d_distal the normal distal diameter:
  the median diameter of the branch beyond the point where the radius has
  recovered to 95% of its distal plateau (the median over the distal half of
  what follows the lesion), one radius further on so that the bulb and the
  post-stenotic flank are excluded.  A narrowest section with less than two
  radii of branch beyond it is a taper towards the outlet, not a lesion, and
  is graded 0;
* ECST = 1 - d_min / d_local, with d_local the estimated original diameter
  at the lesion.  A lesion in a wide bulb can have a positive ECST and a zero
  NASCET (its narrowest diameter still exceeds the distal one), as clinically;
* area reduction = 1 - (d_min / d_local)^2 (circular sections).
"""

from __future__ import annotations

import numpy as np

from carotid.centerline.axes import arclength
from carotid.centerline.model import Branch, Centerlines


def branch_features(branch: Branch) -> dict:
    """Length, radii, tortuosity and kink measures of one branch.

    Returns
    -------
    dict
        ``length_mm``, ``chord_mm``, ``tortuosity`` (arc / chord - 1), ``mean_radius_mm``,
        ``min_radius_mm``, ``max_radius_mm``, ``max_bend_deg`` (largest angle between the axis
        directions over the preceding and following mean radius of arc) and ``max_curvature_per_mm``
        (that angle in radians over the mean radius).
    """
    p, r = branch.points, branch.radii
    s = arclength(p)
    chord = float(np.linalg.norm(p[-1] - p[0]))
    out = {"length_mm": float(s[-1]), "chord_mm": chord,
           "tortuosity": float(s[-1] / chord - 1.0) if chord > 0 else 0.0,
           "mean_radius_mm": float(r.mean()), "min_radius_mm": float(r.min()), "max_radius_mm": float(r.max())}
    window = max(float(np.median(r)), 1e-3)
    m = int(np.ceil(window / max(s[-1] / max(len(p) - 1, 1), 1e-9)))
    if len(p) > 2 * m:
        a = p[m:-m] - p[:-2 * m]
        b = p[2 * m:] - p[m:-m]
        cos = np.sum(a * b, axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        out["max_bend_deg"] = float(np.degrees(angle.max()))
        out["max_curvature_per_mm"] = float(angle.max() / window)
    else:
        out["max_bend_deg"] = out["max_curvature_per_mm"] = 0.0
    return out


def local_healthy_radius(s: np.ndarray, r: np.ndarray, reach: float) -> np.ndarray:
    """Estimated original radius at every point of a radius profile.

    Linear interpolation between the widest point within ``reach`` upstream and the widest point within
    ``reach`` downstream (each window includes the point itself, so the estimate is never below ``r``).

    Parameters
    ----------
    s : ndarray, shape (n,)
        Arc length, mm, increasing and about uniformly spaced.
    r : ndarray, shape (n,)
        Radius, mm.
    reach : float
        Window length on each side, mm.

    Returns
    -------
    ndarray, shape (n,)
    """
    n = len(r)
    w = int(np.clip(round(reach / max(float(np.median(np.diff(s))), 1e-9)), 1, n - 1))
    pad = np.full(w, -np.inf)
    index = np.arange(n)
    i = index - w + np.argmax(np.lib.stride_tricks.sliding_window_view(np.r_[pad, r], w + 1), axis=1)
    j = index + np.argmax(np.lib.stride_tricks.sliding_window_view(np.r_[r, pad], w + 1), axis=1)
    span = s[j] - s[i]
    t = np.where(span > 0, (s - s[i]) / np.where(span > 0, span, 1.0), 0.0)
    return r[i] + t * (r[j] - r[i])


def stenosis(branch: Branch, from_end: bool = False) -> dict | None:
    """Grade the most narrowed section of a branch.

    Parameters
    ----------
    branch : Branch
        Points ordered with the flow.
    from_end : bool
        Whether the bifurcation is the branch's last point (the CCA) rather than its first.

    Returns
    -------
    dict or None
        ``location_mm`` (3,), ``arclength_from_bifurcation_mm``, ``min_diameter_mm``,
        ``distal_diameter_mm``, ``local_diameter_mm``, ``nascet``, ``ecst``, ``area_reduction``
        (fractions, 0 for no narrowing), ``distal_reference`` ("distal", or "none" when the narrowest
        section is at the distal end of the branch: a taper, graded 0); None if the branch is too short.
    """
    p, r = branch.points, branch.radii
    s = arclength(p)
    valid = np.flatnonzero((s >= r[0]) & (s <= s[-1] - r[-1]))
    if len(valid) < 5:
        return None
    healthy = local_healthy_radius(s[valid], r[valid], 4.0 * float(np.median(r[valid])))
    pick = int(np.argmax(1.0 - r[valid] / np.maximum(healthy, 1e-9)))
    k, r_local = int(valid[pick]), float(healthy[pick])
    r_min = float(r[k])
    after = valid[valid > k]
    reference = "distal"
    if len(after) >= 5 and s[after[-1]] - s[k] >= 2.0 * r_min:
        plateau = float(np.median(r[after[len(after) // 2:]]))
        recovered = after[r[after] >= 0.95 * plateau]
        start = s[recovered[0]] + plateau if len(recovered) else s[after[0]]
        window = after[s[after] >= start]
        r_distal = float(np.median(r[window if len(window) >= 3 else after[len(after) // 2:]]))
    else:  # the narrowest section ends the measured branch: a taper, no distal normal segment to grade against
        reference = "none"
        r_distal = r_min
    if min(r_distal, r_local) <= 0.0:
        return None
    return {
        "branch": branch.name,
        "location_mm": p[k].tolist(),
        "arclength_from_bifurcation_mm": float(s[-1] - s[k] if from_end else s[k]),
        "min_diameter_mm": 2.0 * r_min,
        "distal_diameter_mm": 2.0 * r_distal,
        "local_diameter_mm": 2.0 * r_local,
        "nascet": max(0.0, 1.0 - r_min / r_distal),
        "ecst": max(0.0, 1.0 - r_min / r_local),
        "area_reduction": max(0.0, 1.0 - (r_min / r_local) ** 2),
        "distal_reference": reference,
    }


def geometry_features(cl: Centerlines) -> dict:
    """The features of all branches, JSON-ready, as written to ``geometry.json``.

    Returns
    -------
    dict
        ``bifurcation_mm`` (or None), ``branches`` (per branch: id, name, features, end points),
        ``stenosis`` (the ICA's grading, else the most severe), ``stenoses`` (every branch, most severe
        first).
    """
    bif = None if not np.all(np.isfinite(cl.bifurcation)) else cl.bifurcation.tolist()
    branches, grades = [], []
    for k, b in enumerate(cl.branches):
        branches.append({"id": k, "name": b.name, **branch_features(b),
                         "start_mm": b.points[0].tolist(), "end_mm": b.points[-1].tolist()})
        g = stenosis(b, from_end=b.name == "CCA")
        if g is not None:
            grades.append(g)
    grades.sort(key=lambda g: (-g["nascet"], -g["ecst"]))
    ica = [g for g in grades if g["branch"] == "ICA"]
    return {"bifurcation_mm": bif, "branches": branches,
            "stenosis": ica[0] if ica else (grades[0] if grades else None), "stenoses": grades}
