"""``carotid run``: every stage in order, each skipped when its inputs and parameters are unchanged.

A stage's *key* is the SHA-256 of its parameters (canonical JSON) and of the
content of every input file it reads.  When a stage finishes, its key, its
seconds and the content hashes of its outputs are recorded in
``CASE_DIR/case.json`` (written atomically after every stage, together with the
package versions).  On the next run a stage whose key matches the record and
whose outputs are all present is skipped; anything else is run again, and
every stage after it sees new input hashes and runs again too.  Stages write
their outputs atomically, so a run killed at any moment leaves either a
finished stage or none (the hidden temporary of a write it interrupted is
deleted when that stage writes again); the flow stage also resumes from its own checkpoint.

The stages live in their packages; this module only knows their file
contracts (``STAGES``) and calls their ``run_stage(case_dir, params)``
functions, imported lazily so that ``carotid --help`` stays fast.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Callable

from carotid.config import Config
from carotid.errors import CarotidError
from carotid.io import write_json

CASE_FILE = "case.json"


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
        ``"module:function"`` of its ``run_stage(case_dir, params, inputs)``; empty while not built yet.
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
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CarotidError(f"{path} is corrupt ({exc}); delete it to start the case afresh") from exc


def versions() -> dict:
    """Versions of carotid and of the libraries its results depend on."""
    out = {}
    for name in ("carotid", "numpy", "scipy", "SimpleITK", "scikit-image", "numba", "vtk", "pyvista"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _inputs(stage: Stage, case_dir: Path, image: Path) -> list[Path]:
    paths = [image if name == "input" else case_dir / name for name in stage.inputs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise CarotidError(f"stage '{stage.name}' lacks its inputs: {', '.join(missing)}")
    return paths + [case_dir / name for name in stage.optional if (case_dir / name).exists()]


def run_stage(stage: Stage, image: Path, case_dir: Path, config: Config) -> str:
    """Run one stage of a case unless its record shows it done with the same key.

    Returns
    -------
    str
        One line saying what happened (``"segment: done in 12.3 s"``, ``"...: unchanged, skipped"``).
    """
    if not stage.runner:
        return f"{stage.name}: not available yet"
    params = config.section(stage.name)
    inputs = _inputs(stage, case_dir, image)
    key = stage_key(params, inputs)
    record = read_case(case_dir)
    done = record["stages"].get(stage.name, {})
    if done.get("key") == key and all((case_dir / o).exists() for o in stage.outputs):
        return f"{stage.name}: unchanged, skipped"
    t0 = time.perf_counter()
    stage.load()(case_dir, params, inputs)
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


def run(image: str | Path, case_dir: str | Path, config: Config | None = None, *,
        log: Callable[[str], None] = print) -> dict:
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
        Receives one line per stage.

    Returns
    -------
    dict
        The case record as written to ``case.json``.
    """
    image, case_dir = Path(image), Path(case_dir)
    if not image.exists():
        raise CarotidError(f"{image}: no such file or folder")
    config = config or Config()
    for stage in STAGES:
        log(run_stage(stage, image, case_dir, config))
    return read_case(case_dir)
