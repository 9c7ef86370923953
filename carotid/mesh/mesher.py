"""``build_mesh``: boundary layer + core + Lloyd smoothing, assembled into one conforming tetrahedral mesh."""

from __future__ import annotations

import time

import numpy as np
import pyvista as pv

from carotid.errors import CarotidError
from carotid.mesh.boundary import LABELS, WALL, Surface, check_surface
from carotid.mesh.core import boundary_faces, face_keys, mesh_core, regular_tet_volume
from carotid.mesh.layers import BoundaryLayer, build_layers, tet_volumes
from carotid.mesh.quality import (angle_summary, distribution, extreme_dihedrals, histogram, min_dihedral,
                                  prism_measures, radius_ratio, walk_layers)
from carotid.mesh.smooth import lloyd_smooth
from carotid.surface.mesh import signed_volume

LAYER, CORE, BOUNDARY = 0, 1, -1
"""Values of the ``Region`` cell array: layer and core tetrahedra, boundary triangles."""

CORE_MIN_DIHEDRAL = 10.0
"""Floor (degrees) of the smallest dihedral angle of a core tetrahedron, the one the report checks.  gmsh's
HXT with its optimiser keeps most core elements of a well-separated inner surface above ~14 degrees, but its
single worst element is chaotic: on the 10-layer benchmark phantom a layer 1 % thinner moved it from 12.8 to
7.5 degrees.  A core element below the floor spans a place where the layer's inner surface comes close to
itself (a crease, a thin passage), whose vertices no optimiser may move, and such slivers make the
finite-element stiffness ill-conditioned.  :func:`build_mesh` thins the layer there until none is left (gmsh
core)."""

CORE_REPAIR_ROUNDS, THINNING = 6, 0.7
"""Rounds of local layer thinning against core slivers, and the thickness factor of each round.  Only with
the gmsh core: TetGen's ``-q`` leaves slivers of 1.5-2 degrees all through the core, which thinning does
not remove (on the benchmark surfaces all six rounds ran, for 3x the time, and cut the core tetrahedra
below the floor from 476 / 746 to 100 / 96 only by thinning the layer at 56-65 % of the wall vertices,
against 7-15 % with gmsh); they are reported."""

MAX_CORE_TETRAHEDRA = 20_000_000
"""Most core tetrahedra :func:`build_mesh` is asked for: a carotid bifurcation (some 3 cm^3 of lumen) meshed at
its default sizes has about a million, the finest published ones a few million; 20 million take gmsh hours and
the flow solver more memory than a workstation has, so a size giving more is refused at once, not meshed."""

DEGENERATE_PRISM = 0.1
"""A prism lower than this fraction of its requested height counts as degenerate in the report."""


def median_edge(surface: Surface) -> float:
    """Median edge length (mm) of the wall triangles."""
    tri = surface.triangles[surface.labels == WALL]
    p = surface.points
    return float(np.median(np.linalg.norm(p[tri] - p[np.roll(tri, 1, axis=1)], axis=2)))


def check_core_size(surface: Surface, size: float) -> None:
    """Raise CarotidError when the core at ``size`` would exceed ``MAX_CORE_TETRAHEDRA``.

    The estimate is the enclosed volume over the volume of a regular tetrahedron of edge ``size``.

    Parameters
    ----------
    surface : Surface
        The closed labelled surface, mm.
    size : float
        Core edge length, mm.
    """
    volume = abs(signed_volume(surface.points, surface.triangles))
    estimate = volume / regular_tet_volume(size)
    if estimate > MAX_CORE_TETRAHEDRA:
        fit = 1.05 * size * (estimate / MAX_CORE_TETRAHEDRA) ** (1.0 / 3.0)  # 1.05: .2g rounds within 5%
        raise CarotidError(f"a core element size of {size:g} mm would make about {estimate:.2g} tetrahedra in the "
                           f"{volume:.4g} mm^3 lumen, over the {MAX_CORE_TETRAHEDRA:.0e} limit: use a size of at "
                           f"least {fit:.2g} mm (--size, [mesh] size_mm)")


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
        ``ratio`` (None for a single sub-layer), and the fraction of wall
        vertices whose thickness was reduced.
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
            "growth_ratio": None if growth.size == 0 else  # one sub-layer: no ratio to measure
            {"mean": float(growth.mean()), "min": float(growth.min()), "max": float(growth.max()),
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
            "growth_ratio_abs_error": None if growth.size == 0 else
            {"mean": float(np.nanmean(growth)), "max": float(np.nanmax(growth))}}


