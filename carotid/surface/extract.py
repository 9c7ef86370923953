"""The lumen surface from the level set (paper section 3, step 2).

scikit-image's Lewiner marching cubes (the MC33 topology cases) on the signed distance ``phi``
(negative inside), in the image's physical frame: index -> world through spacing, origin and the
direction matrix.  The level set is padded by one voxel of outside values so that a vessel cut by
the image border still gives a closed surface (clipping removes those border faces later).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from skimage.measure import marching_cubes

from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.surface.mesh import largest_component, signed_volume, to_polydata


def extract_surface(levelset: Volume, level: float = 0.0) -> pv.PolyData:
    """Closed triangulated iso-surface ``phi = level`` of a level set, largest component, normals outward.

    Parameters
    ----------
    levelset : Volume
        Signed distance in mm, negative inside the lumen.
    level : float
        Iso-value in mm (0: the wall).

    Returns
    -------
    pyvista.PolyData
        Triangles in mm (LPS), counter-clockwise seen from outside, cell array ``CellEntityIds`` = 1.

    Raises
    ------
    CarotidError
        If the level set holds NaN or has no inside voxel.
    """
    phi = np.asarray(levelset.array, np.float32)
    if not np.isfinite(phi).all():
        raise CarotidError("the level set holds NaN or infinite values")
    if not (phi < level).any() or not (phi > level).any():
        raise CarotidError(f"the level set has no surface at level {level} mm (empty or full segmentation)")
    outside = max(float(phi.max()), level + 1.0)
    padded = np.pad(phi, 1, constant_values=outside)
    verts, faces, _, _ = marching_cubes(padded, level, method="lewiner", allow_degenerate=False)
    points = levelset.index_to_world(verts.astype(float) - 1.0)
    points, faces, labels = largest_component(points, faces.astype(np.int64))
    if signed_volume(points, faces) < 0:
        faces = faces[:, ::-1].copy()
    return to_polydata(points, faces, labels)
