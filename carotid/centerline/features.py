"""Geometric features of the centerlines: lengths, radii, tortuosity, kinks and stenosis degrees.

Every branch's points run with the flow (CCA: inlet to bifurcation; the
others: bifurcation outward), so "distal" is "further along the points".

Stenosis grading, on two radius profiles of a branch: half the narrowest
diameter r(s) of each section (chords through the axis) for the residual lumen, and the median
radius m(s) of each section for the vessel's own size (both robust to the
wall's roughness, ``axes.section_profile``; the inscribed-sphere radius
stands for both on centerlines that carry neither).  Diameters are twice
the radii; the narrowest width is the quantity angiographic grading
approximates, and a round vessel's diameter is its median one:

* the original (healthy) radius at each point is estimated by linear
  interpolation between the widest sections of m(s) within four median radii
  upstream and downstream of it (the sinus bulb, the recovered distal ICA);
* the lesion is where r(s) falls furthest below that estimate, away from the
  branch ends (one end radius, and at least the branch's median radius, is
  skipped at each end, where the radius reflects the junction or the cut);
* NASCET = 1 - d_min / d_distal, with d_min = 2 r at the lesion and d_distal
  the normal distal diameter: the median of 2 m(s) over the branch beyond the
  point where m(s) has recovered to 95% of its distal plateau (the median
  over the distal half of what follows the lesion), one radius further on so
  that the bulb and the post-stenotic flank are excluded.  A narrowest
  section with less than two radii of branch beyond it is a taper towards the
  outlet, not a lesion, and is graded 0;
* ECST = 1 - d_min / d_local, with d_local the estimated original diameter
  at the lesion.  A lesion in a wide bulb can have a positive ECST and a zero
  NASCET (its narrowest diameter still exceeds the distal one), as clinically;
* area reduction = 1 - (d_min / d_local)^2 (circular sections);
* the lesion's extent is its full width at half depth: the stretch around the
  narrowest section where the narrowing 1 - r / r_healthy is at least half its
  value there.

The bifurcation geometry (:func:`bifurcation_geometry`) follows the centerline
definitions of the carotid geometric-risk studies; its landmarks and formulas
are stated there.
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


def grading_profiles(branch: Branch) -> tuple[np.ndarray, np.ndarray]:
    """The two radius profiles of the stenosis grading: half the narrowest diameter and the median radius (n,),
    mm.

    ``branch.narrow_radii`` and ``branch.median_radii`` where the centerlines carry them, else the inscribed
    radius for both.
    """
    narrow = branch.narrow_radii if branch.narrow_radii is not None else branch.radii
    median = branch.median_radii if branch.median_radii is not None else branch.radii
    return np.asarray(narrow, float), np.asarray(median, float)


def end_skips(radii: np.ndarray) -> tuple[float, float]:
    """Arc lengths (mm) to skip at the first and the last point of a branch: the radius there, and at least
    the branch's median radius.

    The radius at an end reflects the junction or the cut, not the vessel.  Where the image border cuts a
    curving vessel, the last points of the axis, continued straight to the border
    (``axes.straighten_border_end``), can lie off the lumen and read a radius near zero (0.14 mm on a 2.5 mm
    ICA): skipping only that would leave the cut's narrowed sections to be graded as the lesion.  The median radius covers an oblique cut
    up to 45 degrees, whose sections within ``r tan(angle)`` of the border are incomplete.

    Sections not measured (NaN: cut by the image border) are left out: the ends are the first and the last
    measured ones.

    Parameters
    ----------
    radii : ndarray, shape (n,)
        Radius profile along the branch, mm; at least one finite.

    Returns
    -------
    (head, tail) : float
    """
    measured = np.asarray(radii, float)[np.isfinite(radii)]
    body = float(np.median(measured))
    return max(float(measured[0]), body), max(float(measured[-1]), body)


def healthy_profile(branch: Branch,
                    radii: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Arc length, the points away from the branch ends, and the estimated original radius there.

    One end radius is skipped at each end (:func:`end_skips`), and the sections not measured (NaN radius:
    cut by the image border) are left out; the original radius is :func:`local_healthy_radius` with a reach
    of four median radii.

    Parameters
    ----------
    branch : Branch
        Points ordered with the flow.
    radii : ndarray, shape (n,), optional
        Radius profile to estimate from, mm; default ``branch.radii``.

    Returns
    -------
    (s, valid, healthy) or None
        ``s`` (n,) arc length from the branch's first point, mm; ``valid`` (m,) indices of the measured
        points away from the ends; ``healthy`` (m,) the original radius at those points, mm.  None when fewer
        than five such points remain.
    """
    r = branch.radii if radii is None else np.asarray(radii, float)
    s = arclength(branch.points)
    if not np.any(np.isfinite(r)):
        return None
    head, tail = end_skips(r)
    valid = np.flatnonzero((s >= head) & (s <= s[-1] - tail) & np.isfinite(r))
    if len(valid) < 5:
        return None
    return s, valid, local_healthy_radius(s[valid], r[valid], 4.0 * float(np.median(r[valid])))