def prism_quality(points: np.ndarray, layer: BoundaryLayer) -> dict:
    """Quality of the layer judged by its prisms (:func:`carotid.mesh.quality.prism_measures`).

    The requested height of a prism is the mean over its three columns of
    the requested thickness times its sub-layer's fraction of it, so
    thickness reductions show as height ratios below 1.

    Returns
    -------
    dict
        ``count``, distributions (min / p1 / median / p99 / max) of the base
        triangle angles, skew (degrees), height (mm) and height ratio, and
        ``degenerate``: the number of prisms lower than ``DEGENERATE_PRISM``
        times their requested height and the smallest height ratio.
    """
    n_layers = len(layer.fractions) - 1
    per_layer = len(layer.prisms) // n_layers
    wall_index = np.full(len(points), -1)
    wall_index[layer.columns] = np.arange(layer.columns.shape[1])[None, :]
    share = np.repeat(np.diff(layer.fractions), per_layer)
    requested = layer.requested[wall_index[layer.prisms[:, :3]]].mean(axis=1) * share
    measures = prism_measures(points, layer.prisms, requested)
    low = measures["height_ratio"] < DEGENERATE_PRISM
    return {"count": int(len(layer.prisms)),
            **{name: distribution(values) for name, values in measures.items()},
            "degenerate": {"height_ratio_below": DEGENERATE_PRISM, "count": int(low.sum())}}


def mesh_quality(points: np.ndarray, tets: np.ndarray, region: np.ndarray, n_boundary: dict, enclosed: float,
                 layer: dict | None = None, prisms: dict | None = None) -> dict:
    """The quality report written to ``mesh_quality.json`` (see :func:`build_mesh`).

    ``mesh`` summarises the whole mesh: the smallest dihedral angle of all
    tetrahedra, the core's against ``CORE_MIN_DIHEDRAL`` (count and worst
    of the core elements below it) and the degenerate prisms.  ``layer``
    holds the dihedral angles of the split-prism tetrahedra (flat by
    construction in a thin layer: the prisms in ``layer_prisms`` are the
    measure of the layer), ``core`` those of the core tetrahedra.
    """
    angles = min_dihedral(points, tets)
    vol = tet_volumes(points, tets)
    report = {"elements": {"tetrahedra": int(len(tets)), "layer": int(np.sum(region == LAYER)),
                           "core": int(np.sum(region == CORE)), "points": int(len(points)),
                           "boundary_triangles": n_boundary}}
    for name, code in (("layer", LAYER), ("core", CORE)):
        sel = region == code
        if sel.any():
            dihedral_max = extreme_dihedrals(points, tets[sel])[1]
            report[name] = {"elements": "split-prism tetrahedra" if code == LAYER else "core tetrahedra",
                            "min_dihedral": angle_summary(angles[sel]),
                            "max_dihedral_deg": float(dihedral_max.max()),
                            "radius_ratio_histogram": histogram(radius_ratio(points, tets[sel]),
                                                                np.linspace(0.0, 1.0, 11))}
    report["volume"] = {"mesh_mm3": float(vol.sum()), "surface_mm3": enclosed,
                        "relative_error": float(abs(vol.sum() - enclosed) / enclosed),
                        "min_tet_mm3": float(vol.min())}
    core_angles = angles[region == CORE]
    below = core_angles < CORE_MIN_DIHEDRAL
    report["mesh"] = {"min_dihedral_deg": float(angles.min()),
                      "core": {"floor_deg": CORE_MIN_DIHEDRAL, "below_floor": int(below.sum()),
                               "worst_deg": float(core_angles.min()) if core_angles.size else None},
                      "layer_prisms_degenerate": prisms["degenerate"]["count"] if prisms is not None else 0}
    if layer is not None:
        report["boundary_layer"] = layer
    if prisms is not None:
        report["layer_prisms"] = prisms
    return report


