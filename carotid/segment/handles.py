"""Handles of the lumen removed where they are thinnest: a bridge cut, a tunnel filled; its cavities filled.

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
screens all pieces at once (``euler_changes``); the global count (``metrics.topology``) confirms.

A lumen also holds no enclosed void, but a front grown around a dark noise blob encloses one; a single voxel
at the axis halves the inscribed radius there, and the stenosis grading reads it as a throat.  ``cavities``
finds them, for the lumen to take.

Topology alone does not tell a bridge from a throat in the same loop: where a stenosis within the loop is
thinner than the bridge, the throat is cut instead.  Every change is reported with its place and size, for
review.

Why written here: SciPy gives the distance transforms and labels, scikit-image the Euler number of a whole
image, but no library corrects the topology of a binary mask (FreeSurfer's correction acts on cortical surfaces
and is not a Python package), and the Euler characteristic's change for each of thousands of pieces is counted
here in one pass over the lattice's cells rather than one scikit-image call per piece.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from carotid.segment.intensity import region_box
from carotid.segment.metrics import NEIGHBOURS_26, topology


def opening_removes(inside: np.ndarray, depth: np.ndarray, spacing_kji: np.ndarray, t: float) -> np.ndarray:
    """Voxels of ``inside`` that an opening by a ball of radius ``t`` (mm) removes: parts thinner than ``2 t``.

    ``depth`` is the distance (mm) of each voxel of ``inside`` to the outside (``distance_transform_edt``).
    """
    return inside & (ndimage.distance_transform_edt(depth <= t, sampling=spacing_kji) > t)


def closing_adds(inside: np.ndarray, distance: np.ndarray, spacing_kji: np.ndarray, t: float) -> np.ndarray:
    """Voxels outside ``inside`` that a closing by a ball of radius ``t`` (mm) adds: gaps narrower than ``2 t``.

    ``distance`` is the distance (mm) of each voxel outside ``inside`` to it.
    """
    return ~inside & (ndimage.distance_transform_edt(distance <= t, sampling=spacing_kji) > t)


def euler_changes(inside: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Change of the Euler characteristic (26-connected) of ``inside`` when each labelled piece alone flips.

    With 26-connectivity a mask is the union of its voxels as closed unit cubes, whose Euler characteristic
    counts the lattice's vertices, edges and faces the union covers, and its cubes: ``V - E + F - C``.  A
    cell of the lattice is covered when one of the 2, 4 or 8 voxels around it is in the mask, and the pieces
    (26-connected components of the candidates) never share a cell, so each covered cell that the flip adds
    or removes counts towards the one piece around it.

    Parameters
    ----------
    inside : ndarray of bool, shape (nk, nj, ni)
    labels : ndarray of int, same shape
        The pieces, 1 to ``n``; 0 elsewhere.
    n : int

    Returns
    -------
    ndarray of int, shape (n + 1,)
        Entry ``i`` for piece ``i`` (entry 0 unused).
    """
    before = np.pad(inside, 1)
    piece = np.pad(labels, 1)
    after = before ^ (piece > 0)
    change = np.zeros(n + 1, np.int64)
    # Cells around a block of 2 voxels along each of ``axes``: vertices (3 axes), edges (2), faces (1), cubes.
    for sign, axes in ((1, (0, 1, 2)), (-1, (1, 2)), (-1, (0, 2)), (-1, (0, 1)), (1, (0,)), (1, (1,)), (1, (2,)),
                       (-1, ())):
        covered_before, covered_after, owner = before, after, piece
        for axis in axes:
            low = tuple(slice(0, -1) if a == axis else slice(None) for a in range(3))
            high = tuple(slice(1, None) if a == axis else slice(None) for a in range(3))
            covered_before = covered_before[low] | covered_before[high]
            covered_after = covered_after[low] | covered_after[high]
            owner = np.maximum(owner[low], owner[high])
        moved = covered_after != covered_before
        change += sign * np.bincount(owner[moved], weights=np.where(covered_after[moved], 1, -1),
                                     minlength=n + 1).astype(np.int64)
    return change


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
        labels, n = ndimage.label(region, structure=NEIGHBOURS_26)
        sizes = np.bincount(labels.ravel())
        rises = euler_changes(inside, labels, n)
        # A piece that removes a handle raises the Euler characteristic by one; the others cannot.
        pieces += [(sizes[number], kind, labels, number, box) for number, box in
                   enumerate(ndimage.find_objects(labels), 1) if rises[number] > 0]
    done = []
    for size, kind, labels, number, box in sorted(pieces, key=lambda piece: piece[0]):
        if not state["handles"]:
            break
        grown = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in box)
        local = labels[grown] == number
        trial = inside.copy()
        trial[grown] ^= local
        # A fill cannot add a component that removes a handle; a cut can split the tree, and is refused then.
        if kind == "cut" and ndimage.label(trial, structure=NEIGHBOURS_26)[1] > state["components"]:
            continue
        after = topology(trial)
        if after["handles"] < state["handles"]:
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
    changes, depth = [], None
    for t in step * np.arange(1, int(np.floor(max_mm / step + 1e-6)) + 1):
        if depth is None:  # the distances to the wall, from either side, until a piece flips
            depth = ndimage.distance_transform_edt(crop, sampling=spacing_kji)
            distance = ndimage.distance_transform_edt(~crop, sampling=spacing_kji)
        flipped = flip_pieces(crop, {"fill": closing_adds(crop, distance, spacing_kji, t),
                                     "cut": opening_removes(crop, depth, spacing_kji, t)}, state, t)
        changes += flipped
        if not state["handles"]:
            break
        if flipped:
            depth = None
    out = inside.copy()
    out[box] = crop
    offset = np.array([s.start for s in box])
    for change in changes:
        change["centre_kji"] = change["centre_kji"] + offset
    return out, changes


def cavities(inside: np.ndarray, spacing_kji) -> np.ndarray:
    """The lumen's enclosed voids: background not connected (6-connected) to the background around the lumen.

    Parameters
    ----------
    inside : ndarray of bool, shape (nk, nj, ni)
    spacing_kji : array_like, shape (3,)

    Returns
    -------
    ndarray of bool, same shape
    """
    out = np.zeros(inside.shape, bool)
    # Within the lumen's box grown by a voxel, whose shell is background connected around it.
    box = region_box(inside, spacing_kji, float(np.max(spacing_kji)))
    if box is not None:
        out[box] = ndimage.binary_fill_holes(inside[box]) & ~inside[box]
    return out
