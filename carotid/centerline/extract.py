"""From a level set to named, smoothed centerlines with inscribed-sphere radii (paper section 3, step 1).

Steps: largest lumen component -> 3D thinning (scikit-image) -> voxel graph ->
spur pruning, loop cutting and junction merging relative to the local radius
-> naming (CCA / ICA / ECA / branch<k>, see ``labels``) -> per axis: Gaussian
smoothing along the arc length, recentring on the maximal inscribed sphere,
trimming of capped ends and straightening of ends cut by the image border ->
the bifurcation where the daughter axes leave the trunk -> radius of the
maximal inscribed sphere at each point (distance to the zero level set of the
level set, see ``axes``), area, median radius and half the narrowest diameter of the
section normal to the axis -> features (``features``).  All geometry is in mm
in the image's physical frame (spacing, origin and direction honoured), so
anisotropic voxels need no special care beyond the thinning itself, which is
topological.
"""

from __future__ import annotations

import numpy as np

from carotid.centerline.axes import (WallDistance, recentre, section_areas, section_profile, section_radii,
                                    smooth_axis, straighten_border_end, trim_open_end)
from carotid.centerline.features import geometry_features
from carotid.centerline.graph import simplify, skeleton_graph
from carotid.centerline.labels import bifurcation_point, label_tree, splice_at
from carotid.centerline.model import Branch, Centerlines
from carotid.centerline.skeleton import largest_component, skeletonize_lumen
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.segment.handles import cavities
from carotid.segment.intensity import region_box


def without_voids(levelset: Volume, lumen: np.ndarray) -> Volume:
    """The level set with the voids it encloses within the lumen set just inside (-1 um).

    A void of one voxel at a vessel's axis (a segmentation grown around a dark noise pit) is a second wall to
    the inscribed spheres and the sections: the radius there halves, and the grading reads a throat.  The
    skeleton's lumen has its cavities filled (``skeleton.largest_component``); so are the radii's.

    Parameters
    ----------
    levelset : Volume
        Negative inside.
    lumen : ndarray of bool, the level set's shape
        The lumen component, cavities filled.

    Returns
    -------
    Volume
        ``levelset`` itself when it encloses no void.
    """
    voids = cavities(lumen & (np.asarray(levelset.array) < 0), levelset.spacing_kji)
    if not voids.any():
        return levelset
    phi = np.array(levelset.array, np.float32, copy=True)
    phi[voids] = -1e-3
    return levelset.with_array(phi)


def deepest_radius(lumen: np.ndarray, phi: np.ndarray, spacing_kji) -> float:
    """Radius (mm) of the largest sphere in the lumen: the level set's deepest value, at least a voxel.

    A sphere inside the lumen fits inside the lumen's bounding box, so its radius is at most half the box's
    narrowest side.  A level set whose deepest value lies beyond that (a corrupt voxel, values in other
    units) is not the mask's signed distance in mm; the skeleton, padded by twice this radius, would then
    ask for more memory than the machine has.

    Parameters
    ----------
    lumen : ndarray of bool, shape (nk, nj, ni)
    phi : ndarray, float, same shape
        Signed distance (mm), negative inside.
    spacing_kji : ndarray, shape (3,)
        Voxel size, mm.

    Returns
    -------
    float
    """
    spacing_kji = np.asarray(spacing_kji, float)
    deepest = float(-phi[lumen].min())
    box = region_box(lumen, spacing_kji, 0.0)
    sides = (np.array([b.stop - b.start for b in box]) * spacing_kji).min()
    if deepest > 0.5 * sides + spacing_kji.max():
        raise CarotidError(f"the level set's deepest value inside the lumen, {deepest:.4g} mm, exceeds what a lumen "
                           f"{sides:.1f} mm across can hold: it is not the lumen's signed distance in mm")
    return max(deepest, float(spacing_kji.max()))


