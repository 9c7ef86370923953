"""Wall regions from the centerlines (CCA, bulb, ICA, ECA, stenosis) and the wall indices per region.

Every wall point (node, or triangle centroid for the ``Region`` cell array of ``indices.vtp``) takes the
region of the centerline point nearest to it (:func:`carotid.centerline.model.nearest_axis_points`):

* the branch of that point: CCA, ICA, ECA, or "other" for any further branch;
* the ICA from the bifurcation point to the bulb's end is the bulb: where the ICA's original radius
  falls back to within ``BULB_EXCESS`` (10 %) of its reference radius past its widest section
  (:func:`carotid.centerline.features.bifurcation_geometry`, ``bulb_end_mm``; no bulb when the widest
  section does not exceed that);
* the graded lesion (``geometry_features``' ``stenosis``: the ICA's, else the most severe), over its full
  width at half depth (``extent_from_bifurcation_mm``), is the stenosis region when its area reduction is at
  least ``STENOSIS_MIN_AREA_REDUCTION`` and it has a distal reference (not a taper at the branch's end).
  It takes precedence over the bulb and the branch.

Statistics are area-weighted over the wall nodes, each node carrying a third of the area of each triangle
around it (:func:`carotid.flow.indices.node_areas`), as the whole-wall fractions of the report and cohort.csv.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carotid.centerline.axes import arclength
from carotid.centerline.features import BULB_EXCESS
from carotid.centerline.model import Centerlines, nearest_axis_points
from carotid.flow.indices import HIGH_OSI, LOW_TAWSS_PA, area_fraction, node_areas

REGION_NAMES = ("CCA", "bulb", "ICA", "ECA", "stenosis", "other")
"""Region codes of the ``Region`` cell array: the index in this tuple."""

STENOSIS_MIN_AREA_REDUCTION = 0.5
"""Area reduction (against the local original lumen) from which the graded lesion is a region of its own."""

PERCENTILES = (5.0, 95.0)
"""Percentiles of each index per region, %."""

INDEX_UNITS = {"TAWSS": "Pa", "OSI": "", "RRT": "1/Pa", "ECAP": "1/Pa", "transWSS": "Pa", "TWSSG": "Pa/s",
               "TWSSG_spatial": "Pa/m"}
"""Units of the wall indices of :func:`carotid.flow.indices.wall_indices`."""

REGION_INDICES = ("TAWSS", "OSI", "RRT", "ECAP", "transWSS", "TWSSG")
"""The indices of the per-region tables of the report and cohort.csv, in this order."""


def lesion_extent(geometry: dict) -> tuple[str, float, float] | None:
    """The graded lesion that is a region of its own: (branch name, near, far arc length from the bifurcation,
    mm), or None (no grading, area reduction under ``STENOSIS_MIN_AREA_REDUCTION``, or a taper at the branch's
    end).

    Parameters
    ----------
    geometry : dict
        :func:`carotid.centerline.features.geometry_features` of the centerlines.
    """
    grade = geometry.get("stenosis")
    if not grade or grade["area_reduction"] < STENOSIS_MIN_AREA_REDUCTION or grade["distal_reference"] != "distal":
        return None
    near, far = grade["extent_from_bifurcation_mm"]
    return grade["branch"], float(near), float(far)


def wall_regions(points: np.ndarray, cl: Centerlines, geometry: dict) -> np.ndarray:
    """Region code (index in ``REGION_NAMES``) of each wall point.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Wall points, mm, in the centerlines' frame.
    cl : Centerlines
    geometry : dict
        :func:`carotid.centerline.features.geometry_features` of ``cl`` (its ``bifurcation_geometry`` gives the
        bulb's end, its ``stenosis`` the lesion and its extent).

    Returns
    -------
    ndarray of int8, shape (n,)
    """
    branch, index = nearest_axis_points(points, cl.branches)
    along = []  # arc length of every centerline point from the bifurcation, upstream along the CCA
    for b in cl.branches:
        s = arclength(b.points)
        along.append(s[-1] - s if b.name == "CCA" else s)
    sizes = np.array([len(b.points) for b in cl.branches])
    distance = np.concatenate(along)[np.cumsum(sizes)[branch] - sizes[branch] + index]
    name = np.array([b.name for b in cl.branches])[branch]
    region = np.full(len(points), REGION_NAMES.index("other"), dtype=np.int8)
    for branch_name in ("CCA", "ICA", "ECA"):
        region[name == branch_name] = REGION_NAMES.index(branch_name)
    bulb_end = (geometry.get("bifurcation_geometry") or {}).get("bulb_end_mm", 0.0)
    region[(name == "ICA") & (distance <= bulb_end) & (bulb_end > 0)] = REGION_NAMES.index("bulb")
    lesion = lesion_extent(geometry)
    if lesion is not None:
        region[(name == lesion[0]) & (distance >= lesion[1]) & (distance <= lesion[2])] = REGION_NAMES.index("stenosis")
    return region


def weighted_percentiles(values: np.ndarray, weights: np.ndarray, q) -> np.ndarray:
    """Percentiles of a weighted sample: the value below which ``q`` % of the weight lies.

    Each sample stands for its weight spread about its value: the sorted samples sit at the centres of their
    weight intervals on [0, 1], and the percentile is interpolated linearly between them (clamped to the
    smallest and largest value beyond the first and last centre).

    Parameters
    ----------
    values : ndarray, shape (n,)
        Finite values.
    weights : ndarray, shape (n,)
        Positive weights (areas).
    q : array_like, shape (k,)
        Percentiles in [0, 100].

    Returns
    -------
    ndarray, shape (k,)
    """
    order = np.argsort(values)
    v, w = values[order], weights[order]
    centre = (np.cumsum(w) - 0.5 * w) / w.sum()
    return np.interp(np.asarray(q, dtype=float) / 100.0, centre, v)


def region_statistics(indices: dict, areas: np.ndarray, regions: np.ndarray, names=REGION_NAMES) -> dict:
    """Area-weighted statistics of the wall indices per region and over the whole wall.

    Parameters
    ----------
    indices : dict of str to ndarray, shape (n,)
        Nodal wall indices (:func:`carotid.flow.indices.wall_indices`), with at least ``TAWSS`` (Pa) and ``OSI``.
    areas : ndarray, shape (n,)
        Wall area of each node, mm^2.
    regions : ndarray of int, shape (n,)
        Region code of each node (:func:`wall_regions`), an index into ``names``.
    names : sequence of str
        Region names (``REGION_NAMES``).

    Returns
    -------
    dict
        Per region name with wall area, and ``"whole wall"``: ``area_mm2``, ``wall_fraction``; per
        index ``mean``, ``p5`` and ``p95`` over its finite values (RRT is infinite and transWSS undefined where
        the mean WSS vanishes), in the index's unit; ``low_tawss_area_fraction`` (TAWSS < ``LOW_TAWSS_PA``),
        ``high_osi_area_fraction`` (OSI > ``HIGH_OSI``) and ``low_tawss_high_osi_area_fraction`` (both), fractions
        of the region's area.
    """
    tawss, osi = np.asarray(indices["TAWSS"]), np.asarray(indices["OSI"])
    groups = [(name, regions == code) for code, name in enumerate(names)]
    result = {}
    for name, member in [*groups, ("whole wall", np.ones(len(areas), bool))]:
        weight = np.where(member, areas, 0.0)
        if weight.sum() <= 0:
            continue
        entry = {"area_mm2": float(weight.sum()), "wall_fraction": float(weight.sum() / areas.sum())}
        for key, values in indices.items():
            keep = member & np.isfinite(values) & (areas > 0)
            if keep.any():
                v, w = np.asarray(values)[keep], areas[keep]
                low, high = weighted_percentiles(v, w, PERCENTILES)
                entry[key] = {"mean": float(w @ v / w.sum()), "p5": float(low), "p95": float(high)}
        entry["low_tawss_area_fraction"] = area_fraction(-tawss, weight, -LOW_TAWSS_PA)
        entry["high_osi_area_fraction"] = area_fraction(osi, weight, HIGH_OSI)
        entry["low_tawss_high_osi_area_fraction"] = area_fraction(
            ((tawss < LOW_TAWSS_PA) & (osi > HIGH_OSI)).astype(float), weight, 0.5)
        result[name] = entry
    return result


def case_regions(case_dir, points: np.ndarray, triangles: np.ndarray, indices: dict) -> tuple[np.ndarray | None, dict]:
    """The regions of a case's wall and the statistics of its indices there, for ``flow/indices.vtp`` and
    ``flow/summary.json``.

    Parameters
    ----------
    case_dir : path
        Case folder holding ``centerlines.vtp``.
    points : ndarray, shape (n, 3)
        Wall nodes, mm.
    triangles : ndarray of int, shape (f, 3)
        Wall triangles.
    indices : dict of str to ndarray, shape (n,)
        Nodal wall indices.

    Returns
    -------
    cells : ndarray of int8, shape (f,), or None
        Region code of each triangle (by its centroid), the ``Region`` cell array; None without centerlines.
    summary : dict
        ``regions`` (``names``, ``definition``, ``bulb_end_mm``, ``stenosis_extent_mm`` or None, and
        ``statistics``: :func:`region_statistics` over the nodes) and ``bifurcation_geometry``
        (:func:`carotid.centerline.features.bifurcation_geometry`); empty without centerlines.
    """
    from carotid.centerline import geometry_features, read_centerlines

    path = Path(case_dir) / "centerlines.vtp"
    if not path.exists():
        return None, {}
    cl = read_centerlines(path)
    geometry = geometry_features(cl)
    nodes = wall_regions(points, cl, geometry)
    cells = wall_regions(points[triangles].mean(axis=1), cl, geometry)
    lesion = lesion_extent(geometry)
    return cells, {"regions": {
        "names": list(REGION_NAMES),
        "definition": "the branch of the nearest centerline point; bulb: the ICA from the bifurcation point to "
                      f"bulb_end_mm (where its original radius falls back to within {100 * BULB_EXCESS:g} % of its "
                      "reference radius); stenosis: the graded lesion's full width at half depth along its branch "
                      f"(stenosis_extent_mm from the bifurcation) when its area reduction is at least "
                      f"{STENOSIS_MIN_AREA_REDUCTION:g}; statistics area-weighted over the wall nodes (a third of "
                      "each adjacent triangle), percentiles of that area distribution",
        "bulb_end_mm": (geometry["bifurcation_geometry"] or {}).get("bulb_end_mm"),
        "stenosis_extent_mm": None if lesion is None else {"branch": lesion[0], "from_mm": lesion[1],
                                                           "to_mm": lesion[2]},
        "statistics": region_statistics(indices, node_areas(points, triangles), nodes)},
        "bifurcation_geometry": geometry["bifurcation_geometry"]}
