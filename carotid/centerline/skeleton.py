"""The lumen's largest connected component and its 3D voxel skeleton.

The thinning itself is scikit-image's ``skeletonize`` (Lee, Kashyap and Chu's
3D medial-axis thinning).  What is added here is what a vessel needs from it:

* only the largest 26-connected component is used; a segmentation with a
  second large component is refused rather than silently cut;
* cavities are filled first, so that holes in a noisy mask do not become
  loops of the skeleton, and the mask is regularised by a Gaussian of 0.7
  voxel (thresholded at 1/2), which removes voxel-scale roughness (each bump
  of a thresholded or noisy mask would otherwise grow a spur, each tunnel a
  loop) but keeps vessels down to a radius of one voxel;
* vessels cut by the image border are extended beyond it by replicating the
  border slices before thinning, and the skeleton is clipped back to the
  image afterwards.  Thinning would otherwise retract the axis from a flat cut
  end by about one radius (and fork it towards the rim); with the extension
  the axis reaches the border, where the open ends of the vessel tree are;
* a straight vessel whose section is mirror-symmetric about a line between
  voxel centres (an axis exactly midway between them) can be thinned away,
  whole or from an end up to where the symmetry breaks (a stenosis), both
  middle layers being deleted together; when nothing is left, or part of the
  lumen lies more than three of its largest inscribed radii from the
  skeleton, the mask is thinned again after a one-voxel erosion from the +i
  and +j sides, which breaks that symmetry (the half-voxel shift is undone by
  the re-centring of the axis), and the skeleton that leaves less of the
  lumen that far away is kept.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from carotid.errors import CarotidError

#: Standard deviation (voxels) of the Gaussian that regularises the mask before thinning.
REGULARISE_VOXELS = 0.7
#: A second component larger than this fraction of the largest one makes the segmentation "fragmented".
FRAGMENT_FRACTION = 0.1


def largest_component(mask: np.ndarray, voxel_mm3: float) -> tuple[np.ndarray, dict]:
    """The largest 26-connected component of a binary mask, with its cavities filled.

    Parameters
    ----------
    mask : ndarray of bool, shape (nk, nj, ni)
    voxel_mm3 : float
        Volume of one voxel in mm^3 (for the messages and the report).

    Returns
    -------
    lumen : ndarray of bool, same shape
    report : dict
        ``components`` (count), ``lumen_volume_mm3`` and ``discarded_volume_mm3``.

    Raises
    ------
    CarotidError
        If the mask is empty, or a second component holds more than ``FRAGMENT_FRACTION``
        of the largest one's volume.
    """
    labels, count = ndimage.label(mask, structure=np.ones((3, 3, 3), bool))
    if count == 0:
        raise CarotidError("the segmentation is empty: no lumen voxel to compute centerlines from")
    sizes = np.bincount(labels.ravel())[1:]
    order = np.argsort(sizes)[::-1]
    if count > 1 and sizes[order[1]] > FRAGMENT_FRACTION * sizes[order[0]]:
        big = int(np.count_nonzero(sizes > FRAGMENT_FRACTION * sizes[order[0]]))
        raise CarotidError(f"the segmentation is fragmented: {big} separate components of "
                           f"{', '.join(f'{s * voxel_mm3:.0f}' for s in sizes[order[:big]])} mm^3; "
                           "segment again (e.g. with seeds in every vessel) so that the lumen is one piece")
    lumen = ndimage.binary_fill_holes(labels == order[0] + 1)
    return lumen, {"components": int(count), "lumen_volume_mm3": float(lumen.sum() * voxel_mm3),
                   "discarded_volume_mm3": float((sizes.sum() - sizes[order[0]]) * voxel_mm3)}


def _stranded(skel: np.ndarray, region: np.ndarray, spacing_kji: np.ndarray, reach_mm: float) -> int:
    """Voxels of ``region`` farther than ``reach_mm`` from the skeleton (all of them when it is empty)."""
    if not skel.any():
        return int(np.count_nonzero(region))
    far = ndimage.distance_transform_edt(~skel, sampling=spacing_kji) > reach_mm
    return int(np.count_nonzero(region & far))


def _padded_crop(lumen: np.ndarray, pad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Crop ``lumen`` to its bounding box plus a 1-voxel margin; faces that touch the image border are
    extended by ``pad[axis]`` voxels replicating the border slice, the others by ``pad`` empty voxels.

    Returns the padded crop and the index (k, j, i) in ``lumen`` of its voxel (0, 0, 0).
    """
    box = ndimage.find_objects(lumen.astype(np.uint8))[0]
    lo = np.array([max(s.start - 1, 0) for s in box])
    hi = np.array([min(s.stop + 1, n) for s, n in zip(box, lumen.shape)])
    crop = lumen[tuple(slice(a, b) for a, b in zip(lo, hi))]
    for axis in range(3):
        widths = [(0, 0)] * 3
        widths[axis] = (int(pad[axis]), int(pad[axis]))
        edge = np.pad(crop, widths, mode="edge")
        keep_lo, keep_hi = lo[axis] == 0, hi[axis] == lumen.shape[axis]
        index = [slice(None)] * 3
        if not keep_lo:
            index[axis] = slice(0, int(pad[axis]))
            edge[tuple(index)] = False
        if not keep_hi:
            index[axis] = slice(edge.shape[axis] - int(pad[axis]), None)
            edge[tuple(index)] = False
        crop = edge
    return crop, lo - pad


def skeletonize_lumen(lumen: np.ndarray, spacing_kji, extend_mm: float) -> np.ndarray:
    """3D skeleton of a lumen mask, reaching the image border where the vessels are cut by it.

    Parameters
    ----------
    lumen : ndarray of bool, shape (nk, nj, ni)
        One connected component (see ``largest_component``).
    spacing_kji : array_like, shape (3,)
        Voxel size in mm in array order.
    extend_mm : float
        How far vessels are extended beyond the border before thinning, mm; about twice the
        largest radius is enough for the axis to run straight through the border.

    Returns
    -------
    ndarray of bool, same shape as ``lumen``
        The skeleton voxels (26-connected, one voxel thick).
    """
    spacing_kji = np.asarray(spacing_kji, float)
    pad = np.ceil(extend_mm / spacing_kji).astype(int) + 1
    crop, corner = _padded_crop(lumen, pad)
    regular = ndimage.gaussian_filter(crop.astype(np.float32), REGULARISE_VOXELS) > 0.5
    skel = skeletonize(regular)
    lost = _stranded(skel, regular, spacing_kji, 1.5 * extend_mm)
    if lost:
        other = skeletonize(regular & np.roll(regular, -1, axis=2) & np.roll(regular, -1, axis=1))
        if _stranded(other, regular, spacing_kji, 1.5 * extend_mm) < lost:
            skel = other
    out = np.zeros(lumen.shape, bool)
    kji = np.argwhere(skel) + corner
    inside = np.all((kji >= 0) & (kji < lumen.shape), axis=1)
    out[tuple(kji[inside].T)] = True
    return out
