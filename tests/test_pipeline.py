"""``carotid run``, its configuration and ``carotid batch``: skipping, restarting, failure isolation."""

import csv
import json
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import time
import tomllib
import zipfile

import numpy as np
import pytest

from carotid.batch import STAGE_NAMES
from carotid.cli import main
from carotid.config import Config
from carotid.errors import CarotidError
from carotid.phantom import make_phantom, write_phantom
from carotid.pipeline import read_case, run

SMALL = {"extent": (30.0, 30.0, 50.0)}  # a short field of view: a segmentation takes ~10 s


# The whole chain at toy settings: a 0.8 mm surface, 2 wall layers, a twentieth of a cycle (a few seconds).
TOY = {"surface": {"target_edge_mm": 0.8}, "mesh": {"layers": 2, "thickness_ratio": 0.15},
       "simulate": {"cycles": 0.05, "output_every": 20, "checkpoint_every": 20}}


@pytest.fixture(scope="module")
def small_image(tmp_path_factory):
    folder = write_phantom(make_phantom(stenosis=0.6, noise=15.0, seed=5, **SMALL),
                           tmp_path_factory.mktemp("pipeline") / "phantom")
    return folder / "image.nii.gz"


def test_config_defaults_overrides_and_toml_round_trip(tmp_path):
    config = Config({"segment": {"alpha": 0.3, "max_iterations": 10}})
    assert config.section("segment")["alpha"] == 0.3 and config.section("segment")["window"] == []
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
    ({"segment": {"seeds_mm": [[float("nan"), 0.0, 10.0]]}}, "finite numbers"),
    ({"segment": {"seeds_mm": [["a", "b", "c"]]}}, "finite numbers"),
    ({"segment": {"kernel_radius_mm": float("inf")}}, "kernel_radius_mm must be a finite number"),
    ({"segment": {"kernel_radius_mm": 1e6}}, "kernel_radius_mm must lie in"),
    ({"segment": {"window": [0.0, float("nan")]}}, "window must be a finite number"),
    ({"segment": {"denoise_iterations": 100000000}}, "denoise_iterations must lie in"),
    ({"segment": {"tolerance": 0.0}}, "tolerance must lie in"),
    ({"segment": {"tolerance": 5.0}}, "tolerance must lie in"),
    ({"segment": {"deblur_iterations": 100000000}}, "deblur_iterations must lie in"),
    ({"segment": {"far_mm": 0.0}}, "far_mm must be positive"),
    ({"segment": {"plateau": -1.0}}, "plateau must lie in"),
    ({"simulate": {"outlets": "windkessel"}}, "--outlets must be one of"),
    ({"simulate": {"turbulence": "kepsilon"}}, "--turbulence must be"),
    ({"simulate": {"outlets": "resistance", "resistance": [-1e9, 1e9]}}, "resistances must be positive"),
    ({"simulate": {"outlets": "rcr", "rcr": [[1.0, 2.0]]}}, "three positive values"),
    ({"simulate": {"waveform": "no-such-waveform.csv"}}, "cannot read waveform file"),
])
def test_config_rejects_bad_values(overrides, message):
    with pytest.raises(CarotidError, match=message.replace("[", r"\[").replace("]", r"\]")):
        Config(overrides)


