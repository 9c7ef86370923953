"""Core tetrahedra inside the innermost layer surface, by TetGen or gmsh, with that surface kept exactly.

Both meshers are maintained libraries (TetGen through the ``tetgen``
package, gmsh's HXT or Delaunay 3D through ``gmsh``); this module only feeds
them the closed inner surface, asks them not to touch it, and checks that
they did not: the first ``n`` output vertices must be the input vertices
unchanged and the faces used once by the output tetrahedra must be exactly
the input triangles (no Steiner point on the boundary, no re-triangulation).
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager

import numpy as np

from carotid.errors import CarotidError

CORES = ("gmsh", "tetgen")


def regular_tet_volume(edge: float) -> float:
    """Volume (mm^3) of the regular tetrahedron with edge ``edge`` (mm)."""
    return edge**3 / (6.0 * np.sqrt(2.0))


def face_keys(faces: np.ndarray) -> np.ndarray:
    """One int64 key per triangle, independent of the vertex order, shape (m,)."""
    f = np.sort(faces, axis=1).astype(np.int64)
    n = int(f.max()) + 1 if f.size else 1
    if n < 2**21:
        return (f[:, 0] * n + f[:, 1]) * n + f[:, 2]
    _, key = np.unique(f, axis=0, return_inverse=True)
    return key.ravel().astype(np.int64)


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces used by exactly one tetrahedron, oriented outward, shape (b, 3)."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    key = face_keys(faces)
    _, first, counts = np.unique(key, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


@contextmanager
def gmsh_session():
    """Initialise gmsh quietly (no signal handler, no terminal output) for the block, then finalise it."""
    import gmsh

    gmsh.initialize(interruptible=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.Verbosity", 1)
    try:
        yield gmsh
    finally:
        gmsh.finalize()


@contextmanager
def _quiet_stdout():
    """Silence C-level writes to stdout (TetGen prints progress lines even with ``Q``)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _check_core(points, triangles, nodes, tets, name):
    """Validate a mesher's output against its input surface; return positively oriented tets."""
    n = len(points)
    if len(nodes) < n or not np.array_equal(nodes[:n], points):
        raise CarotidError(f"{name} moved or dropped boundary vertices of the core surface")
    tets = np.asarray(tets, dtype=np.int64)
    a = nodes[tets[:, 0]]
    vol = np.einsum("ij,ij->i", np.cross(nodes[tets[:, 1]] - a, nodes[tets[:, 2]] - a), nodes[tets[:, 3]] - a)
    tets = np.where((vol < 0)[:, None], tets[:, [0, 2, 1, 3]], tets)
    bfaces = boundary_faces(tets)
    if len(bfaces) != len(triangles) or not np.array_equal(np.sort(face_keys(bfaces)),
                                                           np.sort(face_keys(triangles))):
        raise CarotidError(f"{name} changed the boundary of the core (Steiner points or new triangles on it); "
                           "the layer surface may self-intersect: try a thinner layer")
    return nodes, tets


def mesh_core_tetgen(points: np.ndarray, triangles: np.ndarray, size: float, *, radius_edge: float = 1.2,
                     min_dihedral: float = 15.0) -> tuple[np.ndarray, np.ndarray]:
    """Quality tetrahedra inside a closed surface with TetGen, the surface kept (switch ``Y``).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Surface vertices (mm).
    triangles : ndarray, shape (m, 3)
        Closed surface triangles.
    size : float
        Target edge length (mm): the volume bound is the regular tetrahedron's.
    radius_edge, min_dihedral : float
        TetGen quality bounds (``-q radius_edge/min_dihedral``).

    Returns
    -------
    nodes : ndarray, shape (k, 3)
        ``points`` first, then the interior vertices TetGen added.
    tets : ndarray, shape (t, 4)
        Positively oriented tetrahedra.
    """
    try:
        import tetgen
    except ImportError:
        raise CarotidError("the TetGen core needs the tetgen package: pip install 'carotid[tetgen]' "
                           "(or use --core gmsh)") from None

    switches = f"pYq{radius_edge:g}/{min_dihedral:g}a{regular_tet_volume(size):.6g}O2/7Q"
    try:
        with _quiet_stdout():
            nodes, tets, *_ = tetgen.TetGen(points, triangles).tetrahedralize(switches=switches)
    except RuntimeError as exc:
        raise CarotidError(f"TetGen failed on the core surface ({exc}); "
                           "the surface or the layer may self-intersect") from None
    return _check_core(points, triangles, np.asarray(nodes, dtype=float), tets, "TetGen")


def mesh_core_gmsh(points: np.ndarray, triangles: np.ndarray, size: float, *, algorithm: str = "hxt",
                   optimize: bool = True, threads: int = 1, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedra inside a closed surface with gmsh (HXT or Delaunay 3D); the triangles are kept.

    The surface is given to gmsh as the mesh of one discrete surface entity
    bounding a volume (no reclassification, no geometry is rebuilt), so gmsh
    meshes only the volume.  Sizes follow ``size`` (``Mesh.MeshSizeMax``) and the boundary.

    Parameters
    ----------
    points, triangles : see :func:`mesh_core_tetgen`
    size : float
        Largest edge length (mm).
    algorithm : {"hxt", "delaunay"}
        gmsh 3D algorithm (10 or 1).
    optimize : bool
        Run gmsh's tetrahedral optimiser (``Mesh.Optimize``) on elements of
        quality (gamma) below 0.4.
    threads : int
        Threads for HXT.  With more than one, HXT's parallel insertion order
        (and so the mesh) changes from run to run; one thread and a fixed
        ``seed`` give the same mesh for the same input.
    seed : int
        gmsh's ``Mesh.RandomSeed`` (the perturbations of its Delaunay kernels).

    Returns
    -------
    nodes, tets : see :func:`mesh_core_tetgen`
    """
    with gmsh_session() as gmsh:
        gmsh.model.add("core")
        surf = gmsh.model.addDiscreteEntity(2)
        vol = gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop([surf])])
        gmsh.model.geo.synchronize()
        gmsh.model.mesh.addNodes(2, surf, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(surf, 2, [], (triangles + 1).ravel())
        gmsh.option.setNumber("Mesh.Algorithm3D", {"hxt": 10, "delaunay": 1}[algorithm])
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.Optimize", int(optimize))
        gmsh.option.setNumber("Mesh.OptimizeThreshold", 0.4)  # gmsh's default 0.3 leaves ~1.5 % below 20 deg
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.option.setNumber("Mesh.RandomSeed", seed)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:  # gmsh raises a bare Exception with its log line
            raise CarotidError(f"gmsh failed on the core surface ({exc}); "
                               "the surface or the layer may self-intersect") from None
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, elem_nodes = gmsh.model.mesh.getElementsByType(4, vol)
    order = np.argsort(tags)
    tags = tags[order].astype(np.int64)
    nodes = coords.reshape(-1, 3)[order]
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags] = np.arange(len(tags))
    tets = index[elem_nodes.astype(np.int64)].reshape(-1, 4)
    return _check_core(points, triangles, nodes, tets, "gmsh")


def mesh_core(points: np.ndarray, triangles: np.ndarray, size: float, core: str = "gmsh"):
    """Dispatch to :func:`mesh_core_tetgen` or :func:`mesh_core_gmsh` (``core`` in ``CORES``)."""
    if core not in CORES:
        raise CarotidError(f"unknown core mesher '{core}' (choose from {', '.join(CORES)})")
    return (mesh_core_tetgen if core == "tetgen" else mesh_core_gmsh)(points, triangles, size)
