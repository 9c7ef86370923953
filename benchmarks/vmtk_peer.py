"""VMTK 1.5.2 run headless as a peer of carotid: level-set segmentation and centerlines.

This script runs under the separate Python 3.12 venv that holds VMTK (VMTK 1.5.2
ships wheels for CPython 3.12 only, while carotid runs on 3.11), so it imports
nothing but vmtk, vtk, numpy and the standard library; ``_vmtk.py`` drives it
in a subprocess and exchanges files with it: ``.mha`` images (origin and
spacing kept, no direction: VMTK ignores it) and ``.vtp`` polydata.

Commands
--------
``segment``
    VMTK's usual recipe: ``vmtkImageInitialization`` by colliding fronts from
    the source voxel to each target voxel (voxel indices i, j, k, which VMTK
    turns into point ids with ``vtkImageData.ComputePointId``), the initial
    level sets merged with ``vtkImageMathematics`` Min, then
    ``vmtkLevelSetSegmentation`` (geodesic active contour on the gradient
    feature image) for a fixed number of iterations.  Writes the level set,
    negative inside, on the input grid.
``centerlines``
    ``vmtkMarchingCubes`` at level 0 of a level set (largest connected
    surface, unsmoothed), then ``vmtkCenterlines`` with the ``pointlist`` seed
    selector (source and targets in world mm, snapped by VMTK to the nearest
    surface point) and ``AppendEndPoints``.  Writes the centerlines with
    VMTK's ``MaximumInscribedSphereRadius`` point array, one polyline cell
    per source-to-target path.

Each command prints one JSON line with its timings on stdout; VMTK's own log
and progress output goes to stderr.  A failure exits with status 1 and its
message as the last line of stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import vtk
from vmtk import vmtkscripts


def _quiet(script):
    """Send a VMTK script's log to stderr and make its errors raise instead of exiting."""
    script.OutputStream = sys.stderr
    script.ExitOnError = 0
    return script


def read_image(path: str) -> vtk.vtkImageData:
    """Read an ``.mha`` image as float ``vtkImageData`` with its origin and spacing (extent from 0)."""
    if not os.path.isfile(path):
        raise FileNotFoundError(path)
    reader = vtk.vtkMetaImageReader()
    reader.SetFileName(path)
    cast = vtk.vtkImageCast()
    cast.SetInputConnection(reader.GetOutputPort())
    cast.SetOutputScalarTypeToFloat()
    cast.Update()
    image = vtk.vtkImageData()
    image.DeepCopy(cast.GetOutput())
    if image.GetNumberOfPoints() == 0:
        raise ValueError(f"{path}: not a readable MetaImage")
    return image


def write_image(image: vtk.vtkImageData, path: str) -> None:
    """Write ``vtkImageData`` as an uncompressed ``.mha`` (origin and spacing kept)."""
    writer = vtk.vtkMetaImageWriter()
    writer.SetInputData(image)
    writer.SetFileName(path)
    writer.SetCompression(False)
    writer.Write()


def segment(image_path: str, source_ijk: list[int], targets_ijk: list[list[int]], lower_threshold: float,
            out_path: str, iterations: int) -> dict:
    """Colliding-fronts initialisation from the source to each target, then geodesic level-set evolution.

    Parameters
    ----------
    image_path : str
        Input ``.mha`` image (HU).
    source_ijk : list of 3 int
        Source voxel index (i, j, k): i along x, the fastest axis of the file.
    targets_ijk : list of lists of 3 int
        One target voxel index (i, j, k) per branch.
    lower_threshold : float
        Intensity (HU) below which the colliding fronts do not propagate.
    out_path : str
        Output ``.mha`` level set (VMTK's values, negative inside) on the input grid.
    iterations : int
        Number of level-set iterations.

    Returns
    -------
    dict
        ``init_seconds`` and ``evolution_seconds`` (wall clock, s), ``iterations``.
    """
    image = read_image(image_path)
    dims = image.GetDimensions()
    for point in [source_ijk, *targets_ijk]:
        if not all(0 <= v < n for v, n in zip(point, dims)):
            raise ValueError(f"voxel {list(point)} outside the image of {list(dims)} voxels")
    start = time.perf_counter()
    merged = None
    for target in targets_ijk:
        init = _quiet(vmtkscripts.vmtkImageInitialization())
        init.Image = image
        init.Interactive = 0
        init.Method = "collidingfronts"
        init.SourcePoints = list(source_ijk)
        init.TargetPoints = list(target)
        init.LowerThreshold = lower_threshold
        init.Execute()
        if merged is None:
            merged = init.InitialLevelSets
        else:
            minimum = vtk.vtkImageMathematics()
            minimum.SetOperationToMin()
            minimum.SetInput1Data(merged)
            minimum.SetInput2Data(init.InitialLevelSets)
            minimum.Update()
            merged = minimum.GetOutput()
    init_seconds = time.perf_counter() - start

    start = time.perf_counter()
    levelset = _quiet(vmtkscripts.vmtkLevelSetSegmentation())
    levelset.Image = image
    levelset.InitialLevelSets = merged
    levelset.LevelSetsType = "geodesic"
    levelset.FeatureImageType = "gradient"
    levelset.NumberOfIterations = iterations
    levelset.PropagationScaling = 1.0
    levelset.CurvatureScaling = 0.1
    levelset.AdvectionScaling = 1.0
    levelset.Execute()
    evolution_seconds = time.perf_counter() - start

    write_image(levelset.LevelSets, out_path)
    return {"init_seconds": init_seconds, "evolution_seconds": evolution_seconds, "iterations": iterations}