def _layer_and_core(surf: Surface, scale: np.ndarray, clock: dict, *, layers: int, ratio: float,
                    thickness: float | None, thickness_ratio: float | None, size: float, core: str,
                    lloyd_iterations: int) -> tuple[BoundaryLayer | None, np.ndarray, np.ndarray, dict, dict]:
    """One pass of :func:`build_mesh`: the layer (thickness times ``scale``), the core inside it, Lloyd smoothing.

    Returns the layer (None without one), all points (mm), the global core
    tetrahedra, Lloyd's report and ``clock`` with the end times of the
    ``layers``, ``core`` and ``lloyd`` steps.
    """
    if layers > 0:
        layer = build_layers(surf, layers=layers, ratio=ratio, thickness=thickness, thickness_ratio=thickness_ratio,
                             scale=scale)
        points, inner = layer.points, layer.inner_triangles
    else:
        layer, points, inner = None, surf.points, surf.triangles
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
    return layer, points, core_tets, lloyd, clock


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
        tetrahedron below ~14 degrees in our tests; the layer is thinned where
        one falls below ``CORE_MIN_DIHEDRAL``) or TetGen ``-pYq1.2/15``
        (leaves a few slivers down to ~2 degrees, reported, not repaired).
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
    check_core_size(surf, size)
    scale = np.ones(np.unique(surf.triangles[surf.labels == WALL]).size)
    rounds = CORE_REPAIR_ROUNDS if core == "gmsh" else 0
    for repair in range(rounds + 1):
        layer, points, core_tets, lloyd, clock = _layer_and_core(surf, scale, clock, layers=layers, ratio=ratio,
                                                                 thickness=thickness,
                                                                 thickness_ratio=thickness_ratio, size=size,
                                                                 core=core, lloyd_iterations=lloyd_iterations)
        sliver = core_tets[min_dihedral(points, core_tets) < CORE_MIN_DIHEDRAL]
        wall_index = np.full(len(points), -1)
        if layer is not None:
            wall_index[layer.columns[-1]] = np.arange(layer.columns.shape[1])
        touched = np.unique(wall_index[sliver])
        touched = touched[touched >= 0]
        if touched.size == 0 or repair == rounds:
            break
        scale[touched] *= THINNING
    layer_tets = layer.tets if layer is not None else np.zeros((0, 4), np.int64)
    tets = np.vstack([layer_tets, core_tets])
    region = np.r_[np.full(len(layer_tets), LAYER), np.full(len(core_tets), CORE)]
    faces = boundary_faces(tets)
    labels = _label_boundary(faces, surf, _vertex_caps(surf, len(points), layer))
    profile = layer_profile(points, layer, ratio) if layer is not None else None
    prisms = prism_quality(points, layer) if layer is not None else None
    if profile is not None:
        profile["thinned_against_core_slivers"] = {"rounds": repair, "wall_vertices": int(np.sum(scale < 1.0))}
    points, tets, faces = _compact(points, tets, faces)
    if profile is not None:
        profile["read_back_from_mesh"] = walked_profile(points, tets, faces[labels == WALL], layer, ratio)
    mesh = pv.UnstructuredGrid({pv.CellType.TETRA: tets, pv.CellType.TRIANGLE: faces}, points)
    mesh.cell_data[LABELS] = np.r_[np.zeros(len(tets), np.int32), labels].astype(np.int32)
    mesh.cell_data["Region"] = np.r_[region, np.full(len(faces), BOUNDARY)].astype(np.int32)
    lab, count = np.unique(labels, return_counts=True)
    quality = mesh_quality(points, tets, region, {int(k): int(c) for k, c in zip(lab, count)},
                           signed_volume(surf.points, surf.triangles), profile, prisms)
    quality["parameters"] = {"layers": layers, "ratio": ratio, "thickness_mm": thickness,
                             "thickness_ratio": None if thickness is not None else thickness_ratio,
                             "size_mm": size, "core": core, "lloyd_iterations": lloyd_iterations}
    quality["lloyd"] = lloyd
    quality["seconds"] = {"layers": clock["layers"] - clock["start"], "core": clock["core"] - clock["layers"],
                          "lloyd": clock["lloyd"] - clock["core"], "total": time.perf_counter() - clock["start"]}
    return mesh, quality
