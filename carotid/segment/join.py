"""Seeds left in separate pieces, joined along the minimal path through lumen-like intensity.

A long, tight stenosis (a "string sign") is a tube about as thin as the scanner's blur: its axis keeps only
part of the lumen's contrast, and the evolution's curvature term pinches the front there, so that the seeds
on either side end in separate components and no centerline joins them.  VMTK's colliding-fronts
initialisation joins its seeds by letting fronts from both meet.  Here, after the evolution, each seed's
component that the first seed's does not hold is joined to it along the minimal-cost path (scikit-image's
``MCP_Geometric``, cost ``1 / u^2``, ``u`` the lumen-contrast fraction of the lightly smoothed image),
provided the path stays lumen-like all along (``u >= min_contrast``) and crosses no neighbour held out of
the lumen: an occlusion, or a gap only a vein spans, stays open.  Each path voxel becomes a ball of the
radius of the cylinder whose blurred axis keeps the contrast ``u`` read there, ``r = s sqrt(-2 ln(1 - u))``
for a Gaussian blur of standard deviation ``s``; the blur-model refinement (``deblur``) then fits its wall.

Only the path search is scikit-image's; the acceptance rule and the radius are what no library offers.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric

from carotid.segment.init import ball_levelset

#: Largest contrast fraction a path voxel's radius is computed from: ``u -> 1`` means a tube wider than the
#: blur, whose radius the axis intensity no longer tells (``r`` at 0.95 is 2.45 blur widths).
SATURATION = 0.95
#: Lightest contrast fraction in the path cost, so that tissue is expensive but passable.
COST_FLOOR = 0.01


def join_seeds(image: np.ndarray, phi: np.ndarray, seeds_kji: np.ndarray, spacing_kji, lumen: float,
               background: float, blur_mm: float, excluded: np.ndarray | None = None, min_contrast: float = 0.25,
               margin_mm: float = 5.0) -> tuple[np.ndarray, list[dict]]:
    """Join the seeds' components of ``phi < 0`` to the first seed's along lumen-like minimal paths.

    Parameters
    ----------
    image : ndarray, float32, shape (nk, nj, ni)
        Image in its own units (calcium and bone already taken out: ``calcium.hyperdense_edge``).
    phi : ndarray, float32, same shape
        Level set of the evolved front (negative inside).
    seeds_kji : ndarray, shape (m, 3)
        Seed positions (fractional array indices); the first seed's component is the one the others join.
    spacing_kji : array_like, shape (3,)
        Voxel size, mm.
    lumen, background : float
        Lumen and tissue levels of the intensity model (``u = (I - background) / (lumen - background)``).
    blur_mm : float
        Standard deviation (mm) of the image's blur.
    excluded : ndarray of bool, same shape, optional
        Neighbours held out of the lumen; a path through them is refused.
    min_contrast : float
        Least ``u`` along an accepted path.
    margin_mm : float
        The path is searched in the box around the two components' nearest voxels, widened by this margin
        or by their distance, whichever is larger.

    Returns
    -------
    phi : ndarray, float32, same shape
        ``phi`` with the accepted paths' balls added (their signed distance, mm, where it is smaller).
    joins : list of dict
        Per component joined or refused: ``seed`` (index), ``accepted``, ``length_mm`` of the path,
        ``min_contrast`` along it, ``crosses_excluded``.
    """
    labels, _ = ndimage.label(phi < 0)
    idx = tuple(np.clip(np.round(seeds_kji).astype(int), 0, np.asarray(phi.shape) - 1).T)
    seed_labels = labels[idx]
    if seed_labels[0] == 0 or len(set(seed_labels[seed_labels > 0].tolist())) < 2:
        return phi, []
    spacing = np.asarray(spacing_kji, float)
    smoothing = 0.5 * float(spacing.min())
    smooth = ndimage.gaussian_filter(np.asarray(image, np.float32), smoothing / spacing)
    u = np.clip((smooth - np.float32(background)) / np.float32(lumen - background), 0.0, 1.0)
    del smooth
    width = float(np.hypot(blur_mm, smoothing))
    joined = labels == seed_labels[0]
    out = np.array(phi, np.float32, copy=True)
    joins = []
    for number, label in enumerate(seed_labels.tolist()):
        target = labels == label
        if label == 0 or (joined & target).any():
            continue
        box = _search_box(joined, target, spacing, margin_mm)
        path = _minimal_path(u[box], joined[box], target[box], spacing)
        along = u[box][tuple(path.T)]
        crosses = bool(excluded is not None and excluded[box][tuple(path.T)].any())
        record = {"seed": number, "length_mm": float(np.sum(np.linalg.norm(np.diff(path, axis=0) * spacing, axis=1))),
                  "min_contrast": float(along.min()), "crosses_excluded": crosses}
        record["accepted"] = bool(record["min_contrast"] >= min_contrast and not crosses)
        joins.append(record)
        if not record["accepted"]:
            continue
        radii = width * np.sqrt(-2.0 * np.log(1.0 - np.minimum(along, SATURATION)))
        balls = ball_levelset(out[box].shape, path, radii, spacing)
        out[box] = np.minimum(out[box], balls)
        joined |= target
        joined[box] |= balls < 0
    return out, joins


def _search_box(joined: np.ndarray, target: np.ndarray, spacing: np.ndarray, margin_mm: float) -> tuple:
    """Box (slices) around the nearest pair of voxels of two regions, widened by ``margin_mm`` or by their
    distance, whichever is larger."""
    distance, nearest = ndimage.distance_transform_edt(~joined, sampling=spacing, return_indices=True)
    distance[~target] = np.inf
    end = np.unravel_index(np.argmin(distance), distance.shape)
    start = nearest[(slice(None), *end)]
    reach = np.ceil(max(margin_mm, float(distance[end])) / spacing).astype(int)
    lo = np.maximum(np.minimum(start, end) - reach, 0)
    hi = np.minimum(np.maximum(start, end) + reach + 1, joined.shape)
    return tuple(slice(a, b) for a, b in zip(lo, hi))


def _minimal_path(u: np.ndarray, joined: np.ndarray, target: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Voxels (indices, shape (n, 3)) of the cheapest path from ``joined`` to ``target`` at cost ``1 / u^2``
    per mm (``MCP_Geometric``), from the cheapest target voxel back to ``joined``."""
    cost = 1.0 / np.maximum(u, COST_FLOOR) ** 2
    mcp = MCP_Geometric(cost, sampling=tuple(spacing))
    starts = np.argwhere(joined & ~ndimage.binary_erosion(joined))
    ends = np.argwhere(target & ~ndimage.binary_erosion(target))
    costs, _ = mcp.find_costs(starts, ends, find_all_ends=False)
    end = ends[np.argmin(costs[tuple(ends.T)])]
    return np.asarray(mcp.traceback(tuple(end)))
