"""VMTK 1.5.2 itself as a benchmark peer: its segmentation and centerlines on carotid's inputs.

VMTK 1.5.2 installs (from PyPI wheels) for CPython 3.12 only, and carotid
runs on 3.11, so VMTK lives in a venv of its own and this module drives
``vmtk_peer.py`` in a subprocess: it writes the image or level set as
``.mha`` into a temporary folder, runs the peer with the same seed points
carotid gets, and reads back the level set (``.mha``) or the centerlines
(``.vtp``).  The benchmarks find the interpreter through the environment
variable ``CAROTID_VMTK_PYTHON`` (default ``/tmp/vmtk-venv/bin/python``);
see benchmarks/README.md for the install commands.

Frames: VMTK ignores the direction matrix, so images go to it on the grid
frame (the volume's origin and spacing, identity direction); seed points go
as voxel indices (i, j, k) to the segmentation and as grid-frame mm to the
centerlines, and the centerline points come back to world mm (LPS) through
the volume's own geometry.  On a volume with identity direction the two
frames coincide.

``python benchmarks/_vmtk.py`` runs the end-to-end check on a phantom:
Dice of VMTK's segmentation, and the NASCET degree of VMTK's centerlines on
the true and on VMTK's level set, against the phantom's truth.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from functools import cache
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from carotid.centerline import Branch, stenosis
from carotid.centerline.axes import arclength, resample
from carotid.io import Volume, read_image, write_image

VMTK_PYTHON = Path(os.environ.get("CAROTID_VMTK_PYTHON", "/tmp/vmtk-venv/bin/python"))
PEER_SCRIPT = Path(__file__).resolve().parent / "vmtk_peer.py"
TIMEOUT_S = 600.0
RADIUS_ARRAY = "MaximumInscribedSphereRadius"


@cache
def vmtk_available() -> bool:
    """Whether ``VMTK_PYTHON`` exists and imports ``vmtk.vmtkscripts`` (checked once per process)."""
    if not VMTK_PYTHON.is_file():
        return False
    try:
        done = subprocess.run([str(VMTK_PYTHON), "-c", "from vmtk import vmtkscripts"],
                              capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _grid(volume: Volume, array: np.ndarray) -> Volume:
    """``array`` on the volume's origin and spacing with identity direction: the frame VMTK works in."""
    return Volume(np.ascontiguousarray(array, np.float32), volume.spacing, volume.origin)


def _to_grid_mm(volume: Volume, xyz) -> np.ndarray:
    """World points (..., 3) mm (LPS) in the grid frame (origin + spacing * (i, j, k)), mm."""
    ijk = volume.world_to_index(np.asarray(xyz, float))[..., ::-1]
    return np.asarray(volume.origin) + ijk * np.asarray(volume.spacing)


def _from_grid_mm(volume: Volume, grid_xyz: np.ndarray) -> np.ndarray:
    """Grid-frame points (..., 3) mm back to world mm (LPS)."""
    ijk = (np.asarray(grid_xyz, float) - np.asarray(volume.origin)) / np.asarray(volume.spacing)
    return volume.index_to_world(ijk[..., ::-1])


def _fixed(values: np.ndarray) -> list[str]:
    """Coordinates (mm) as command-line arguments in fixed notation: argparse takes ``-3.6e-05`` for an
    option, not a negative number."""
    return [f"{v:.9f}" for v in np.asarray(values, float).ravel()]


