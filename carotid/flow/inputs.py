"""Reading the case files of earlier stages (VTK meshes and polylines, JSON records) with one clear message
when a file exists but cannot be read.

VTK reports a corrupt file by printing its own error dump on stderr (logged by pyvista as well) and returning
an empty dataset; :func:`read_vtk` keeps that dump quiet, and turns the first error VTK reported, or an empty
result, into a :class:`carotid.errors.CarotidError` naming the file.  :func:`read_record` tells a JSON record
that is missing (None: its stage has not run) from one that is there but is not a JSON object.
"""

from __future__ import annotations

import json
import logging
import warnings
from contextlib import contextmanager
from pathlib import Path

from carotid.errors import CarotidError


@contextmanager
def quiet_vtk():
    """Silence VTK's error output, pyvista's warnings and log lines about it inside the block.

    Yields
    ------
    pyvista.VtkErrorCatcher
        Its ``error_events`` hold the errors VTK reported in the block.
    """
    import pyvista as pv

    disabled = logging.root.manager.disable
    logging.disable(logging.CRITICAL)  # pyvista logs every VTK error event on the root logger
    try:
        with pv.vtk_verbosity("off"), pv.VtkErrorCatcher(send_to_logging=False) as catcher, \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield catcher
    finally:
        logging.disable(disabled)


def read_vtk(path, what: str, remedy: str):
    """Read a VTK file (any format pyvista reads) quietly.

    Parameters
    ----------
    path : path-like
        An existing file.
    what : str
        What the file should be, for the message ("mesh file", "centerline file").
    remedy : str
        What to do about a file that cannot be read ("rerun `carotid mesh`").

    Returns
    -------
    pyvista.DataSet

    Raises
    ------
    CarotidError
        ``<path>: not a readable <what> (<VTK's first error>): <remedy>`` when VTK reports an error, raises, or
        reads no points.
    """
    import pyvista as pv

    with quiet_vtk() as catcher:
        try:
            data = pv.read(path)
        except Exception as exc:  # noqa: BLE001 - VTK and meshio raise assorted types on corrupt files
            raise CarotidError(f"{path}: not a readable {what} ({exc}): {remedy}") from None
    if catcher.error_events or not data.n_points:
        reason = catcher.error_events[0].alert.splitlines()[0] if catcher.error_events else "no points"
        raise CarotidError(f"{path}: not a readable {what} ({reason}): {remedy}")
    return data


def read_record(path, remedy: str) -> dict | None:
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
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CarotidError(f"{path}: not valid JSON ({exc}); {remedy}") from None
    if not isinstance(data, dict):
        raise CarotidError(f"{path}: not a JSON object (it holds {json.dumps(data)[:40]}); {remedy}")
    return data


def read_case_centerlines(path):
    """:func:`carotid.centerline.read_centerlines` of ``centerlines.vtp`` with its ``geometry.json``, one
    CarotidError naming the file when either cannot be read."""
    from carotid.centerline import read_centerlines

    path = Path(path)
    remedy = "rerun `carotid centerlines`"
    read_record(path.parent / "geometry.json", remedy)
    read_vtk(path, "centerline file", remedy)
    with quiet_vtk():
        return read_centerlines(path)
