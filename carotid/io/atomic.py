"""Atomic outputs: nothing half-written is ever left where a result is expected.

A file is written under a temporary name in its destination folder and renamed
into place; a stage's output folder is assembled under a temporary name and
renamed into place as a whole, replacing the previous one only once complete.
A process killed mid-write leaves only such a temporary; the next write of the
same file or folder deletes it first.  One writer per path at a time is
assumed: a concurrent writer's temporary would be taken for a leftover.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from carotid.errors import CarotidError

RANDOM_PART = "[a-z0-9_]{8}"  # the part of a temporary's name that tempfile draws


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _suffixes(path: Path) -> str:
    return "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix


def remove_leftovers(folder: Path, pattern: str) -> None:
    """Delete the files and folders in ``folder`` whose names match the regular expression ``pattern``
    (the temporaries of a write to the same path that was killed)."""
    for entry in folder.iterdir():
        if re.fullmatch(pattern, entry.name):
            if entry.is_dir():
                shutil.rmtree(entry)
            else:
                entry.unlink()


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path`` (same suffix); rename it to ``path`` on success.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix, suffix = f".{path.name.split('.')[0]}.", _suffixes(path)
    remove_leftovers(path.parent, re.escape(prefix) + RANDOM_PART + re.escape(suffix))
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    tmp.chmod(0o666 & ~_umask())
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_json(path: str | os.PathLike) -> dict:
    """A JSON record, or an empty dict when it is missing or unreadable (a stage that has not run)."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def read_record(path: str | Path, remedy: str) -> dict | None:
    """A JSON record (an object), or None when the file does not exist.

    Parameters
    ----------
    path : path-like
    remedy : str
        What to do about a record that cannot be read ("rerun `carotid centerlines`").

    Raises
    ------
    CarotidError
        ``<path>: not valid JSON (...); <remedy>``, or ``not a JSON object`` for valid JSON of another type.
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CarotidError(f"{path}: not valid JSON ({exc}); {remedy}") from None
    if not isinstance(data, dict):
        raise CarotidError(f"{path}: not a JSON object (it holds {json.dumps(data)[:40]}); {remedy}")
    return data


def write_json(data, path: str | os.PathLike) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
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
    prefix = f".{path.name}."
    remove_leftovers(parent, re.escape(prefix) + r"(old\.)?" + RANDOM_PART)  # a killed write's folders
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f"{prefix}old.", dir=parent))
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
