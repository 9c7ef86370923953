"""Bifurcation geometry and wall regions against an analytic bifurcation; region statistics against known
distributions; the regions of a simulated case in indices.vtp, summary.json, cohort.csv and the report."""

import json
import re

import numpy as np
import pytest

from carotid.centerline import Branch, Centerlines
from carotid.centerline.features import bifurcation_geometry, geometry_features
from carotid.flow.regions import REGION_NAMES, region_statistics, wall_regions, weighted_percentiles

# The analytic bifurcation (mm, degrees): CCA radius, ICA and ECA radii beyond the bulb, the section area of each
# branch over pi r^2 (non-circular sections: the area ratios must use the areas, the diameters the radii), the
# angles of the ICA and ECA from the CCA's continuation, the bulb's peak excess over the ICA radius, and the ICA
# stenosis (diameter reduction, centre and half-width along the ICA).
R_CCA, R_ICA, R_ECA = 3.0, 2.4, 1.8
AREA_FACTOR = {"CCA": 1.05, "ICA": 1.08, "ECA": 1.0}
ALPHA_ICA, ALPHA_ECA = 25.0, 30.0
BULB = 0.4  # the ICA radius rises to (1 + BULB) R_ICA, a raised cosine centred 2 R_CCA with half-width 1.5 R_CCA
STENOSIS = (0.5, 30.0, 3.0)
CCA_STRAIGHT, CCA_BEND = 30.0, 40.0  # the CCA is straight for 30 mm below the bifurcation, bent 40 degrees beyond
STEP = 0.05


def raised_cosine(s, centre, half_width):
    return np.where(np.abs(s - centre) < half_width, 0.5 * (1.0 + np.cos(np.pi * (s - centre) / half_width)), 0.0)


def bent_axis(start, direction, bend, straight, arc_radius, arc_deg):
    """Points (n, 3) every STEP mm: ``straight`` mm along ``direction``, then a circular arc of ``arc_radius``
    through ``arc_deg`` turning towards ``bend`` (a unit vector normal to ``direction``); and the arc length."""
    length = straight + arc_radius * np.radians(arc_deg)
    s = np.linspace(0.0, length, int(round(length / STEP)) + 1)
    phi = np.clip(s - straight, 0.0, None) / arc_radius
    along = np.minimum(s, straight) + arc_radius * np.sin(phi)
    across = arc_radius * (1.0 - np.cos(phi))
    return start + along[:, None] * direction + across[:, None] * bend, s


def tortuosity(straight, arc_radius, arc_deg):
    """Arc length over chord minus one of a straight segment followed by a circular arc."""
    theta = np.radians(arc_deg)
    chord = np.hypot(straight + arc_radius * np.sin(theta), arc_radius * (1.0 - np.cos(theta)))
    return (straight + arc_radius * theta) / chord - 1.0


def analytic_bifurcation(beta_deg):
    """Centerlines of a bifurcation whose ECA leaves the CCA-ICA plane by ``beta_deg``, in a rotated frame, and
    its directions in that frame (e1: the CCA's continuation, e2: towards the ICA in the CCA-ICA plane, e3)."""
    rotation = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    e1, e2, e3 = rotation.T
    bif = np.array([4.0, -7.0, 20.0])
    a_i, a_e, beta = np.radians([ALPHA_ICA, ALPHA_ECA, beta_deg])
    v_ica = np.cos(a_i) * e1 + np.sin(a_i) * e2
    v_eca = np.cos(beta) * (np.cos(a_e) * e1 - np.sin(a_e) * e2) + np.sin(beta) * e3
    cca_points, s_cca = bent_axis(bif, -e1, e3, CCA_STRAIGHT, 15.0, CCA_BEND)  # from the bifurcation down
    cca_points = cca_points[::-1]  # with the flow
    ica_points, s_ica = bent_axis(bif, v_ica, e3, 40.0, 15.0, 60.0)
    eca_points, s_eca = bent_axis(bif, v_eca, np.cross(v_eca, e3) / np.linalg.norm(np.cross(v_eca, e3)), 20.0, 10.0,
                                  45.0)
    depth, centre, half = STENOSIS
    r_ica = R_ICA * (1.0 + BULB * raised_cosine(s_ica, 2.0 * R_CCA, 1.5 * R_CCA)
                     - depth * raised_cosine(s_ica, centre, half))
    r_cca = np.where(s_cca > CCA_STRAIGHT, 1.2 * R_CCA, R_CCA)[::-1]  # wider where it bends, near the inlet
    branches = [Branch("CCA", cca_points, r_cca), Branch("ICA", ica_points, r_ica),
                Branch("ECA", eca_points, np.full(len(eca_points), R_ECA))]
    for b in branches:
        b.areas = AREA_FACTOR[b.name] * np.pi * b.radii ** 2
    return Centerlines(branches, bif), (e1, v_ica, v_eca)


