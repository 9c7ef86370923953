"""``carotid run``: every stage in order, each skipped when its inputs and parameters are unchanged.

A stage's *key* is the SHA-256 of its parameters (canonical JSON) and of the
content of every input file it reads.  When a stage finishes, its key, its
seconds and the content hashes of its outputs are recorded in
``CASE_DIR/case.json`` (written atomically after every stage, together with the
package versions).  On the next run a stage whose key matches the record and
whose outputs are all present is skipped; anything else is run again, and
every stage after it sees new input hashes and runs again too.  Stages write
their outputs atomically, so a run killed at any moment leaves either a
finished stage or none; the hidden temporaries of the writes it interrupted are
deleted by the next run.  The flow stage also resumes from its own checkpoint.

While a stage runs, :class:`StageProgress` reports on stderr: a tqdm bar on a
terminal, otherwise (a pipe, a log file) a line with the stage, its elapsed
time and, when the stage reports its fraction done, its ETA, at least every
``PROGRESS_SECONDS``.

The stages live in their packages; this module only knows their file
contracts (``STAGES``) and calls their ``run_stage(case_dir, params)``
functions, imported lazily so that ``carotid --help`` stays fast.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import re
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Callable, TextIO

from carotid.config import Config
from carotid.errors import CarotidError
from carotid.io import write_json
from carotid.io.atomic import RANDOM_PART, remove_leftovers

CASE_FILE = "case.json"
PROGRESS_SECONDS = 5.0  # longest silence of a running stage's progress report, s


@dataclass(frozen=True)
class Stage:
    """One pipeline stage and its file contract.

    Attributes
    ----------
    name : str
        Config section and ``case.json`` key.
    inputs : tuple of str
        Files it reads, relative to CASE_DIR (``"input"`` is the case's input image).
    outputs : tuple of str
        Files or folders it writes, relative to CASE_DIR.
    runner : str
        ``"module:function"`` of its ``run_stage(case_dir, params, inputs)``; empty while not built yet.  A
        runner with a ``progress`` keyword receives a :class:`StageProgress` to report through.
    optional : tuple of str
        Files it reads when they exist (hashed into its key only then).
    """

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    runner: str = ""
    optional: tuple[str, ...] = ()

    def load(self) -> Callable:
        """The stage's ``run_stage`` function."""
        module, function = self.runner.split(":")
        return getattr(importlib.import_module(module), function)


STAGES = (
    Stage("segment", ("input",), ("segmentation",), "carotid.segment.segmentation:run_stage"),
    Stage("centerlines", ("segmentation",), ("centerlines.vtp", "geometry.json"), "carotid.stages:run_centerlines"),
    Stage("surface", ("segmentation", "centerlines.vtp"), ("surface.vtp", "surface_quality.json"),
          "carotid.stages:run_surface"),
    Stage("mesh", ("surface.vtp",), ("mesh.vtu", "mesh_quality.json"), "carotid.stages:run_mesh"),
    Stage("simulate", ("mesh.vtu",), ("flow/summary.json",), "carotid.stages:run_simulate"),
    Stage("report", ("segmentation",), ("report.html",), "carotid.report.html:run_stage",
          optional=("centerlines.vtp", "geometry.json", "surface.vtp", "mesh.vtu", "flow")),
)


def file_hash(path: Path) -> str:
    """SHA-256 of a file, or of every file under a folder (relative names and contents, sorted)."""
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        digest.update(str(f.relative_to(path) if path.is_dir() else f.name).encode())
        with open(f, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def stage_key(params: dict, input_paths: list[Path]) -> str:
    """SHA-256 of a stage's parameters and of its inputs' contents."""
    digest = hashlib.sha256(json.dumps(params, sort_keys=True, default=str).encode())
    for path in input_paths:
        digest.update(file_hash(path).encode())
    return digest.hexdigest()


def read_case(case_dir: Path) -> dict:
    """``case.json`` of a case folder, or an empty record."""
    path = case_dir / CASE_FILE
    if not path.exists():
        return {"stages": {}}
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CarotidError(f"{path} is corrupt ({exc}); delete it to start the case afresh") from None
    if not isinstance(record, dict) or not isinstance(record.get("stages"), dict):
        raise CarotidError(f"{path} is corrupt (not a record of stages); delete it to start the case afresh")
    return record


def versions() -> dict:
    """Versions of carotid and of the libraries its results depend on."""
    out = {}
    for name in ("carotid", "numpy", "scipy", "SimpleITK", "scikit-image", "numba", "vtk", "pyvista"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def format_duration(seconds: float) -> str:
    """``"42 s"``, ``"12 min 5 s"`` or ``"3 h 20 min"``."""
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"


class StageProgress:
    """The progress report of one running stage on a text stream.

    On a terminal it is a tqdm bar (like the single-stage commands'); elsewhere it is one line
    ``LABEL: 43% after 30 s, ETA 40 s; FIGURES`` (or ``LABEL: running, 30 s elapsed; FIGURES`` while the
    stage reports no fraction) at least every ``every`` seconds.  The ETA extrapolates the rate since the
    stage's first report (a resumed stage starts part done).  A daemon thread repeats the latest state
    whenever the stage has been silent that long, so stages without a progress callback and the set-up
    phases of those with one are reported too.  The runner calls the object with its progress and may
    ``write`` lines of its own.

    Parameters
    ----------
    label : str
        Name of the stage as shown, e.g. ``"[5/6] simulate"``.
    stream : text stream
        Where the report goes.
    every : float
        Seconds between lines when the stream is not a terminal.
    """

    def __init__(self, label: str, stream: TextIO, every: float = PROGRESS_SECONDS):
        self.label, self.stream, self.every = label, stream, every
        self.start = self.last = time.monotonic()
        self.done, self.total, self.figures = 0.0, None, ""
        self.first = None  # (time s, fraction) of the first report with a total
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.bar = None
        if stream.isatty():
            from tqdm import tqdm

            self.bar = tqdm(desc=label, file=stream, dynamic_ncols=True, leave=False)
        self._thread = threading.Thread(target=self._beat, name=f"progress {label}", daemon=True)
        self._thread.start()

    def __call__(self, done: float, total: float | None = None, **figures) -> None:
        """Record the stage's progress: ``done`` of ``total`` (None: unknown) and figures to show with it."""
        with self._lock:
            self.done, self.total = done, total
            if total and self.first is None:
                self.first = (time.monotonic(), done / total)
            self.figures = " ".join(f"{k}={v}" for k, v in figures.items())
            if self.bar is not None:
                self.bar.total = total
                self.bar.set_postfix_str(self.figures, refresh=False)
                self.bar.update(done - self.bar.n)
            elif time.monotonic() - self.last >= self.every:
                self._line()

    def write(self, line: str) -> None:
        """Show one line of the stage's own (above the bar on a terminal)."""
        with self._lock:
            if self.bar is not None:
                self.bar.write(f"{self.label}: {line}", file=self.stream)
            else:
                print(f"{self.label}: {line}", file=self.stream, flush=True)

    def _line(self) -> None:
        now = time.monotonic()
        elapsed = now - self.start
        if self.total and self.first is not None:
            fraction = min(self.done / self.total, 1.0)
            since, then = now - self.first[0], self.first[1]
            eta = format_duration(since * (1 - fraction) / (fraction - then)) if fraction > then else "unknown"
            state = f"{100 * fraction:.0f}% after {format_duration(elapsed)}, ETA {eta}"
        else:
            state = f"running, {format_duration(elapsed)} elapsed"
        print(f"{self.label}: {state}" + (f"; {self.figures}" if self.figures else ""), file=self.stream, flush=True)
        self.last = now

    def _beat(self) -> None:
        while not self._stop.wait(min(1.0, self.every)):
            with self._lock:
                if self.bar is not None:
                    self.bar.refresh()
                elif time.monotonic() - self.last >= self.every:
                    self._line()

    def close(self) -> None:
        """Stop the report (the bar disappears; the stage's result line follows)."""
        self._stop.set()
        self._thread.join()
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> "StageProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def remove_temporaries(stage: Stage, case_dir: Path) -> None:
    """Delete the hidden temporaries that killed writes of ``stage``'s outputs left in ``case_dir``.

    These are ``.NAME.XXXXXXXX[.suffix]`` (and ``.NAME.old.XXXXXXXX``) beside an output ``NAME[.suffix]``
    (:mod:`carotid.io.atomic` and the staging folder of the mesh writer), and every such hidden temporary
    inside an output folder (``flow/``, ``segmentation/``).
    """
    if not case_dir.is_dir():
        return
    tops = {Path(output).parts[0] for output in stage.outputs}
    for top in tops:
        stem = top.split(".")[0]
        remove_leftovers(case_dir, rf"\.{re.escape(stem)}\.(old\.)?{RANDOM_PART}(\.\w+)*")
        folder = case_dir / top
        if folder.is_dir():
            for sub in [folder, *(p for p in folder.rglob("*") if p.is_dir())]:
                if sub.exists():
                    remove_leftovers(sub, rf"\.[\w-]+\.(old\.)?{RANDOM_PART}(\.\w+)*")


def _inputs(stage: Stage, case_dir: Path, image: Path) -> list[Path]:
    paths = [image if name == "input" else case_dir / name for name in stage.inputs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise CarotidError(f"stage '{stage.name}' lacks its inputs: {', '.join(missing)}")
    return paths + [case_dir / name for name in stage.optional if (case_dir / name).exists()]


def run_stage(stage: Stage, image: Path, case_dir: Path, config: Config, *, progress: TextIO | None = None,
              label: str | None = None) -> str:
    """Run one stage of a case unless its record shows it done with the same key.

    The temporaries of the stage's interrupted writes are deleted first, whether it runs or not.

    Parameters
    ----------
    stage : Stage
    image : Path
        The case's input image.
    case_dir : Path
    config : Config
    progress : text stream, optional
        Where a :class:`StageProgress` reports while the stage runs (None: nowhere).
    label : str, optional
        Name of the stage in that report (default: ``stage.name``).

    Returns
    -------
    str
        One line saying what happened (``"segment: done in 12.3 s"``, ``"...: unchanged, skipped"``).
    """
    if not stage.runner:
        return f"{stage.name}: not available yet"
    remove_temporaries(stage, case_dir)
    params = config.section(stage.name)
    inputs = _inputs(stage, case_dir, image)
    key = stage_key(params, inputs)
    record = read_case(case_dir)
    done = record["stages"].get(stage.name, {})
    if done.get("key") == key and all((case_dir / o).exists() for o in stage.outputs):
        return f"{stage.name}: unchanged, skipped"
    runner = stage.load()
    t0 = time.perf_counter()
    if progress is None:
        runner(case_dir, params, inputs)
    else:
        with StageProgress(label or stage.name, progress) as report:
            extra = {"progress": report} if "progress" in inspect.signature(runner).parameters else {}
            runner(case_dir, params, inputs, **extra)
    seconds = time.perf_counter() - t0
    record = read_case(case_dir)
    record.update({"input": str(image.resolve()), "versions": versions()})
    record["stages"][stage.name] = {
        "key": key, "seconds": round(seconds, 3),
        "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "outputs": {o: file_hash(case_dir / o) for o in stage.outputs},
    }
    write_json(record, case_dir / CASE_FILE)
    return f"{stage.name}: done in {seconds:.1f} s"


def _print_now(line: str) -> None:
    print(line, flush=True)


def run(image: str | Path, case_dir: str | Path, config: Config | None = None, *,
        log: Callable[[str], None] = _print_now, progress: TextIO | bool = True) -> dict:
    """Run every available stage on ``image`` into ``case_dir``, skipping those already done.

    Parameters
    ----------
    image : path
        CT angiogram (DICOM folder, NIfTI, NRRD or MHA).
    case_dir : path
        Output folder; ``case.json`` in it records keys, timings and versions.
    config : Config, optional
        Parameters of every stage (defaults when omitted).
    log : callable
        Receives one line per stage (default: printed on stdout at once).
    progress : text stream or bool
        Where each running stage reports its progress (:class:`StageProgress`): True for stderr, False for
        nowhere.

    Returns
    -------
    dict
        The case record as written to ``case.json``.
    """
    image, case_dir = Path(image), Path(case_dir)
    if not image.exists():
        raise CarotidError(f"{image}: no such file or folder")
    config = config or Config()
    stream = sys.stderr if progress is True else (progress or None)
    available = [stage for stage in STAGES if stage.runner]
    for stage in STAGES:
        label = f"[{available.index(stage) + 1}/{len(available)}] {stage.name}" if stage.runner else stage.name
        log(run_stage(stage, image, case_dir, config, progress=stream, label=label))
    return read_case(case_dir)
