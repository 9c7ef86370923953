"""The HTML report: self-contained, rendered by a real headless browser, every picture non-blank."""

import base64
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
    page = (out / "case" / "report.html").read_text()
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
                          "--window-size=1200,1600", f"--screenshot={shot}", (out / "case" / "report.html").as_uri()],
                         capture_output=True, text=True, timeout=120)
    assert shot.exists(), run.stderr
    assert non_blank(shot.read_bytes())
