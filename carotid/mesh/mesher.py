"""``build_mesh``: boundary layer + core + Lloyd smoothing, assembled into one conforming tetrahedral mesh."""

from __future__ import annotations

import time

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError
from carotid.mesh.boundary import LABELS, WALL, Surface, check_surface, signed_volume
from carotid.mesh.core import boundary_faces, face_keys, mesh_core
from carotid.mesh.layers import BoundaryLayer, build_layers, tet_volumes
from carotid.mesh.quality import (angle_summary, extreme_dihedrals, histogram, min_dihedral, radius_ratio,
                                  walk_layers)
from carotid.mesh.smooth import lloyd_smooth

LAYER, CORE, BOUNDARY = 0, 1, -1
"""Values of the ``Region`` cell array: layer and core tetrahedra, boundary triangles."""


def median_edge(surface: Surface) -> float:
    """Median edge length (mm) of the wall triangles."""
    tri = surface.triangles[surface.labels == WALL]
    p = surface.points
    return float(np.median(np.linalg.norm(p[tri] - p[np.roll(tri, 1, axis=1)], axis=2)))


def _vertex_caps(surface: Surface, n_points: int, layer: BoundaryLayer | None) -> np.ndarray:
    """Cap label of every vertex lying in a cap plane (cap vertices and rim columns), 0 elsewhere."""
    caps = np.zeros(n_points, dtype=np.int32)
    cap = surface.labels != WALL
    caps[surface.triangles[cap].ravel()] = np.repeat(surface.labels[cap], 3)
    if layer is not None:
        caps[layer.columns] = caps[layer.wall_vertices][None, :]
        inner_cap = layer.inner_labels != WALL
        caps[layer.inner_triangles[inner_cap].ravel()] = np.repeat(layer.inner_labels[inner_cap], 3)
    return caps


def _compact(points: np.ndarray, *cells: np.ndarray) -> tuple[np.ndarray, ...]:
    """Drop unused points and renumber the cell arrays."""
    used = np.zeros(len(points), dtype=bool)
    for c in cells:
        used[c.ravel()] = True
    if used.all():
        return (points, *cells)
    new_index = np.cumsum(used) - 1
    return (points[used], *(new_index[c] for c in cells))


def _label_boundary(faces: np.ndarray, surface: Surface, caps: np.ndarray) -> np.ndarray:
    """CellEntityIds of the mesh's boundary faces: wall where a face is an input wall triangle, else its cap."""
    wall = surface.triangles[surface.labels == WALL]
    keys = face_keys(np.vstack([faces, wall]))
    is_wall = np.isin(keys[:len(faces)], keys[len(faces):])
    labels = np.where(is_wall, WALL, caps[faces[:, 0]])
    consistent = is_wall | ((caps[faces[:, 0]] > 0) & (caps[faces] == caps[faces[:, :1]]).all(axis=1))
    if not consistent.all() or np.count_nonzero(is_wall) != len(wall):
        raise CarotidError("internal error: the mesh boundary does not match the input surface")
    return labels


def layer_profile(points: np.ndarray, layer: BoundaryLayer, ratio: float) -> dict:
    """Sub-layer heights measured along the extrusion directions and their errors against the request.

    Errors are against the requested thickness, so local reductions count as errors.

    Returns
    -------
    dict
        ``layers``, ``first_height_mm`` (mean / min / max), relative error of
        the first height against the requested one (mean / max), measured
        growth ratio (mean / min / max) and its largest deviation from
        ``ratio``, and the fraction of wall vertices whose thickness was reduced.
    """
    col = points[layer.columns]  # (N + 1, w, 3)
    heights = np.einsum("kwi,wi->kw", np.diff(col, axis=0), layer.directions)
    requested_first = layer.requested * layer.fractions[1]
    first_error = np.abs(heights[0] - requested_first) / requested_first
    growth = heights[1:] / heights[:-1]
    return {"layers": int(len(heights)), "requested_ratio": ratio,
            "first_height_mm": {"mean": float(heights[0].mean()), "min": float(heights[0].min()),
                                "max": float(heights[0].max())},
            "first_height_rel_error": {"mean": float(first_error.mean()), "max": float(first_error.max())},
            "growth_ratio": {"mean": float(growth.mean()), "min": float(growth.min()), "max": float(growth.max()),
                             "max_abs_error": float(np.abs(growth - ratio).max())},
            "thickness_mm": {"mean": float(layer.thickness.mean()), "min": float(layer.thickness.min()),
                             "max": float(layer.thickness.max())},
            "reduced_fraction": float(np.mean(layer.thickness < 0.99 * layer.requested))}