def _run_peer(args: list[str]) -> dict:
    """Run ``vmtk_peer.py`` with ``args``; its JSON line, or ``{"error": last stderr line}``."""
    try:
        done = subprocess.run([str(VMTK_PYTHON), str(PEER_SCRIPT), *args], capture_output=True, text=True,
                              timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return {"error": f"VMTK did not finish within {TIMEOUT_S:.0f} s"}
    except OSError as exc:
        return {"error": f"{VMTK_PYTHON}: {exc}"}
    if done.returncode != 0:
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        return {"error": lines[-1] if lines else f"vmtk_peer.py exited with status {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_vmtk_segmentation(volume: Volume, source_xyz, targets_xyz, lower_threshold: float,
                          iterations: int = 300) -> dict:
    """VMTK's colliding-fronts initialisation and geodesic level set, run from carotid's seed points.

    Parameters
    ----------
    volume : Volume
        CT image in HU.
    source_xyz : array_like, shape (3,)
        Source seed (the CCA) in world mm (LPS).
    targets_xyz : array_like, shape (m, 3)
        One target seed per branch (ICA, ECA...) in world mm; a colliding-fronts initialisation runs
        from the source to each, and their level sets are merged by their minimum.
    lower_threshold : float
        HU below which the colliding fronts do not propagate.
    iterations : int
        Geodesic active-contour iterations.

    Returns
    -------
    dict
        ``levelset`` (ndarray float32, shape of ``volume.array``, (k, j, i) order, negative inside; VMTK's
        level-set values, which are a signed distance in mm only near the zero level),
        ``seconds`` (initialisation + evolution inside VMTK, s), ``init_seconds``, ``evolution_seconds``,
        ``wall_seconds`` (the whole subprocess, with interpreter start and file I/O, s) and ``iterations``;
        or ``{"error": message}`` if VMTK failed, timed out or a seed lies outside the image.
    """
    seeds = np.vstack([np.reshape(source_xyz, (1, 3)), np.reshape(targets_xyz, (-1, 3))])
    if not np.all(volume.contains(seeds)):
        return {"error": "a seed point lies outside the image"}
    ijk = np.rint(volume.world_to_index(seeds)[:, ::-1]).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(volume.array.shape[::-1]) - 1)
    with tempfile.TemporaryDirectory(prefix="carotid-vmtk-") as folder:
        image, out = Path(folder) / "image.mha", Path(folder) / "levelset.mha"
        write_image(_grid(volume, volume.array), image, compress=False)
        args = ["segment", "--image", str(image), "--source", *map(str, ijk[0]),
                "--lower-threshold", repr(float(lower_threshold)), "--out-levelset", str(out),
                "--iterations", str(int(iterations))]
        for target in ijk[1:]:
            args += ["--target", *map(str, target)]
        start = time.perf_counter()
        result = _run_peer(args)
        wall = time.perf_counter() - start
        if "error" in result:
            return result
        levelset = read_image(out).array
    if levelset.shape != volume.array.shape:
        return {"error": f"VMTK level set of shape {levelset.shape}, image {volume.array.shape}"}
    return {"levelset": levelset, "seconds": result["init_seconds"] + result["evolution_seconds"],
            "init_seconds": result["init_seconds"], "evolution_seconds": result["evolution_seconds"],
            "wall_seconds": wall, "iterations": result["iterations"]}


def run_vmtk_centerlines(levelset_array: np.ndarray, volume: Volume, source_xyz, targets_xyz) -> dict:
    """VMTK's centerlines of the zero surface of a level set, from the source seed to each target seed.

    Parameters
    ----------
    levelset_array : ndarray, shape of ``volume.array``
        Level set in (k, j, i) order, negative inside (carotid's, VMTK's or the phantom's true one).
    volume : Volume
        Supplies the grid geometry (origin, spacing, direction).
    source_xyz : array_like, shape (3,)
        Source seed (the CCA) in world mm (LPS).
    targets_xyz : array_like, shape (m, 3)
        Target seeds in world mm.

    Returns
    -------
    dict
        ``branches``: one ``(points (n, 3) world mm, radii (n,) mm)`` per target, in the order of
        ``targets_xyz``, each running from the source to its target (VMTK's raw polyline: its first and
        last points are the seeds snapped to the nearest surface vertex, i.e. on the wall, appended by
        ``AppendEndPoints``; radii are VMTK's maximal inscribed sphere radii); ``seconds`` (surface +
        centerlines inside VMTK, s), ``surface_seconds``, ``centerline_seconds``, ``wall_seconds``;
        or ``{"error": message}``.
    """
    source = _to_grid_mm(volume, np.reshape(source_xyz, 3))
    targets = _to_grid_mm(volume, np.reshape(targets_xyz, (-1, 3)))
    with tempfile.TemporaryDirectory(prefix="carotid-vmtk-") as folder:
        image, out = Path(folder) / "levelset.mha", Path(folder) / "centerlines.vtp"
        write_image(_grid(volume, levelset_array), image, compress=False)
        args = ["centerlines", "--levelset", str(image), "--source", *_fixed(source), "--out", str(out)]
        for target in targets:
            args += ["--target", *_fixed(target)]
        start = time.perf_counter()
        result = _run_peer(args)
        wall = time.perf_counter() - start
        if "error" in result:
            return result
        lines = pv.read(out)
    if RADIUS_ARRAY not in lines.point_data or lines.n_lines != len(targets):
        return {"error": f"VMTK gave {lines.n_lines} centerlines for {len(targets)} targets"}
    cells, flat, at = [], lines.lines, 0
    while at < len(flat):
        cells.append(flat[at + 1:at + 1 + flat[at]])
        at += 1 + flat[at]
    points, radii = np.asarray(lines.points, float), np.asarray(lines.point_data[RADIUS_ARRAY], float)
    branches = []
    for target in targets:
        ids = min(cells, key=lambda c: min(np.linalg.norm(points[c[[0, -1]]] - target, axis=1)))
        if np.linalg.norm(points[ids[0]] - target) < np.linalg.norm(points[ids[-1]] - target):
            ids = ids[::-1]
        branches.append((_from_grid_mm(volume, points[ids]), radii[ids].copy()))
    return {"branches": branches, "seconds": result["surface_seconds"] + result["centerline_seconds"],
            "surface_seconds": result["surface_seconds"], "centerline_seconds": result["centerline_seconds"],
            "wall_seconds": wall}


