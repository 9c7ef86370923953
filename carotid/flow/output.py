"""Flow outputs: XDMF + HDF5 time series, the wall indices surface, and checkpoints.

Layout of ``CASE_DIR/flow``::

    fields.xdmf          temporal collection over the volume mesh: velocity (m/s), pressure (Pa), nu_t (m^2/s)
    wall.xdmf            temporal collection over the wall triangles: WSS (Pa) at the nodes and on the faces
    mesh.h5, wall.h5     geometry (m) and connectivity, written once
    steps/step_<n>.h5    the fields of one output step (volume and wall)
    indices.vtp          TAWSS, OSI, RRT, ECAP, transWSS, TWSSG on the wall (carotid.flow.indices), mm, and the
                         Region cell array (codes named by the field array RegionNames; carotid.flow.regions)
    checkpoint.npz       solver state to resume from
    summary.json

The series are in SI units throughout, coordinates included (metres, unlike the mesh files of ``CASE_DIR``
which are in mm like every geometry of the project), so that gradients taken on them (ParaView, FEniCS,
meshio + numpy) come out in SI: a velocity gradient in 1/s, ``mu`` times it in Pa.

Every file is written atomically (a temporary name, then a rename: carotid.io.atomic), and the XDMF
indexes are rewritten after each output step, so a run killed at any moment leaves readable series up to
its last complete step.  The XDMF XML is written here (meshio's TimeSeriesWriter keeps one HDF5 file open
for the whole run, which is neither atomic nor resumable); ``meshio.xdmf.TimeSeriesReader`` and ParaView
read it.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from xml.sax.saxutils import escape

import h5py
import numpy as np

from carotid.errors import CarotidError
from carotid.io import atomic_path
from carotid.flow.mesh import FlowMesh

_TYPES = {np.dtype(np.float64): ("Float", 8), np.dtype(np.float32): ("Float", 4), np.dtype(np.int64): ("Int", 8),
          np.dtype(np.int32): ("Int", 4)}


def write_h5(path: Path, arrays: dict) -> None:
    """Write ``arrays`` (name -> ndarray) to a new HDF5 file, atomically."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for name, value in arrays.items():
                f.create_dataset(name, data=np.ascontiguousarray(value))


def _item(ref: str, array_shape: tuple, dtype) -> str:
    kind, precision = _TYPES[np.dtype(dtype)]
    dims = " ".join(str(d) for d in array_shape)
    return (f'<DataItem Dimensions="{dims}" NumberType="{kind}" Precision="{precision}" Format="HDF">'
            f"{escape(ref)}</DataItem>")


def xdmf_document(topology: tuple, geometry: tuple, steps: list[tuple[float, list]]) -> str:
    """XDMF 3 temporal collection.

    Parameters
    ----------
    topology : (type, h5 reference, shape, dtype)
        e.g. ``("Tetrahedron", "mesh.h5:/tets", (m, 4), int64)``.
    geometry : (h5 reference, shape, dtype)
        XYZ points.
    steps : list of (time, attributes)
        ``attributes``: list of (name, "Node"|"Cell", h5 reference, shape, dtype).
    """
    kind, ref, shape, dtype = topology
    topo = f'<Topology TopologyType="{kind}" NumberOfElements="{shape[0]}">{_item(ref, shape, dtype)}</Topology>'
    geo = f'<Geometry GeometryType="XYZ">{_item(*geometry)}</Geometry>'
    lines = ['<?xml version="1.0" ?>', '<Xdmf Version="3.0">', "<Domain>",
             '<Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">']
    for k, (time, attributes) in enumerate(steps):
        lines.append(f'<Grid Name="step{k}" GridType="Uniform">')
        lines += [topo, geo, f'<Time Value="{time!r}"/>']
        for name, center, aref, ashape, adtype in attributes:
            atype = "Vector" if len(ashape) == 2 and ashape[1] == 3 else "Scalar"
            lines.append(f'<Attribute Name="{name}" AttributeType="{atype}" Center="{center}">'
                         f"{_item(aref, ashape, adtype)}</Attribute>")
        lines.append("</Grid>")
    lines += ["</Grid>", "</Domain>", "</Xdmf>", ""]
    return "\n".join(lines)