def stenosis(branch: Branch, from_end: bool = False) -> dict | None:
    """Grade the most narrowed section of a branch.

    Parameters
    ----------
    branch : Branch
        Points ordered with the flow; graded on :func:`grading_profiles`.
    from_end : bool
        Whether the bifurcation is the branch's last point (the CCA) rather than its first.

    Returns
    -------
    dict or None
        ``location_mm`` (3,), ``arclength_from_bifurcation_mm``, ``min_diameter_mm``,
        ``distal_diameter_mm``, ``local_diameter_mm``, ``nascet``, ``ecst``, ``area_reduction``
        (fractions, 0 for no narrowing), ``distal_reference`` ("distal", or "none" when the narrowest
        section is at the distal end of the branch: a taper, graded 0), ``extent_from_bifurcation_mm``
        (the lesion's full width at half depth, [near, far] arc lengths from the bifurcation, mm); None if
        the branch is too short.
    """
    narrow, median = grading_profiles(branch)
    profile = healthy_profile(branch, median)
    if profile is None:
        return None
    s, valid, healthy = profile
    p = branch.points
    depth = 1.0 - narrow[valid] / np.maximum(healthy, 1e-9)
    pick = int(np.argmax(depth))
    k, r_local = int(valid[pick]), float(healthy[pick])
    r_min = float(narrow[k])
    outside = np.flatnonzero((depth < 0.5 * depth[pick]) | ((depth[pick] <= 0) & (np.arange(len(valid)) != pick)))
    first = int(outside[outside < pick].max() + 1) if np.any(outside < pick) else 0
    last = int(outside[outside > pick].min() - 1) if np.any(outside > pick) else len(valid) - 1
    extent = s[valid[[first, last]]]
    after = valid[valid > k]
    reference = "distal"
    if len(after) >= 5 and s[after[-1]] - s[k] >= 2.0 * r_min:
        plateau = float(np.median(median[after[len(after) // 2:]]))
        recovered = after[median[after] >= 0.95 * plateau]
        start = s[recovered[0]] + plateau if len(recovered) else s[after[0]]
        window = after[s[after] >= start]
        r_distal = float(np.median(median[window if len(window) >= 3 else after[len(after) // 2:]]))
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
        "extent_from_bifurcation_mm": sorted((s[-1] - extent if from_end else extent).tolist()),
    }


# Landmarks of the bifurcation geometry, in CCA radii R of arc length from the bifurcation point (see
# bifurcation_geometry).
CCA_WINDOW = (2.0, 6.0)
"""Upstream along the CCA (1 to 3 CCA diameters below the bifurcation point): its diameter, area and direction."""
DIRECTION_WINDOW = (2.0, 6.0)
"""Downstream along the ICA and ECA (1 to 3 CCA diameters): their directions."""
DAUGHTER_START = 4.0
"""Downstream along the ICA and ECA from 2 CCA diameters to their distal end (less one end radius): their
reference diameter and area, beyond the junction and, in a normal ICA, beyond most of the bulb."""
BULB_WINDOW = (1.0, 6.0)
"""Downstream along the ICA (0.5 to 3 CCA diameters): where the widest section of the bulb is looked for."""
BULB_EXCESS = 0.1
"""The bulb is where the ICA radius exceeds its reference radius by more than this fraction."""


def _window(s: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Indices (m,) of the arc lengths ``s`` (n,) within [lo, hi] mm; ValueError when fewer than 3."""
    inside = np.flatnonzero((s >= lo) & (s <= hi))
    if len(inside) < 3:
        raise ValueError(f"fewer than 3 centerline points between {lo:.3g} and {hi:.3g} mm from the bifurcation")
    return inside


def _direction(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Unit principal axis (3,) of ``points`` (m, 3), pointing away from ``origin`` (3,)."""
    centred = points - points.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    return axis if axis @ (points.mean(axis=0) - origin) >= 0 else -axis


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two unit vectors (3,), degrees."""
    return float(np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))))


def bifurcation_geometry(cl: Centerlines) -> dict | None:
    """Bifurcation angle, area ratios, bulb size, tortuosity and planarity of a carotid bifurcation.

    The quantities of the carotid geometric-risk studies: Thomas et al. 2005 (Stroke 36:2450, "Variation in
    the carotid bifurcation geometry of young versus older adults": bifurcation angle, ICA angle, ICA/CCA
    diameter ratio and (ICA + ECA)/CCA "bifurcation area ratio", planarity, tortuosity as arc length over chord
    minus one), Lee et al. 2008 (Stroke 39:2341, "Geometry of the carotid bifurcation predicts its exposure to
    disturbed flow": bulb size as the maximum ICA/CCA diameter ratio, planarity, tortuosity) and Bijari et al.
    2012 (J Biomech 45:1632, which revisits them).  Like those studies, the landmarks are placed along the
    centerlines (VMTK-style, maximal inscribed sphere radii) in units of the CCA radius from the bifurcation
    point.  The offsets are this function's own choice, stated here; the papers' landmarks differ in detail, so
    values compare exactly between cases of this package and approximately with the published ones.  With s the
    arc length from the bifurcation point along each branch (upstream along the CCA), r(s) the median section
    radius (the median of the ray lengths to the wall in the normal plane, the radius the stenosis grading
    takes for the vessel's size, :func:`grading_profiles`; the maximal inscribed sphere radius when the
    centerlines carry no section profile), which a rough segmented wall does not bias the way it biases the
    inscribed sphere, and A(s) the lumen section area normal to the axis (``Branch.areas``, or pi r^2 when the
    centerlines carry none):

    * R, the CCA radius: the median of r over s in [2, 6] rho, 1 to 3 diameters below the bifurcation
      point, with rho the median r of the whole CCA (the first pass that places the window).  D_CCA = 2 R;
      A_CCA is the median of A over s in [2, 6] R (``CCA_WINDOW``).
    * Directions: the principal axis (least-squares line) of each branch's points over s in [2, 6] R
      (``CCA_WINDOW``, ``DIRECTION_WINDOW``), pointing away from the bifurcation; the first CCA diameter
      is left out, where the centerlines curve into one another.
    * Bifurcation angle: between the ICA and ECA directions; ICA (ECA) angle: between the ICA (ECA)
      direction and the CCA's continuation (minus the CCA direction); degrees.
    * Planarity of each branch: the angle between its direction and the plane spanned by the other two
      branches' directions, degrees; 0 for all three when the bifurcation lies in one plane.
    * A_ICA, A_ECA: the median of A over s from 4 R (2 CCA diameters, ``DAUGHTER_START``) to one end radius
      before the branch's end; ICA/CCA area ratio A_ICA / A_CCA; bifurcation area ratio
      (A_ICA + A_ECA) / A_CCA.  Their diameters are twice the median of r over the same stretch.
    * Bulb: the maximum ICA diameter 2 max r over s in [1, 6] R (``BULB_WINDOW``; the section at the
      bifurcation point itself spans the junction), and its ratio to D_CCA.  The bulb ends where,
      past that widest section, the ICA's original radius (:func:`local_healthy_radius`, which bridges a
      stenosis in the bulb) falls to (1 + ``BULB_EXCESS``) times the ICA's reference radius (the median r
      of its reference stretch above); 0 when the widest section does not exceed that.
    * Tortuosity of each branch: arc length over chord minus one over the whole branch
      (:func:`branch_features`).

    Sections cut by the image border (NaN ``r`` and ``A``, ``axes.section_radii``) are left out of every
    median and maximum.

    Parameters
    ----------
    cl : Centerlines
        With branches named CCA, ICA and ECA; the CCA runs to the bifurcation, the others from it.

    Returns
    -------
    dict or None
        ``cca_diameter_mm``, ``cca_area_mm2``, ``ica_diameter_mm``, ``ica_area_mm2``, ``eca_diameter_mm``,
        ``eca_area_mm2``, ``ica_cca_area_ratio``, ``bifurcation_area_ratio``, ``bifurcation_angle_deg``,
        ``ica_angle_deg``, ``eca_angle_deg``, ``bulb_max_diameter_mm``, ``bulb_diameter_ratio``,
        ``bulb_end_mm`` (arc length from the bifurcation point along the ICA), and ``branches``: per branch
        name ``tortuosity`` and ``planarity_deg``.  None without a CCA, ICA and ECA; ``{"reason": text}``
        when a branch is too short for its landmarks.
    """
    names = [b.name for b in cl.branches]
    if not {"CCA", "ICA", "ECA"} <= set(names):
        return None
    cca, ica, eca = cl.branch("CCA"), cl.branch("ICA"), cl.branch("ECA")
    s_cca = arclength(cca.points)
    s_cca = s_cca[-1] - s_cca  # upstream from the bifurcation
    s_ica, s_eca = arclength(ica.points), arclength(eca.points)

    def area(branch: Branch) -> np.ndarray:
        return branch.areas if branch.areas is not None else np.pi * branch.radii ** 2

    radii = {b.name: grading_profiles(b)[1] for b in (cca, ica, eca)}  # median section radius r(s)
    try:
        rho = float(np.nanmedian(radii["CCA"]))
        first = _window(s_cca, CCA_WINDOW[0] * rho, CCA_WINDOW[1] * rho)
        radius = float(np.nanmedian(radii["CCA"][first]))
        in_cca = _window(s_cca, CCA_WINDOW[0] * radius, CCA_WINDOW[1] * radius)
        directions, reference = {}, {}
        for b, s in ((ica, s_ica), (eca, s_eca)):
            window = _window(s, DIRECTION_WINDOW[0] * radius, DIRECTION_WINDOW[1] * radius)
            directions[b.name] = _direction(b.points[window], b.points[0])
            reference[b.name] = _window(s, DAUGHTER_START * radius, s[-1] - end_skips(radii[b.name])[1])
        in_bulb = _window(s_ica, BULB_WINDOW[0] * radius, BULB_WINDOW[1] * radius)
        widest = int(in_bulb[np.nanargmax(radii["ICA"][in_bulb])])
    except ValueError as exc:
        return {"reason": str(exc)}
    directions["CCA"] = _direction(cca.points[in_cca], cca.points[-1])
    a_cca = float(np.nanmedian(area(cca)[in_cca]))
    a_ica, a_eca = (float(np.nanmedian(area(b)[reference[b.name]])) for b in (ica, eca))
    r_ica = float(np.nanmedian(radii["ICA"][reference["ICA"]]))
    bulb_end = 0.0
    threshold = (1.0 + BULB_EXCESS) * r_ica
    profile = healthy_profile(ica, radii["ICA"])
    if radii["ICA"][widest] > threshold and profile is not None:
        s, valid, healthy = profile
        fallen = valid[(valid > widest) & (healthy <= threshold)]
        bulb_end = float(s[fallen[0]] if len(fallen) else s[valid[-1]])
    planarity = {}
    for name, others in (("CCA", ("ICA", "ECA")), ("ICA", ("CCA", "ECA")), ("ECA", ("CCA", "ICA"))):
        normal = np.cross(directions[others[0]], directions[others[1]])
        planarity[name] = float(np.degrees(np.arcsin(min(abs(directions[name] @ normal) /
                                                         np.linalg.norm(normal), 1.0))))
    return {
        "cca_diameter_mm": 2.0 * radius, "cca_area_mm2": a_cca,
        "ica_diameter_mm": 2.0 * r_ica, "ica_area_mm2": a_ica,
        "eca_diameter_mm": 2.0 * float(np.nanmedian(radii["ECA"][reference["ECA"]])), "eca_area_mm2": a_eca,
        "ica_cca_area_ratio": a_ica / a_cca, "bifurcation_area_ratio": (a_ica + a_eca) / a_cca,
        "bifurcation_angle_deg": _angle_deg(directions["ICA"], directions["ECA"]),
        "ica_angle_deg": _angle_deg(directions["ICA"], -directions["CCA"]),
        "eca_angle_deg": _angle_deg(directions["ECA"], -directions["CCA"]),
        "bulb_max_diameter_mm": 2.0 * float(radii["ICA"][widest]),
        "bulb_diameter_ratio": float(radii["ICA"][widest]) / radius,
        "bulb_end_mm": bulb_end,
        "branches": {b.name: {"tortuosity": branch_features(b)["tortuosity"], "planarity_deg": planarity[b.name]}
                     for b in (cca, ica, eca)},
    }


def geometry_features(cl: Centerlines) -> dict:
    """The features of all branches, JSON-ready, as written to ``geometry.json``.

    Returns
    -------
    dict
        ``bifurcation_mm`` (or None), ``branches`` (per branch: id, name, features, end points),
        ``stenosis`` (the ICA's grading, else the most severe), ``stenoses`` (every branch, most severe
        first), ``bifurcation_geometry`` (:func:`bifurcation_geometry`).
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
            "stenosis": ica[0] if ica else (grades[0] if grades else None), "stenoses": grades,
            "bifurcation_geometry": bifurcation_geometry(cl)}
