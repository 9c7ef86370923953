"""Reading the case's VTK files quietly, with one clear message when a file exists but cannot be read.

VTK reports a corrupt file by printing its own error dump on stderr (its error text, the failed pipeline
request and pyvista's warning, 20-odd lines) and returning an empty dataset; :func:`read_vtk` keeps that dump
quiet and turns the first error VTK reported, an empty result or non-finite coordinates into a
:class:`carotid.errors.CarotidError` naming the file.  Its twin for JSON records is
:func:`carotid.io.atomic.read_record`.
"""

from __future__ import annotations

import logging
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError


@contextmanager
def quiet_vtk():
    """Silence VTK's error output, pyvista's warnings and its log lines about them inside the block.

    Yields
    ------
    pyvista.VtkErrorCatcher
        Its ``error_events`` hold the errors VTK reported in the block.
    """
    disabled = logging.root.manager.disable
    logging.disable(logging.CRITICAL)  # pyvista logs every VTK error event on the root logger
    try:
        with pv.vtk_verbosity("off"), pv.VtkErrorCatcher(send_to_logging=False) as catcher, \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield catcher
    finally:
        logging.disable(disabled)


def read_vtk(path: str | Path, kind: str, suffixes: tuple[str, ...] | None = None, remedy: str = "") -> pv.DataSet:
    """Read a file with VTK's reader for its extension, with VTK's own error output silenced.

    Parameters
    ----------
    path : str or Path
        The file.
    kind : str
        What the file should hold, for the messages ("surface", "mesh", "centerline").
    suffixes : tuple of str, optional
        Lower-case extensions accepted (".stl", ...); any other is refused before reading.
    remedy : str
        What to do about a file that cannot be read ("rerun `carotid mesh`"), appended to the message.

    Returns
    -------
    pyvista.DataSet
        The data as read (coordinates in the file's units), with points, every coordinate finite.

    Raises
    ------
    CarotidError
        A missing file, an extension not in ``suffixes`` or without a VTK reader, a file the reader fails on
        (empty, truncated, not of its format) or that holds no points, or non-finite (NaN, infinite) point
        coordinates.
    """
    path = Path(path)
    tail = f": {remedy}" if remedy else ""
    suffix = "".join(path.suffixes[-2:]) if path.suffix.lower() == ".gz" else path.suffix
    if suffixes is not None and suffix.lower() not in suffixes:
        raise CarotidError(f"{path}: not a {kind} file (extension '{suffix}'; give one of {', '.join(suffixes)})")
    if not path.is_file():
        raise CarotidError(f"{path}: no such file{tail}")
    with quiet_vtk() as catcher:
        try:
            reader = pv.get_reader(path)
        except ValueError:
            raise CarotidError(f"{path}: not a readable {kind} file (no VTK reader for '{suffix}')") from None
        try:
            data, failure = reader.read(), ""
        except Exception as exc:  # noqa: BLE001 - VTK and meshio raise assorted types on corrupt files
            data, failure = None, str(exc)
    if data is None or catcher.error_events or not data.n_points:
        alerts = [e.alert.strip() for e in catcher.error_events]  # VTK's message without its file and line
        if any("non-finite" in alert for alert in alerts):
            raise CarotidError(f"{path}: non-finite coordinates (NaN or infinity) in the {kind} file{tail}")
        reason = (alerts[0] if alerts else failure or "no points").splitlines()[-1].strip()
        raise CarotidError(f"{path}: not a readable {kind} file ({reason}){tail}")
    if not np.isfinite(np.asarray(data.points, float)).all():
        raise CarotidError(f"{path}: non-finite coordinates (NaN or infinity) in the {kind} file{tail}")
    return data
