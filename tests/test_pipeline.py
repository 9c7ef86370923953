"""``carotid run``, its configuration and ``carotid batch``: skipping, restarting, failure isolation."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
import tomllib

import numpy as np
import pytest

from carotid.cli import main
from carotid.config import Config
from carotid.errors import CarotidError
from carotid.io import read_image
from carotid.phantom import make_phantom, write_phantom
from carotid.pipeline import read_case, run

SMALL = {"extent": (30.0, 30.0, 50.0)}  # a short field of view: a segmentation takes ~10 s


@pytest.fixture(scope="module")
def small_image(tmp_path_factory):
    folder = write_phantom(make_phantom(stenosis=0.6, noise=15.0, seed=5, **SMALL),
                           tmp_path_factory.mktemp("pipeline") / "phantom")
    return folder / "image.nii.gz"


def test_config_defaults_overrides_and_toml_round_trip(tmp_path):
    config = Config({"segment": {"alpha": 0.3, "max_iterations": 10}})
    assert config.section("segment")["alpha"] == 0.3 and config.section("segment")["hu_high"] == 550.0
    path = tmp_path / "run.toml"
    path.write_text(config.to_toml())
    assert tomllib.loads(path.read_text()) == config.sections
    assert Config.from_toml(path).sections == config.sections
    assert "# Weight of the curvature term" in config.to_toml()


@pytest.mark.parametrize("overrides, message", [
    ({"segmnt": {}}, "unknown section"),
    ({"segment": {"alphaa": 0.1}}, "unknown key 'alphaa'"),
    ({"segment": {"alpha": "high"}}, "expected float"),
    ({"segment": {"max_iterations": 1.5}}, "expected int"),
    ({"segment": {"alpha": 1.5}}, "alpha must lie in"),
    ({"segment": {"seeds_mm": [[1.0, 2.0]]}}, "[x, y, z]"),
])
def test_config_rejects_bad_values(overrides, message):
    with pytest.raises(CarotidError, match=message.replace("[", r"\[").replace("]", r"\]")):
        Config(overrides)


def test_bad_toml_is_one_clear_error(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[segment\nalpha = ")
    assert main(["config", "--config", str(path)]) == 2
    assert "not valid TOML" in capsys.readouterr().err


def test_run_skips_unchanged_stages_and_reruns_changed_ones(small_image, tmp_path):
    case = tmp_path / "case"
    lines = []
    run(small_image, case, log=lines.append)
    assert lines[0].startswith("segment: done") and lines[-1].startswith("report: done")
    assert all(": done" in line or "not available yet" in line for line in lines)
    first = read_case(case)["stages"]["segment"]
    lines.clear()
    run(small_image, case, log=lines.append)
    assert lines[0] == "segment: unchanged, skipped" and lines[-1] == "report: unchanged, skipped"
    assert read_case(case)["stages"]["segment"] == first
    lines.clear()
    run(small_image, case, Config({"segment": {"alpha": 0.25}}), log=lines.append)
    assert lines[0].startswith("segment: done") and read_case(case)["stages"]["segment"]["key"] != first["key"]
    report = json.loads((case / "segmentation" / "report.json").read_text())
    assert report["parameters"]["alpha"] == 0.25


def test_killed_run_resumes_to_the_same_result(small_image, tmp_path):
    reference = tmp_path / "reference"
    run(small_image, reference, log=lambda line: None)
    case = tmp_path / "killed"
    for delay in (1.0, 4.0):  # during start-up and imports, then inside the level-set evolution
        proc = subprocess.Popen([sys.executable, "-m", "carotid", "run", str(small_image), "-o", str(case)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(delay)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        assert not (case / "segmentation").exists() or (case / "case.json").exists()
    lines = []
    run(small_image, case, log=lines.append)
    assert lines[0].startswith("segment: done")
    for name in ("mask.nii.gz", "levelset.nii.gz"):
        a = read_image(case / "segmentation" / name).array
        b = read_image(reference / "segmentation" / name).array
        assert np.array_equal(a, b), name
    assert [p.name for p in case.iterdir() if p.name.startswith(".")] == []


def test_batch_isolates_a_corrupt_case(small_image, tmp_path, capsys):
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"\x1f\x8b not really gzip")
    manifest = tmp_path / "manifest.csv"
    manifest.write_text(f"case_id,image\nfirst,{small_image}\nsecond,{small_image}\nbroken,{corrupt}\n")
    out = tmp_path / "cohort"
    code = main(["batch", str(manifest), "-o", str(out), "--workers", "2"])
    captured = capsys.readouterr()
    assert code == 3 and "1 of 3 cases failed" in captured.err
    rows = {row["case_id"]: row for row in csv.DictReader(open(out / "cohort.csv"))}
    assert rows["first"]["status"] == rows["second"]["status"] == "ok"
    assert float(rows["first"]["lumen_volume_mm3"]) > 0
    assert rows["broken"]["status"] == "failed" and rows["broken"]["failed_stage"] == "segment"
    assert "cannot be read as an image" in rows["broken"]["reason"]
    assert not (out / "broken").exists()


def test_bad_manifest_is_one_clear_error(tmp_path, capsys):
    manifest = tmp_path / "m.csv"
    manifest.write_text("id,path\na,b\n")
    assert main(["batch", str(manifest), "-o", str(tmp_path / "out")]) == 2
    assert "case_id,image" in capsys.readouterr().err
