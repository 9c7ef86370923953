"""Probes: velocity and pressure time series at points of the fluid, sampled from the solver's state.

A probe is a small set of sample points: one point (a user's probe, a centreline probe, a pressure point), or
a sample volume (a Doppler gate, :mod:`carotid.flow.duplex`): the centre and shells of points around it.  At
each sample time the velocity and pressure of the P1 solution are interpolated at every sample point in the
tetrahedron that contains it, ``f(x) = sum_j lambda_j(x) f_j`` with the barycentric coordinates ``lambda_j``
of x in that tetrahedron (exact for a field linear in space); a probe reports the velocity of its sample point
with the largest speed (what a Doppler gate reads: the highest velocity in its sample volume) and the pressure
at its centre.

Point location is vectorised: a ``scipy.spatial.cKDTree`` on the tetrahedron centroids gives each point its
nearest candidates, whose barycentric coordinates are computed all at once; a point none of them contains
(outside the fluid, or inside a stretched boundary-layer element whose centroid lies far away) is checked
against every tetrahedron whose bounding box holds it.  Points outside the fluid are refused.

Outputs in ``CASE_DIR/flow`` (atomically): ``probes.csv`` (time s, then per probe u, v, w, |u| in m/s and p in
Pa) and ``probes.xdmf`` with ``probes.h5``, a Polyvertex grid of the probe centres (m, SI like the other flow
series) carrying ``velocity``, ``speed`` and ``pressure`` at each sample time (ParaView, meshio).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from carotid.errors import CarotidError
from carotid.flow.mesh import MM, FlowMesh
from carotid.flow.output import write_h5, xdmf_document
from carotid.io import atomic_path

COLUMNS = (("u", "m_s"), ("v", "m_s"), ("w", "m_s"), ("speed", "m_s"), ("p", "pa"))
"""Per-probe quantities of a sample: velocity components and speed, m/s, and pressure, Pa."""

SAMPLES_PER_CYCLE = 2000
"""At most this many probe samples per cardiac cycle (one per T / 2000, 0.46 ms for the built-in waveform), plus
every output step: a run of millions of explicit steps keeps series of a sane size."""

CANDIDATES = (8, 64, 512)
"""Nearest tetrahedron centroids tried per point, in rounds, before the bounding-box search."""


def barycentric(vertices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points in tetrahedra.

    Parameters
    ----------
    vertices : ndarray, shape (..., 4, 3)
        Tetrahedron vertices.
    points : ndarray, shape (..., 3)
        Points, in the same unit.

    Returns
    -------
    ndarray, shape (..., 4)
        ``lambda`` with ``sum_j lambda_j x_j = point`` and ``sum_j lambda_j = 1``; all >= 0 inside.
    """
    edges = np.swapaxes(vertices[..., 1:, :] - vertices[..., :1, :], -1, -2)  # columns x_j - x_0
    lam = np.linalg.solve(edges, (points - vertices[..., 0, :])[..., None])[..., 0]
    return np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)


