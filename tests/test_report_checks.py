"""The report's judgements on their own: stenosis category, quality flags, stale and partial results."""

import json
import os
import shutil

import numpy as np
import pytest
import pyvista as pv

from carotid.report.checks import periodicity_error, quality_checks, stenosis_category
from carotid.report.html import Case, case_warnings, exposure_rows, readable


@pytest.mark.parametrize("nascet, d_min, d_distal, expected", [
    (0.0, 5.0, 5.0, "<50 %"), (0.499, 2.5, 5.0, "<50 %"), (0.50, 2.5, 5.0, "50-69 %"),
    (0.699, 1.6, 5.3, "50-69 %"), (0.70, 1.5, 5.0, ">=70 %"), (0.85, 0.75, 5.0, ">=70 %"),
    # near-occlusion: residual lumen <= 1.3 mm with a collapsed distal ICA <= 3.5 mm, whatever NASCET says
    (0.60, 1.3, 3.25, "near-occlusion"), (0.30, 1.0, 1.43, "near-occlusion"),
    (0.74, 1.3, 5.0, ">=70 %"), (0.55, 1.5, 3.3, "50-69 %")])
def test_stenosis_category_thresholds(nascet, d_min, d_distal, expected):
    assert stenosis_category(nascet, d_min, d_distal) == expected


def test_mesh_quality_flags_thin_tetrahedra_and_missing_layers():
    mesh = {"layer": {"min_dihedral": {"min_deg": 1.65}}, "core": {"min_dihedral": {"min_deg": 19.0}},
            "boundary_layer": {"read_back_from_mesh": {"layers_found": {"min": 0, "median": 2.0}}},
            "volume": {"relative_error": 1e-12}}
    flags = {c.quantity: c.passed for c in quality_checks({}, {}, mesh, {})}
    assert flags["smallest dihedral angle, wall layers (deg)"] is False
    assert flags["wall layers found under every wall node, fewest"] is False
    assert flags["smallest dihedral angle, core (deg)"] is True
    assert flags["volume error against the surface"] is True


def test_periodicity_error_of_a_signal_settling_between_cycles():
    t = np.linspace(0.0, 3.0, 301)
    periodic = np.sin(2 * np.pi * t)
    assert periodicity_error(t, periodic, 1.0) == pytest.approx(0.0, abs=1e-9)
    drifting = periodic + 0.1 * t  # rises 0.1 per cycle on a range of about 2.1
    assert periodicity_error(t, drifting, 1.0) == pytest.approx(0.1 / np.ptp(drifting[t >= 2.0]), rel=1e-6)
    assert periodicity_error(t[t <= 1.5], periodic[t <= 1.5], 1.0) is None


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
    _edit(case / "flow" / "summary.json", lambda d: d.update(cycles=0.3))
    assert any("0.3 of a cardiac cycle" in w and "partial" in w for w in case_warnings(Case.read(case)))


def test_segmentation_rerun_makes_the_centerlines_stale(demo_run, tmp_path):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = _copy_case(out / "case", tmp_path / "case")
    _edit(case / "segmentation" / "report.json", lambda d: d.update(lumen_volume_mm3=d["lumen_volume_mm3"] + 50))
    assert any("centerlines were computed" in w for w in case_warnings(Case.read(case)))
