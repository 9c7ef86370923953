"""Writing a volume mesh: VTU (VMTK layout), Gmsh 4.1, XDMF + HDF5, and the quality report.

Files in ``CASE_DIR`` (each complete or absent: everything is written in a
temporary folder inside ``CASE_DIR`` and renamed into place):

* ``mesh.vtu``: tetrahedra then boundary triangles in one UnstructuredGrid,
  as VMTK's mesh generator writes it: cell array ``CellEntityIds`` 0 for
  tetrahedra and the face label for triangles (wall 1, inlet 2, outlets 3,
  4, ...); cell array ``Region`` 0 for layer, 1 for core tetrahedra, -1
  for the boundary triangles.
* ``mesh.msh``: Gmsh 4.1 with physical groups ``fluid`` (3D, tag 1) and
  ``wall`` (tag 1), ``inlet`` (2) and one per outlet (3, 4, ...) (2D, tag =
  ``CellEntityIds``), readable by gmsh, dolfinx.io.gmshio and OpenFOAM's
  gmshToFoam.  The outlets are named by branch, ``outlet_ICA``,
  ``outlet_ECA``, from the caps the surface stage records in
  ``CASE_DIR/geometry.json``; ``outlet_1`` (label 3), ``outlet_2`` (4), ...
  when there is no such record or it belongs to another surface (see
  :func:`group_names`).
* ``mesh.xdmf`` + ``mesh.h5``: tetrahedra with cell data ``Region``;
  ``mesh_facets.xdmf`` + ``mesh_facets.h5``: boundary triangles with
  ``CellEntityIds`` (the legacy FEniCS recipe: one cell type per file), and
  the group names as XDMF ``Information`` (meshio's ``field_data``
  ``{name: [tag, 2]}``, as for the ``.msh``).
* ``mesh_quality.json``: the quality dict of :func:`carotid.mesh.build_mesh`
  plus ``"groups"``: ``{name: CellEntityIds}`` of the boundary groups.

All coordinates are in mm.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyvista as pv

from carotid.io import write_json
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


def recorded_caps(case_dir: Path) -> list[dict]:
    """The caps the surface stage recorded in ``case_dir/geometry.json`` (``[]`` when there are none)."""
    try:
        return json.loads((Path(case_dir) / "geometry.json").read_text(encoding="utf-8")).get("caps", [])
    except (OSError, ValueError):
        return []


def group_names(points: np.ndarray, triangles: np.ndarray, labels: np.ndarray, caps: list[dict]) -> dict[int, str]:
    """Physical group name of every face label present: wall, inlet, then the outlets.

    The outlets are ``outlet_<branch>`` when ``caps`` name every outlet label of the mesh, with distinct
    names, and each recorded centre lies within half its equivalent radius of the area-weighted centroid
    of that label's triangles (so a ``geometry.json`` left by another surface is not used); otherwise
    ``outlet_1`` (label 3), ``outlet_2`` (4), ...

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Node coordinates, mm.
    triangles : ndarray, shape (b, 3)
        Boundary triangles.
    labels : ndarray, shape (b,)
        Their ``CellEntityIds`` (wall 1, inlet 2, outlets 3, 4, ...).
    caps : list of dict
        :func:`recorded_caps`: ``id`` (label), ``name`` (branch), ``centre`` (mm) and ``equivalent_radius``
        (mm) of each cap (see :func:`carotid.surface.clip.cap_info`).

    Returns
    -------
    dict
        Label -> name.
    """
    present = np.unique(labels).tolist()
    names = {k: {WALL: "wall", INLET: "inlet"}.get(k, f"outlet_{k - INLET}") for k in present}
    outlets = [k for k in present if k > INLET]
    record = {int(c["id"]): c for c in caps}
    if not outlets or any(k not in record for k in outlets):
        return names
    p = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    weighted = np.stack([np.bincount(labels, area * p[:, :, d].mean(axis=1)) for d in range(3)], axis=1)
    centroid = weighted[outlets] / np.bincount(labels, area)[outlets, None]
    centre = np.array([record[k]["centre"] for k in outlets], dtype=float)
    radius = np.array([record[k]["equivalent_radius"] for k in outlets], dtype=float)
    branch = [str(record[k]["name"]) for k in outlets]
    if len(set(branch)) == len(branch) and np.all(np.linalg.norm(centroid - centre, axis=1) <= 0.5 * radius):
        names.update({k: f"outlet_{b}" for k, b in zip(outlets, branch)})
    return names


def write_gmsh(points: np.ndarray, tets: np.ndarray, triangles: np.ndarray, labels: np.ndarray,
               names: dict[int, str], path: Path) -> None:
    """Gmsh 4.1 file with one discrete entity per face label and physical groups (see module doc)."""
    with gmsh_session() as gmsh:
        gmsh.model.add("carotid")
        volume = gmsh.model.addDiscreteEntity(3)
        gmsh.model.mesh.addNodes(3, volume, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(volume, 4, [], (tets + 1).ravel())
        for label in np.unique(labels):
            surface = gmsh.model.addDiscreteEntity(2)
            gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles[labels == label] + 1).ravel())
            gmsh.model.addPhysicalGroup(2, [surface], int(label), name=names[int(label)])
        gmsh.model.addPhysicalGroup(3, [volume], 1, name="fluid")
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.option.setNumber("Mesh.Binary", 1)
        gmsh.write(str(path))


def write_xdmf(points: np.ndarray, tets: np.ndarray, region: np.ndarray, triangles: np.ndarray,
               labels: np.ndarray, names: dict[int, str], folder: Path) -> None:
    """``mesh.xdmf``/``.h5`` (tetrahedra, ``Region``) and ``mesh_facets.xdmf``/``.h5`` (triangles, labels,
    group ``names``: label -> name)."""
    import meshio

    meshio.write(folder / "mesh.xdmf", meshio.Mesh(points, [("tetra", tets)], cell_data={"Region": [region]}))
    facets = folder / "mesh_facets.xdmf"
    meshio.write(facets, meshio.Mesh(points, [("triangle", triangles)], cell_data={LABELS: [labels]}))
    # meshio writes no field_data to XDMF but reads it back from an Information element holding
    # <main><map key="name" dim="2">tag</map>...</main>
    tree = ET.parse(facets)
    table = ET.Element("main")
    for label, name in names.items():
        ET.SubElement(table, "map", key=name, dim="2").text = str(label)
    info = ET.Element("Information", Name="Information", Value=str(len(names)))
    info.text = ET.tostring(table, encoding="unicode")
    tree.find("Domain/Grid").insert(0, info)
    tree.write(facets, encoding="utf-8", xml_declaration=True)


def write_mesh(mesh: pv.UnstructuredGrid, case_dir: str | os.PathLike, quality: dict | None = None) -> Path:
    """Write the mesh files of the module docstring into ``case_dir`` atomically.

    Parameters
    ----------
    mesh : pyvista.UnstructuredGrid
        Output of :func:`carotid.mesh.build_mesh`.
    case_dir : path
        Case folder (created if needed); the outlet groups are named from its ``geometry.json`` when it
        records this surface's caps (:func:`group_names`).
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
    names = group_names(points, triangles, labels, recorded_caps(case_dir))
    staging = Path(tempfile.mkdtemp(prefix=".mesh.", dir=case_dir))
    try:
        mesh.save(staging / "mesh.vtu")
        write_gmsh(points, tets, triangles, labels, names, staging / "mesh.msh")
        write_xdmf(points, tets, region.astype(np.int32), triangles, labels.astype(np.int32), names, staging)
        if quality is not None:
            report = {**quality, "groups": {name: label for label, name in names.items()}}
            write_json(report, staging / "mesh_quality.json")
        for name in FILES:
            if (staging / name).exists():
                os.replace(staging / name, case_dir / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return case_dir