def walked_profile(points: np.ndarray, tets: np.ndarray, wall_faces: np.ndarray, layer: BoundaryLayer,
                   ratio: float) -> dict:
    """The layer read back from the final mesh alone by :func:`carotid.mesh.quality.walk_layers`.

    ``wall_faces`` must be the outward wall triangles of the mesh, whose
    vertices are the layer's wall vertices in the same order.
    """
    n_layers = len(layer.fractions) - 1
    depth = walk_layers(points, tets, wall_faces, 1.001 * layer.thickness.max(), n_layers)
    heights = np.diff(depth, axis=0)
    found = np.sum(~np.isnan(heights), axis=0)
    first = np.abs(heights[0] - layer.requested * layer.fractions[1]) / (layer.requested * layer.fractions[1])
    growth = np.abs(heights[1:] / heights[:-1] - ratio)
    return {"layers_found": {"min": int(found.min()), "median": float(np.median(found))},
            "first_height_rel_error": {"mean": float(np.nanmean(first)), "max": float(np.nanmax(first))},
            "growth_ratio_abs_error": {"mean": float(np.nanmean(growth)), "max": float(np.nanmax(growth))}}


def mesh_quality(points: np.ndarray, tets: np.ndarray, region: np.ndarray, n_boundary: dict, enclosed: float,
                 layer: dict | None = None) -> dict:
    """The quality report written to ``mesh_quality.json`` (see :func:`build_mesh`)."""
    angles = min_dihedral(points, tets)
    vol = tet_volumes(points, tets)
    report = {"elements": {"tetrahedra": int(len(tets)), "layer": int(np.sum(region == LAYER)),
                           "core": int(np.sum(region == CORE)), "points": int(len(points)),
                           "boundary_triangles": n_boundary}}
    for name, code in (("layer", LAYER), ("core", CORE)):
        sel = region == code
        if sel.any():
            dihedral_max = extreme_dihedrals(points, tets[sel])[1]
            report[name] = {"min_dihedral": angle_summary(angles[sel]),
                            "max_dihedral_deg": float(dihedral_max.max()),
                            "radius_ratio_histogram": histogram(radius_ratio(points, tets[sel]),
                                                                np.linspace(0.0, 1.0, 11))}
    report["volume"] = {"mesh_mm3": float(vol.sum()), "surface_mm3": enclosed,
                        "relative_error": float(abs(vol.sum() - enclosed) / enclosed),
                        "min_tet_mm3": float(vol.min())}
    if layer is not None:
        report["boundary_layer"] = layer
    return report


