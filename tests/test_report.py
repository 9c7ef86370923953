"""The HTML report: self-contained, rendered by a real headless browser, every picture non-blank."""

import base64
import json
import io
import re
import shutil
import subprocess

import numpy as np
from PIL import Image


def non_blank(png: bytes) -> bool:
    """True when a picture has real content: several distinct grey levels over >= 2% of its pixels."""
    grey = np.asarray(Image.open(io.BytesIO(png)).convert("L"), float)
    background = np.median(grey)
    return grey.std() > 5 and np.mean(np.abs(grey - background) > 20) > 0.02


def test_report_is_self_contained_with_non_blank_pictures(demo_run):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    page = (out / "case" / "report.html").read_text(encoding="utf-8")
    assert not re.search(r'src="(?!data:)', page), "every picture must be embedded"
    pictures = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert pictures, "the report has no pictures"
    for number, data in enumerate(pictures):
        assert non_blank(base64.b64decode(data)), f"picture {number} is blank"
    for title in ("Segmentation", "Geometry", "Volume mesh", "Flow", "Run record"):
        assert f"<h2>{title}" in page


def test_report_renders_in_headless_chromium(demo_run, tmp_path):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    assert browser, "headless Chromium is needed (scripts/system-packages.sh installs it)"
    shot = tmp_path / "page.png"
    run = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                          "--window-size=1400,900", f"--screenshot={shot}", (out / "case" / "report.html").as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert shot.exists(), run.stderr
    assert non_blank(shot.read_bytes())
    width, height = Image.open(shot).size
    assert (width, height) == (1400, 900)


def _drawn_inside(panel) -> np.ndarray:
    """Pixels of a slice panel inside its contour as drawn: pixel centres placed where imshow puts them."""
    from matplotlib.path import Path as MplPath

    picture, image = panel["picture"], panel["axes"].images[0]
    left, right, bottom, top = image.get_extent()
    rows, cols = np.indices(picture.shape)
    x = left + (cols + 0.5) * (right - left) / picture.shape[1]
    first, last = (top, bottom) if image.origin == "upper" else (bottom, top)
    y = first + (rows + 0.5) * (last - first) / picture.shape[0]
    points = np.c_[x.ravel(), y.ravel()]
    inside = np.zeros(len(points), bool)
    for path in panel["contour"].get_paths():
        for polygon in path.to_polygons():
            inside ^= MplPath(polygon).contains_points(points)
    return inside.reshape(picture.shape)


def test_lumen_contour_is_drawn_over_the_lumen(demo_run):
    import json

    import matplotlib.pyplot as plt

    from carotid.io import read_image
    from carotid.report.figures import slice_panels

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    intensity = json.loads((out / "case" / "segmentation" / "report.json").read_text())["intensity"]
    threshold = 0.5 * (intensity["lumen"] + intensity["background"])  # HU halfway from tissue to lumen
    fig, panels = slice_panels(read_image(out / "phantom" / "image.nii.gz"),
                               read_image(out / "case" / "segmentation" / "mask.nii.gz"))
    for panel in panels:
        inside = _drawn_inside(panel)
        assert inside.sum() > 20, panel["name"]
        assert panel["picture"][inside].mean() > threshold, f"{panel['name']}: the contour misses the lumen"
    plt.close(fig)


def _first_page(page: str) -> str:
    return page[:page.index("<h2>Details")]


def test_verdict_states_the_grading_of_geometry_json(demo_run):
    import json

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    grade = json.loads((out / "case" / "geometry.json").read_text())["stenosis"]
    page = (out / "case" / "report.html").read_text(encoding="utf-8")
    verdict = re.search(r'<div class="verdict".*?</table>', page, re.S)[0]
    assert f"NASCET {100 * grade['nascet']:.1f} %" in verdict
    assert f"{100 * grade['ecst']:.1f} %" in verdict
    for key in ("min_diameter_mm", "distal_diameter_mm", "local_diameter_mm"):
        assert f"{grade[key]:.2f} mm" in verdict
    assert f"{grade['arclength_from_bifurcation_mm']:.1f} mm distal to the bifurcation" in verdict
    assert grade["branch"] in verdict
    # NASCET categories: < 50 %, 50-69 %, >= 70 % (the demo's residual lumen is far from a near-occlusion)
    expected = "<50 %" if grade["nascet"] < 0.5 else "50-69 %" if grade["nascet"] < 0.7 else ">=70 %"
    assert f">{html_escape(expected)}</span>" in verdict


