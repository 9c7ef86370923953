"""Calcium at a graded stenosis: how far the hyperdense structures lie from the lumen around the throat.

A calcified plaque at the throat is where a CT angiogram's grade is least certain: the calcium's blur
("blooming") spreads over the lumen next to it, and a layer thinner than the blur is as bright as the lumen
after it, so the wall there is placed from a model of the blur rather than seen.  The grade is reported with
the distance from the lumen's wall around the throat to the nearest hyperdense voxel the segmentation took
out (``segmentation/calcium_mask.nii.gz``), so that a reader knows which stenoses are calcified.  A calcium
that the scan shows no brighter than the lumen is never found, so a missing distance does not prove a plaque
soft.

The distances are scipy's Euclidean distance transform on a box around the throat.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from carotid.io import Volume

# The lumen's wall is looked at within this distance (mm) of the throat's point beyond the local radius.
SEARCH_MM = 2.0
# Calcium this close (mm) to the lumen's wall makes a stenosis calcified: two widths of a CT angiogram's
# 0.5 mm blur, the reach of its blooming.
CALCIFIED_MM = 1.0


def calcium_distance(location_mm, local_diameter_mm: float, levelset: Volume, calcium: Volume) -> float | None:
    """Distance (mm) from the lumen's wall around a throat to the nearest hyperdense voxel.

    Parameters
    ----------
    location_mm : array_like, shape (3,)
        The throat's point on the centerline, world mm (LPS).
    local_diameter_mm : float
        The vessel's diameter there without the narrowing (the ECST reference), mm: the wall is looked at
        within half of it plus ``SEARCH_MM`` of the point.
    levelset : Volume
        Signed distance (mm, negative inside) of the lumen.
    calcium : Volume
        Hyperdense structures (nonzero), on the level set's grid.

    Returns
    -------
    float or None
        The smallest distance (mm) from a wall voxel (``|phi|`` at most half the coarsest voxel) within
        reach of the throat to a hyperdense voxel's centre, 0 where they touch; None when no hyperdense
        voxel lies within twice that reach of the throat's point (along each axis), or no wall voxel within
        reach.
    """
    spacing = np.asarray(levelset.spacing_kji, float)
    reach = 0.5 * float(local_diameter_mm) + SEARCH_MM
    centre = levelset.world_to_index(np.asarray(location_mm, float))
    half = np.ceil(2.0 * reach / spacing).astype(int)
    box = tuple(slice(min(max(int(round(c)) - h, 0), n), min(max(int(round(c)) + h + 1, 0), n))
                for c, h, n in zip(centre, half, levelset.array.shape))
    dense = np.asarray(calcium.array[box]) > 0
    phi = np.asarray(levelset.array[box])
    if not dense.any() or phi.size == 0:
        return None
    offsets = np.ogrid[tuple(slice(s.start, s.stop) for s in box)]
    distance2 = sum(((o - c) * h) ** 2 for o, c, h in zip(offsets, centre, spacing))
    wall = (np.abs(phi) <= 0.5 * spacing.max()) & (distance2 <= reach ** 2)
    if not wall.any():
        return None
    return float(ndimage.distance_transform_edt(~dense, sampling=spacing)[wall].min())


def annotate(geometry: dict, levelset: Volume, calcium: Volume) -> dict:
    """``geometry`` (``geometry_features``) with ``calcium_mm`` (``calcium_distance``) in every grade."""
    for grade in geometry.get("stenoses") or []:
        grade["calcium_mm"] = calcium_distance(grade["location_mm"], grade["local_diameter_mm"], levelset, calcium)
    return geometry


def calcified(grade: dict) -> bool:
    """Whether a grading (``annotate``) found calcium within ``CALCIFIED_MM`` of the lumen at its throat."""
    distance = grade.get("calcium_mm")
    return distance is not None and distance <= CALCIFIED_MM
