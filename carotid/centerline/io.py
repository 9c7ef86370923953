"""Centerlines on disk: ``centerlines.vtp`` (VMTK's layout) and ``geometry.json``.

The VTP holds one polyline cell per branch, in mm, with the point array
``MaximumInscribedSphereRadius`` (mm), ``CenterlineSectionArea`` (mm^2, as
VMTK's ``vmtkcentersections``), ``CenterlineSectionMedianRadius`` and
``CenterlineSectionNarrowRadius`` (mm, the section's median radius and
half its narrowest diameter, ``axes.section_profile``) and the cell arrays ``BranchId`` (int)
and ``BranchName`` (string), so ParaView and VMTK scripts read it as they
read VMTK's own centerlines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.centerline.model import Branch, Centerlines
from carotid.errors import CarotidError
from carotid.io import atomic_path, read_record, write_json
from carotid.io.vtkfile import read_vtk

VTP_NAME = "centerlines.vtp"
JSON_NAME = "geometry.json"
RADIUS = "MaximumInscribedSphereRadius"
AREA = "CenterlineSectionArea"
MEDIAN = "CenterlineSectionMedianRadius"
NARROW = "CenterlineSectionNarrowRadius"


def to_polydata(cl: Centerlines) -> pv.PolyData:
    """The centerlines as polylines: one cell per branch, radii as point data, ids and names as cell data."""
    points = np.concatenate([b.points for b in cl.branches])
    sizes = np.array([len(b.points) for b in cl.branches])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    lines = np.concatenate([np.concatenate([[n], s + np.arange(n)]) for n, s in zip(sizes, starts)])
    poly = pv.PolyData(points, lines=lines)
    poly.point_data[RADIUS] = np.concatenate([b.radii for b in cl.branches]).astype(float)
    for name, attribute in ((AREA, "areas"), (MEDIAN, "median_radii"), (NARROW, "narrow_radii")):
        if all(getattr(b, attribute) is not None for b in cl.branches):
            poly.point_data[name] = np.concatenate([getattr(b, attribute) for b in cl.branches]).astype(float)
    poly.cell_data["BranchId"] = np.arange(len(cl.branches), dtype=np.int32)
    poly.cell_data["BranchName"] = np.array([b.name for b in cl.branches])
    return poly


def write_centerlines(cl: Centerlines, case_dir: str | Path) -> tuple[Path, Path]:
    """Write ``CASE_DIR/centerlines.vtp`` and ``CASE_DIR/geometry.json`` (each atomically).

    ``geometry.json`` holds ``cl.info`` (features, stenosis grading, labelling cues) with the
    bifurcation point and the branch names in VTP cell order.

    Returns
    -------
    (Path, Path)
        The two files.
    """
    case_dir = Path(case_dir)
    vtp = case_dir / VTP_NAME
    with atomic_path(vtp) as tmp:
        to_polydata(cl).save(tmp, binary=True)
    bif = cl.bifurcation.tolist() if np.all(np.isfinite(cl.bifurcation)) else None
    document = {**cl.info, "bifurcation_mm": bif, "branch_names": [b.name for b in cl.branches],
                "centerlines_file": VTP_NAME}
    return vtp, write_json(_plain(document), case_dir / JSON_NAME)


def read_centerlines(path: str | Path) -> Centerlines:
    """Read centerlines written by ``write_centerlines``.

    Parameters
    ----------
    path : path-like
        A case folder holding ``centerlines.vtp`` (and ``geometry.json``), or a ``.vtp`` file.

    Returns
    -------
    Centerlines
        Branch names from ``BranchName``; bifurcation and info from ``geometry.json`` beside the VTP if
        present (otherwise the last CCA point, or NaN).
    """
    path = Path(path)
    vtp = path / VTP_NAME if path.is_dir() else path
    if not vtp.exists():
        raise CarotidError(f"{vtp}: no such file; run `carotid centerlines CASE_DIR` first")
    poly = read_vtk(vtp, "centerline", remedy="rerun `carotid centerlines`")
    if RADIUS not in poly.point_data or "BranchName" not in poly.cell_data:
        raise CarotidError(f"{vtp}: not a carotid centerline file (arrays {RADIUS} and BranchName missing)")
    names = [str(n) for n in poly.cell_data["BranchName"]]
    radii = np.asarray(poly.point_data[RADIUS], float)
    optional = [np.asarray(poly.point_data[a], float) if a in poly.point_data else None
                for a in (AREA, MEDIAN, NARROW)]
    branches = []
    for k, name in enumerate(names):
        ids = np.asarray(poly.get_cell(k).point_ids)
        branches.append(Branch(name, np.asarray(poly.points[ids], float), radii[ids],
                               *(None if a is None else a[ids] for a in optional)))
    geometry = vtp.parent / JSON_NAME
    info = read_record(geometry, "rerun `carotid centerlines`") or {}
    bif = info.get("bifurcation_mm")
    if bif is None:
        bif = branches[names.index("CCA")].points[-1] if "CCA" in names and len(names) > 1 else np.full(3, np.nan)
    return Centerlines(branches, np.asarray(bif, float), info)


def _plain(value):
    """numpy scalars and arrays (also nested) as plain Python for JSON."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value