def test_first_page_shows_the_virtual_duplex_of_summary_json(demo_run):
    """The duplex table beside the NASCET: readable labels, units, and the numbers of flow/summary.json."""
    import json

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    duplex = json.loads((out / "case" / "flow" / "summary.json").read_text())["duplex"]
    page = (out / "case" / "report.html").read_text(encoding="utf-8")
    table = re.search(r'id="duplex".*?</div></div>', _first_page(page), re.S)[0]
    ica, cca = duplex["gates"]["ICA"], duplex["gates"]["CCA"]
    for text in (f"<th>ICA PSV</th><td>{ica['psv_cm_s']:.0f} cm/s</td><td>{html_escape(duplex['sru']['by_psv'])}",
                 f"<th>ICA EDV</th><td>{ica['edv_cm_s']:.0f} cm/s</td><td>{html_escape(duplex['sru']['by_edv'])}",
                 f"<th>ICA/CCA PSV ratio</th><td>{duplex['psv_ratio']:.2f}</td>",
                 f"<th>CCA PSV / EDV</th><td>{cca['psv_cm_s']:.0f} / {cca['edv_cm_s']:.0f} cm/s</td>",
                 f"{duplex['pressure']['drop_mean_mmhg']:.1f} / {duplex['pressure']['drop_peak_systole_mmhg']:.1f} mmHg",
                 f"<th>NASCET (geometry)</th><td>{100 * duplex['nascet']:.1f} %</td>",
                 f">{html_escape(duplex['sru']['grade'])}</span> SRU grade from the ICA PSV"):
        assert text in table, text
    # the demo's split outlets give relative pressures: no ratio, and the first cycle is said to start from rest
    assert duplex["pressure"]["ratio_mean"] is None and "no ratio" in table and "from rest" in table
    # the gates: at the graded ICA section, and 20 mm (or as far as the mesh allows) up the CCA; probes.csv holds them
    grade = json.loads((out / "case" / "geometry.json").read_text())["stenosis"]
    assert grade["branch"] == "ICA" and np.allclose(ica["position_mm"], grade["location_mm"], atol=1e-6)
    assert 0.0 < cca["arclength_from_bifurcation_mm"] <= 20.0 + 1e-9 and 0 < cca["gate_radius_mm"] <= 1.0
    header = (out / "case" / "flow" / "probes.csv").read_text().splitlines()[0].split(",")
    assert {"ICA_gate_speed_m_s", "CCA_gate_p_pa", "ICA_distal_p_pa", "CCA_1_speed_m_s"} <= set(header)


def html_escape(text: str) -> str:
    import html

    return html.escape(text)


def test_first_page_holds_verdict_profile_maps_and_flow(demo_run):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    first = _first_page((out / "case" / "report.html").read_text(encoding="utf-8"))
    for anchor in ('id="verdict"', 'id="profile"', 'id="wss-maps"', 'id="warnings"'):
        assert anchor in first
    maps = re.search(r'id="wss-maps".*?</div>', first, re.S)[0]
    assert maps.count("<img") == 4 and all(name in maps for name in ("TAWSS (Pa)", "OSI", "RRT (1/Pa)", "ECAP"))
    assert "Outlet flow split" in first and "Inflow waveform" in first and "cardiac cycle" in first
    assert "low TAWSS (&lt; 0.4 Pa)" in first or "low TAWSS (< 0.4 Pa)" in first


def test_wall_maps_state_their_clipping(demo_run):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    wall = pv_read(out / "case" / "flow" / "indices.vtp")
    first = _first_page((out / "case" / "report.html").read_text(encoding="utf-8"))
    for name in ("TAWSS", "RRT", "ECAP"):
        top = np.percentile(np.asarray(wall[name]), 98)
        assert f"clipped at the 98th percentile, {top:.3g}" in first, name


def pv_read(path):
    import pyvista as pv

    return pv.read(path)


def test_surface_regions_are_named_after_the_branches(demo_run):
    """Each outlet cap lies at the end of the branch geometry.json names it after."""
    import json

    from carotid.centerline import read_centerlines
    from carotid.centerline.model import branch_regions

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    caps = json.loads((out / "case" / "geometry.json").read_text())["caps"]
    branches = read_centerlines(out / "case" / "centerlines.vtp").branches
    found = branch_regions(np.array([cap["centre"] for cap in caps]), branches)
    assert [branches[k].name for k in found] == [cap["name"] for cap in caps]


def test_detail_tables_are_readable(demo_run):
    import json

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    page = (out / "case" / "report.html").read_text(encoding="utf-8")
    assert "values]" not in page
    segmentation = json.loads((out / "case" / "segmentation" / "report.json").read_text())
    assert segmentation["wall"] is None  # the wall stage is off in the demo: none of its parameters show
    assert not re.search(r"<th>wall[ _]", page)
    seeds = "; ".join("({:.1f}, {:.1f}, {:.1f})".format(*seed) for seed in segmentation["seeds_mm"])
    assert f"<th>seeds (mm)</th><td>{seeds}</td>" in page  # the seeds the seedless start placed, in LPS mm
    captions = re.findall(r"<caption>(.*?)</caption>", page)
    assert len(captions) == len(set(captions)), "a table is printed twice"
    assert page.count("equivalent radius (mm)") == 1, "the caps are tabled once"
    assert "<th>stenosis.nascet" not in page and "quality checks" in page.lower()
    assert 'class="fail">FAIL' in page or 'class="pass">pass' in page


