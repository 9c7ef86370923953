"""Atomic outputs: nothing half-written is ever left where a result is expected.

A file is written under a temporary name in its destination folder and renamed
into place; a stage's output folder is assembled under a temporary name and
renamed into place as a whole, replacing the previous one only once complete.
A process killed mid-write leaves only such temporaries, which
``remove_leftovers`` clears before the stage is run again.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path


# Names of the temporaries below: "." + name + "." + tempfile's 8 random characters (+ suffixes);
# a folder being replaced is parked under "." + name + ".old." + 8 characters.
_TEMPORARY = re.compile(r"\.[^.]+\.(old\.)?[a-z0-9_]{8}(\.[A-Za-z0-9]+)*")


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _suffixes(path: Path) -> str:
    return "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path`` (same suffix); rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name.split('.')[0]}.", suffix=_suffixes(path), dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(data, path: str | os.PathLike) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path


@contextmanager
def atomic_dir(path: str | os.PathLike):
    """Yield a temporary folder that replaces ``path`` as a whole on success.

    Parent folders that had to be created are removed again if the stage
    fails, so a failed stage leaves no trace in a new case folder.
    """
    path = Path(path)
    parent = path.parent
    created = [p for p in (parent, *parent.parents) if not p.exists()]
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=parent))
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for folder in created:  # innermost first
            try:
                folder.rmdir()
            except OSError:
                break
        raise


def remove_leftovers(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporaries that a killed ``atomic_path`` or ``atomic_dir`` left in ``folder``.

    Only names of the form these helpers create are touched, so a user's own
    files stay.  One writer per folder at a time is assumed: a concurrent
    writer's temporaries would be taken for leftovers.

    Returns
    -------
    list of Path
        The files and folders removed (none when ``folder`` does not exist).
    """
    folder = Path(folder)
    found = [p for p in folder.iterdir() if _TEMPORARY.fullmatch(p.name)] if folder.is_dir() else []
    for path in found:
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    return found
