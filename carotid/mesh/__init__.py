"""Boundary-layer tetrahedral volume mesh of the labelled lumen surface (paper section 3, "Volume meshing").

``build_mesh`` extrudes N prism sub-layers with height ratio f inward from
the wall (continued inside the planar caps), splits each prism into three
tetrahedra by global vertex index (conforming), fills the rest with a
maintained mesher (gmsh HXT by default, TetGen optional) that keeps the
inner layer surface exactly, and Lloyd-smooths the interior core vertices.
``write_mesh`` writes VTU, Gmsh 4.1, XDMF + HDF5 and ``mesh_quality.json``.
"""

from carotid.mesh.boundary import Surface, cap_open_ends, check_surface, label_flat_caps
from carotid.mesh.io import write_mesh
from carotid.mesh.mesher import build_mesh

__all__ = ["build_mesh", "write_mesh", "check_surface", "cap_open_ends", "label_flat_caps", "Surface"]