class FlowWriter:
    """Writes the volume and wall time series of one run into ``flow_dir``, coordinates in metres.

    Parameters
    ----------
    flow_dir : Path
    mesh : FlowMesh
    wall_nodes : ndarray, shape (k,)
        Global indices of the wall nodes.
    wall_triangles : ndarray, shape (f, 3)
        Wall triangles in wall-node numbering.
    """

    def __init__(self, flow_dir: Path, mesh: FlowMesh, wall_nodes: np.ndarray, wall_triangles: np.ndarray):
        self.dir = Path(flow_dir)
        (self.dir / "steps").mkdir(parents=True, exist_ok=True)
        self.n, self.m = mesh.n_points, len(mesh.tets)
        self.n_wall, self.f_wall = len(wall_nodes), len(wall_triangles)
        write_h5(self.dir / "mesh.h5", {"points": mesh.points, "tets": mesh.tets})
        write_h5(self.dir / "wall.h5", {"points": mesh.points[wall_nodes], "triangles":
                                        np.asarray(wall_triangles, np.int64), "nodes": wall_nodes})
        self.records: list[dict] = []

    def write(self, step: int, time: float, fields: dict, wall_fields: dict) -> None:
        """Write one output step.

        Parameters
        ----------
        step : int
        time : float
            s.
        fields : dict
            Name -> nodal array (n,) or (n, 3) on the volume mesh.
        wall_fields : dict
            Name -> array on the wall nodes (k, ...) or faces (f, ...), told apart by length.
        """
        name = f"steps/step_{step:08d}.h5"
        write_h5(self.dir / name, {**{f"volume/{k}": v for k, v in fields.items()},
                                   **{f"wall/{k}": v for k, v in wall_fields.items()}})
        self.records = [r for r in self.records if r["step"] < step]
        self.records.append({"step": int(step), "time": float(time), "file": name,
                             "fields": {k: [list(np.shape(v)), str(np.asarray(v).dtype)] for k, v in fields.items()},
                             "wall": {k: [list(np.shape(v)), str(np.asarray(v).dtype)]
                                      for k, v in wall_fields.items()}})
        self.write_index()

    def truncate(self, records: list[dict]) -> None:
        """Resume: keep the given records (from a checkpoint) and rewrite the indexes."""
        self.records = list(records)
        self.write_index()

    def write_index(self) -> None:
        """Rewrite ``fields.xdmf`` and ``wall.xdmf`` from the records, atomically."""
        vol, wall = [], []
        for r in self.records:
            vol.append((r["time"], [(k, "Node", f"{r['file']}:/volume/{k}", tuple(s), d)
                                    for k, (s, d) in r["fields"].items()]))
            wall.append((r["time"], [(k, "Node" if s[0] == self.n_wall else "Cell", f"{r['file']}:/wall/{k}",
                                      tuple(s), d) for k, (s, d) in r["wall"].items()]))
        docs = {"fields.xdmf": xdmf_document(("Tetrahedron", "mesh.h5:/tets", (self.m, 4), np.int64),
                                             ("mesh.h5:/points", (self.n, 3), np.float64), vol),
                "wall.xdmf": xdmf_document(("Triangle", "wall.h5:/triangles", (self.f_wall, 3), np.int64),
                                           ("wall.h5:/points", (self.n_wall, 3), np.float64), wall)}
        for fname, text in docs.items():
            with atomic_path(self.dir / fname) as tmp:
                tmp.write_text(text, encoding="utf-8")

    def read_wall(self, name: str, since: float) -> tuple[np.ndarray, np.ndarray]:
        """Times (k,) and values (k, ...) of wall field ``name`` at the output steps with time >= ``since``."""
        recs = [r for r in self.records if r["time"] >= since - 1e-12]
        times = np.array([r["time"] for r in recs])
        values = []
        for r in recs:
            with h5py.File(self.dir / r["file"], "r") as f:
                values.append(f[f"wall/{name}"][()])
        return times, np.array(values)


def write_wall_vtp(path: Path, points_mm: np.ndarray, triangles: np.ndarray, point_data: dict,
                   cell_data: dict | None = None, field_data: dict | None = None) -> None:
    """Wall surface with point arrays (n, ...), cell arrays (f, ...) and field arrays (any length, e.g. the
    names of a cell array's codes) as VTP (pyvista), atomically."""
    import pyvista as pv

    surf = pv.PolyData(points_mm, np.hstack([np.full((len(triangles), 1), 3), triangles]).ravel())
    for data, arrays in ((surf.point_data, point_data), (surf.cell_data, cell_data or {}),
                         (surf.field_data, field_data or {})):
        for k, v in arrays.items():
            data[k] = v
    with atomic_path(path) as tmp:
        surf.save(tmp)


def save_checkpoint(path: Path, state: dict, meta: dict) -> None:
    """Solver ``state`` (arrays and scalars) plus JSON-able ``meta``, as one ``.npz`` written atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **{k: np.asarray(v) for k, v in state.items()}, meta=np.array(json.dumps(meta)))


def load_checkpoint(path: Path) -> tuple[dict, dict]:
    """``(state, meta)`` saved by :func:`save_checkpoint`.

    Raises
    ------
    CarotidError
        ``<path>: not a readable checkpoint (<why>)`` for a file that is not such an archive (truncated, replaced,
        or holding pickled objects, which are never loaded).
    """
    try:
        if not zipfile.is_zipfile(path):
            raise ValueError("not a NumPy .npz archive")
        with np.load(path, allow_pickle=False) as z:
            state = {k: z[k] for k in z.files if k != "meta"}
            meta = json.loads(str(z["meta"]))
        for k in ("t", "step"):
            state[k] = state[k].item()
        if not isinstance(meta, dict):
            raise ValueError("its meta record is not a JSON object")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        reason = f"no {exc} entry" if isinstance(exc, KeyError) else str(exc)
        raise CarotidError(f"{path}: not a readable checkpoint ({reason})") from None
    return state, meta