@pytest.mark.parametrize("beta", [0.0, 20.0])
def test_geometry_of_an_analytic_bifurcation(beta):
    """Angles to 1 degree, area and diameter ratios and tortuosities to 2 % (Thomas et al. 2005 quantities)."""
    cl, _ = analytic_bifurcation(beta)
    g = bifurcation_geometry(cl)
    a_i, a_e, b = np.radians([ALPHA_ICA, ALPHA_ECA, beta])
    # the ICA and ECA directions in the (e1, e2, e3) frame: (cos a_i, sin a_i, 0) and
    # cos b (cos a_e, -sin a_e, 0) + sin b (0, 0, 1)
    expected_angles = {
        "bifurcation_angle_deg": np.arccos(np.cos(b) * np.cos(a_i + a_e)),
        "ica_angle_deg": a_i,
        "eca_angle_deg": np.arccos(np.cos(b) * np.cos(a_e))}
    for key, value in expected_angles.items():
        assert g[key] == pytest.approx(np.degrees(value), abs=1.0), key
    expected_planarity = {
        "ECA": b,  # out of the CCA-ICA plane by construction
        "ICA": np.arcsin(np.sin(a_i) * np.sin(b) / np.hypot(np.sin(b), np.cos(b) * np.sin(a_e))),
        "CCA": np.arcsin(np.sin(a_i) * np.sin(b) / np.hypot(np.sin(b), np.cos(b) * np.sin(a_i + a_e)))}
    for name, value in expected_planarity.items():
        assert g["branches"][name]["planarity_deg"] == pytest.approx(np.degrees(value), abs=1.0), name
    area = {name: AREA_FACTOR[name] * r ** 2 for name, r in (("CCA", R_CCA), ("ICA", R_ICA), ("ECA", R_ECA))}
    assert g["ica_cca_area_ratio"] == pytest.approx(area["ICA"] / area["CCA"], rel=0.02)
    assert g["bifurcation_area_ratio"] == pytest.approx((area["ICA"] + area["ECA"]) / area["CCA"], rel=0.02)
    assert g["cca_diameter_mm"] == pytest.approx(2 * R_CCA, rel=0.02)
    assert g["ica_diameter_mm"] == pytest.approx(2 * R_ICA, rel=0.02)
    assert g["bulb_diameter_ratio"] == pytest.approx((1 + BULB) * R_ICA / R_CCA, rel=0.02)
    # the bulb ends where 1 + BULB cos-bump = 1.1, past its peak at 2 R_CCA
    bulb_end = 2 * R_CCA + 1.5 * R_CCA / np.pi * np.arccos(2 * 0.1 / BULB - 1)
    assert g["bulb_end_mm"] == pytest.approx(bulb_end, abs=0.1)
    assert g["branches"]["CCA"]["tortuosity"] == pytest.approx(tortuosity(CCA_STRAIGHT, 15.0, CCA_BEND), rel=0.02)
    assert g["branches"]["ICA"]["tortuosity"] == pytest.approx(tortuosity(40.0, 15.0, 60.0), rel=0.02)
    assert g["branches"]["ECA"]["tortuosity"] == pytest.approx(tortuosity(20.0, 10.0, 45.0), rel=0.02)


