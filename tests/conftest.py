"""Shared fixtures: phantoms are generated once per session (they take a few seconds each)."""

import functools
import os
from pathlib import Path

import pytest

from carotid.phantom import make_phantom


def _shared_file(relative: str) -> Path:
    """A file of the project's shared data (``../shared/data`` beside the repository, ``/work/shared/data``,
    or ``$CAROTID_SHARED_DATA``); the first candidate when none exists (tests then skip)."""
    roots = [os.environ.get("CAROTID_SHARED_DATA"), Path(__file__).resolve().parents[2] / "shared/data",
             "/work/shared/data"]
    paths = [Path(root) / relative for root in roots if root]
    return next((path for path in paths if path.exists()), paths[0])


# The real carotid lumen surface (SPHinXsys, closed, flat caps, mm): see its PROVENANCE.txt.
FLUID_STL = _shared_file("carotid-surface-sphinxsys/fluid.stl")
needs_fluid_stl = pytest.mark.skipif(not FLUID_STL.exists(), reason=f"shared data not found: {FLUID_STL}")

# Stenosis (area fraction), noise (HU) and random seed of the accuracy phantoms.
ACCURACY_CASES = [(0.5, 30.0, 2), (0.6, 10.0, 4), (0.7, 20.0, 1), (0.75, 25.0, 7), (0.8, 30.0, 11)]


def pytest_collection_modifyitems(config, items):
    """Group the tests for pytest-xdist's ``--dist loadgroup`` (the README's test command runs two workers):
    each file on one worker, so that its module fixtures are computed once, and every file that uses the
    session's ``demo_run`` on one worker, first, so that the demo runs once and its long group starts early."""
    demo_files = {item.path for item in items if "demo_run" in getattr(item, "fixturenames", ())}
    for item in items:
        item.add_marker(pytest.mark.xdist_group("demo" if item.path in demo_files else item.path.name))
    items.sort(key=lambda item: item.path not in demo_files)


@functools.lru_cache(maxsize=None)
def phantom(stenosis: float = 0.7, noise: float = 20.0, seed: int = 1):
    """A cached phantom (do not modify its arrays)."""
    return make_phantom(stenosis=stenosis, noise=noise, seed=seed)


@pytest.fixture
def small_phantom():
    """A cached default phantom."""
    return phantom()


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``python -m carotid demo`` run once per session: (completed process, output folder)."""
    import subprocess
    import sys

    out = tmp_path_factory.mktemp("demo") / "demo"
    proc = subprocess.run([sys.executable, "-m", "carotid", "demo", "-o", str(out)], capture_output=True, text=True,
                          timeout=1200)
    return proc, out
