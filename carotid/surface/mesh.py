"""Triangle-mesh plumbing shared by the surface stage: PolyData conversion, edges, components, volume.

A surface is handled as ``points`` (n, 3) float64 mm, ``faces`` (m, 3) int64 (counter-clockwise seen
from outside) and ``labels`` (m,) int32 (``CellEntityIds``: wall 1, inlet 2, outlets 3, 4, ...).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy import sparse
from scipy.sparse import csgraph

LABEL_ARRAY = "CellEntityIds"
WALL = 1


def to_polydata(points: np.ndarray, faces: np.ndarray, labels: np.ndarray | None = None) -> pv.PolyData:
    """PolyData of a triangle mesh, with ``CellEntityIds`` when ``labels`` are given."""
    faces = np.asarray(faces, np.int64)
    cells = np.hstack([np.full((len(faces), 1), 3, np.int64), faces]).ravel()
    poly = pv.PolyData(np.asarray(points, float), cells)
    if labels is not None:
        poly.cell_data[LABEL_ARRAY] = np.asarray(labels, np.int32)
    return poly


def from_polydata(poly: pv.PolyData) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points (n,3), faces (m,3), labels (m,))`` of a triangulated PolyData; labels default to the wall."""
    if not poly.is_all_triangles:
        poly = poly.triangulate()
    faces = np.asarray(poly.faces).reshape(-1, 4)[:, 1:].astype(np.int64) if poly.n_cells else np.zeros((0, 3), int)
    labels = (np.asarray(poly.cell_data[LABEL_ARRAY], np.int32) if LABEL_ARRAY in poly.cell_data
              else np.full(len(faces), WALL, np.int32))
    return np.asarray(poly.points, float), faces, labels


def edges_of(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique undirected edges of a triangle mesh.

    Returns
    -------
    edges : ndarray, shape (ne, 2)
        Vertex pairs, smaller index first.
    half_edge : ndarray, shape (3 m,)
        Edge index of half-edge ``3 f + i`` (from corner ``i`` to corner ``i + 1`` of face ``f``).
    count : ndarray, shape (ne,)
        Number of faces sharing each edge (2 on a closed manifold).
    """
    he = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    key = np.sort(he, axis=1)
    edges, half_edge, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return edges, half_edge.ravel(), count


def compact(points: np.ndarray, faces: np.ndarray, *arrays: np.ndarray):
    """Drop unreferenced points; returns ``(points, faces, *point arrays)`` re-indexed."""
    used = np.zeros(len(points), bool)
    used[faces.ravel()] = True
    new = np.cumsum(used) - 1
    return (points[used], new[faces], *(a[used] for a in arrays))


def face_components(n_points: int, faces: np.ndarray) -> np.ndarray:
    """Connected-component label (m,) of every face, faces linked through shared vertices."""
    m = len(faces)
    rows = np.repeat(np.arange(m), 3)
    inc = sparse.csr_matrix((np.ones(3 * m), (rows, faces.ravel())), shape=(m, n_points))
    _, vertex_label = csgraph.connected_components(inc.T @ inc, directed=False)
    return vertex_label[faces[:, 0]]


def largest_component(points: np.ndarray, faces: np.ndarray, labels: np.ndarray | None = None):
    """Keep the component with the most faces; returns ``(points, faces, labels)``."""
    comp = face_components(len(points), faces)
    keep = comp == np.argmax(np.bincount(comp))
    labels = np.full(len(faces), WALL, np.int32) if labels is None else labels
    pts, fcs = compact(points, faces[keep])
    return pts, fcs, labels[keep]


def face_normals(points: np.ndarray, faces: np.ndarray, unit: bool = True) -> np.ndarray:
    """Face normals (m, 3); unnormalised (twice the area) if ``unit`` is False."""
    p = points[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    if unit:
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def face_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas (m,) in mm^2."""
    return 0.5 * np.linalg.norm(face_normals(points, faces, unit=False), axis=1)


def signed_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume in mm^3 (divergence theorem); positive when the normals point outward."""
    p = points[faces]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3)."""
    fn = face_normals(points, faces, unit=False)
    vn = np.zeros_like(points)
    for i in range(3):
        np.add.at(vn, faces[:, i], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def adjacency(n_points: int, faces: np.ndarray) -> sparse.csr_matrix:
    """Symmetric vertex adjacency (n, n) with ones on mesh edges."""
    edges, _, _ = edges_of(faces)
    a = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_points, n_points))
    return (a + a.T).tocsr()


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops, each an ordered vertex array following the faces' orientation.

    Boundary half-edges (a, b) are those whose edge belongs to one face only; a loop is the depth-first
    order of its half-edge chain, so a vertex shared by two loops (a pinch) shows up as a loop whose
    length differs from its number of boundary edges (see ``carotid.surface.quality``).
    """
    edges, half_edge, count = edges_of(faces)
    he = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    bnd = he[count[half_edge] == 1]
    if len(bnd) == 0:
        return []
    n = int(faces.max()) + 1
    succ = sparse.csr_matrix((np.ones(len(bnd)), (bnd[:, 0], bnd[:, 1])), shape=(n, n))
    _, comp = csgraph.connected_components(succ, directed=True, connection="weak")
    loops = []
    for c in np.unique(comp[bnd[:, 0]]):  # loop over boundary loops, a handful
        members = bnd[comp[bnd[:, 0]] == c, 0]
        order = csgraph.depth_first_order(succ, members[0], directed=True, return_predecessors=False)
        loops.append(np.asarray(order, np.int64))
    return loops
