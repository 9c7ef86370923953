"""The report's judgements on their own: stenosis category, quality flags, stale and partial results, and the
first page's cycle state and grid convergence study shown as the records hold them."""

import html
import json
import os
import re
import shutil

import numpy as np
import pytest
import pyvista as pv

from carotid.report.checks import quality_checks, stenosis_category
from carotid.report.html import Case, case_warnings, exposure_rows, readable


@pytest.mark.parametrize("nascet, d_min, d_distal, expected", [
    (0.0, 5.0, 5.0, "<50 %"), (0.499, 2.5, 5.0, "<50 %"), (0.50, 2.5, 5.0, "50-69 %"),
    (0.699, 1.6, 5.3, "50-69 %"), (0.70, 1.5, 5.0, ">=70 %"), (0.85, 0.75, 5.0, ">=70 %"),
    # near-occlusion: residual lumen <= 1.3 mm with a collapsed distal ICA <= 3.5 mm, whatever NASCET says
    (0.60, 1.3, 3.25, "near-occlusion"), (0.30, 1.0, 1.43, "near-occlusion"),
    (0.74, 1.3, 5.0, ">=70 %"), (0.55, 1.5, 3.3, "50-69 %")])
def test_stenosis_category_thresholds(nascet, d_min, d_distal, expected):
    assert stenosis_category(nascet, d_min, d_distal) == expected


def test_mesh_quality_flags_flat_core_twisted_layers_and_missing_layers():
    def flags(layer_max, core_min, found):
        mesh = {"layer": {"min_dihedral": {"min_deg": 0.3}, "max_dihedral_deg": layer_max},
                "core": {"min_dihedral": {"min_deg": core_min}},
                "boundary_layer": {"read_back_from_mesh": {"layers_found": {"min": found, "median": 2.0}}},
                "volume": {"relative_error": 1e-12}}
        return {c.quantity: c.passed for c in quality_checks({}, {}, mesh, {})}

    bad, good = flags(171.0, 9.0, 0), flags(150.0, 19.0, 2)
    for quantity in ("largest dihedral angle, wall layers (deg)", "smallest dihedral angle, core (deg)",
                     "wall layers found under every wall node, fewest"):
        assert bad[quantity] is False and good[quantity] is True
    assert good["volume error against the surface"] is True
    assert all(good.values())  # a thin layer's flat tetrahedra (0.3 degrees) are its design, not a failure


def test_a_lumen_noisier_than_validated_is_flagged():
    def passed(ratio):
        record = {"intensity": {"contrast_to_noise": ratio, "contrast_to_noise_validated": 7.5}}
        return {c.quantity: c.passed for c in quality_checks(record, {}, {}, {})}[
            "lumen contrast-to-noise ratio (validated down to the criterion)"]

    assert passed(5.4) is False and passed(7.5) is True and passed(30.0) is True
    assert not any("contrast-to-noise" in c.quantity for c in quality_checks({"intensity": {}}, {}, {}, {}))


def test_exposure_fractions_are_area_weighted():
    # two unit squares side by side (x in [0, 1] and [1, 2]); TAWSS low and OSI high on the left one only
    square = pv.Plane(center=(1.0, 0.5, 0.0), i_size=2.0, j_size=1.0, i_resolution=40, j_resolution=20).triangulate()
    left = np.asarray(square.points)[:, 0] < 1.0 - 1e-9
    square.point_data["TAWSS"] = np.where(left, 0.1, 2.0)
    square.point_data["OSI"] = np.where(left, 0.3, 0.0)
    rows = exposure_rows(square, (~left).astype(int), ["A", "B"])
    table = {row[0]: [float(v) for v in row[1:]] for row in rows}
    assert table["whole wall"][0] == pytest.approx(2.0, abs=0.5)
    low, high = table["whole wall"][1], table["whole wall"][2]
    assert abs(low - 50.0) < 3.0 and abs(high - 50.0) < 3.0  # the nodes on x = 1 share their area
    assert table["B"][1] == 0.0 and table["A"][1] == 100.0


