"""The labelled lumen surface as plain arrays, checked for what the volume mesher needs.

A surface is accepted when it is a closed, edge-manifold, orientable triangle
mesh; it is oriented outward (positive enclosed volume).  Faces carry the VMTK
labels ``CellEntityIds``: wall 1, inlet 2, outlets 3, 4, ...; every cap
(label >= 2) must be planar.  Open surfaces can be closed by
:func:`cap_open_ends`, which adds one planar, labelled cap per boundary loop.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pyvista as pv
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree
from skimage.measure import points_in_poly

from carotid.errors import CarotidError, CarotidWarning

WALL, INLET = 1, 2
LABELS = "CellEntityIds"
HOLE_PERIMETER = 0.15
"""An open end whose perimeter is under this fraction of the largest end's is more likely a hole in the wall than a
vessel's cut end (a carotid's smallest branches, 1 mm across beside a 7 mm CCA, have 0.15 of its perimeter):
it is still capped, with a warning."""


@dataclass(frozen=True)
class Surface:
    """A closed, outward-oriented, labelled triangle surface.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
        Vertex coordinates in mm.
    triangles : ndarray, shape (m, 3), int64
        Vertex indices, counter-clockwise seen from outside.
    labels : ndarray, shape (m,), int32
        Face labels (wall 1, inlet 2, outlets 3, ...).
    """

    points: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray

    def to_polydata(self) -> pv.PolyData:
        """The surface as PolyData with the ``CellEntityIds`` cell array."""
        poly = pv.PolyData.from_regular_faces(self.points, self.triangles)
        poly.cell_data[LABELS] = self.labels.astype(np.int32)
        return poly


def edge_faces(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges of a triangle mesh and how often each occurs.

    Returns
    -------
    edges : ndarray, shape (3m, 2)
        Directed edges (v0->v1, v1->v2, v2->v0 of every face, face-major).
    key : ndarray, shape (3m,)
        Index of each directed edge's undirected edge in the unique list.
    counts : ndarray, shape (e,)
        Number of faces on each undirected edge.
    """
    edges = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    _, key, counts = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True, return_counts=True)
    return edges, key.ravel(), counts