@pytest.mark.parametrize("roughness", [0.0, 0.2])
def test_geometry_of_a_tube_bifurcation_through_the_centerline_stage(roughness):
    """A union of capsules (radii 3, 2.4, 1.8 mm; ICA 25 degrees, ECA 30 degrees from the CCA's continuation and
    20 degrees out of the CCA-ICA plane) as a level set, through compute_centerlines: the same angles to 1 degree,
    area and diameter ratios to 2 %, no bulb.  With a wall rough by +-``roughness`` mm (eight lobes around, a
    2.5 mm wavelength along each axis), as a segmented wall is, the diameters still hold to 2 %: they are
    medians of the section rays, not the inscribed sphere, which touches the deepest dents (mutation: the
    inscribed radii read the CCA over 4 % narrow)."""
    from carotid.centerline import compute_centerlines
    from carotid.io import Volume

    vol = Volume(np.zeros((120, 80, 80), np.float32), (0.4, 0.4, 0.4), (-16.0, -16.0, 0.0))
    xyz = vol.index_to_world(np.indices(vol.array.shape).reshape(3, -1).T)
    e1, e2, e3 = np.eye(3)[[2, 1, 0]]
    a_i, a_e, b = np.radians([ALPHA_ICA, ALPHA_ECA, 20.0])
    v_ica = np.cos(a_i) * e1 + np.sin(a_i) * e2
    v_eca = np.cos(b) * (np.cos(a_e) * e1 - np.sin(a_e) * e2) + np.sin(b) * e3
    bif = np.array([0.0, 0.0, 22.0])

    def capsule(start, end, radius):
        axis = (end - start) / np.linalg.norm(end - start)
        u = np.cross(axis, e3 if abs(axis @ e3) < 0.9 else e2)
        u /= np.linalg.norm(u)
        d = xyz - start
        along = d @ axis
        wall = radius + roughness * np.sin(8.0 * np.arctan2(d @ np.cross(axis, u), d @ u)) * np.sin(
            2.0 * np.pi * along / 2.5)
        t = np.clip(along / np.linalg.norm(end - start), 0.0, 1.0)
        return np.linalg.norm(d - t[:, None] * (end - start), axis=1) - wall

    sdf = np.minimum.reduce([capsule(bif - 40 * e1, bif, R_CCA), capsule(bif, bif + 60 * v_ica, R_ICA),
                             capsule(bif, bif + 60 * v_eca, R_ECA)])
    cl = compute_centerlines(vol.with_array(sdf.reshape(vol.array.shape).astype(np.float32)))
    g = bifurcation_geometry(cl)
    assert g["bifurcation_angle_deg"] == pytest.approx(np.degrees(np.arccos(np.cos(b) * np.cos(a_i + a_e))), abs=1.0)
    assert g["ica_angle_deg"] == pytest.approx(ALPHA_ICA, abs=1.0)
    assert g["eca_angle_deg"] == pytest.approx(np.degrees(np.arccos(np.cos(b) * np.cos(a_e))), abs=1.0)
    assert g["branches"]["ECA"]["planarity_deg"] == pytest.approx(20.0, abs=1.0)
    assert g["branches"]["ICA"]["planarity_deg"] == pytest.approx(np.degrees(np.arcsin(
        np.sin(a_i) * np.sin(b) / np.hypot(np.sin(b), np.cos(b) * np.sin(a_e)))), abs=1.0)
    assert g["ica_cca_area_ratio"] == pytest.approx(R_ICA ** 2 / R_CCA ** 2, rel=0.02)
    assert g["bifurcation_area_ratio"] == pytest.approx((R_ICA ** 2 + R_ECA ** 2) / R_CCA ** 2, rel=0.02)
    assert g["cca_diameter_mm"] == pytest.approx(2 * R_CCA, rel=0.02)
    assert g["ica_diameter_mm"] == pytest.approx(2 * R_ICA, rel=0.02)
    assert g["eca_diameter_mm"] == pytest.approx(2 * R_ECA, rel=0.02)
    assert g["bulb_diameter_ratio"] == pytest.approx(R_ICA / R_CCA, rel=0.02) and g["bulb_end_mm"] == 0.0
    assert all(branch["tortuosity"] < 0.005 for branch in g["branches"].values())
    if roughness:
        for b in cl.branches:
            b.median_radii = b.narrow_radii = None
        assert bifurcation_geometry(cl)["cca_diameter_mm"] < 0.96 * 2 * R_CCA