def compute_centerlines(levelset: Volume, mask: Volume | None = None, *, prune: float = 2.0,
                        smoothing: float = 1.0, step: float | None = None, merge: float = 0.5,
                        anatomical_frame: bool = True, centre: bool = True) -> Centerlines:
    """Centerlines of the vessel tree of a segmented lumen.

    Parameters
    ----------
    levelset : Volume
        Signed distance to the lumen wall in mm, negative inside (the segment stage's ``levelset``).
    mask : Volume, optional
        Binary lumen on the same grid (nonzero inside); default ``levelset < 0``.
    prune : float
        Terminal branches shorter than ``prune`` times the radius of the vessel they leave are spurs and
        are removed.
    smoothing : float
        Standard deviation (mm) of the Gaussian applied to each axis along its arc length; 0: none.
    step : float, optional
        Spacing of the output axis points, mm; default half the smallest voxel size.
    merge : float
        Junctions closer than ``merge`` times the local radius are merged into one node.
    anatomical_frame : bool
        Whether world z is superior (a CTA in LPS); see ``carotid.centerline.labels``.  Pass False for a
        surface in an arbitrary frame (an external STL).
    centre : bool
        Recentre the smoothed axes on the maximal inscribed spheres (False: the thinned axis as is).

    Returns
    -------
    Centerlines
        Branches named CCA, ICA, ECA, branch<k>; ``bifurcation`` is where the ICA and ECA axes leave the
        CCA axis (the skeleton's junction node if that cannot be fitted; NaN if the tree has no
        bifurcation); ``info`` holds the features of ``features.geometry_features``, the labelling cues
        and the lumen component report.

    Raises
    ------
    CarotidError
        On an empty or fragmented lumen, a lumen with no axis, or a mask on another grid.
    """
    phi = np.asarray(levelset.array)
    if not np.isfinite(phi).all():
        raise CarotidError("the level set holds NaN or infinite values")
    if mask is not None and not mask.same_grid(levelset):
        raise CarotidError(f"the mask is not on the level set's grid ({mask.grid()}; the level set: {levelset.grid()})")
    inside = (mask.array > 0) if mask is not None else (phi < 0)
    spacing_kji = levelset.spacing_kji
    lumen, report = largest_component(inside, float(np.prod(spacing_kji)))
    if np.count_nonzero(phi[lumen] < 0) < 0.5 * np.count_nonzero(lumen):
        raise CarotidError("the level set is not negative inside the lumen mask (is its sign flipped?); "
                           "it must be a signed distance, negative inside")
    levelset = without_voids(levelset, lumen)
    phi = levelset.array
    r_max = deepest_radius(lumen, phi, spacing_kji)
    skel = skeletonize_lumen(lumen, spacing_kji, extend_mm=2.0 * r_max)
    if np.count_nonzero(skel) < 2:
        raise CarotidError(f"the lumen ({np.count_nonzero(lumen)} voxels) is too small to hold a vessel axis")

    try:
        radius_at = WallDistance(levelset, lumen)
    except ValueError:
        raise CarotidError("the level set has no zero level (wall) near the lumen; "
                           "is it a signed distance, negative inside?") from None

    graph = simplify(skeleton_graph(skel, levelset.index_to_world), radius_at, prune=prune, merge=merge)
    if sum(e.length for e in graph.edges) < 2.0 * r_max:
        raise CarotidError(f"the lumen has no vessel axis (its skeleton is shorter than its diameter, "
                           f"{2 * r_max:.1f} mm): is the segmentation a blob rather than a vessel?")
    if not np.any(graph.degree() == 1):
        raise CarotidError("the vessel axis has no open end (it is a closed loop); check the segmentation")
    labelled = label_tree(graph, radius_at, anatomical_frame=anatomical_frame)
    step = float(step if step is not None else 0.5 * spacing_kji.min())
    axes = {}
    open_ends = labelled.open_ends()
    for name, raw in labelled.paths.items():
        pts = smooth_axis(raw, smoothing, step)
        if centre:
            pts = smooth_axis(recentre(radius_at, pts, max_shift=float(spacing_kji.max())), 0.5 * smoothing, step)
        for at_start in open_ends.get(name, ()):
            pts = trim_open_end(pts, radius_at(pts), at_start)
            r_end = float(np.median(radius_at(pts[:len(pts) // 2] if at_start else pts[len(pts) // 2:])))
            pts = straighten_border_end(levelset, pts, r_end, at_start)
        axes[name] = smooth_axis(pts, 0.0, step)
    bif, bif_method = np.full(3, np.nan), "none"
    if labelled.bifurcation_node is not None:
        bif, bif_method = graph.nodes[labelled.bifurcation_node], "junction"
        r_junction = float(radius_at(bif)[0])
        point = bifurcation_point(axes["CCA"], axes["ICA"], axes["ECA"], r_junction)
        if point is not None:
            bif, bif_method = point, "daughter_lines"
            axes["CCA"], (axes["ICA"], axes["ECA"]) = splice_at(point, axes["CCA"], [axes["ICA"], axes["ECA"]],
                                                                 skip=0.5 * r_junction)
            for name in ("CCA", "ICA", "ECA"):
                axes[name] = smooth_axis(axes[name], 0.0, step)
    branches = []
    for name, pts in axes.items():
        radii = radius_at(pts)
        median, narrow = section_profile(section_radii(levelset, pts, radii))
        areas = section_areas(levelset, pts, radii)
        areas[np.isnan(median)] = np.nan  # a section the image border cuts is not measured
        branches.append(Branch(name, pts, radii, areas, median, narrow))
    labelled.info["bifurcation_method"] = bif_method
    info = {"lumen": report, "labelling": labelled.info,
            "parameters": {"prune": prune, "smoothing_mm": smoothing, "step_mm": step, "merge": merge}}
    cl = Centerlines(branches, np.asarray(bif, float), info)
    cl.info.update(geometry_features(cl))
    return cl