def centerlines(levelset_path: str, source_xyz: list[float], targets_xyz: list[list[float]], out_path: str) -> dict:
    """Zero surface of a level set and VMTK's centerlines from the source to each target.

    Parameters
    ----------
    levelset_path : str
        Input ``.mha`` level set, negative inside.
    source_xyz : list of 3 float
        Source point in mm, in the frame of the image's origin and spacing.
    targets_xyz : list of lists of 3 float
        Target points in mm.
    out_path : str
        Output ``.vtp`` centerlines: one polyline cell per target, point array
        ``MaximumInscribedSphereRadius`` (mm).

    Returns
    -------
    dict
        ``surface_seconds`` and ``centerline_seconds`` (wall clock, s), ``surface_points``, ``cells``.
    """
    image = read_image(levelset_path)
    start = time.perf_counter()
    cubes = _quiet(vmtkscripts.vmtkMarchingCubes())
    cubes.Image = image
    cubes.Level = 0.0
    cubes.Connectivity = 1
    cubes.Execute()
    surface_seconds = time.perf_counter() - start
    if cubes.Surface.GetNumberOfPoints() == 0:
        raise ValueError(f"{levelset_path}: the level set has no zero surface")

    start = time.perf_counter()
    lines = _quiet(vmtkscripts.vmtkCenterlines())
    lines.Surface = cubes.Surface
    lines.SeedSelectorName = "pointlist"
    lines.SourcePoints = [float(v) for v in source_xyz]
    lines.TargetPoints = [float(v) for t in targets_xyz for v in t]
    lines.AppendEndPoints = 1
    lines.Execute()
    centerline_seconds = time.perf_counter() - start

    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetInputData(lines.Centerlines)
    writer.SetFileName(out_path)
    writer.Write()
    return {"surface_seconds": surface_seconds, "centerline_seconds": centerline_seconds,
            "surface_points": cubes.Surface.GetNumberOfPoints(), "cells": lines.Centerlines.GetNumberOfCells()}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line: ``segment`` or ``centerlines`` (see the module docstring)."""
    parser = argparse.ArgumentParser(description="VMTK 1.5.2 run headless as a benchmark peer.")
    commands = parser.add_subparsers(dest="command", required=True)
    seg = commands.add_parser("segment", help="colliding-fronts initialisation and geodesic level set")
    seg.add_argument("--image", required=True, help="input image (.mha, HU)")
    seg.add_argument("--source", type=int, nargs=3, required=True, metavar=("I", "J", "K"), help="source voxel")
    seg.add_argument("--target", type=int, nargs=3, action="append", required=True, metavar=("I", "J", "K"),
                     help="target voxel (repeat for each branch)")
    seg.add_argument("--lower-threshold", type=float, required=True, metavar="HU",
                     help="lower intensity threshold of the colliding fronts")
    seg.add_argument("--out-levelset", required=True, help="output level set (.mha, negative inside)")
    seg.add_argument("--iterations", type=int, default=300, help="level-set iterations (default 300)")
    cl = commands.add_parser("centerlines", help="zero surface of a level set and its centerlines")
    cl.add_argument("--levelset", required=True, help="input level set (.mha, negative inside)")
    cl.add_argument("--source", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"), help="source, mm")
    cl.add_argument("--target", type=float, nargs=3, action="append", required=True, metavar=("X", "Y", "Z"),
                    help="target, mm (repeat for each branch)")
    cl.add_argument("--out", required=True, help="output centerlines (.vtp)")
    return parser.parse_args(argv)


def main() -> int:
    """Run one command; its JSON line goes to the real stdout, everything else (VMTK's log) to stderr."""
    args = parse_args()
    result = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # VMTK and VTK print to stdout: keep it for the JSON line only
    try:
        if args.command == "segment":
            figures = segment(args.image, args.source, args.target, args.lower_threshold, args.out_levelset,
                              args.iterations)
        else:
            figures = centerlines(args.levelset, args.source, args.target, args.out)
    except Exception as exc:  # VMTK raises RuntimeError, VTK anything: report the message as the last line
        sys.stderr.write(f"\n{type(exc).__name__}: {exc}\n")
        return 1
    result.write(json.dumps(figures) + "\n")
    result.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
