"""The surface stage end to end: level set + centerlines -> clipped, smoothed, remeshed, labelled surface;
or an external closed surface + its centerlines -> the same surface remeshed, its own flat caps labelled and kept."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.centerline.model import Centerlines
from carotid.errors import CarotidError
from carotid.io import Volume, atomic_path, write_json
from carotid.surface.clip import cap_info, clip_surface, extrude_rim, planar_cap
from carotid.surface.external import label_caps
from carotid.surface.extract import extract_surface
from carotid.surface.mesh import WALL, boundary_loops, compact, from_polydata, to_polydata
from carotid.surface.quality import surface_quality
from carotid.surface.remesh import SizeField, radius_size_field, remesh
from carotid.surface.smooth import taubin_smooth


def build_surface(levelset: Volume, centerlines: Centerlines, *, target_edge_mm: float | None = 0.3,
                  edge_radius_ratio: float | None = None, edge_bounds_mm: tuple[float, float] = (0.15, 1.0),
                  inset_radii: float = 1.5, flow_extension_radii: float = 0.0, smoothing_iterations: int = 30,
                  remesh_iterations: int = 8) -> tuple[pv.PolyData, list[dict], dict]:
    """Marching cubes, clipping with flat caps, Taubin smoothing and isotropic remeshing.

    Parameters
    ----------
    levelset : Volume
        Signed distance in mm, negative inside.
    centerlines : Centerlines
        Centerlines of the same lumen (their ends are clipped).
    target_edge_mm : float, optional
        Global target edge length, mm (used when ``edge_radius_ratio`` is None).
    edge_radius_ratio : float, optional
        Target edge length ``k r`` from the inscribed radius of the nearest axis point, bounded by
        ``edge_bounds_mm``.
    inset_radii, flow_extension_radii : float
        See ``clip_surface``.
    smoothing_iterations, remesh_iterations : int
        Taubin lambda|mu pairs and remeshing rounds.

    Returns
    -------
    surface : pyvista.PolyData
        Labelled (``CellEntityIds``) closed surface in mm.
    caps : list of dict
        Per cap: id, name, centre, normal, area, equivalent radius, planarity (see ``cap_info``).
    quality : dict
        ``surface_quality`` of the result.
    """
    target = _size_target(centerlines, target_edge_mm, edge_radius_ratio, edge_bounds_mm)
    surface = extract_surface(levelset)
    clipped, caps = clip_surface(surface, centerlines, inset_radii=inset_radii,
                                 flow_extension_radii=flow_extension_radii, domain=levelset)
    smoothed = taubin_smooth(clipped, smoothing_iterations)
    return _finish(smoothed, [c["name"] for c in caps], target, remesh_iterations)


def build_surface_keeping_caps(surface: pv.PolyData, centerlines: Centerlines, *,
                               target_edge_mm: float | None = 0.3, edge_radius_ratio: float | None = None,
                               edge_bounds_mm: tuple[float, float] = (0.15, 1.0), flow_extension_radii: float = 0.0,
                               remesh_iterations: int = 12) -> tuple[pv.PolyData, list[dict], dict]:
    """Isotropic remeshing of a closed surface that keeps its own flat caps (no clipping, no smoothing).

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed, outward-oriented surface in mm with flat end caps (e.g. from ``load_external_surface``).
    centerlines : Centerlines
        Centerlines of the same lumen: they name the caps (see ``carotid.surface.external.label_caps``).
    target_edge_mm, edge_radius_ratio, edge_bounds_mm
        See ``build_surface``.
    remesh_iterations : int
        Remeshing rounds: more than ``build_surface``'s, as another tool's wall may have needles and
        creases that a smoothed marching-cubes surface has not.
    flow_extension_radii : float
        Length of the cylindrical flow extension at each cap, in equivalent radii of the cap (0: none);
        the cap moves along its normal to the end of its extension.

    Returns
    -------
    surface : pyvista.PolyData
        Labelled (``CellEntityIds``) closed surface in mm, its wall on the input's wall and its caps in the
        planes of the input's caps (moved by the flow extensions).
    caps : list of dict
        As ``build_surface``.
    quality : dict
        ``surface_quality`` of the result.
    """
    target = _size_target(centerlines, target_edge_mm, edge_radius_ratio, edge_bounds_mm)
    labelled = label_caps(surface, centerlines)
    if flow_extension_radii > 0:
        labelled = _extend_caps(labelled, flow_extension_radii)
    return _finish(labelled, [name for name, _, _, _ in centerlines.ends()], target, remesh_iterations)


def _extend_caps(surface: pv.PolyData, radii: float) -> pv.PolyData:
    """Replace every cap of a labelled surface by a flow extension of ``radii`` cap radii and a new flat cap."""
    points, faces, labels = from_polydata(surface)
    wall = faces[labels == WALL]
    loops = boundary_loops(wall)
    all_faces, all_labels = [wall], [labels[labels == WALL]]
    for cap in cap_info(surface, [""] * (labels.max() - 1)):  # loop over caps, a handful
        loop = next(lp for lp in loops if np.isin(lp, faces[labels == cap["id"]]).all())
        normal = np.asarray(cap["normal"])
        points, ext, loop = extrude_rim(points, loop, normal, radii * cap["equivalent_radius"])
        interior, disc = planar_cap(points, loop, normal)
        points = np.vstack([points, interior])
        all_faces += [ext, disc]
        all_labels += [np.full(len(ext), WALL), np.full(len(disc), cap["id"])]
    points, faces = compact(points, np.concatenate(all_faces))
    return to_polydata(points, faces, np.concatenate(all_labels))


RESOLVING_RATIO = 0.5
"""Largest edge length of the remeshed wall in local radii: a section keeps at least ``2 pi / 0.5``, about 12,
edges around.  A global edge coarser than that on a tight throat (0.8 mm edges on a 1.5 mm throat: six around)
leaves creases whose faces turn by up to 174 degrees around one vertex: the boundary layer's prisms there are
nearly flat (a 180-degree dihedral angle)."""


def _size_target(centerlines: Centerlines, target_edge_mm: float | None, edge_radius_ratio: float | None,
                 edge_bounds_mm: tuple[float, float]) -> SizeField:
    """The remeshing target of ``build_surface``: a global edge length, at most ``RESOLVING_RATIO`` local radii
    (not below the lower bound of ``edge_bounds_mm``), or a radius-based size field."""
    if edge_radius_ratio is not None:
        if not edge_radius_ratio > 0:
            raise CarotidError(f"edge/radius ratio {edge_radius_ratio} must be positive")
        return radius_size_field(centerlines, edge_radius_ratio, *edge_bounds_mm)
    if target_edge_mm is not None and target_edge_mm > 0:
        target = float(target_edge_mm)
        return radius_size_field(centerlines, RESOLVING_RATIO, min(edge_bounds_mm[0], target), target)
    raise CarotidError(f"target edge length {target_edge_mm} mm must be positive")


def _finish(surface: pv.PolyData, names: list[str], target: SizeField, iterations: int
            ) -> tuple[pv.PolyData, list[dict], dict]:
    """Remesh a labelled closed surface; returns it with its ``cap_info`` and ``surface_quality``."""
    final = remesh(surface, target, iterations=iterations)
    caps = cap_info(final, names)
    quality = surface_quality(final, target if isinstance(target, float) else None)
    quality["caps"] = caps
    return final, caps, quality


def write_surface(surface: pv.PolyData, case_dir: str | Path, stl: bool = False, quality: dict | None = None,
                  caps: list[dict] | None = None) -> Path:
    """Write ``CASE_DIR/surface.vtp`` (and ``surface.stl``, ``surface_quality.json``) atomically.

    When ``caps`` are given and ``CASE_DIR/geometry.json`` exists, they are recorded there under ``"caps"``
    (the order and branch names of ``CellEntityIds`` 2, 3, ...).

    Returns
    -------
    Path
        The VTP file.
    """
    case_dir = Path(case_dir)
    out = case_dir / "surface.vtp"
    with atomic_path(out) as tmp:
        surface.save(tmp)
    if stl:
        with atomic_path(case_dir / "surface.stl") as tmp:
            pv.PolyData(surface.points, surface.faces).save(tmp)
    if quality is not None:
        write_json(quality, case_dir / "surface_quality.json")
    geometry = case_dir / "geometry.json"
    if caps is not None and geometry.is_file():
        doc = json.loads(geometry.read_text())
        doc["caps"] = caps
        write_json(doc, geometry)
    return out


def read_levelset_and_centerlines(case_dir: str | Path) -> tuple[Volume, Centerlines]:
    """The segmentation's level set and the centerlines of a case folder."""
    from carotid.io import read_image

    case_dir = Path(case_dir)
    ls_path = case_dir / "segmentation" / "levelset.nii.gz"
    if not ls_path.is_file():
        raise CarotidError(f"{ls_path} not found: run `carotid segment` first")
    cl_path = case_dir / "centerlines.vtp"
    if not cl_path.is_file():
        raise CarotidError(f"{cl_path} not found: run `carotid centerlines {case_dir}` first")
    from carotid.centerline import read_centerlines

    return read_image(ls_path), read_centerlines(cl_path)