def build_mesh(surface: pv.PolyData, *, layers: int = 10, ratio: float = 1.2, thickness: float | None = None,
               thickness_ratio: float | None = 0.3, size: float | None = None, core: str = "gmsh",
               lloyd_iterations: int = 5) -> tuple[pv.UnstructuredGrid, dict]:
    """Boundary-layer tetrahedral mesh of a labelled lumen surface.

    Parameters
    ----------
    surface : pyvista.PolyData
        Closed triangle surface (mm) with ``CellEntityIds`` (wall 1, inlet 2,
        outlets 3, ...), planar caps.
    layers : int
        Number of prism sub-layers N (0: no layer, core only).
    ratio : float
        Height ratio f between neighbouring sub-layers (thinnest at the wall).
    thickness : float, optional
        Total layer thickness in mm; overrides ``thickness_ratio``.
    thickness_ratio : float, optional
        Total thickness as a fraction of the local radius (default 0.3).
    size : float, optional
        Target core edge length (mm); default the median wall edge.
    core : {"gmsh", "tetgen"}
        Core mesher: gmsh's HXT with its optimiser (default; no core
        tetrahedron below ~14 degrees in our tests) or TetGen ``-pYq1.2/15``
        (leaves a few slivers down to ~2 degrees).
    lloyd_iterations : int
        Lloyd smoothing iterations of the interior core vertices.

    Returns
    -------
    mesh : pyvista.UnstructuredGrid
        Tetrahedra (``CellEntityIds`` 0, ``Region`` 0 layer / 1 core) followed
        by the boundary triangles (``CellEntityIds`` = face label, ``Region``
        -1), the VMTK layout of a volume mesh with its boundary.
    quality : dict
        Element counts, dihedral angles, radius-ratio histograms, volume
        check, measured sub-layer heights and growth ratio, timings.
    """
    clock = {"start": time.perf_counter()}
    surf = check_surface(surface)
    size = median_edge(surf) if size is None else float(size)
    if size <= 0:
        raise CarotidError("the element size must be positive")
    if layers > 0:
        layer = build_layers(surf, layers=layers, ratio=ratio, thickness=thickness, thickness_ratio=thickness_ratio)
        points, layer_tets, inner = layer.points, layer.tets, layer.inner_triangles
    else:
        layer, points, layer_tets, inner = None, surf.points, np.zeros((0, 4), np.int64), surf.triangles
    clock["layers"] = time.perf_counter()
    used = np.unique(inner)
    local = np.full(len(points), -1)
    local[used] = np.arange(used.size)
    nodes, core_tets = mesh_core(points[used], local[inner], size, core)
    to_global = np.concatenate([used, len(points) + np.arange(len(nodes) - used.size)])
    points = np.vstack([points, nodes[used.size:]])
    core_tets = to_global[core_tets]
    clock["core"] = time.perf_counter()
    free = np.zeros(len(points), dtype=bool)
    free[len(points) - (len(nodes) - used.size):] = True
    points, lloyd = lloyd_smooth(points, core_tets, free, iterations=lloyd_iterations)
    clock["lloyd"] = time.perf_counter()
    tets = np.vstack([layer_tets, core_tets])
    region = np.r_[np.full(len(layer_tets), LAYER), np.full(len(core_tets), CORE)]
    faces = boundary_faces(tets)
    labels = _label_boundary(faces, surf, _vertex_caps(surf, len(points), layer))
    profile = layer_profile(points, layer, ratio) if layer is not None else None
    points, tets, faces = _compact(points, tets, faces)
    if profile is not None:
        profile["read_back_from_mesh"] = walked_profile(points, tets, faces[labels == WALL], layer, ratio)
    mesh = pv.UnstructuredGrid({pv.CellType.TETRA: tets, pv.CellType.TRIANGLE: faces}, points)
    mesh.cell_data[LABELS] = np.r_[np.zeros(len(tets), np.int32), labels].astype(np.int32)
    mesh.cell_data["Region"] = np.r_[region, np.full(len(faces), BOUNDARY)].astype(np.int32)
    lab, count = np.unique(labels, return_counts=True)
    quality = mesh_quality(points, tets, region, {int(k): int(c) for k, c in zip(lab, count)},
                           signed_volume(surf.points, surf.triangles), profile)
    quality["parameters"] = {"layers": layers, "ratio": ratio, "thickness_mm": thickness,
                             "thickness_ratio": None if thickness is not None else thickness_ratio,
                             "size_mm": size, "core": core, "lloyd_iterations": lloyd_iterations}
    quality["lloyd"] = lloyd
    quality["seconds"] = {"layers": clock["layers"] - clock["start"], "core": clock["core"] - clock["layers"],
                          "lloyd": clock["lloyd"] - clock["core"], "total": time.perf_counter() - clock["start"]}
    return mesh, quality