class PointLocator:
    """Finds the tetrahedron of a mesh that contains each of a set of points.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Mesh nodes.
    tets : ndarray, shape (m, 4)
        Tetrahedra.
    tol : float
        Barycentric tolerance: a point counts as inside a tetrahedron when every coordinate is >= -tol (points
        on a face or on the wall are inside).
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, tol: float = 1e-9):
        from scipy.spatial import cKDTree

        self.points, self.tets, self.tol = np.asarray(points, float), np.asarray(tets, np.int64), tol
        self.tree = cKDTree(self.points[self.tets].mean(axis=1))
        self._boxes = None

    def _containing(self, query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first of ``candidates`` (q, c) containing each point of ``query`` (q, 3): index into the
        candidates' rows (-1: none) and the barycentric coordinates (q, 4)."""
        lam = barycentric(self.points[self.tets[candidates]], query[:, None, :])  # (q, c, 4)
        inside = lam.min(axis=-1) >= -self.tol
        first = np.argmax(inside, axis=1)
        rows = np.arange(len(query))
        return np.where(inside[rows, first], first, -1), lam[rows, first]

    def locate(self, query) -> tuple[np.ndarray, np.ndarray]:
        """Containing tetrahedron and barycentric coordinates of each point.

        Parameters
        ----------
        query : array_like, shape (q, 3)
            Points, in the mesh's unit.

        Returns
        -------
        tet : ndarray of int, shape (q,)
            Index of the containing tetrahedron, -1 for a point outside the mesh.
        weights : ndarray, shape (q, 4)
            Barycentric coordinates in that tetrahedron (zeros outside).
        """
        query = np.atleast_2d(np.asarray(query, dtype=float))
        tet, weights = np.full(len(query), -1), np.zeros((len(query), 4))
        todo = np.arange(len(query))
        for k in CANDIDATES:
            if not todo.size:
                break
            k = min(k, len(self.tets))
            cand = self.tree.query(query[todo], k=k)[1].reshape(len(todo), k)
            first, lam = self._containing(query[todo], cand)
            found = first >= 0
            tet[todo[found]] = cand[found, first[found]]
            weights[todo[found]] = lam[found]
            todo = todo[~found]
        if todo.size:  # outside, or in an element far from its centroid: every element whose box holds it
            if self._boxes is None:
                corners = self.points[self.tets]
                pad = self.tol * np.ptp(self.points, axis=0).max()
                self._boxes = corners.min(axis=1) - pad, corners.max(axis=1) + pad
            lo, hi = self._boxes
            for i in todo:  # the few points left (a handful of probes), each against the boxes of all elements
                cand = np.flatnonzero(np.all((lo <= query[i]) & (hi >= query[i]), axis=1))
                if cand.size:
                    first, lam = self._containing(query[i:i + 1], cand[None])
                    if first[0] >= 0:
                        tet[i], weights[i] = cand[first[0]], lam[0]
        return tet, weights


@dataclass
class ProbeSpec:
    """One probe: a name, its centre (mm, LPS) and the radius of its spherical sample volume (mm; 0: a point).

    ``kind`` says where it comes from ("user", "gate", "pressure", "centreline"); ``info`` is kept for the
    summary (e.g. the arc length along its branch)."""

    name: str
    centre_mm: np.ndarray
    radius_mm: float = 0.0
    kind: str = "user"
    info: dict | None = None


def sphere_offsets(radius: float) -> np.ndarray:
    """Sample points of a spherical sample volume, relative to its centre: the centre, then 14 directions (the 6
    axes and the 8 diagonals) on shells at 1/3, 2/3 and 3/3 of ``radius``; shape (43, 3), unit of ``radius``."""
    axes = np.vstack([np.eye(3), -np.eye(3)])
    diagonals = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T / math.sqrt(3.0)
    directions = np.vstack([axes, diagonals])
    shells = radius * np.array([1.0, 2.0, 3.0]) / 3.0
    return np.vstack([np.zeros((1, 3)), (shells[:, None, None] * directions[None]).reshape(-1, 3)])