def orient_outward(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Consistently orient a closed edge-manifold surface, outward in every connected part.

    The orientation of every face relative to one face per part is found as
    the connected components of a doubled face graph (face kept / face
    flipped), so no face-by-face traversal is needed.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    triangles : ndarray, shape (m, 3)

    Returns
    -------
    ndarray, shape (m, 3)
        The triangles, some reversed.

    Raises
    ------
    CarotidError
        If the surface is not orientable.
    """
    m = len(triangles)
    edges, key, _ = edge_faces(triangles)
    order = np.argsort(key, kind="stable")
    first, second = order[0::2], order[1::2]  # the two directed copies of every (manifold) edge
    fa, fb = first // 3, second // 3
    flip = edges[first, 0] == edges[second, 0]  # same direction in both faces: one of them must turn
    rows = np.concatenate([fa, fa + m])
    cols = np.concatenate([np.where(flip, fb + m, fb), np.where(flip, fb, fb + m)])
    graph = sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(2 * m, 2 * m))
    _, comp = connected_components(graph, directed=False)
    if np.any(comp[:m] == comp[m:]):
        raise CarotidError("the surface is not orientable (a Moebius-like defect); repair it before meshing")
    # A face keeps its orientation when it shares the component of the smallest face of its part.
    part_rep = np.minimum(comp[:m], comp[m:])
    keep = comp[:m] == part_rep
    tri = np.where(keep[:, None], triangles, triangles[:, ::-1])
    a, b, c = (points[tri[:, k]] for k in range(3))
    part_volume = np.bincount(part_rep, weights=np.einsum("ij,ij->i", a, np.cross(b, c)), minlength=2 * m)
    outward = part_volume[part_rep] > 0
    return np.where(outward[:, None], tri, tri[:, ::-1])


def cap_planes(surface: Surface) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Plane of every cap: ``{label: (centre (3,), outward unit normal (3,))}``."""
    planes = {}
    for label in np.unique(surface.labels[surface.labels != WALL]):
        tri = surface.triangles[surface.labels == label]
        a, b, c = (surface.points[tri[:, k]] for k in range(3))
        area_normal = 0.5 * np.cross(b - a, c - a)
        normal = area_normal.sum(axis=0)
        normal /= np.linalg.norm(normal)
        centre = surface.points[np.unique(tri)].mean(axis=0)
        planes[int(label)] = (centre, normal)
    return planes


def check_surface(poly: pv.PolyData, *, planar_tolerance: float = 1e-4) -> Surface:
    """Validate a labelled lumen surface and return it as arrays, oriented outward.

    Parameters
    ----------
    poly : pyvista.PolyData
        Closed triangle surface in mm with the cell array ``CellEntityIds``.
    planar_tolerance : float
        Largest distance of a cap vertex from the cap's plane, relative to the
        cap's size.

    Returns
    -------
    Surface

    Raises
    ------
    CarotidError
        Missing labels, no wall, open or non-manifold surface, non-planar cap.
    """
    if poly.n_cells == 0:
        raise CarotidError("the surface is empty")
    if LABELS not in poly.cell_data:
        raise CarotidError(f"the surface has no '{LABELS}' face labels (wall 1, inlet 2, outlets 3...); "
                           "run `carotid surface` or use `carotid mesh --from-surface`")
    poly = poly.triangulate().clean(tolerance=0.0)
    triangles = poly.regular_faces.astype(np.int64)
    labels = np.asarray(poly.cell_data[LABELS], dtype=np.int32)
    points = np.asarray(poly.points, dtype=float)
    if not np.any(labels == WALL):
        raise CarotidError(f"no wall faces ({LABELS} == 1) on the surface")
    if np.any(labels < WALL):
        raise CarotidError(f"invalid face labels {np.unique(labels[labels < WALL]).tolist()}: wall 1, caps >= 2")
    _, _, counts = edge_faces(triangles)
    if np.any(counts == 1):
        raise CarotidError(f"the surface is open ({int(np.sum(counts == 1))} boundary edges); "
                           "cap it (`carotid mesh --from-surface` caps open ends) before meshing")
    if np.any(counts > 2):
        raise CarotidError(f"the surface is not manifold ({int(np.sum(counts > 2))} edges with > 2 faces)")
    surface = Surface(points, orient_outward(points, triangles), labels)
    for label, (centre, normal) in cap_planes(surface).items():
        ids = np.unique(surface.triangles[surface.labels == label])
        offset = (points[ids] - centre) @ normal
        extent = np.linalg.norm(points[ids] - centre, axis=1).max()
        if np.abs(offset).max() > planar_tolerance * extent:
            raise CarotidError(f"cap {label} is not planar (off its plane by {np.abs(offset).max():.3g} mm)")
    return surface


def _boundary_loops(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Directed boundary edges (as oriented in their faces) and the loop index of each."""
    edges, key, counts = edge_faces(triangles)
    boundary = edges[counts[key] == 1]
    n = int(triangles.max()) + 1
    graph = sparse.coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    loop_ids, loop = np.unique(comp[boundary[:, 0]], return_inverse=True)
    return boundary, loop, len(loop_ids)


def triangulate_loop(points: np.ndarray, loop_edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar triangulation of one boundary loop: new points (k, 3) and triangles on global indices.

    The rim is ordered by angle around its centroid in its best-fit plane (a
    vessel cross-section is star-shaped); interior points on a triangular
    lattice with the rim's edge length are triangulated with the rim by
    Delaunay.  If a rim edge is missing from the triangulation, a fan from
    the centroid is used instead.  Rim vertices are not moved; interior
    points lie in the best-fit plane.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        All vertices (mm).
    loop_edges : ndarray, shape (e, 2)
        The loop's edges (indices into ``points``).

    Returns
    -------
    new_points : ndarray, shape (k, 3)
        Interior points, to be appended to ``points``.
    triangles : ndarray, shape (t, 3)
        Triangles on the indices of ``points`` followed by the new points
        (orientation arbitrary but consistent).
    """
    rim = np.unique(loop_edges)
    centre = points[rim].mean(axis=0)
    _, _, vt = np.linalg.svd(points[rim] - centre)
    u, v = vt[0], vt[1]
    rim_uv = np.c_[(points[rim] - centre) @ u, (points[rim] - centre) @ v]
    order = np.argsort(np.arctan2(rim_uv[:, 1], rim_uv[:, 0]))
    rim, rim_uv = rim[order], rim_uv[order]
    h = np.linalg.norm(points[loop_edges[:, 0]] - points[loop_edges[:, 1]], axis=1).mean()
    extent = np.abs(rim_uv).max()
    g = np.arange(-extent, extent + h, h)
    gu, gv = np.meshgrid(g, g * np.sqrt(3) / 2, indexing="ij")
    lattice = np.c_[gu.ravel() + 0.5 * h * (np.arange(gv.shape[1]) % 2)[None, :].repeat(len(g), 0).ravel(),
                    gv.ravel()]
    inside = points_in_poly(lattice, rim_uv)
    dist = np.min(np.linalg.norm(lattice[:, None, :] - rim_uv[None, :, :], axis=2), axis=1)
    inner = lattice[inside & (dist > 0.6 * h)]
    local = Delaunay(np.vstack([rim_uv, inner])).simplices
    all_uv = np.vstack([rim_uv, inner])
    centroids = all_uv[local].mean(axis=1)
    local = local[points_in_poly(centroids, rim_uv)]
    n_new = len(inner)
    ids = np.concatenate([rim, len(points) + np.arange(n_new)])
    tri = ids[local]
    edges, key, counts = edge_faces(tri)
    rim_edges = np.unique(np.sort(edges[counts[key] == 1], axis=1), axis=0)
    if np.any(counts > 2) or not np.array_equal(rim_edges, np.unique(np.sort(loop_edges, axis=1), axis=0)):
        # the Delaunay triangulation misses a rim edge: fall back to a fan
        n_new, inner = 1, np.zeros((1, 2))
        nxt = np.roll(np.arange(len(rim)), -1)
        tri = np.c_[rim, rim[nxt], np.full(len(rim), len(points))]
    new_points = centre + inner[:, :1] * u + inner[:, 1:] * v
    return new_points, tri


def cap_open_ends(poly: pv.PolyData) -> pv.PolyData:
    """Close every boundary loop of an open surface with a planar, labelled cap.

    The existing faces become wall (1); the loop with the largest perimeter
    (the common carotid inlet) is labelled 2 and the others 3, 4, ... by
    decreasing perimeter.  A loop under ``HOLE_PERIMETER`` of the largest
    one's perimeter is capped too, with a CarotidWarning: it may be a hole.

    Parameters
    ----------
    poly : pyvista.PolyData
        Open triangle surface (mm).

    Returns
    -------
    pyvista.PolyData
        Closed surface with ``CellEntityIds``.  A boundary loop that is far
        from planar gives a cap that :func:`check_surface` rejects.
    """
    poly = poly.triangulate().clean()
    points = np.asarray(poly.points, dtype=float)
    triangles = poly.regular_faces.astype(np.int64)
    boundary, loop, n_loops = _boundary_loops(triangles)
    lengths = np.bincount(loop, weights=np.linalg.norm(points[boundary[:, 0]] - points[boundary[:, 1]], axis=1))
    small = np.sort(lengths[lengths < HOLE_PERIMETER * lengths.max()])
    if small.size:
        warnings.warn(f"{small.size} open end(s) of perimeter {', '.join(f'{x:.2g}' for x in small)} mm, under "
                      f"{HOLE_PERIMETER:g} of the largest end's ({lengths.max():.3g} mm), capped as outlets: if they "
                      "are holes in the wall, close them first", CarotidWarning, stacklevel=2)
    faces, labels = [triangles], [np.full(len(triangles), WALL)]
    for rank, index in enumerate(np.argsort(-lengths)):
        new_points, tri = triangulate_loop(points, boundary[loop == index])
        points = np.vstack([points, new_points])
        faces.append(tri)
        labels.append(np.full(len(tri), INLET + rank))
    out = pv.PolyData.from_regular_faces(points, np.vstack(faces))
    out.cell_data[LABELS] = np.concatenate(labels).astype(np.int32)
    return out


def _patch_loops(triangles: np.ndarray, patch: np.ndarray, n_patches: int) -> np.ndarray:
    """Number of boundary loops of every patch of a closed surface, shape (n_patches,).

    An edge whose two faces lie in different patches is a boundary edge of
    both; the loops of a patch are the connected components of its boundary
    edges, found for all patches at once on the graph of (patch, vertex) pairs.
    """
    edges, key, _ = edge_faces(triangles)
    order = np.argsort(key, kind="stable")
    first, second = order[0::2], order[1::2]
    pa, pb = patch[first // 3], patch[second // 3]
    cut = pa != pb
    ends = edges[first[cut]]
    owner = np.r_[pa[cut], pb[cut]]
    pairs = np.c_[np.r_[owner, owner], np.r_[ends[:, 0], ends[:, 0], ends[:, 1], ends[:, 1]]]
    nodes, node = np.unique(pairs, axis=0, return_inverse=True)
    node = node.ravel()
    half = len(pairs) // 2
    graph = sparse.coo_matrix((np.ones(half), (node[:half], node[half:])), shape=(len(nodes), len(nodes)))
    _, comp = connected_components(graph, directed=False)
    loops = np.unique(np.c_[nodes[:, 0], comp], axis=0)[:, 0]
    return np.bincount(loops, minlength=n_patches)


def label_flat_caps(poly: pv.PolyData, *, feature_deg: float = 60.0, flat_deg: float = 1.0,
                    min_area_fraction: float = 1e-3, end_ball: float = 1.5, end_tolerance: float = 0.05
                    ) -> pv.PolyData:
    """Label the flat end caps of a closed, unlabelled surface (wall 1, inlet 2, outlets 3, ...).

    Faces are grouped into patches bounded by sharp edges (adjacent normals
    more than ``feature_deg`` apart).  A patch is an end cap when

    * its normals all lie within ``flat_deg`` of its mean normal, it is not
      the largest patch and it covers at least ``min_area_fraction`` of the
      surface (a flat patch);
    * its boundary is a single loop (a disc: the flat annulus of a sudden
      expansion or contraction has two loops);
    * the lumen ends there, so that the lumen's axis crosses it: every
      vertex within ``end_ball`` equivalent radii (``sqrt(area / pi)``) of
      the cap's centroid lies on the inner side of the cap's plane, within
      ``end_tolerance`` equivalent radii (a flat step inside the lumen has
      wall on both sides of its plane).

    The cap with the largest area (the common carotid inlet) is 2, the
    others 3, 4, ... by decreasing area; every other patch is wall.

    Parameters
    ----------
    poly : pyvista.PolyData
        Closed triangle surface (mm).
    feature_deg, flat_deg : float
        Sharp-edge and flatness angles (degrees).
    min_area_fraction : float
        Smallest cap area relative to the whole surface (smaller flat patches are wall).
    end_ball, end_tolerance : float
        Radius of the neighbourhood checked to lie behind the cap, and the
        tolerance of that check, in equivalent cap radii.

    Returns
    -------
    pyvista.PolyData
        The cleaned surface with ``CellEntityIds``.

    Raises
    ------
    CarotidError
        If no flat end cap is found.
    """
    poly = poly.triangulate().clean()
    points = np.asarray(poly.points, dtype=float)
    triangles = orient_outward(points, poly.regular_faces.astype(np.int64))
    normal = np.cross(points[triangles[:, 1]] - points[triangles[:, 0]],
                      points[triangles[:, 2]] - points[triangles[:, 0]])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    unit = normal / np.maximum(2.0 * area[:, None], 1e-300)
    _, key, _ = edge_faces(triangles)
    order = np.argsort(key, kind="stable")
    fa, fb = order[0::2] // 3, order[1::2] // 3
    smooth = np.einsum("ij,ij->i", unit[fa], unit[fb]) > np.cos(np.radians(feature_deg))
    m = len(triangles)
    graph = sparse.coo_matrix((np.ones(int(smooth.sum())), (fa[smooth], fb[smooth])), shape=(m, m))
    n_patches, patch = connected_components(graph, directed=False)
    patch_area = np.bincount(patch, weights=area, minlength=n_patches)
    mean = np.stack([np.bincount(patch, weights=area * unit[:, k], minlength=n_patches) for k in range(3)], axis=1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    spread = np.zeros(n_patches)
    np.maximum.at(spread, patch, 1.0 - np.einsum("ij,ij->i", unit, mean[patch]))
    flat = ((spread < 1.0 - np.cos(np.radians(flat_deg))) & (np.arange(n_patches) != np.argmax(patch_area))
            & (patch_area >= min_area_fraction * area.sum()))
    flat &= _patch_loops(triangles, patch, n_patches) == 1
    centroid = np.stack([np.bincount(patch, weights=area * points[triangles].mean(axis=1)[:, k],
                                     minlength=n_patches) for k in range(3)], axis=1)
    centroid /= np.maximum(patch_area[:, None], 1e-300)
    tree = cKDTree(points)
    for index in np.flatnonzero(flat):  # a few flat candidates
        radius = np.sqrt(patch_area[index] / np.pi)
        near = tree.query_ball_point(centroid[index], end_ball * radius)
        flat[index] = ((points[near] - centroid[index]) @ mean[index]).max() <= end_tolerance * radius
    caps = np.flatnonzero(flat)
    if caps.size == 0:
        raise CarotidError("the surface has no face labels and no flat end caps: label the inlet and outlets "
                           "(CellEntityIds) or give the open surface so that its ends can be capped")
    label_of = np.full(n_patches, WALL, dtype=np.int32)
    label_of[caps[np.argsort(-patch_area[caps])]] = INLET + np.arange(caps.size)
    out = pv.PolyData.from_regular_faces(points, triangles)
    out.cell_data[LABELS] = label_of[patch]
    return out