def test_wall_regions_of_an_analytic_bifurcation():
    """Wall points on each branch's tube fall in the CCA, the bulb (to its end), the ICA, the stenosis (its full
    width at half depth) and the ECA, by their arc length along the branch."""
    cl, (e1, v_ica, v_eca) = analytic_bifurcation(0.0)
    geometry = geometry_features(cl)
    bulb_end = geometry["bifurcation_geometry"]["bulb_end_mm"]
    depth, centre, half = STENOSIS
    near, far = centre - half / 2, centre + half / 2  # the raised cosine is at half depth at +- half / 2
    assert geometry["stenosis"]["extent_from_bifurcation_mm"] == pytest.approx([near, far], abs=0.1)
    points, expected = [], []
    ring = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    for b in cl.branches:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(b.points, axis=0), axis=1))])
        s = s[-1] - s if b.name == "CCA" else s
        tangent = np.gradient(b.points, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        other = v_eca if b.name == "ICA" else v_ica  # the ring's half away from the other daughter
        u = np.cross(tangent, np.cross(other, tangent))
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        w = np.cross(tangent, u)
        angle = ring if b.name == "CCA" else ring[(ring > np.pi / 2) & (ring < 3 * np.pi / 2)]
        keep = (s > 2 * R_CCA) if b.name != "ICA" else (s > 1.0)
        offsets = b.radii[keep, None, None] * (np.cos(angle)[None, :, None] * u[keep, None] +
                                               np.sin(angle)[None, :, None] * w[keep, None])
        points.append((b.points[keep, None] + offsets).reshape(-1, 3))
        where = np.repeat(s[keep], len(angle))
        if b.name == "ICA":
            label = np.where(where <= bulb_end, "bulb", np.where((where >= near) & (where <= far), "stenosis", "ICA"))
            clear = np.min(np.abs(where[:, None] - np.array([bulb_end, near, far])), axis=1) > 0.5
            label = np.where(clear, label, "")
        else:
            label = np.full(len(where), b.name)
        expected.append(label)
    points, expected = np.concatenate(points), np.concatenate(expected)
    found = np.array(REGION_NAMES)[wall_regions(points, cl, geometry)]
    checked = expected != ""
    assert np.all(found[checked] == expected[checked])
    assert set(expected[checked]) == {"CCA", "bulb", "ICA", "stenosis", "ECA"}


def test_mild_narrowing_and_no_bulb_make_no_regions():
    """Under 50 % area reduction there is no stenosis region; an ICA without widening has no bulb."""
    cl, _ = analytic_bifurcation(0.0)
    ica = cl.branch("ICA")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ica.points, axis=0), axis=1))])
    ica.radii = R_ICA * (1.0 - 0.25 * raised_cosine(s, 30.0, 3.0))  # area reduction 44 %, no bulb
    ica.areas = np.pi * ica.radii ** 2
    geometry = geometry_features(cl)
    assert geometry["bifurcation_geometry"]["bulb_end_mm"] == 0.0
    assert geometry["stenosis"]["area_reduction"] == pytest.approx(1 - 0.75 ** 2, abs=0.01)
    found = np.array(REGION_NAMES)[wall_regions(ica.points[s > 2 * R_CCA], cl, geometry)]
    assert set(found) == {"ICA"}