class ProbeSet:
    """The probes of a run located in its mesh, ready to sample the solver's state.

    Parameters
    ----------
    mesh : FlowMesh
    specs : list of ProbeSpec
        Probes, centres in mm.  A sample point of a sample volume outside the fluid (a gate clipped by the wall)
        is dropped; a centre outside the fluid is an error naming the probe.
    locator : PointLocator, optional
        Of ``mesh`` (one is built when not given).

    Raises
    ------
    CarotidError
        A probe centre outside the fluid domain, or two probes of the same name.
    """

    def __init__(self, mesh: FlowMesh, specs: list[ProbeSpec], locator: PointLocator | None = None):
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise CarotidError(f"probe names must differ: {sorted({n for n in names if names.count(n) > 1})}")
        bad = [n for n in names if not n or any(c in n for c in ',"\n')]
        if bad:
            raise CarotidError(f"probe name {bad[0]!r} is empty or holds a comma, quote or line break")
        self.specs, self.names = list(specs), names
        self.centres_mm = np.array([s.centre_mm for s in specs], dtype=float).reshape(-1, 3)
        offsets = [sphere_offsets(s.radius_mm) if s.radius_mm > 0 else np.zeros((1, 3)) for s in specs]
        group = np.repeat(np.arange(len(specs)), [len(o) for o in offsets])
        samples = (np.repeat(self.centres_mm, [len(o) for o in offsets], axis=0) +
                   (np.vstack(offsets) if offsets else np.zeros((0, 3)))) * MM
        locator = locator or PointLocator(mesh.points, mesh.tets)
        tet, weights = locator.locate(samples)
        centre = np.diff(group, prepend=-1) != 0
        outside = np.flatnonzero(centre & (tet < 0))
        if outside.size:
            bad = specs[group[outside[0]]]
            where = ", ".join(f"{v:g}" for v in bad.centre_mm)
            raise CarotidError(f"probe {bad.name!r} at ({where}) mm LPS is outside the fluid domain of the mesh"
                               + (f" ({outside.size} probes are)" if outside.size > 1 else ""))
        keep = tet >= 0
        self.group, self.nodes, self.weights = group[keep], mesh.tets[tet[keep]], weights[keep]
        self.samples_m = samples[keep]
        self.first = np.flatnonzero(np.diff(self.group, prepend=-1))  # the centre of each probe
        self.last = np.r_[self.first[1:], len(self.group)][:len(self.first)] - 1
        self.sample_counts = self.last - self.first + 1

    def __len__(self) -> int:
        return len(self.specs)

    def sample(self, u: np.ndarray, p: np.ndarray) -> np.ndarray:
        """One sample of every probe.

        Parameters
        ----------
        u : ndarray, shape (n, 3)
            Nodal velocity, m/s.
        p : ndarray, shape (n,)
            Nodal pressure, Pa.

        Returns
        -------
        ndarray, shape (k, 5)
            Per probe: u, v, w and the speed (m/s) of its sample point with the largest speed, and the pressure
            at its centre (Pa).
        """
        vel = np.einsum("sj,sjd->sd", self.weights, u[self.nodes])
        pressure = np.einsum("sj,sj->s", self.weights, p[self.nodes])
        speed = np.linalg.norm(vel, axis=1)
        fastest = np.lexsort((speed, self.group))[self.last]  # within each probe, sorted by speed: its last
        return np.column_stack([vel[fastest], speed[fastest], pressure[self.first]])

    def columns(self) -> list[str]:
        """The ``probes.csv`` header: ``time_s``, then ``NAME_u_m_s``, ... ``NAME_p_pa`` per probe."""
        return ["time_s"] + [f"{name}_{q}_{unit}" for name in self.names for q, unit in COLUMNS]

    def describe(self) -> list[dict]:
        """Per probe, for summary.json: name, kind, centre (mm LPS), sample-volume radius (mm), sample points."""
        return [{"name": s.name, "kind": s.kind, "position_mm": [float(v) for v in s.centre_mm],
                 "radius_mm": float(s.radius_mm), "samples": int(c), **(s.info or {})}
                for s, c in zip(self.specs, self.sample_counts)]


