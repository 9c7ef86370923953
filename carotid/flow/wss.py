"""Wall shear stress vectors on the wall triangles and at the wall nodes.

``tau = mu (grad u + grad u^T) n_in`` minus its normal part, with ``n_in`` the unit normal pointing into
the fluid (so tau points along the near-wall flow).  Two gradients:

* ``"wall_tet"``: the constant gradient of the tetrahedron owning the wall face.  On a layered mesh it is
  the secant slope over the first layer, exact at mid-layer: the error is first order in the first-layer
  thickness (``-delta / 2R`` for Poiseuille);
* ``"extrapolated"`` (default): that gradient, taken at the mid-height ``y1`` of the wall tetrahedron,
  linearly extrapolated to the wall with the recovered (volume-averaged) gradient at the tetrahedron's apex
  node, taken at the volume-averaged mid-height ``y2`` of the elements around that node.  A P1 element's
  normal gradient is exact at the middle of the wall-distance range it spans for a field quadratic in the
  wall distance, so the extrapolation is exact for such fields and second order on layered meshes.  Where
  the layering is missing (``y2 - y1 < y1 / 2``) it falls back to the wall-tet gradient.

The mid-heights use the exact nodal wall distance (:func:`carotid.flow.turbulence.wall_distance`).
"""

from __future__ import annotations

import numpy as np

from carotid.flow import assembly as asm
from carotid.flow.mesh import WALL, FlowMesh
from carotid.flow.turbulence import wall_distance


class WallShear:
    """Precomputed wall geometry for repeated WSS evaluations.

    Parameters
    ----------
    mesh : FlowMesh
    volumes : ndarray, shape (m,)
        Element volumes, m^3.
    method : {"extrapolated", "wall_tet"}
    distance : ndarray, shape (n,), optional
        Nodal wall distance, m (computed if not given).
    """

    def __init__(self, mesh: FlowMesh, volumes: np.ndarray, method: str = "extrapolated",
                 distance: np.ndarray | None = None):
        if method not in ("extrapolated", "wall_tet"):
            raise ValueError(f"unknown WSS method {method!r}")
        self.mesh, self.volumes, self.method = mesh, volumes, method
        sel = mesh.labels == WALL
        self.faces = mesh.faces[sel]
        self.face_tet = mesh.face_tets[sel]
        an = mesh.face_area_normals(WALL)
        self.areas = np.linalg.norm(an, axis=1)
        self.normals_in = -an / self.areas[:, None]
        self.nodes, inverse = np.unique(self.faces, return_inverse=True)
        self.local_faces = inverse.reshape(-1, 3)
        n_w = len(self.nodes)
        nn = asm.nodal_average(-self.normals_in, self.areas, self.local_faces, n_w)
        # on a knife edge (a zero-thickness septum's edge) the faces' normals cancel: take one face's normal
        any_face = np.zeros((n_w, 3))
        any_face[self.local_faces.ravel()] = np.repeat(-self.normals_in, 3, axis=0)
        norm = np.linalg.norm(nn, axis=1)
        edge = norm < 1e-6
        nn[edge], norm[edge] = any_face[edge], 1.0
        self.node_normals = nn / norm[:, None]  # outward, at the wall nodes
        if method == "extrapolated":
            d = wall_distance(mesh) if distance is None else distance
            dt = d[mesh.tets]
            y_e = 0.5 * (dt.min(axis=1) + dt.max(axis=1))
            tets = mesh.tets[self.face_tet]
            on_face = (tets[:, :, None] == self.faces[:, None, :]).any(axis=2)
            self.apex = tets[~on_face]  # (f,) the vertex of the wall tet off the wall face
            self.y1 = y_e[self.face_tet]
            self.y2 = asm.nodal_average(y_e, volumes, mesh.tets, mesh.n_points)[self.apex]
            self.layered = self.y2 - self.y1 >= 0.5 * self.y1

    def face_gradients(self, grad_e: np.ndarray) -> np.ndarray:
        """Velocity gradient at each wall face, 1/s, shape (f, 3, 3), from element gradients (m, 3, 3)."""
        g1 = grad_e[self.face_tet]
        if self.method == "wall_tet":
            return g1
        g2 = asm.nodal_average(grad_e, self.volumes, self.mesh.tets, self.mesh.n_points)[self.apex]
        w = np.where(self.layered, self.y1 / np.maximum(self.y2 - self.y1, 1e-300), 0.0)
        return g1 - w[:, None, None] * (g2 - g1)

    def faces_wss(self, grad_e: np.ndarray, mu) -> np.ndarray:
        """WSS vector on each wall triangle, Pa, shape (f, 3), for the dynamic viscosity ``mu`` (Pa s): a number,
        or a :class:`carotid.flow.rheology.Rheology` evaluated at each face's shear rate."""
        from carotid.flow.rheology import Rheology, shear_rate

        g = self.face_gradients(grad_e)
        if isinstance(mu, Rheology):
            mu = mu.viscosity(shear_rate(g))[:, None]
        tau = mu * np.einsum("fij,fj->fi", g + g.transpose(0, 2, 1), self.normals_in)
        return tau - np.einsum("fi,fi->f", tau, self.normals_in)[:, None] * self.normals_in

    def nodes_wss(self, face_wss: np.ndarray) -> np.ndarray:
        """Area-weighted WSS at the wall nodes ``self.nodes``, Pa, shape (k, 3), tangential to the node normal."""
        tau = asm.nodal_average(face_wss, self.areas, self.local_faces, len(self.nodes))
        return tau - np.einsum("ki,ki->k", tau, self.node_normals)[:, None] * self.node_normals
