"""Flow-side mesh: nodes in metres, positively oriented P1 tetrahedra and labelled boundary triangles.

The volume mesh comes from the mesh stage as one VMTK-style ``UnstructuredGrid`` in mm: tetrahedra plus
boundary triangles carrying the face label cell array ``CellEntityIds`` (wall 1, inlet 2, outlets 3, 4, ...).
:class:`FlowMesh` converts the coordinates to metres once, orients every tetrahedron positively, finds the
tetrahedron that owns each boundary triangle (its outward normal and, for the wall, the element whose
gradient gives the wall shear stress) and checks that the labels the solver needs are present.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carotid.errors import CarotidError

WALL, INLET = 1, 2
MM = 1e-3  # metres per millimetre
# the four faces of a tetrahedron (vertex 0..3), each listed opposite the vertex of the same index
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _face_keys(tri: np.ndarray, n_points: int) -> np.ndarray:
    """One int64 key per triangle, independent of its vertex order; shape (f,)."""
    s = np.sort(tri, axis=1).astype(np.int64)
    return (s[:, 0] * n_points + s[:, 1]) * n_points + s[:, 2]


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes of tetrahedra ``tets`` (m, 4) on ``points`` (n, 3); positive when right-handed."""
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


@dataclass
class FlowMesh:
    """P1 tetrahedral mesh with labelled boundary triangles, in metres.

    Attributes
    ----------
    points : ndarray, shape (n, 3)
        Node coordinates, m.
    tets : ndarray, shape (m, 4), int64
        Tetrahedra, positively oriented.
    faces : ndarray, shape (f, 3), int64
        Boundary triangles, ordered so that their normal points out of the fluid.
    labels : ndarray, shape (f,), int64
        Face labels: wall 1, inlet 2, outlets 3, 4, ...
    face_tets : ndarray, shape (f,), int64
        The tetrahedron owning each boundary triangle.
    """

    points: np.ndarray
    tets: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    face_tets: np.ndarray = field(init=False)

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)
        self.labels = np.asarray(self.labels, dtype=np.int64).ravel()
        n = len(self.points)
        bad = np.count_nonzero(~np.isfinite(self.points).all(axis=1)) if self.points.ndim == 2 else 0
        if bad:
            raise CarotidError(f"{bad} nodes have non-finite coordinates (NaN or infinite): the mesh is corrupt; "
                               "rebuild it with `carotid mesh`")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4 or len(self.tets) == 0:
            raise CarotidError("the flow mesh has no tetrahedra")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) != len(self.labels):
            raise CarotidError("the flow mesh needs boundary triangles with one CellEntityIds label each")
        if self.tets.min() < 0 or self.tets.max() >= n or (len(self.faces) and self.faces.max() >= n):
            raise CarotidError("the flow mesh refers to nodes that do not exist")
        vol = tet_volumes(self.points, self.tets)
        if np.any(np.abs(vol) <= 1e-12 * np.abs(vol).max()):
            raise CarotidError(f"the flow mesh has {int(np.sum(np.abs(vol) <= 1e-12 * np.abs(vol).max()))} "
                               "degenerate (zero-volume) tetrahedra")
        flip = vol < 0
        self.tets[flip] = self.tets[flip][:, [0, 2, 1, 3]]
        self._check_labels()
        self._attach_faces()

    def _check_labels(self) -> None:
        present = set(np.unique(self.labels).tolist())
        missing = [name for name, lab in (("wall (1)", WALL), ("inlet (2)", INLET)) if lab not in present]
        if not self.outlet_labels:
            missing.append("outlet (3, 4, ...)")
        if missing:
            raise CarotidError(f"the mesh has no boundary faces labelled {', '.join(missing)} in CellEntityIds: "
                               "re-run `carotid mesh` (wall 1, inlet 2, outlets 3, 4, ...)")

    def _attach_faces(self) -> None:
        """Find each boundary face's tetrahedron and orient the face outward."""
        n = len(self.points)
        tet_faces = self.tets[:, TET_FACES].reshape(-1, 3)
        keys = _face_keys(tet_faces, n)
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        fkeys = _face_keys(self.faces, n)
        pos = np.minimum(np.searchsorted(sorted_keys, fkeys), len(sorted_keys) - 1)
        if np.any(sorted_keys[pos] != fkeys):
            bad = int(np.sum(sorted_keys[pos] != fkeys))
            raise CarotidError(f"{bad} labelled boundary triangles are not faces of any tetrahedron in the mesh")
        self.face_tets = order[pos] // 4
        # tet faces listed in TET_FACES order point outward for a positive tet: reuse that orientation
        self.faces = tet_faces[order[pos]]

    # ----------------------------------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, points_mm, tets, faces, labels) -> FlowMesh:
        """Build from arrays in mm (nodes (n, 3), tets (m, 4), triangles (f, 3), labels (f,))."""
        return cls(np.asarray(points_mm, dtype=np.float64) * MM, tets, faces, labels)

    @classmethod
    def from_pyvista(cls, grid) -> FlowMesh:
        """Build from a VMTK-style ``pyvista.UnstructuredGrid`` in mm (tets + labelled triangles)."""
        import pyvista as pv

        types = np.asarray(grid.celltypes)
        tet_ids = np.flatnonzero(types == pv.CellType.TETRA)
        tri_ids = np.flatnonzero(types == pv.CellType.TRIANGLE)
        if "CellEntityIds" not in grid.cell_data:
            raise CarotidError("the mesh has no CellEntityIds cell array: re-run `carotid mesh`")
        conn = np.asarray(grid.cell_connectivity)
        offsets = np.asarray(grid.cell_offsets)
        tets = conn[offsets[tet_ids][:, None] + np.arange(4)]
        tris = conn[offsets[tri_ids][:, None] + np.arange(3)] if len(tri_ids) else np.zeros((0, 3), np.int64)
        labels = np.asarray(grid.cell_data["CellEntityIds"]).ravel()[tri_ids]
        return cls.from_arrays(np.asarray(grid.points), tets, tris, labels)

    @classmethod
    def from_vtu(cls, path) -> FlowMesh:
        """Read ``mesh.vtu`` written by the mesh stage; CarotidError naming the file when it cannot be read or is
        not a usable flow mesh."""
        from carotid.io.vtkfile import read_vtk

        path = Path(path)
        if not path.is_file():
            raise CarotidError(f"{path} not found: run `carotid mesh` first")
        grid = read_vtk(path, "mesh", remedy="rerun `carotid mesh`")
        try:
            return cls.from_pyvista(grid)
        except CarotidError as exc:
            raise CarotidError(f"{path}: {exc}") from None

    def to_pyvista(self):
        """The mesh as a VMTK-style ``pyvista.UnstructuredGrid`` in mm (tets + labelled triangles)."""
        import pyvista as pv

        cells = np.concatenate([np.hstack([np.full((len(self.tets), 1), 4), self.tets]).ravel(),
                                np.hstack([np.full((len(self.faces), 1), 3), self.faces]).ravel()])
        types = np.concatenate([np.full(len(self.tets), pv.CellType.TETRA, np.uint8),
                                np.full(len(self.faces), pv.CellType.TRIANGLE, np.uint8)])
        grid = pv.UnstructuredGrid(cells, types, self.points / MM)
        grid.cell_data["CellEntityIds"] = np.concatenate([np.zeros(len(self.tets), np.int64), self.labels])
        return grid

    # ----------------------------------------------------------------------------------------------
    @property
    def outlet_labels(self) -> list[int]:
        """Labels of the outlets (>= 3), ascending."""
        return sorted(int(v) for v in np.unique(self.labels) if v >= 3)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def face_area_normals(self, label: int | None = None) -> np.ndarray:
        """Area-weighted outward normals (area x unit normal) of the faces with ``label`` (all if None), m^2."""
        f = self.faces if label is None else self.faces[self.labels == label]
        p = self.points[f]
        return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])

    def face_nodes(self, label: int) -> np.ndarray:
        """Sorted unique node indices of the faces with ``label``."""
        return np.unique(self.faces[self.labels == label])

    def flux_weights(self, label: int) -> tuple[np.ndarray, np.ndarray]:
        """Nodes of face ``label`` and ``int N_i n dS`` at each, so that the P1 flux is ``sum(w * u[nodes])``.

        Returns
        -------
        nodes : ndarray, shape (k,)
        weights : ndarray, shape (k, 3)
            Outward area vectors shared to the nodes (each triangle gives a third to each vertex), m^2.
        """
        f = self.faces[self.labels == label]
        an = self.face_area_normals(label)
        nodes, inverse = np.unique(f, return_inverse=True)
        weights = np.zeros((len(nodes), 3))
        for d in range(3):
            weights[:, d] = np.bincount(inverse.ravel(), np.repeat(an[:, d] / 3.0, 3), minlength=len(nodes))
        return nodes, weights

    def face_area(self, label: int) -> float:
        """Area of the faces with ``label``, m^2."""
        return float(np.linalg.norm(self.face_area_normals(label), axis=1).sum())

    def face_normal(self, label: int) -> np.ndarray:
        """Mean outward unit normal of the faces with ``label``, shape (3,)."""
        s = self.face_area_normals(label).sum(axis=0)
        return s / np.linalg.norm(s)

    def face_patch(self, label: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The faces with ``label`` as a stand-alone triangle patch.

        Returns
        -------
        nodes : ndarray, shape (k,)
            Global node indices of the patch's points.
        points : ndarray, shape (k, 3)
            Their coordinates, m.
        triangles : ndarray, shape (t, 3)
            Triangles in local (patch) numbering, outward-oriented.
        """
        f = self.faces[self.labels == label]
        nodes, inverse = np.unique(f, return_inverse=True)
        return nodes, self.points[nodes], inverse.reshape(-1, 3)