class ProbeRecorder:
    """The time series of a :class:`ProbeSet` over a run, sampled from the solver's state.

    A sample is kept at every output step and otherwise when at least ``period / SAMPLES_PER_CYCLE`` has passed
    since the last one (every step of an implicit run on a patient mesh, a subset of a run of millions of
    explicit steps).

    Parameters
    ----------
    probes : ProbeSet
    period : float
        Cardiac cycle, s.
    """

    def __init__(self, probes: ProbeSet, period: float):
        self.probes, self.interval = probes, period / SAMPLES_PER_CYCLE
        self.times: list[float] = []
        self.values: list[np.ndarray] = []

    def due(self, t: float, force: bool = False) -> bool:
        """Whether a sample at time ``t`` (s) is kept: after the last one, and an output step (``force``) or at
        least one sampling interval after it."""
        if self.times and t <= self.times[-1]:
            return False
        return force or not self.times or t - self.times[-1] >= self.interval * (1 - 1e-9)

    def record(self, t: float, u: np.ndarray, p: np.ndarray, force: bool = False) -> None:
        """Sample at time ``t`` (s) if :meth:`due`: ``u`` (n, 3) m/s, ``p`` (n,) Pa."""
        if self.due(t, force):
            self.times.append(float(t))
            self.values.append(self.probes.sample(u, p))

    def arrays(self, since: float = -np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Times (T,) s and values (T, k, 5) of the samples at or after ``since`` (s)."""
        times = np.array(self.times)
        keep = times >= since - 1e-12
        values = np.array(self.values).reshape(len(times), len(self.probes), len(COLUMNS))
        return times[keep], values[keep]

    def state(self) -> dict:
        """Arrays to store in a checkpoint."""
        times, values = self.arrays()
        return {"probe_times": times, "probe_values": values, "probe_samples": self.probes.samples_m}

    def load(self, state: dict, records: list[dict], flow_dir: Path) -> None:
        """Restore the series of a checkpoint ``state``; when it was recorded at other probes (or before probes
        existed), rebuild it from the stored output steps (``records`` of :class:`carotid.flow.output.FlowWriter`
        in ``flow_dir``), at their times only."""
        same = ("probe_samples" in state and np.shape(state["probe_samples"]) == self.probes.samples_m.shape
                and np.allclose(state["probe_samples"], self.probes.samples_m, rtol=0, atol=1e-12))
        if same:
            self.times = [float(t) for t in state["probe_times"]]
            self.values = list(np.asarray(state["probe_values"]))
            return
        self.times, self.values = [], []
        for record in records:
            with h5py.File(Path(flow_dir) / record["file"], "r") as f:
                self.record(record["time"], f["volume/velocity"][()], f["volume/pressure"][()], force=True)

    def write(self, flow_dir: Path) -> list[Path]:
        """Write ``probes.csv`` and ``probes.xdmf`` (+ ``probes.h5``) into ``flow_dir``, atomically."""
        flow_dir = Path(flow_dir)
        times, values = self.arrays()
        with atomic_path(flow_dir / "probes.csv") as tmp:
            with open(tmp, "w", newline="", encoding="utf-8") as handle:
                writer = csv.writer(handle)
                writer.writerow(self.probes.columns())
                writer.writerows(np.column_stack([times, values.reshape(len(times), -1)]).tolist())
        k = len(self.probes)
        arrays = {"points": self.probes.centres_mm * MM, "vertices": np.arange(k, dtype=np.int64)[:, None],
                  "time": times}
        steps = []
        for i, t in enumerate(times):
            arrays.update({f"step{i:07d}/velocity": values[i, :, :3], f"step{i:07d}/speed": values[i, :, 3],
                           f"step{i:07d}/pressure": values[i, :, 4]})
            steps.append((float(t), [(name, "Node", f"probes.h5:/step{i:07d}/{name}", shape, np.float64)
                                     for name, shape in (("velocity", (k, 3)), ("speed", (k,)),
                                                         ("pressure", (k,)))]))
        write_h5(flow_dir / "probes.h5", arrays)
        document = xdmf_document(("Polyvertex", "probes.h5:/vertices", (k, 1), np.int64),
                                  ("probes.h5:/points", (k, 3), np.float64), steps)
        with atomic_path(flow_dir / "probes.xdmf") as tmp:
            tmp.write_text(document.replace('TopologyType="Polyvertex"',
                                            'TopologyType="Polyvertex" NodesPerElement="1"'), encoding="utf-8")
        return [flow_dir / "probes.csv", flow_dir / "probes.xdmf"]


def read_probe_csv(path, start: int = 1) -> list[tuple[str, tuple[float, float, float]]]:
    """Probe points from a CSV file of rows ``x, y, z[, name]`` (mm, LPS); an optional header; ``#`` comments.

    Returns
    -------
    list of (name, (x, y, z))
        Unnamed rows are called ``probe<k>``, k counting the points from ``start``.

    Raises
    ------
    CarotidError
        An unreadable file, a row without three finite numbers (naming its line), or no rows.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CarotidError(f"cannot read the probe file {path}: {exc}") from None
    probes = []
    for lineno, row in enumerate(csv.reader(lines), start=1):
        fields = [f.strip() for f in row]
        if not any(fields) or fields[0].startswith("#"):
            continue
        try:
            xyz = tuple(float(v) for v in fields[:3])
        except ValueError:
            if not probes and lineno == 1:
                continue  # a header
            xyz = ()
        if len(xyz) != 3 or len(fields) > 4 or not all(math.isfinite(v) for v in xyz):
            raise CarotidError(f"{path}: line {lineno}: expected 'x, y, z[, name]' in mm, got {','.join(row)!r}")
        probes.append((fields[3] if len(fields) == 4 and fields[3] else f"probe{len(probes) + start}", xyz))
    if not probes:
        raise CarotidError(f"{path}: no probe rows 'x, y, z[, name]'")
    return probes
