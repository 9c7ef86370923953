"""``carotid run`` reports while a stage runs, and an interrupted flow stage resumes where it stopped."""

import os
import re
import shutil
import signal
import subprocess
import tempfile
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import carotid.flow.simulate as flow_simulate
from carotid.config import Config
from carotid.phantom import write_phantom
from carotid.pipeline import PROGRESS_SECONDS, run
from conftest import phantom

# The demo's coarse chain with half a cycle (some 4000 steps; a quarter cycle took 9.9 s on a fast machine,
# too short for the silence test below to mean anything) and the default checkpoint interval.
SETTINGS = {"surface": {"target_edge_mm": 0.8}, "mesh": {"layers": 2, "thickness_ratio": 0.15},
            "simulate": {"cycles": 0.5, "output_every": 20, "checkpoint_every": 500}}
MAX_SILENCE_S = 10.0
SIMULATE = flow_simulate.simulate


@pytest.fixture(scope="module")
def piped_run(tmp_path_factory):
    """``carotid run`` on the demo phantom with stdout and stderr piped (not a terminal), every line timestamped:
    (image, case folder, [(seconds since the start, line)], exit status)."""
    root = tmp_path_factory.mktemp("progress")
    image = write_phantom(phantom(0.7, 20.0, 0), root / "phantom") / "image.nii.gz"
    config = root / "run.toml"
    config.write_text(Config(SETTINGS).to_toml())
    case = root / "case"
    start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "carotid", "run", str(image), "-o", str(case), "--config",
                             str(config)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend((time.monotonic() - start, line.rstrip())
                                                          for line in proc.stdout))
    reader.start()
    code = proc.wait(timeout=900)
    reader.join()
    return image, case, lines, code


def test_run_reports_at_least_every_10_s_when_piped(piped_run):
    image, case, lines, code = piped_run
    assert code == 0, lines
    times = [0.0] + [t for t, _ in lines]
    gaps = np.diff(times)
    assert gaps.max() <= MAX_SILENCE_S, f"{gaps.max():.1f} s without a line: {lines}"
    seconds = float(next(re.search(r"done in ([\d.]+) s", line)[1] for _, line in lines if line.startswith("simulate")))
    assert seconds > MAX_SILENCE_S  # the simulation is long enough to show its periodic lines
    simulating = [line for _, line in lines if re.match(r"\[5/6\] simulate: \d+% after .*, ETA ", line)]
    assert len(simulating) >= 2, lines


def _spy_simulate(monkeypatch, steps, interrupt_at=None):
    """Record ``(step, time)`` of every flow step; Ctrl-C (SIGINT to this process) after step ``interrupt_at``."""
    simulate = SIMULATE

    def spy(*args, progress=None, **kwargs):
        def tap(info):
            steps.append((info["step"], info["time"]))
            if info["step"] == interrupt_at:
                os.kill(os.getpid(), signal.SIGINT)
            if progress is not None:
                progress(info)

        return simulate(*args, progress=tap, **kwargs)

    monkeypatch.setattr(flow_simulate, "simulate", spy)


def _files(folder: Path) -> set:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


def test_interrupted_simulation_resumes_where_it_stopped(piped_run, tmp_path, monkeypatch):
    image, reference, _, code = piped_run
    assert code == 0
    case = tmp_path / "case"
    shutil.copytree(reference, case)  # a finished case; without flow/ its simulation and report run again
    shutil.rmtree(case / "flow")
    interrupted, resumed = [], []
    _spy_simulate(monkeypatch, interrupted, interrupt_at=100)  # before the first periodic checkpoint (step 500)
    with pytest.raises(KeyboardInterrupt):
        run(image, case, Config(SETTINGS), log=lambda line: None)
    assert interrupted[-1][0] == 100
    # What writes killed mid-way leave: the mesh writer's staging folder, an atomic write's temporary.
    tempfile.mkdtemp(prefix=".mesh.", dir=case)
    os.close(tempfile.mkstemp(prefix=".checkpoint.", suffix=".npz", dir=case / "flow")[0])
    _spy_simulate(monkeypatch, resumed)
    lines = []
    run(image, case, Config(SETTINGS), log=lines.append)
    assert [line.split(":")[1].strip() for line in lines[:4]] == ["unchanged, skipped"] * 4
    assert resumed[0][0] == 101 and resumed[0][1] > interrupted[-1][1], "the simulation did not resume at step 101"
    done, uninterrupted = np.load(case / "flow" / "checkpoint.npz"), np.load(reference / "flow" / "checkpoint.npz")
    for field in ("u", "p", "t", "step"):
        scale = max(np.abs(uninterrupted[field]).max(), 1e-30)
        assert np.abs(done[field] - uninterrupted[field]).max() <= 1e-10 * scale, field
    assert _files(case / "flow") == _files(reference / "flow")
    assert [str(p.relative_to(case)) for p in case.rglob(".*")] == []


def test_single_stage_simulate_reports_when_piped(piped_run, tmp_path):
    """``carotid simulate CASE`` with its output piped (a batch job's log) shows its progress lines, not only its
    result at the end: a tqdm bar alone is silent there."""
    _, reference, _, code = piped_run
    assert code == 0
    case = tmp_path / "case"
    case.mkdir()
    for name in ("mesh.vtu", "centerlines.vtp", "geometry.json"):
        shutil.copy(reference / name, case / name)
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "carotid", "simulate", str(case), "--cycles", "0.5"],
                          capture_output=True, text=True, timeout=600)
    seconds = time.monotonic() - start
    assert proc.returncode == 0, proc.stderr
    periodic = [line for line in proc.stderr.splitlines() if re.match(r"simulate: \d+% after .*, ETA .*; step=\d+",
                                                                        line)]
    # A line at least every PROGRESS_SECONDS (5 s) of the stage, which starts a few seconds into the process:
    # the count follows the machine's speed (13-26 s here), and a silent stage fails on any machine.
    assert len(periodic) >= max(1, int(seconds // PROGRESS_SECONDS) - 2), (seconds, proc.stderr)
