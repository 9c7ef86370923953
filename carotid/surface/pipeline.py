"""The surface stage end to end: level set + centerlines -> clipped, smoothed, remeshed, labelled surface;
or an external closed surface + its centerlines -> the same surface remeshed, its own flat caps labelled and kept."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy import ndimage

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
    check_centerlines_match(levelset, centerlines)
    target = _size_target(centerlines, target_edge_mm, edge_radius_ratio, edge_bounds_mm, flow_extension_radii)
    surface = extract_surface(levelset)
    clipped, caps = clip_surface(surface, centerlines, inset_radii=inset_radii,
                                 flow_extension_radii=flow_extension_radii, domain=levelset)
    smoothed = taubin_smooth(clipped, smoothing_iterations)
    return _finish(smoothed, [c["name"] for c in caps], target, remesh_iterations)


def check_centerlines_match(levelset: Volume, centerlines: Centerlines) -> None:
    """Raise CarotidError unless the centerlines run inside this level set's lumen and reach each of its open ends.

    Centerlines of another case (or of an older segmentation) would be clipped where they are not: ends the
    lumen leaves the image by would be closed as wall without a word.  Every centerline point must lie in the
    image with the level set below one voxel there (trilinear), and every place where the lumen crosses the image
    border (a connected patch of lumen voxels on a face of the grid, of equivalent radius r at least half the
    smallest end radius of the branches) must have a branch end within 2 r + one voxel of its centroid.

    Parameters
    ----------
    levelset : Volume
        Signed distance in mm, negative inside.
    centerlines : Centerlines
        Centerlines (mm) said to be of this lumen.
    """
    voxel = max(levelset.spacing)
    shape = np.asarray(levelset.array.shape)
    points = np.vstack([b.points for b in centerlines.branches])
    kji = levelset.world_to_index(points)
    phi = ndimage.map_coordinates(levelset.array, kji.T, order=1, mode="nearest")
    outside = np.any((kji < -0.5) | (kji > shape - 0.5), axis=1) | (phi > voxel)
    if outside.any():
        raise CarotidError(f"the centerlines do not match this segmentation ({np.count_nonzero(outside)} of "
                           f"{len(points)} centerline points lie outside its lumen); rerun carotid centerlines")
    tips = np.array([b.points[end] for b in centerlines.branches for end in (0, -1)])
    smallest = min(float(b.radii[end]) for b in centerlines.branches for end in (0, -1))
    lumen = levelset.array < 0
    for axis, side in itertools.product(range(3), (0, -1)):  # the six faces of the grid
        patches, n = ndimage.label(np.take(lumen, side, axis=axis))
        if not n:
            continue
        pixel = np.prod(np.delete(levelset.spacing_kji, axis))
        radii = np.sqrt(np.bincount(patches.ravel())[1:] * pixel / np.pi)
        centroids = np.insert(np.array(ndimage.center_of_mass(patches > 0, patches, np.arange(1, n + 1))),
                              axis, side % shape[axis], axis=1)
        centres = levelset.index_to_world(centroids)
        reach = np.linalg.norm(centres[:, None] - tips[None], axis=2).min(axis=1)
        missed = (radii >= 0.5 * smallest) & (reach > 2.0 * radii + voxel)
        if missed.any():
            where = ", ".join(str(np.round(c, 1).tolist()) for c in centres[missed])
            raise CarotidError(f"the centerlines do not match this segmentation (its lumen leaves the image at "
                               f"{where} mm, where no centerline ends); rerun carotid centerlines")


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
    target = _size_target(centerlines, target_edge_mm, edge_radius_ratio, edge_bounds_mm, flow_extension_radii)
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


MAX_TRIANGLES = 5_000_000
"""Most triangles the remeshed surface may get: a carotid bifurcation at the default 0.3 mm edge has about 50 000;
5 million take the remesher hours and give a volume mesh of tens of millions of elements, so edge lengths that would
give more are refused at once, not remeshed."""


def _size_target(centerlines: Centerlines, target_edge_mm: float | None, edge_radius_ratio: float | None,
                 edge_bounds_mm: tuple[float, float], flow_extension_radii: float = 0.0) -> SizeField:
    """The remeshing target of ``build_surface``: a global edge length, at most ``RESOLVING_RATIO`` local radii
    (not below the lower bound of ``edge_bounds_mm``), or a radius-based size field.

    Raises CarotidError for a non-positive edge length or ratio, and when the remeshed surface, flow extensions of
    ``flow_extension_radii`` radii included, would have more than ``MAX_TRIANGLES`` triangles
    (:func:`estimated_triangles`)."""
    if edge_radius_ratio is not None:
        if not edge_radius_ratio > 0:
            raise CarotidError(f"edge/radius ratio {edge_radius_ratio} must be positive")
        target = radius_size_field(centerlines, edge_radius_ratio, *edge_bounds_mm)
        remedy = f"edge/radius ratio above {edge_radius_ratio:g}, edge_min_mm above {edge_bounds_mm[0]:g} mm"
    elif target_edge_mm is not None and target_edge_mm > 0:
        target_edge_mm = float(target_edge_mm)
        target = radius_size_field(centerlines, RESOLVING_RATIO, min(edge_bounds_mm[0], target_edge_mm),
                                   target_edge_mm)
        remedy = f"--target-edge or target_edge_mm above {target_edge_mm:g} mm"
    else:
        raise CarotidError(f"target edge length {target_edge_mm} mm must be positive")
    triangles, area = estimated_triangles(centerlines, target, flow_extension_radii)
    if triangles > MAX_TRIANGLES:
        factor = 1.05 * np.sqrt(triangles / MAX_TRIANGLES)  # 1.05: .2g rounds within 5%
        raise CarotidError(f"these edge lengths would give the remeshed surface about {triangles:.2g} triangles "
                           f"(a wall of about {area:.3g} mm^2), over the {MAX_TRIANGLES:.0e} limit: use edges "
                           f"{factor:.2g} times as long ({remedy})")
    return target


def estimated_triangles(centerlines: Centerlines, target: SizeField, flow_extension_radii: float = 0.0
                        ) -> tuple[float, float]:
    """Triangle count of a wall remeshed to ``target``, from its centerlines.

    Each branch is taken as a tube of its inscribed radius r (wall 2 pi r per mm of axis), each end extended by
    ``flow_extension_radii`` r, and each triangle as equilateral with the local target edge h (area
    sqrt(3)/4 h^2, about 0.433 h^2).

    Parameters
    ----------
    centerlines : Centerlines
        Axis points (mm) and radii (mm) of the lumen.
    target : float or callable
        Target edge length, mm (see :func:`carotid.surface.remesh.remesh`).
    flow_extension_radii : float
        Length of the flow extension at every end, in end radii.

    Returns
    -------
    triangles : float
        Estimated triangle count.
    area : float
        Estimated wall area, mm^2.
    """
    points = [b.points for b in centerlines.branches]
    radii = np.concatenate([b.radii for b in centerlines.branches])
    segments = [np.linalg.norm(np.diff(p, axis=0), axis=1) for p in points]
    lengths = np.concatenate([np.r_[s, 0.0] / 2 + np.r_[0.0, s] / 2 for s in segments])  # axis length per point, mm
    ends = centerlines.ends()
    end_points = np.array([point for _, point, _, _ in ends])
    end_radii = np.array([radius for _, _, _, radius in ends])
    areas = 2.0 * np.pi * np.r_[radii * lengths, end_radii * flow_extension_radii * end_radii]
    where = np.vstack([*points, end_points])
    edges = target(where) if callable(target) else np.full(len(where), float(target))
    return float(np.sum(areas / (np.sqrt(3.0) / 4.0 * edges**2))), float(areas.sum())


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
        doc = json.loads(geometry.read_text(encoding="utf-8"))
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

    centerlines = read_centerlines(cl_path)  # the small file first: a junk one is refused before the image is read
    return read_image(ls_path), centerlines

