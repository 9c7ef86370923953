"""The surface stage end to end: level set + centerlines -> clipped, smoothed, remeshed, labelled surface."""

from __future__ import annotations

import json
from pathlib import Path

import pyvista as pv

from carotid.centerline.model import Centerlines
from carotid.errors import CarotidError
from carotid.io import Volume, atomic_path, write_json
from carotid.surface.clip import cap_info, clip_surface
from carotid.surface.extract import extract_surface
from carotid.surface.quality import surface_quality
from carotid.surface.remesh import radius_size_field, remesh
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
    if edge_radius_ratio is not None:
        if not edge_radius_ratio > 0:
            raise CarotidError(f"edge/radius ratio {edge_radius_ratio} must be positive")
        target = radius_size_field(centerlines, edge_radius_ratio, *edge_bounds_mm)
    elif target_edge_mm is not None and target_edge_mm > 0:
        target = float(target_edge_mm)
    else:
        raise CarotidError(f"target edge length {target_edge_mm} mm must be positive")
    surface = extract_surface(levelset)
    clipped, caps = clip_surface(surface, centerlines, inset_radii=inset_radii,
                                 flow_extension_radii=flow_extension_radii, domain=levelset)
    smoothed = taubin_smooth(clipped, smoothing_iterations)
    final = remesh(smoothed, target, iterations=remesh_iterations)
    caps = cap_info(final, [c["name"] for c in caps])
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