def test_a_cca_lesion_is_placed_from_the_bifurcation():
    """Without an ICA the most severe grading is the region: a CCA lesion 15 mm below the bifurcation (the CCA's
    last point) with its half-depth width of 4 mm."""
    s = np.linspace(0.0, 40.0, 801)
    radii = 3.0 - 1.8 * raised_cosine(s, 25.0, 4.0)
    cl = Centerlines([Branch("CCA", np.stack([0 * s, 0 * s, s], axis=1), radii)], np.array([0.0, 0.0, 40.0]))
    geometry = geometry_features(cl)
    found = np.array(REGION_NAMES)[wall_regions(cl.branches[0].points, cl, geometry)]
    assert set(found[np.abs(s - 25.0) < 1.5]) == {"stenosis"}
    assert set(found[np.abs(s - 25.0) > 2.5]) == {"CCA"}


def test_weighted_percentiles_match_the_repeated_sample():
    """Integer weights are repeated samples: the percentiles of the weighted sample are those of the repeated
    one (to its own interpolation); equal weights at (i + 0.5) / n put the q-th percentile at q / 100."""
    rng = np.random.default_rng(1)
    values, weights = rng.normal(size=20000), rng.integers(1, 6, 20000)
    repeated = np.repeat(values, weights)
    for q in (5.0, 50.0, 95.0):
        assert weighted_percentiles(values, weights.astype(float), [q])[0] == pytest.approx(
            np.percentile(repeated, q), abs=0.005)
    uniform = (np.arange(1000) + 0.5) / 1000
    assert weighted_percentiles(uniform, np.ones(1000), [5.0, 95.0]) == pytest.approx([0.05, 0.95], abs=1e-12)


def test_region_statistics_are_area_weighted():
    """TAWSS takes the values (i + 0.5) / n on [0, 1] in both regions: with equal node areas in the first, with
    areas proportional to TAWSS in the second (area distribution 2 v dv: mean 2/3, CDF v^2), where OSI is 0.3 below
    TAWSS 0.2; RRT is 2 except one infinite node, left out."""
    n = 2000
    v = (np.arange(n) + 0.5) / n
    tawss = np.r_[v, v]
    osi = np.r_[np.zeros(n), np.where(v < 0.2, 0.3, 0.0)]
    rrt = np.r_[np.full(2 * n - 1, 2.0), np.inf]
    areas = np.r_[np.full(n, 2.0 / n), 8.0 * v / n]  # 2 mm^2 and 4 mm^2
    regions = np.r_[np.zeros(n, int), np.ones(n, int)]
    stats = region_statistics({"TAWSS": tawss, "OSI": osi, "RRT": rrt}, areas, regions)
    first, second, whole = stats["CCA"], stats["bulb"], stats["whole wall"]
    assert set(stats) == {"CCA", "bulb", "whole wall"}
    assert first["area_mm2"] == pytest.approx(2.0) and second["area_mm2"] == pytest.approx(4.0)
    assert first["wall_fraction"] == pytest.approx(1 / 3)
    assert first["TAWSS"]["mean"] == pytest.approx(0.5)
    assert [first["TAWSS"]["p5"], first["TAWSS"]["p95"]] == pytest.approx([0.05, 0.95], abs=1e-9)
    assert first["low_tawss_area_fraction"] == pytest.approx(0.4)
    assert first["high_osi_area_fraction"] == 0.0
    assert second["TAWSS"]["mean"] == pytest.approx(2 / 3, abs=1e-6)
    assert [second["TAWSS"]["p5"], second["TAWSS"]["p95"]] == pytest.approx(np.sqrt([0.05, 0.95]), abs=2e-3)
    assert second["low_tawss_area_fraction"] == pytest.approx(0.4 ** 2, abs=1e-6)
    assert second["high_osi_area_fraction"] == pytest.approx(0.2 ** 2, abs=1e-6)
    assert second["low_tawss_high_osi_area_fraction"] == pytest.approx(0.2 ** 2, abs=1e-6)
    assert second["RRT"]["mean"] == pytest.approx(2.0) and second["RRT"]["p95"] == pytest.approx(2.0)
    assert whole["low_tawss_area_fraction"] == pytest.approx((2 * 0.4 + 4 * 0.16) / 6, abs=1e-6)
    assert whole["low_tawss_high_osi_area_fraction"] == pytest.approx(4 * 0.04 / 6, abs=1e-6)


