"""Writing a volume mesh: VTU (VMTK layout), Gmsh 4.1, XDMF + HDF5, and the quality report.

Files in ``CASE_DIR`` (each complete or absent: everything is written in a
temporary folder inside ``CASE_DIR`` and renamed into place):

* ``mesh.vtu``: tetrahedra then boundary triangles in one UnstructuredGrid,
  as VMTK's mesh generator writes it: cell array ``CellEntityIds`` 0 for
  tetrahedra and the face label for triangles (wall 1, inlet 2, outlets 3,
  4, ...); cell array ``Region`` 0 for layer, 1 for core tetrahedra, -1
  for the boundary triangles.
* ``mesh.msh``: Gmsh 4.1 with physical groups ``fluid`` (3D, tag 1) and
  ``wall`` (tag 1), ``inlet`` (2), ``outlet_1`` (3), ``outlet_2`` (4), ... (2D,
  tag = ``CellEntityIds``), readable by gmsh, dolfinx.io.gmshio and
  OpenFOAM's gmshToFoam.
* ``mesh.xdmf`` + ``mesh.h5``: tetrahedra with cell data ``Region``;
  ``mesh_facets.xdmf`` + ``mesh_facets.h5``: boundary triangles with
  ``CellEntityIds`` (the legacy FEniCS recipe: one cell type per file).
* ``mesh_quality.json``: the quality dict of :func:`carotid.mesh.build_mesh`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.mesh.boundary import INLET, LABELS, WALL
from carotid.mesh.core import gmsh_session

FILES = ("mesh.vtu", "mesh.msh", "mesh.xdmf", "mesh.h5", "mesh_facets.xdmf", "mesh_facets.h5", "mesh_quality.json")


def split_cells(mesh: pv.UnstructuredGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tetrahedra (t, 4), their ``Region`` (t,), boundary triangles (b, 3) and their labels (b,)."""
    tet = mesh.celltypes == pv.CellType.TETRA
    tri = mesh.celltypes == pv.CellType.TRIANGLE
    cells = mesh.cells_dict
    return (cells[pv.CellType.TETRA], np.asarray(mesh.cell_data["Region"])[tet],
            cells[pv.CellType.TRIANGLE], np.asarray(mesh.cell_data[LABELS])[tri])


def group_name(label: int) -> str:
    """Physical group name of a face label: wall, inlet, outlet_1 (label 3), outlet_2, ..."""
    return {WALL: "wall", INLET: "inlet"}.get(int(label), f"outlet_{int(label) - INLET}")


def write_gmsh(points: np.ndarray, tets: np.ndarray, triangles: np.ndarray, labels: np.ndarray, path: Path) -> None:
    """Gmsh 4.1 file with one discrete entity per face label and physical groups (see module doc)."""
    with gmsh_session() as gmsh:
        gmsh.model.add("carotid")
        volume = gmsh.model.addDiscreteEntity(3)
        gmsh.model.mesh.addNodes(3, volume, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(volume, 4, [], (tets + 1).ravel())
        for label in np.unique(labels):
            surface = gmsh.model.addDiscreteEntity(2)
            gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles[labels == label] + 1).ravel())
            gmsh.model.addPhysicalGroup(2, [surface], int(label), name=group_name(label))
        gmsh.model.addPhysicalGroup(3, [volume], 1, name="fluid")
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.write(str(path))


def write_xdmf(points: np.ndarray, tets: np.ndarray, region: np.ndarray, triangles: np.ndarray,
               labels: np.ndarray, folder: Path) -> None:
    """``mesh.xdmf``/``.h5`` (tetrahedra, ``Region``) and ``mesh_facets.xdmf``/``.h5`` (triangles, labels)."""
    import meshio

    meshio.write(folder / "mesh.xdmf", meshio.Mesh(points, [("tetra", tets)], cell_data={"Region": [region]}))
    meshio.write(folder / "mesh_facets.xdmf",
                 meshio.Mesh(points, [("triangle", triangles)], cell_data={LABELS: [labels]}))


def write_mesh(mesh: pv.UnstructuredGrid, case_dir: str | os.PathLike, quality: dict | None = None) -> Path:
    """Write the mesh files of the module docstring into ``case_dir`` atomically.

    Parameters
    ----------
    mesh : pyvista.UnstructuredGrid
        Output of :func:`carotid.mesh.build_mesh`.
    case_dir : path
        Case folder (created if needed).
    quality : dict, optional
        Quality report; ``mesh_quality.json`` is written when given.

    Returns
    -------
    Path
        ``case_dir``.
    """
    case_dir = Path(case_dir)
    case_dir.mkdir(parents=True, exist_ok=True)
    points = np.asarray(mesh.points, dtype=float)
    tets, region, triangles, labels = split_cells(mesh)
    staging = Path(tempfile.mkdtemp(prefix=".mesh.", dir=case_dir))
    try:
        mesh.save(staging / "mesh.vtu")
        write_gmsh(points, tets, triangles, labels, staging / "mesh.msh")
        write_xdmf(points, tets, region.astype(np.int32), triangles, labels.astype(np.int32), staging)
        if quality is not None:
            (staging / "mesh_quality.json").write_text(json.dumps(quality, indent=2) + "\n")
        for name in FILES:
            if (staging / name).exists():
                os.replace(staging / name, case_dir / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return case_dir