def test_report_of_a_case_without_case_json(demo_run, tmp_path):
    """A case built by the per-stage commands has no case.json: the report skips the CT slices and says so."""
    import os
    import shutil

    from carotid.report import build_report

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = tmp_path / "case"
    case.mkdir()
    for item in (out / "case").iterdir():
        if item.name not in ("case.json", "report.html"):
            (shutil.copytree if item.name == "segmentation" else os.symlink)(item, case / item.name)
    page = build_report(case).read_text(encoding="utf-8")
    assert "CT slices omitted" not in page  # the segmentation records its image
    assert "could not be built" not in page
    assert 'id="verdict"' in page and 'id="wss-maps"' in page
    assert "No case.json" in page
    record = case / "segmentation" / "report.json"
    report = json.loads(record.read_text())
    del report["image"]["path"]
    record.write_text(json.dumps(report))
    page = build_report(case).read_text(encoding="utf-8")
    assert "CT slices omitted: the input CT image is not recorded" in page


def _report_lines(capfd, case):
    """Exit code, stderr lines and HTML of `carotid report CASE`."""
    from carotid.cli import main

    code = main(["report", str(case)])
    err = capfd.readouterr().err.strip().splitlines()
    return code, err, (case / "report.html").read_text(encoding="utf-8")


def test_an_unreadable_record_is_a_warning_not_a_stage_that_has_not_run(tmp_path, capfd):
    (tmp_path / "flow").mkdir()
    (tmp_path / "flow" / "summary.json").write_text("{bad")
    (tmp_path / "geometry.json").write_text("[1, 2, 3]")
    code, err, page = _report_lines(capfd, tmp_path)
    assert code == 0 and len(err) == 2, err
    assert err[0].startswith("carotid: warning: geometry.json could not be read: not a JSON object (it holds [1, 2")
    assert err[1].startswith("carotid: warning: flow/summary.json could not be read: not valid JSON")
    warnings = page[page.index('id="warnings"'):]
    assert "flow/summary.json could not be read" in warnings and "No stale, partial or failed" not in warnings
    assert "The flow stage has not run" not in page and "The centerline stage has not run" not in page
    assert "could not be built" not in page


def test_a_junk_surface_or_mesh_is_one_warning_and_the_report_is_built(tmp_path, capfd):
    (tmp_path / "surface.vtp").write_text("not VTK")
    (tmp_path / "mesh.vtu").write_text("not VTK either")
    code, err, page = _report_lines(capfd, tmp_path)
    assert code == 0 and len(err) == 2, err
    assert "surface.vtp could not be read: not a readable surface file" in err[0]
    assert "mesh.vtu could not be read: not a readable mesh file" in err[1]
    assert "mesh.vtu could not be read" in page[page.index("Volume mesh"):]
    assert "could not be built" not in page


def test_a_junk_vtk_file_in_the_case_is_one_warning_without_vtk_output(tmp_path, capfd):
    (tmp_path / "flow").mkdir()
    (tmp_path / "flow" / "summary.json").write_text("null")
    (tmp_path / "flow" / "indices.vtp").write_text("not VTK")
    code, err, page = _report_lines(capfd, tmp_path)
    assert code == 0 and len(err) == 2, err
    assert "flow/summary.json could not be read: not a JSON object (it holds null)" in err[0]
    assert "flow/indices.vtp could not be read: not a readable wall indices file (Error parsing XML" in err[1]
    assert "flow/indices.vtp could not be read" in page and "could not be built" not in page


def test_the_report_is_utf8_whatever_the_locale(demo_run, tmp_path):
    """The page declares utf-8 and is written so: in a process whose locale is plain ASCII (C, without
    Python's UTF-8 mode) its units (mm³, °) and dashes used to stop the report with an internal error."""
    import os
    import sys

    proc, out = demo_run
    assert proc.returncode == 0, proc.stderr
    case = tmp_path / "case"
    case.mkdir()
    for item in (out / "case").iterdir():
        if item.name != "report.html":
            os.symlink(item, case / item.name)
    env = {**os.environ, "LC_ALL": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    code = ("import sys; from pathlib import Path; from carotid.report import build_report; "
            "build_report(Path(sys.argv[1]))")
    run = subprocess.run([sys.executable, "-c", code, str(case)], env=env, capture_output=True, text=True,
                         encoding="utf-8")
    assert run.returncode == 0, run.stderr
    page = (case / "report.html").read_text(encoding="utf-8")
    assert "<meta charset='utf-8'>" in page and "mm³" in page