def test_regions_of_the_demo_reach_indices_summary_cohort_and_report(demo_run):
    """indices.vtp carries the Region cell array, summary.json the statistics of its indices per region (as
    recomputed from indices.vtp) and the bifurcation geometry, cohort.csv both, the report the tables."""
    import pyvista as pv

    from carotid.batch import Case, case_summary

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = out / "case"
    wall = pv.read(case / "flow" / "indices.vtp")
    assert list(wall.field_data["RegionNames"]) == list(REGION_NAMES)
    cells = np.asarray(wall.cell_data["Region"])
    assert {"CCA", "bulb", "ICA", "ECA", "stenosis"} <= set(np.array(REGION_NAMES)[np.unique(cells)])
    summary = json.loads((case / "flow" / "summary.json").read_text())
    stats = summary["regions"]["statistics"]
    p = np.asarray(wall.points)[wall.faces.reshape(-1, 4)[:, 1:]]
    cell_area = np.bincount(cells, 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1),
                            minlength=len(REGION_NAMES))
    for code, name in enumerate(REGION_NAMES):
        if name in stats:  # the node and cell partitions differ by parts of the triangles along the borders
            assert stats[name]["area_mm2"] == pytest.approx(cell_area[code], rel=0.1), name
    assert stats["whole wall"]["area_mm2"] == pytest.approx(cell_area.sum(), rel=1e-9)
    geometry = json.loads((case / "geometry.json").read_text())["bifurcation_geometry"]
    for key in ("bifurcation_angle_deg", "ica_cca_area_ratio", "bulb_diameter_ratio"):
        assert summary["bifurcation_geometry"][key] == pytest.approx(geometry[key], rel=1e-4), key
    row = case_summary(Case("demo", out / "phantom.nii.gz", {}), case, {"status": "ok"})
    assert row["bulb_tawss_mean_pa"] == stats["bulb"]["TAWSS"]["mean"]
    assert row["stenosis_osi_p95"] == stats["stenosis"]["OSI"]["p95"]
    assert row["ica_low_tawss_area_fraction"] == stats["ICA"]["low_tawss_area_fraction"]
    assert row["bifurcation_angle_deg"] == geometry["bifurcation_angle_deg"]
    assert row["eca_planarity_deg"] == geometry["branches"]["ECA"]["planarity_deg"]
    page = (case / "report.html").read_text(encoding="utf-8")
    table = re.search(r"<caption>Wall regions: area with low TAWSS.*?</table>", page, re.S)[0]
    rows = {row[0]: row[1:] for row in (re.findall(r"<td>(.*?)</td>", r) for r in re.findall(r"<tr>(.*?)</tr>", table))
            if row}
    for name in ("bulb", "stenosis", "whole wall"):  # area, three fractions, then TAWSS mean, p5, p95
        assert rows[name][4:7] == [f"{stats[name]['TAWSS'][k]:.3g}" for k in ("mean", "p5", "p95")], name
        assert rows[name][1] == f"{100 * stats[name]['low_tawss_area_fraction']:.1f}", name
    assert f"<td>{geometry['bifurcation_angle_deg']:.1f}</td>" in page