def test_readable_labels_carry_units():
    assert readable("dt_s.min") == "dt › min (s)"
    assert readable("boundary_layer.first_height_mm.mean") == "boundary layer › first height › mean (mm)"
    assert readable("mass_balance.inflow_mean_m3s") == "mass balance › inflow mean (m³/s)"
    assert readable("duplex.gates.ICA.psv_cm_s") == "duplex › gates › ICA › psv (cm/s)"
    assert readable("duplex.pressure.drop_mean_mmhg") == "duplex › pressure › drop mean (mmHg)"
    assert readable("inflow_calibration.b_ml_s") == "inflow calibration › b (mL/s)"


def _copy_case(source, target):
    """The records of a case copied, its large files linked."""
    target.mkdir()
    for item in source.iterdir():
        if item.suffix == ".json" or item.name == "segmentation":
            (shutil.copytree if item.is_dir() else shutil.copy)(item, target / item.name)
        elif item.name == "flow":
            (target / "flow").mkdir()
            for f in item.iterdir():
                (shutil.copy if f.name == "summary.json" else os.symlink)(f, target / "flow" / f.name)
        else:
            os.symlink(item, target / item.name)
    return target


def _edit(path, change):
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_flow_on_another_mesh_is_reported_stale(demo_run, tmp_path):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = _copy_case(out / "case", tmp_path / "case")
    assert not any("stale" in w for w in case_warnings(Case.read(case)))
    _edit(case / "flow" / "summary.json", lambda d: d["mesh"].update(tetrahedra=69602, nodes=14000))
    tets = int(np.count_nonzero(pv.read(case / "mesh.vtu").celltypes == pv.CellType.TETRA))
    stale = [w for w in case_warnings(Case.read(case)) if "stale" in w]
    assert len(stale) == 1 and "69,602" in stale[0] and f"{tets:,}" in stale[0]


def test_indices_from_under_one_cycle_are_reported_partial(demo_run, tmp_path):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = _copy_case(out / "case", tmp_path / "case")
    assert not any("partial" in w for w in case_warnings(Case.read(case)))
    _edit(case / "flow" / "summary.json", lambda d: d.update(partial=True, indices_cycle_fraction=0.3))
    partial = [w for w in case_warnings(Case.read(case)) if "partial" in w]
    assert len(partial) == 1 and "only 0.3 of a cardiac cycle" in partial[0]


def test_segmentation_rerun_makes_the_centerlines_stale(demo_run, tmp_path):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = _copy_case(out / "case", tmp_path / "case")
    _edit(case / "segmentation" / "report.json", lambda d: d.update(lumen_volume_mm3=d["lumen_volume_mm3"] + 50))
    assert any("centerlines were computed" in w for w in case_warnings(Case.read(case)))


def _cells(page: str, caption: str) -> list[list[str]]:
    """The body cells of the table of a page whose caption starts with ``caption``, unescaped."""
    table = re.search(rf"<caption>{re.escape(html.escape(caption))}.*?</table>", page, re.S)[0]
    return [[html.unescape(c) for c in re.findall(r"<t[dh]>(.*?)</t[dh]>", row)]
            for row in re.findall(r"<tr>(<td>.*?)</tr>", table)]


def _write_study(case, names: list[str]) -> dict:
    """A made-up three-mesh study of the case written as ``flow/convergence.json`` and ``flow/convergence.vtp``:
    per-branch means from ``grid_convergence`` (the first branch oscillatory, the second divergent) and a per-node
    TAWSS GCI rising along x with a few nodes without an estimate."""
    from carotid.flow.convergence import QUANTITIES, STATUS, _tables, grid_convergence
    from carotid.flow.output import write_wall_vtp

    h = np.array([0.4, 0.6, 0.9])
    phi = 1.0 + np.arange(len(names)) + np.outer(h ** 2, 0.5 + 0.1 * np.arange(len(names)))
    phi[:, 0] = [1.0, 1.1, 0.85]  # eps32 / eps21 = -2.5: oscillatory
    phi[:, 1] = [1.0, 1.2, 1.3]  # eps32 / eps21 = 0.5: divergent
    wall = pv.read(case / "flow" / "indices.vtp")
    x = np.asarray(wall.points)[:, 0]
    gci = 0.01 + 0.1 * (x - x.min()) / np.ptp(x)
    gci[::50] = np.nan
    study = {"levels": [{"level": k, "h_mm": h[k], "tetrahedra": 1000 * (3 - k), "nodes": 300 * (3 - k), "cycles": 1.0,
                         "partial": False, "periodic": {"status": "not assessed"}, "seconds": 10.0} for k in range(3)],
             "branches": {q: _tables(grid_convergence(h, phi * (k + 1)), names) for k, q in enumerate(QUANTITIES)},
             "map": {q: {"median_gci": 0.05, **{s: 0.25 for s in STATUS}} for q in QUANTITIES}}
    (case / "flow" / "convergence.json").write_text(json.dumps(study))
    write_wall_vtp(case / "flow" / "convergence.vtp", np.asarray(wall.points), wall.faces.reshape(-1, 4)[:, 1:],
                   {"TAWSS_GCI": gci})
    return study