def vmtk_nascet(branches: list[tuple[np.ndarray, np.ndarray]], step_mm: float, ica: int = 0,
                eca: int = 1) -> dict | None:
    """Stenosis grading of VMTK's ICA centerline by carotid's own grading, so that only the centerlines differ.

    The ICA branch is the part of the source-to-ICA path beyond the point where it leaves the tube of
    maximal inscribed spheres of the source-to-ECA path for good (the branch-splitting criterion of
    ``vmtkBranchExtractor``); it is resampled at a uniform ``step_mm`` (points and VMTK's radii
    interpolated linearly, nothing smoothed), since carotid's grading expects about uniform spacing and
    VMTK's polylines are not, and graded by ``carotid.centerline.stenosis`` exactly as carotid grades the
    ICA of its own centerlines.

    Parameters
    ----------
    branches : list of (ndarray (n, 3), ndarray (n,))
        Source-to-target paths in world mm with their radii in mm, as ``run_vmtk_centerlines`` returns.
    step_mm : float
        Resampling step, mm: carotid's centerline step is half the smallest voxel spacing.
    ica, eca : int
        Indices of the ICA and the ECA path in ``branches``.

    Returns
    -------
    dict or None
        ``carotid.centerline.stenosis``'s dict (``nascet``, ``ecst``, ``min_diameter_mm``,
        ``distal_diameter_mm``, ``arclength_from_bifurcation_mm``...) plus ``bifurcation_mm`` (the first
        point of the ICA branch, (3,)); None if the ICA path never leaves the ECA tube or its branch is
        too short to grade.
    """
    (p_ica, r_ica), (p_eca, r_eca) = branches[ica], branches[eca]
    distance, nearest = cKDTree(p_eca).query(p_ica)
    inside = np.flatnonzero(distance <= r_eca[nearest])
    start = int(inside[-1]) + 1 if len(inside) else 0
    if start >= len(p_ica) - 1:
        return None
    points, radii = p_ica[start:], r_ica[start:]
    uniform = resample(points, step_mm)
    s, t = arclength(points), arclength(uniform)
    graded = stenosis(Branch("ICA", uniform, np.interp(t, s, radii)))
    if graded is None:
        return None
    return {**graded, "bifurcation_mm": points[0].tolist()}


def _grading(graded: dict | None, truth: float) -> dict:
    """The NASCET figures of one grading against the true degree (fractions; error in percentage points)."""
    if graded is None:
        return {"nascet": None}
    return {"nascet": graded["nascet"], "nascet_error_points": 100.0 * (graded["nascet"] - truth),
            "min_diameter_mm": graded["min_diameter_mm"], "distal_diameter_mm": graded["distal_diameter_mm"]}


def _check() -> int:
    """End-to-end check on a phantom (70 % area stenosis, 20 HU noise, seed 1); prints the figures as JSON."""
    from carotid.centerline import compute_centerlines
    from carotid.phantom import make_phantom
    from carotid.segment.metrics import dice

    if not vmtk_available():
        print(f"VMTK not found at {VMTK_PYTHON} (set CAROTID_VMTK_PYTHON)", file=sys.stderr)
        return 1
    phantom = make_phantom(0.7, 20.0, 1)
    seeds = phantom.info["seeds_mm"]
    source, targets = seeds["CCA"], [seeds["ICA"], seeds["ECA"]]
    truth = phantom.info["stenosis"]["nascet"]
    step = 0.5 * min(phantom.image.spacing)
    figures = {"truth_nascet": truth}

    seg = run_vmtk_segmentation(phantom.image, source, targets, lower_threshold=200.0)
    if "error" in seg:
        print(f"segmentation failed: {seg['error']}", file=sys.stderr)
        return 1
    calcium = phantom.labels.array == phantom.info["labels"]["calcium"]
    inside = seg["levelset"] < 0
    figures["segmentation"] = {"dice": dice(inside, phantom.mask.array > 0),
                               "calcium_inside_fraction": float((calcium & inside).sum() / calcium.sum()),
                               **{k: v for k, v in seg.items() if k != "levelset"}}
    for name, levelset in (("true_levelset", phantom.sdf.array), ("vmtk_levelset", seg["levelset"])):
        cl = run_vmtk_centerlines(levelset, phantom.image, source, targets)
        figures[name] = cl if "error" in cl else {**_grading(vmtk_nascet(cl["branches"], step), truth),
                                                  **{k: v for k, v in cl.items() if k != "branches"}}
    start = time.perf_counter()
    own = compute_centerlines(phantom.sdf).info["stenosis"]
    figures["carotid_on_true_levelset"] = {**_grading(own, truth), "seconds": time.perf_counter() - start}
    print(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(_check())