def test_files_named_in_a_config_are_found_beside_it_wherever_the_run_starts(tmp_path, monkeypatch):
    """A per-case config with its own waveform and probe files (``waveform = "flow.csv"``) works from any
    working directory, as a manifest's per-case configs must; absolute paths are kept."""
    case = tmp_path / "patient"
    case.mkdir()
    (case / "flow.csv").write_text("time,flow\n0,6\n0.2,9\n0.4,8\n0.6,7\n0.9,6\n")
    (case / "probes.csv").write_text("x,y,z\n1,2,3\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (case / "config.toml").write_text(f'[simulate]\nwaveform = "flow.csv"\nprobes_file = "{case / "probes.csv"}"\n')
    monkeypatch.chdir(elsewhere)
    simulate = Config.from_toml(case / "config.toml").section("simulate")
    assert simulate["waveform"] == str(case / "flow.csv") and simulate["probes_file"] == str(case / "probes.csv")
    with pytest.raises(CarotidError, match="flow.csv"):  # a dict has no folder: relative to the working directory
        Config({"simulate": {"waveform": "flow.csv"}})


def test_a_config_folder_and_a_case_record_that_is_not_one_are_clear_errors(tmp_path):
    from carotid.pipeline import read_case

    with pytest.raises(CarotidError, match="cannot read the config file"):
        Config.from_toml(tmp_path)
    (tmp_path / "case.json").write_text("[1, 2]")
    with pytest.raises(CarotidError, match="not a record of stages"):
        read_case(tmp_path)


def test_bad_toml_is_one_clear_error(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[segment\nalpha = ")
    assert main(["config", "--config", str(path)]) == 2
    assert "not valid TOML" in capsys.readouterr().err


def test_run_skips_unchanged_stages_and_reruns_changed_ones(small_image, tmp_path):
    case = tmp_path / "case"
    lines = []
    run(small_image, case, Config(TOY), log=lines.append)
    assert [line.split(":")[0] for line in lines] == ["segment", "centerlines", "surface", "mesh", "simulate", "report"]
    assert all(": done" in line for line in lines)
    first = read_case(case)["stages"]["segment"]
    lines.clear()
    run(small_image, case, Config(TOY), log=lines.append)
    assert all(line.endswith(": unchanged, skipped") for line in lines) and len(lines) == 6
    assert read_case(case)["stages"]["segment"] == first
    lines.clear()
    run(small_image, case, Config({**TOY, "segment": {"alpha": 0.25}}), log=lines.append)
    assert lines[0].startswith("segment: done") and read_case(case)["stages"]["segment"]["key"] != first["key"]
    report = json.loads((case / "segmentation" / "report.json").read_text())
    assert report["parameters"]["alpha"] == 0.25


# ``carotid run`` whose segmentation hangs once its first image file is written, after touching argv[1]:
# a kill then lands mid-write at a known moment, however fast the machine.
_HANG_IN_SEGMENTATION_WRITE = """
import pathlib, sys, time
import carotid.segment.segmentation as segmentation
from carotid.cli import main
write = segmentation.write_image
def write_then_hang(image, path):
    write(image, path)
    pathlib.Path(sys.argv[1]).touch()
    time.sleep(600)
segmentation.write_image = write_then_hang
sys.exit(main(sys.argv[2:]))
"""


def _start_run(image, case, config_path, hang_marker=None):
    """``carotid run`` in its own process group; with ``hang_marker``, hanging mid-write of the segmentation."""
    command = ["-m", "carotid"] if hang_marker is None else ["-c", _HANG_IN_SEGMENTATION_WRITE, str(hang_marker)]
    return subprocess.Popen([sys.executable, *command, "run", str(image), "-o", str(case), "--config",
                             str(config_path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def _kill_when(proc, condition, timeout=300.0):
    """SIGKILL the run's process group as soon as ``condition()`` holds."""
    start = time.monotonic()
    while not condition():
        assert proc.poll() is None, "the run ended before the moment to kill it"
        assert time.monotonic() - start < timeout
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _finished(case):
    try:
        return {name: s["finished"] for name, s in read_case(case)["stages"].items()}
    except (CarotidError, FileNotFoundError, json.JSONDecodeError):
        return {}


def _checkpoint_step(case):
    """Step of the flow checkpoint (-1 when there is none yet)."""
    try:
        return int(np.load(case / "flow" / "checkpoint.npz")["step"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return -1


def test_killed_run_resumes_to_the_same_result(small_image, tmp_path):
    config_path = tmp_path / "toy.toml"
    config_path.write_text(Config(TOY).to_toml())
    reference = tmp_path / "reference"
    run(small_image, reference, Config.from_toml(config_path), log=lambda line: None)
    case, marker = tmp_path / "killed", tmp_path / "hanging"
    moments = {  # name -> (condition at which the run is killed, stage it interrupts, marker of a hanging write)
        "mid-write of the segmentation": (marker.exists, "segment", marker),
        "after the surface": (lambda: "surface" in _finished(case), "simulate", None),
        "mid-simulation": (lambda: 20 <= _checkpoint_step(case) < 60, "simulate", None),  # of ~67 steps
    }
    for name, (condition, interrupted, hang_marker) in moments.items():
        before = _finished(case)
        _kill_when(_start_run(small_image, case, config_path, hang_marker), condition)
        after = _finished(case)
        assert {k: after[k] for k in before} == before, f"{name}: a finished stage was repeated"
        assert interrupted not in after, f"{name}: the run was not interrupted in time"
        if hang_marker is not None:  # the half-written folder is a temporary, never the result
            assert not (case / "segmentation").exists()
            assert [p.name.split(".")[1] for p in case.iterdir()] == ["segmentation"]
    before = _finished(case)
    lines = []
    run(small_image, case, Config.from_toml(config_path), log=lines.append)
    after = _finished(case)
    assert {k: after[k] for k in before} == before, "a stage finished before the kills was repeated"
    assert lines[-1].startswith("report: done")
    for name in ("segmentation/mask.nii.gz", "segmentation/levelset.nii.gz", "surface.vtp", "mesh.vtu"):
        assert (case / name).read_bytes() == (reference / name).read_bytes(), name
    resumed, uninterrupted = np.load(case / "flow" / "checkpoint.npz"), np.load(reference / "flow" / "checkpoint.npz")
    for field in ("u", "p", "t"):
        scale = max(np.abs(uninterrupted[field]).max(), 1e-30)
        assert np.abs(resumed[field] - uninterrupted[field]).max() <= 1e-10 * scale, field
    assert [p.name for p in case.iterdir() if p.name.startswith(".")] == []


def test_an_unexpected_stage_error_names_its_stage(tmp_path, monkeypatch):
    """A stage that raises something other than CarotidError is retried by Dask (``StageFailure``) and, if it
    persists, fails its case at that stage (before, ``failed_stage`` was empty)."""
    import carotid.batch as batch
    from carotid.batch import Case, StageFailure, _outcome, _stage_task

    def broken(stage, *args):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(batch, "run_stage", broken)
    case = Case("a", tmp_path / "a.nii.gz", {})
    (tmp_path / "a.nii.gz").write_bytes(b"")
    with pytest.raises(StageFailure) as caught:
        _stage_task(case, str(tmp_path / "a"), "mesh", {"status": "ok", "log": []})
    restored = pickle.loads(pickle.dumps(caught.value))  # it crosses process boundaries

    class Erred:
        def result(self):
            raise restored

    assert _outcome(Erred()) == {"status": "failed", "failed_stage": "mesh",
                                 "reason": "ZeroDivisionError: float division by zero"}


def test_batch_isolates_a_corrupt_case(small_image, tmp_path, capsys, monkeypatch):
    """Five cases on two workers: the corrupt one fails alone, the others finish.  No stage task depends on a
    Dask future (a dependency pins a case's stages to one worker, which can leave the other idle)."""
    from dask.distributed import Client, Future

    submitted = []
    submit = Client.submit

    def recording(self, func, *args, **kwargs):
        submitted.append(any(isinstance(a, Future) for a in (*args, *kwargs.values())))
        return submit(self, func, *args, **kwargs)

    monkeypatch.setattr(Client, "submit", recording)
    images = {"first": small_image}
    for k, stenosis in enumerate((0.4, 0.5, 0.7)):
        folder = write_phantom(make_phantom(stenosis=stenosis, noise=15.0, seed=6 + k, **SMALL), tmp_path / f"p{k}")
        images[f"phantom{k}"] = folder / "image.nii.gz"
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"\x1f\x8b not really gzip")
    manifest = tmp_path / "manifest.csv"
    manifest.write_text("case_id,image\n" + "".join(f"{name},{path}\n" for name, path in images.items())
                        + f"broken,{corrupt}\n")
    config = tmp_path / "toy.toml"
    config.write_text(Config(TOY).to_toml())
    out = tmp_path / "cohort"
    code = main(["batch", str(manifest), "-o", str(out), "--workers", "2", "--config", str(config)])
    captured = capsys.readouterr()
    assert code == 3 and "1 of 5 cases failed" in captured.err
    progress = [line for line in captured.err.splitlines() if line.startswith("batch: ")]
    assert "batch: broken failed at segment: " in captured.err and "batch: phantom0 done" in captured.err
    counts = [re.fullmatch(r"batch: (\d) of 5 cases done, (\d) failed, (\d) running, (\d) waiting; .* elapsed, "
                           r"ETA .*", line) for line in progress]
    counts = [tuple(int(n) for n in match.groups()) for match in counts if match]
    assert counts and all(sum(c) == 5 for c in counts) and counts[-1] == (4, 1, 0, 0)
    rows = {row["case_id"]: row for row in csv.DictReader(open(out / "cohort.csv"))}
    for name in images:
        row = rows[name]
        assert row["status"] == "ok", row
        assert float(row["lumen_volume_mm3"]) > 0 and int(row["mesh_tetrahedra"]) > 0
        assert float(row["lumen_contrast_to_noise"]) > 7.5  # phantoms at 15 HU of noise
        assert float(row["tawss_mean_pa"]) > 0 and 0 <= float(row["osi_area_fraction"]) <= 1
        assert 0 <= float(row["low_tawss_area_fraction"]) <= 1
        assert 0 <= float(row["nascet"]) < 1  # a fraction, as in geometry.json (phantom0's true NASCET is 5 %)
        assert row["stenosis_branch"] == "ICA"
    for name in images:  # each case's line names the quality checks that its row says failed
        line = next(line for line in progress if line.startswith(f"batch: {name} done"))
        failed = int(rows[name]["checks_failed"])
        assert line == f"batch: {name} done" + (f"; {failed} quality check{'s' if failed > 1 else ''} failed: "
                                               f"{rows[name]['failed_checks']}" if failed else "")
    assert rows["broken"]["status"] == "failed" and rows["broken"]["failed_stage"] == "segment"
    assert "cannot be read as an image" in rows["broken"]["reason"]
    assert not (out / "broken").exists()
    assert len(submitted) == 4 * len(STAGE_NAMES) + 1 and not any(submitted)


def test_the_line_of_a_case_that_ends_says_what_to_doubt():
    from carotid.batch import _ended_line

    row = {"status": "ok", "failed_stage": "", "reason": "", "checks_failed": 2,
           "failed_checks": "mesh: largest dihedral angle, wall layers (deg); flow: outlet model as configured "
                            "(no RCR fallback after a blow-up)"}
    assert _ended_line(row) == ("done; 2 quality checks failed: mesh: largest dihedral angle, wall layers (deg); "
                                "flow: outlet model as configured (no RCR fallback after a blow-up)")
    assert _ended_line({**row, "checks_failed": 0, "failed_checks": ""}) == "done"
    assert _ended_line({**row, "status": "failed", "failed_stage": "simulate", "reason": "it blew up"}) == (
        "failed at simulate: it blew up")


def test_bad_manifest_is_one_clear_error(tmp_path, capsys):
    manifest = tmp_path / "m.csv"
    manifest.write_text("id,path\na,b\n")
    assert main(["batch", str(manifest), "-o", str(tmp_path / "out")]) == 2
    assert "case_id,image" in capsys.readouterr().err


def _significant_digits(cell: str) -> int:
    mantissa = cell.lstrip("-").split("e")[0].replace(".", "").lstrip("0")
    return len(mantissa)


def test_cohort_csv_is_tidy_and_described(small_image, tmp_path):
    """Numbers to 4 significant digits, one column per stage time, no JSON in a cell, NASCET beside its
    branch and empty without a bifurcation, every column and threshold described in cohort.json."""
    from carotid.batch import Case, case_summary, write_cohort

    case = tmp_path / "bifurcation"
    run(small_image, case, Config(TOY), log=lambda line: None)
    tube = tmp_path / "tube"  # the same case where the centerlines found no bifurcation
    shutil.copytree(case, tube)
    geometry = json.loads((tube / "geometry.json").read_text())
    (tube / "geometry.json").write_text(json.dumps({**geometry, "bifurcation_mm": None}))
    rows = [case_summary(Case(path.name, small_image, {}), path, {"status": "ok"}) for path in (case, tube)]
    write_cohort(rows, tmp_path / "cohort.csv")
    with open(tmp_path / "cohort.csv", newline="") as handle:
        header = next(csv.reader(handle))
        handle.seek(0)
        found, tube_row = csv.DictReader(handle)
    stages = [name for name in read_case(case)["stages"]]
    assert [f"seconds_{name}" for name in stages] == [c for c in header if c.startswith("seconds_") and c != "seconds_total"]
    for name, cell in found.items():
        assert not cell.startswith(("{", "[")), name
        try:
            float(cell)
        except ValueError:
            continue
        if name != "mesh_tetrahedra":  # a count, exact
            assert _significant_digits(cell) <= 4, (name, cell)
    assert float(found["seconds_total"]) == pytest.approx(sum(s["seconds"] for s in read_case(case)["stages"].values()),
                                                          rel=1e-3)
    assert found["stenosis_branch"] == geometry["stenosis"]["branch"]
    assert float(found["nascet"]) == pytest.approx(geometry["stenosis"]["nascet"], rel=1e-3)
    report = json.loads((case / "segmentation" / "report.json").read_text())
    assert float(found["lumen_contrast_to_noise"]) == pytest.approx(report["intensity"]["contrast_to_noise"], rel=1e-3)
    assert tube_row["nascet"] == tube_row["ecst"] == tube_row["stenosis_branch"] == ""
    sidecar = json.loads((tmp_path / "cohort.json").read_text())
    assert list(sidecar["columns"]) == header
    assert all(column["description"] for column in sidecar["columns"].values())
    assert sidecar["columns"]["tawss_mean_pa"]["unit"] == "Pa" and sidecar["columns"]["seconds_total"]["unit"] == "s"
    assert set(sidecar["thresholds"]) == {"osi", "low_tawss_pa"}
    for key, column in (("osi", "osi_area_fraction"), ("low_tawss_pa", "low_tawss_area_fraction")):
        assert f"{sidecar['thresholds'][key]:g}" in sidecar["columns"][column]["description"]


def test_cohort_columns_of_cycle_state_and_convergence_are_the_records(tmp_path):
    """indices_cycle_fraction, periodic_status, tawss_last_cycle_change and tawss_gci_percent are the values of
    flow/summary.json and flow/convergence.json (the GCI in %), empty when a record lacks them."""
    from carotid.batch import COHORT_COLUMNS, Case, case_summary, write_cohort

    studied, plain = tmp_path / "studied", tmp_path / "plain"
    for case, periodic in ((studied, {"status": "not periodic", "last_relative_change": 0.02345}),
                           (plain, {"status": "not assessed", "last_relative_change": None})):
        (case / "flow").mkdir(parents=True)
        (case / "flow" / "summary.json").write_text(json.dumps(
            {"indices_cycle_fraction": 0.3, "partial": True, "periodic": {"tolerance": 0.01, **periodic}}))
    (studied / "flow" / "convergence.json").write_text(json.dumps(
        {"branches": {"TAWSS": {"ICA": {"gci_fine21": 0.5}, "whole wall": {"gci_fine21": 0.04321}}}}))
    rows = [case_summary(Case(path.name, tmp_path / "image.nii.gz", {}), path, {"status": "ok"})
            for path in (studied, plain)]
    write_cohort(rows, tmp_path / "cohort.csv")
    with open(tmp_path / "cohort.csv", newline="") as handle:
        found, empty = csv.DictReader(handle)
    assert float(found["indices_cycle_fraction"]) == 0.3 and found["periodic_status"] == "not periodic"
    assert float(found["tawss_last_cycle_change"]) == pytest.approx(0.02345, rel=1e-3)
    assert float(found["tawss_gci_percent"]) == pytest.approx(4.321, rel=1e-3)
    assert empty["periodic_status"] == "not assessed"
    assert empty["tawss_last_cycle_change"] == empty["tawss_gci_percent"] == ""
    columns = json.loads((tmp_path / "cohort.json").read_text())["columns"]
    assert columns["tawss_gci_percent"]["unit"] == "%" and columns["indices_cycle_fraction"]["unit"] == "fraction"
    for name in ("indices_cycle_fraction", "periodic_status", "tawss_last_cycle_change", "tawss_gci_percent"):
        assert columns[name]["description"] == COHORT_COLUMNS[name][1]


def test_cohort_columns_say_which_grades_and_results_to_doubt(tmp_path):
    """stenosis_category is the report's (a near-occlusion whatever its percentage), stenosis_calcified says
    whether calcium lies within CALCIFIED_MM of the throat's lumen, checks_failed / failed_checks list the
    report's failed quality checks, and outlets / outlets_fallback the outlet model the flow ran with and the
    split it replaced after a blow-up; all empty or zero when the records are absent."""
    from carotid.batch import Case, case_summary, write_cohort
    from carotid.centerline.plaque import CALCIFIED_MM
    from carotid.report.checks import MAX_DIHEDRAL_LAYER_DEG, MAX_SPLIT_ERROR

    near, calcified, soft, empty = (tmp_path / name for name in ("near", "calcified", "soft", "empty"))
    grades = {near: {"nascet": 0.45, "min_diameter_mm": 1.2, "distal_diameter_mm": 2.2, "calcium_mm": None},
              calcified: {"nascet": 0.72, "min_diameter_mm": 1.5, "distal_diameter_mm": 5.4,
                          "calcium_mm": 0.9 * CALCIFIED_MM},
              soft: {"nascet": 0.55, "min_diameter_mm": 2.2, "distal_diameter_mm": 4.9, "calcium_mm": 1.1 * CALCIFIED_MM}}
    for case, grade in grades.items():
        case.mkdir()
        (case / "geometry.json").write_text(json.dumps({"bifurcation_mm": [0.0, 0.0, 0.0],
                                                        "stenosis": {"branch": "ICA", "ecst": 0.5, **grade}}))
    (calcified / "mesh_quality.json").write_text(json.dumps({"layer": {"max_dihedral_deg": MAX_DIHEDRAL_LAYER_DEG + 1}}))
    (calcified / "flow").mkdir()
    (calcified / "flow" / "summary.json").write_text(json.dumps({"mass_balance": {"outlets": {
        "3": {"error_max": 0.5 * MAX_SPLIT_ERROR}, "4": {"error_max": 2.0 * MAX_SPLIT_ERROR}}},
        "outlets": {"model": "rcr", "fallback": {"from": "murray", "reason": "blew up"}}}))
    (soft / "mesh_quality.json").write_text(json.dumps({"layer": {"max_dihedral_deg": MAX_DIHEDRAL_LAYER_DEG - 1}}))
    empty.mkdir()
    rows = [case_summary(Case(path.name, tmp_path / "image.nii.gz", {}), path, {"status": "ok"})
            for path in (near, calcified, soft, empty)]
    write_cohort(rows, tmp_path / "cohort.csv")
    with open(tmp_path / "cohort.csv", newline="") as handle:
        near_row, calcified_row, soft_row, empty_row = csv.DictReader(handle)
    assert near_row["stenosis_category"] == "near-occlusion" and near_row["stenosis_calcium_mm"] == ""
    assert calcified_row["stenosis_category"] == ">=70 %" and soft_row["stenosis_category"] == "50-69 %"
    assert [r["stenosis_calcified"] for r in (near_row, calcified_row, soft_row)] == ["False", "True", "False"]
    assert calcified_row["checks_failed"] == "3"
    assert calcified_row["failed_checks"] == ("mesh: largest dihedral angle, wall layers (deg); "
                                              "flow: outlet 4: flow-split error, largest; "
                                              "flow: outlet model as configured (no RCR fallback after a blow-up)")
    assert (calcified_row["outlets"], calcified_row["outlets_fallback"]) == ("rcr", "murray")
    assert soft_row["outlets"] == soft_row["outlets_fallback"] == ""
    assert soft_row["checks_failed"] == "0" and soft_row["failed_checks"] == ""
    assert empty_row["stenosis_category"] == empty_row["stenosis_calcified"] == empty_row["failed_checks"] == ""
    assert empty_row["checks_failed"] == "0"


def test_manifest_doppler_columns_and_cohort_duplex_columns(tmp_path):
    """doppler_cca_psv/edv of a manifest row reach that case's simulate section (bad values name the line); the
    duplex and calibration columns of cohort.csv are the values of flow/summary.json, empty when absent."""
    from carotid.batch import COHORT_COLUMNS, DUPLEX_KEYS, Case, case_summary, read_manifest, write_cohort
    from carotid.errors import CarotidError

    manifest = tmp_path / "manifest.csv"
    manifest.write_text("case_id,image,doppler_cca_psv,doppler_cca_edv\na,a.nii.gz,85,22.5\nb,b.nii.gz,,\n")
    a, b = read_manifest(manifest)
    assert a.overrides["simulate"] == {"doppler_cca_psv": 85.0, "doppler_cca_edv": 22.5}
    assert "simulate" not in b.overrides
    for row, message in (("c,c.nii.gz,85,\n", "must be two velocities"), ("c,c.nii.gz,40,50\n", "below the peak"),
                         ("c,c.nii.gz,fast,20\n", "must be two velocities")):
        manifest.write_text("case_id,image,doppler_cca_psv,doppler_cca_edv\n" + row)
        with pytest.raises(CarotidError, match=f"manifest.csv:2: case c: .*{message}"):
            read_manifest(manifest)
    case = tmp_path / "case"
    (case / "flow").mkdir(parents=True)
    (case / "flow" / "summary.json").write_text(json.dumps({
        "duplex": {"gates": {"ICA": {"psv_cm_s": 251.5, "edv_cm_s": 90.25}, "CCA": {"psv_cm_s": 80.0, "edv_cm_s": 20.0}},
                   "psv_ratio": 3.14375, "sru": {"grade": ">=70 %", "concordant": False},
                   "pressure": {"drop_mean_mmhg": 12.5, "drop_peak_systole_mmhg": 40.0, "ratio_mean": None}},
        "inflow_calibration": {"target_psv_cm_s": 80.0, "target_edv_cm_s": 20.0, "mean_flow_ml_s": 6.5}}))
    write_cohort([case_summary(Case("case", tmp_path / "image.nii.gz", {}), case, {"status": "ok"})],
                 tmp_path / "cohort.csv")
    with open(tmp_path / "cohort.csv", newline="") as handle:
        (row,) = csv.DictReader(handle)
    assert row["ica_psv_cm_s"] == "251.5" and row["psv_ratio"] == "3.144" and row["sru_grade"] == ">=70 %"
    assert row["sru_concordant"] == "False" and row["stenosis_pressure_ratio"] == ""
    assert row["doppler_cca_psv_cm_s"] == "80" and row["inflow_mean_ml_s"] == "6.5"
    columns = json.loads((tmp_path / "cohort.json").read_text())["columns"]
    for name in DUPLEX_KEYS:
        assert columns[name]["description"] == COHORT_COLUMNS[name][1] and name in row
