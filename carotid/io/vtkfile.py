"""Reading VTK-readable files (VTP, VTU, VTK, STL, OBJ, PLY) quietly: a bad file is one CarotidError, not VTK's
console dump (its error text, the failed pipeline request and pyvista's warning, 20-odd lines on stderr)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError


def read_vtk(path: str | Path, kind: str, suffixes: tuple[str, ...] | None = None) -> pv.DataSet:
    """Read a file with VTK's reader for its extension, with VTK's own error output silenced.

    Parameters
    ----------
    path : str or Path
        The file.
    kind : str
        What the file should hold, for the messages ("surface", "centerline").
    suffixes : tuple of str, optional
        Lower-case extensions accepted (".stl", ...); any other is refused before reading.

    Returns
    -------
    pyvista.DataSet
        The data as read (coordinates in the file's units), every point coordinate finite.

    Raises
    ------
    CarotidError
        A missing file, an extension not in ``suffixes`` or without a VTK reader, a file the reader fails on
        (empty, truncated, not of its format), or non-finite (NaN, infinite) point coordinates.
    """
    path = Path(path)
    suffix = "".join(path.suffixes[-2:]) if path.suffix.lower() == ".gz" else path.suffix
    if suffixes is not None and suffix.lower() not in suffixes:
        raise CarotidError(f"{path}: not a {kind} file (extension '{suffix}'; give one of {', '.join(suffixes)})")
    if not path.is_file():
        raise CarotidError(f"{path}: no such file")
    with pv.vtk_verbosity("off"), pv.VtkErrorCatcher(send_to_logging=False) as catcher:
        try:
            reader = pv.get_reader(path)
        except ValueError:
            raise CarotidError(f"{path}: not a readable {kind} file (no VTK reader for '{suffix}')") from None
        reader.reader.Update()
    if catcher.error_events:
        alerts = " ".join(e.alert.split("\n")[0] for e in catcher.error_events)
        if "non-finite" in alerts:
            raise CarotidError(f"{path}: non-finite coordinates (NaN or infinity) in the {kind} file")
        raise CarotidError(f"{path}: not a readable {kind} file ({catcher.error_events[0].alert.splitlines()[0]})")
    data = reader.read()
    if not np.isfinite(np.asarray(data.points, float)).all():
        raise CarotidError(f"{path}: non-finite coordinates (NaN or infinity) in the {kind} file")
    return data