def test_first_page_shows_cycle_state_partial_indices_and_convergence_study(demo_run, tmp_path):
    """The cycle state, the partial warning and the grid convergence table and map carry the numbers of
    ``flow/summary.json`` and ``flow/convergence.json``; without a study the page says so."""
    from carotid.centerline import read_centerlines
    from carotid.report import build_report

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    demo_page = (out / "case" / "report.html").read_text(encoding="utf-8")
    assert "No convergence study (carotid simulate --convergence)" in demo_page[:demo_page.index("<h2>Details")]
    case = _copy_case(out / "case", tmp_path / "case")
    cycles = [{"cycle": 1, "tawss_mean_pa": 1.8123, "relative_change": None, "mean_change": None},
              {"cycle": 2, "tawss_mean_pa": 1.7034, "relative_change": 0.0871, "mean_change": 0.0639},
              {"cycle": 3, "tawss_mean_pa": 1.6991, "relative_change": 0.0234, "mean_change": 0.00253}]
    _edit(case / "flow" / "summary.json", lambda d: d.update(
        partial=True, indices_cycle_fraction=0.3, indices_note="PARTIAL: the indices average only 0.3 of a cycle",
        periodicity=cycles,
        periodic={"tolerance": 0.01, "status": "not periodic", "last_relative_change": 0.0234,
                  "criterion": "area-weighted L2 relative change"}))
    names = [b.name for b in read_centerlines(case / "centerlines.vtp").branches] + ["whole wall"]
    study = _write_study(case, names)
    page = build_report(case).read_text()
    first = page[:page.index("<h2>Details")]
    assert "could not be built" not in page

    warnings = html.unescape(re.search(r'id="warnings".*?</ul>', first, re.S)[0])
    assert "only 0.3 of a cardiac cycle" in warnings
    assert "TAWSS change of the last cycle from the previous (L2, relative) = 0.0234 (criterion < 0.01)" in warnings

    assert _cells(first, "TAWSS of each whole cycle") == [
        [str(c["cycle"]), f"{c['tawss_mean_pa']:.4g}",
         *("–" if c[k] is None else f"{100 * c[k]:.3g}" for k in ("relative_change", "mean_change"))] for c in cycles]
    state = html.unescape(re.search(r'<p id="cycle-state">(.*?)</p>', first)[1])
    assert "changed by 2.34 % from the previous cycle's" in state
    assert "the indices average only 0.3 of a cycle" in state and "not periodic against the tolerance of 1 %" in state

    def shown(value, scale=1.0, digits=4):
        return "–" if value is None else f"{scale * value:.{digits}g}"

    block = re.search(r'<div class="more" id="convergence">.*?</figure></div>', first, re.S)[0]
    rows = _cells(block, "Grid convergence of the mean TAWSS per branch")
    expected = [[name, shown(r["phi_fine_to_coarse"][-1]), shown(r["phi_fine_to_coarse"][0]), shown(r["phi_ext21"]),
                 shown(r["p"]), shown(r["gci_fine21"], 100.0, 3), r["status"]]
                for name, r in study["branches"]["TAWSS"].items()]
    assert rows == expected
    assert [row[-1] for row in rows[:2]] == ["oscillatory", "divergent"] and rows[1][3] == rows[1][5] == "–"
    assert "GCI of TAWSS at each wall node" in block and block.count("<img") == 1
    assert "No convergence study" not in page
    assert "Grid convergence of the mean OSI per branch" in page and "Grid convergence levels" in page
