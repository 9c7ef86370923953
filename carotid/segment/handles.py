"""Handles of the lumen removed where they are thinnest: a bridge cut, a tunnel filled.

A vessel tree has no handles (genus 0).  A segmentation gains one where two vessels, or two limbs of a looped
artery, lie closer than the image resolves: the front crosses the partial-volume gap between them and closes a
loop.  The bridge may lie well under a voxel outside the true wall, so that every voxel measure stays good, but
the centerlines take it as a shortcut (a looped ICA then reads as a stenosis of the bridge's width) and a flow
simulation runs through it.  A mask also gains handles where a tunnel a voxel or two wide runs through a thin
part of it.

Each handle is removed by the smallest morphological change that removes it.  At the scales ``t = h/2, h,
3h/2, ...`` (``h`` the finest voxel size) up to ``max_mm``, the candidates are

* the background's pieces that a closing by a ball of radius ``t`` adds (gaps narrower than ``2 t``: tunnels),
* the lumen's pieces that an opening by that ball removes (parts thinner than ``2 t``: bridges),

each connected piece on its own, the smallest first.  A piece is flipped when that lowers the count of handles
and adds no component: a cut that would split the tree, through a stenosis' throat or a thin branch, is refused.
The Euler characteristic, which a piece that removes a handle raises by one and which is a sum of local terms,
screens the pieces on their own boxes; the global count (``metrics.topology``) confirms.

Topology alone does not tell a bridge from a throat in the same loop: where a stenosis within the loop is
thinner than the bridge, the throat is cut instead.  Every change is reported with its place and size, for
review.

Why written here: scikit-image and SciPy give the distance transforms and the Euler number, but no library
corrects the topology of a binary mask (FreeSurfer's correction acts on cortical surfaces and is not a Python
package).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.measure import euler_number

from carotid.segment.metrics import topology

NEIGHBOURS_26 = np.ones((3, 3, 3), bool)


def opening_removes(inside: np.ndarray, spacing_kji: np.ndarray, t: float) -> np.ndarray:
    """Voxels of ``inside`` that an opening by a ball of radius ``t`` (mm) removes: parts thinner than ``2 t``."""
    core = ndimage.distance_transform_edt(inside, sampling=spacing_kji) > t
    return inside & (ndimage.distance_transform_edt(~core, sampling=spacing_kji) > t)


def closing_adds(inside: np.ndarray, spacing_kji: np.ndarray, t: float) -> np.ndarray:
    """Voxels outside ``inside`` that a closing by a ball of radius ``t`` (mm) adds: gaps narrower than ``2 t``."""
    grown = ndimage.distance_transform_edt(~inside, sampling=spacing_kji) <= t
    return ~inside & (ndimage.distance_transform_edt(grown, sampling=spacing_kji) > t)


def flip_pieces(inside: np.ndarray, candidates: dict, state: dict, t: float) -> list[dict]:
    """Flip, one at a time and the smallest first, each connected piece of the candidates that lowers the
    handles of ``inside`` without adding a component; ``inside`` and ``state`` (its ``metrics.topology``) are
    updated in place.

    Parameters
    ----------
    inside : ndarray of bool, shape (nk, nj, ni)
    candidates : dict
        ``{"fill": gaps, "cut": thin parts}``, boolean arrays of ``inside``'s shape.
    state : dict
        ``topology(inside)``.
    t : float
        Scale (mm) of the candidates, for the record.

    Returns
    -------
    list of dict
        One per piece flipped: ``kind``, ``scale_mm`` (``t``), ``voxels``, ``centre_kji`` and ``handles_removed``.
    """
    pieces = []
    for kind, region in candidates.items():
        labels, _ = ndimage.label(region, structure=NEIGHBOURS_26)
        sizes = np.bincount(labels.ravel())
        pieces += [(sizes[n], kind, labels, n, box) for n, box in enumerate(ndimage.find_objects(labels), 1)]
    done = []
    for size, kind, labels, number, box in sorted(pieces, key=lambda piece: piece[0]):
        if not state["handles"]:
            break
        # The Euler characteristic is a sum over 2x2x2 windows: the piece's box grown by two voxels holds its change.
        grown = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in box)
        local = labels[grown] == number
        before = inside[grown]
        if int(euler_number(before ^ local, connectivity=3)) <= int(euler_number(before, connectivity=3)):
            continue
        trial = inside.copy()
        trial[grown] ^= local
        after = topology(trial)
        if after["handles"] < state["handles"] and after["components"] <= state["components"]:
            inside[...] = trial
            offset = np.array([s.start for s in grown])
            done.append({"kind": kind, "scale_mm": round(float(t), 3), "voxels": int(size),
                         "centre_kji": np.argwhere(local).mean(axis=0) + offset,
                         "handles_removed": state["handles"] - after["handles"]})
            state.update(after)
    return done


def remove_handles(inside: np.ndarray, spacing_kji, max_mm: float) -> tuple[np.ndarray, list[dict]]:
    """Remove the handles of a lumen mask by the thinnest cuts and fills (see the module's docstring).

    Parameters
    ----------
    inside : ndarray of bool, shape (nk, nj, ni)
        The lumen.
    spacing_kji : array_like, shape (3,)
        Voxel size in mm, array order.
    max_mm : float
        Largest scale tried: half-width (mm) of the widest bridge cut or tunnel filled.

    Returns
    -------
    inside : ndarray of bool
        The lumen with its handles removed, as far as ``max_mm`` allows (a copy; the input when it had none).
    changes : list of dict
        The pieces flipped, in order (``flip_pieces``); ``centre_kji`` in the input's voxel indices.
    """
    state = topology(inside) if max_mm > 0 else {"handles": 0}
    if not state["handles"]:
        return inside, []
    spacing_kji = np.asarray(spacing_kji, float)
    step = 0.5 * float(spacing_kji.min())
    margin = np.ceil(2.0 * max_mm / spacing_kji).astype(int) + 2
    box = ndimage.find_objects(inside.astype(np.uint8))[0]
    box = tuple(slice(max(s.start - m, 0), min(s.stop + m, n)) for s, m, n in zip(box, margin, inside.shape))
    crop = inside[box].copy()
    changes = []
    for t in step * np.arange(1, int(np.floor(max_mm / step + 1e-6)) + 1):
        changes += flip_pieces(crop, {"fill": closing_adds(crop, spacing_kji, t),
                                      "cut": opening_removes(crop, spacing_kji, t)}, state, t)
        if not state["handles"]:
            break
    out = inside.copy()
    out[box] = crop
    offset = np.array([s.start for s in box])
    for change in changes:
        change["centre_kji"] = change["centre_kji"] + offset
    return out, changes
