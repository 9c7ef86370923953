"""Discretisation error of a result from three meshes: Richardson extrapolation and the grid convergence index.

The procedure is the one recommended by the Journal of Fluids Engineering (Celik, Ghia, Roache, Freitas,
Coleman and Raad 2008, "Procedure for estimation and reporting of uncertainty due to discretization in CFD
applications", J. Fluids Eng. 130:078001), which is Roache's grid convergence index (GCI; Roache 1998,
"Verification and Validation in Computational Science and Engineering") as ASME V&V 20-2009 uses it for the
numerical uncertainty u_num.  With three meshes of representative cell sizes h1 < h2 < h3 and solutions
phi1, phi2, phi3 (1 the finest):

* h = (V / N)^(1/3), V the volume and N the element count (eq. 1);
* r21 = h2 / h1, r32 = h3 / h2 (they need not be equal); eps21 = phi2 - phi1, eps32 = phi3 - phi2;
* the apparent order p solves (eqs. 2a-c)

      p = |ln |eps32 / eps21| + q(p)| / ln r21,    q(p) = ln((r21^p - s) / (r32^p - s)),
      s = sign(eps32 / eps21),

  by fixed-point iteration from q = 0 (exact in one step when r21 = r32);
* phi_ext21 = (r21^p phi1 - phi2) / (r21^p - 1)                   (eq. 3)
* e_a21 = |(phi1 - phi2) / phi1|, e_ext21 = |(phi_ext21 - phi1) / phi_ext21|   (eq. 4)
* GCI_fine21 = Fs e_a21 / (r21^p - 1) with the safety factor Fs = 1.25 of three-mesh studies   (eq. 5).

s < 0 is oscillatory convergence: the order and GCI are still given (as the paper does) but flagged, and the
extrapolated value is then not exact even for an error that is exactly a power of h.  The sequence diverges
when the observed change does not shrink: for s > 0 when |eps32 / eps21| <= ln r32 / ln r21 (the ratio of a
power law h^p with p -> 0), for s < 0 when |eps32 / eps21| <= 1; both reduce to the usual |eps21| >= |eps32|
for equal ratios.  Diverging, indeterminate (eps21 or eps32 zero) and non-converging iterations get NaN order,
extrapolation and GCI.
"""

from __future__ import annotations

import numpy as np

from carotid.errors import CarotidError

SAFETY_FACTOR = 1.25
"""Fs of a three-mesh GCI (Roache 1998; Celik et al. 2008)."""

MONOTONIC, OSCILLATORY, DIVERGENT, INDETERMINATE = 0, 1, 2, 3
STATUS = ("monotonic", "oscillatory", "divergent", "indeterminate")
"""Names of the status codes returned by :func:`grid_convergence`."""


def representative_size(volume, elements) -> np.ndarray:
    """Representative cell size h = (V / N)^(1/3) (Celik et al. 2008, eq. 1).

    Parameters
    ----------
    volume : float or array_like
        Domain volume, any length unit cubed (mm^3).
    elements : int or array_like
        Element count N.

    Returns
    -------
    ndarray
        h in the length unit of ``volume``.
    """
    return np.cbrt(np.asarray(volume, dtype=float) / np.asarray(elements, dtype=float))


def apparent_order(eps21, eps32, r21, r32, *, tol: float = 1e-12, max_iterations: int = 200):
    """Apparent order p of three solutions by the fixed-point iteration of Celik et al. (2008, eq. 2).

    Parameters
    ----------
    eps21, eps32 : array_like
        phi2 - phi1 and phi3 - phi2 (same shape).
    r21, r32 : float
        Refinement ratios h2 / h1 and h3 / h2, both > 1.
    tol : float
        Stop when p changes by less than this between iterations.
    max_iterations : int

    Returns
    -------
    p : ndarray
        Apparent order; NaN where the sequence diverges, is indeterminate or the iteration does not settle.
    status : ndarray of int
        MONOTONIC, OSCILLATORY, DIVERGENT or INDETERMINATE (see ``STATUS``).
    """
    eps21, eps32 = np.broadcast_arrays(np.asarray(eps21, dtype=float), np.asarray(eps32, dtype=float))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = eps32 / eps21
    s = np.sign(ratio)
    size = np.abs(ratio)
    defined = np.isfinite(ratio) & (ratio != 0)
    threshold = np.where(s > 0, np.log(r32) / np.log(r21), 1.0)
    converging = defined & (size > threshold)
    status = np.select([~defined, ~converging, s < 0], [INDETERMINATE, DIVERGENT, OSCILLATORY], MONOTONIC)
    log_ratio = np.log(np.where(converging, size, 2.0))
    sign = np.where(converging, s, 1.0)
    p = np.abs(log_ratio) / np.log(r21)
    settled = np.zeros(p.shape, dtype=bool)
    for _ in range(max_iterations):
        q = np.log((r21 ** p - sign) / (r32 ** p - sign))
        new = np.abs(log_ratio + q) / np.log(r21)
        settled = np.abs(new - p) <= tol * np.maximum(1.0, np.abs(new))
        p = new
        if settled.all():
            break
    return np.where(converging & settled, p, np.nan), status


def grid_convergence(h, phi, safety_factor: float = SAFETY_FACTOR) -> dict[str, np.ndarray]:
    """Richardson extrapolation and fine-grid GCI of many quantities computed on three meshes.

    Parameters
    ----------
    h : array_like, shape (3,)
        Representative cell sizes (:func:`representative_size`), any length unit, in any order.
    phi : array_like, shape (3, ...)
        The quantities on each mesh, in the order of ``h`` (e.g. per-node or per-branch TAWSS, Pa).
    safety_factor : float
        Fs (1.25 for three meshes).

    Returns
    -------
    dict of str to ndarray, each of the shape of ``phi[0]`` except the scalars ``h`` and ``r21``, ``r32``
        ``"h"`` (the sizes, finest first), ``"r21"``, ``"r32"``, ``"phi"`` (finest first, shape (3, ...)),
        ``"p"`` (apparent order), ``"status"`` (codes of ``STATUS``), ``"phi_ext21"`` (unit of phi),
        ``"e_a21"``, ``"e_ext21"``, ``"gci_fine21"`` (fractions, not %), and ``"u_num"`` = GCI_fine21 |phi1|
        (the numerical uncertainty in the unit of phi).
    """
    h = np.asarray(h, dtype=float)
    phi = np.asarray(phi, dtype=float)
    if h.shape != (3,) or phi.shape[:1] != (3,):
        raise CarotidError(f"the GCI needs three meshes: h of shape (3,) and phi of shape (3, ...), got {h.shape}, "
                           f"{phi.shape}")
    order = np.argsort(h)
    h, phi = h[order], phi[order]
    if not (h[0] > 0 and h[1] > h[0] and h[2] > h[1]):
        raise CarotidError(f"the three meshes must have distinct positive cell sizes, got {h.tolist()}")
    r21, r32 = h[1] / h[0], h[2] / h[1]
    p, status = apparent_order(phi[1] - phi[0], phi[2] - phi[1], r21, r32)
    rp = r21 ** p
    with np.errstate(divide="ignore", invalid="ignore"):
        ext = (rp * phi[0] - phi[1]) / (rp - 1.0)
        e_a = np.abs((phi[0] - phi[1]) / phi[0])
        e_ext = np.abs((ext - phi[0]) / ext)
        gci = safety_factor * e_a / (rp - 1.0)
    return {"h": h, "r21": r21, "r32": r32, "phi": phi, "p": p, "status": status, "phi_ext21": ext,
            "e_a21": e_a, "e_ext21": e_ext, "gci_fine21": gci, "u_num": gci * np.abs(phi[0])}


QUANTITIES = ("TAWSS", "OSI", "RRT")
"""Wall indices of a convergence study (``flow/indices.vtp`` point arrays)."""

TIME_DIVISORS = (1, 2, 4)
"""Time steps of the temporal levels of :func:`run_convergence`: the coarsest mesh's step divided by these."""


def coarsened_mesh_parameters(parameters: dict, factor: float) -> dict:
    """Mesh-stage parameters of a mesh ``factor`` times coarser (``factor`` < 1: finer).

    The core edge length ``size_mm`` is multiplied by ``factor``; the wall layer keeps its total thickness
    and grading span while its sub-layer count N becomes ``round(N / factor)``, at least min(N, 2) (the mesher's
    quality report needs two sub-layers), and the growth ratio
    f becomes ``f^(N / N')``, so that f'^N' = f^N and the first-layer height T (f' - 1) / (f'^N' - 1)
    scales by (f' - 1) / (f - 1), about N / N' (the rule of :meth:`carotid.flow.verify.TubeSpec.refined`).
    The wall triangles are those of the surface given to :func:`carotid.mesh.mesher.build_mesh`: scale them
    with :func:`carotid.surface.remesh.coarsened_surface`.

    Parameters
    ----------
    parameters : dict
        ``mesh_quality.json`` ``"parameters"`` (``layers``, ``ratio``, ``thickness_mm``, ``thickness_ratio``,
        ``size_mm`` in mm, ``core``, ``lloyd_iterations``).
    factor : float
        Coarsening factor, > 0.

    Returns
    -------
    dict
        Keyword arguments of :func:`carotid.mesh.mesher.build_mesh`.
    """
    layers = int(parameters["layers"])
    new_layers = max(min(layers, 2), round(layers / factor))
    return {"layers": new_layers, "ratio": float(parameters["ratio"]) ** (layers / max(new_layers, 1)),
            "thickness": parameters.get("thickness_mm"), "thickness_ratio": parameters.get("thickness_ratio"),
            "size": float(parameters["size_mm"]) * factor, "core": parameters.get("core", "gmsh"),
            "lloyd_iterations": int(parameters.get("lloyd_iterations", 5))}


def wall_interpolation(wall, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation from the nodes of a triangle surface to other points: the vertices and barycentric
    weights of each point's closest point on it.

    Parameters
    ----------
    wall : pyvista.PolyData
        Triangles (e.g. a level's ``flow/indices.vtp``), mm.
    query : ndarray, shape (q, 3)
        Points near it, mm.

    Returns
    -------
    vertices : ndarray of int, shape (q, 3)
        The three vertices of the closest triangle.
    weights : ndarray, shape (q, 3)
        Their barycentric weights at the closest point (sum 1): a nodal field f is ``(f[vertices] *
        weights).sum(axis=1)`` at the query points.
    """
    from carotid.surface.project import TriangleProjector

    points = np.asarray(wall.points, dtype=float)
    triangles = wall.faces.reshape(-1, 4)[:, 1:]
    closest, face = TriangleProjector(points, triangles)(np.asarray(query, dtype=float))
    vertices = triangles[face]
    a, b, c = (points[vertices[:, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, closest - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    det = np.maximum(d00 * d11 - d01 ** 2, 1e-300)
    wb, wc = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
    return vertices, np.stack([1.0 - wb - wc, wb, wc], axis=1)


def _branch_means(wall, regions: np.ndarray, n_branches: int) -> np.ndarray:
    """Area-weighted means (len(QUANTITIES), n_branches + 1) of the indices per branch and over the whole wall
    (last column); non-finite values (RRT of a purely reversing shear) are left out."""
    from carotid.flow.indices import node_areas

    area = node_areas(wall.points, wall.faces.reshape(-1, 4)[:, 1:])
    groups = np.r_[regions, np.full(len(regions), n_branches)]
    out = []
    for name in QUANTITIES:
        value = np.tile(np.asarray(wall[name], dtype=float), 2)
        weight = np.tile(area, 2) * np.isfinite(value)
        total = np.bincount(groups, np.where(weight > 0, weight * value, 0.0), minlength=n_branches + 1)
        out.append(total / np.maximum(np.bincount(groups, weight, minlength=n_branches + 1), 1e-300))
    return np.array(out)


def _tables(result: dict, names: list[str], **extra: np.ndarray) -> dict:
    """JSON rows of a vectorised :func:`grid_convergence` result, one per name (the last axis); each ``extra``
    array (one value per name) is one more column."""
    columns = {k: result[k] for k in ("p", "phi_ext21", "e_a21", "e_ext21", "gci_fine21", "u_num")} | extra

    def number(x):
        return float(x) if np.isfinite(x) else None

    return {name: {"phi_fine_to_coarse": [number(v) for v in result["phi"][:, j]],
                   "status": STATUS[int(result["status"][j])], **{k: number(v[j]) for k, v in columns.items()}}
            for j, name in enumerate(names)}


_PROGRESS = None
"""The queue on which a worker process of :func:`run_convergence` reports ``(run name, fraction done)``."""


def _worker_init(queue) -> None:
    """Initialiser of the worker processes: keep the progress queue."""
    global _PROGRESS
    _PROGRESS = queue


def _run_level(name: str, mesh, out, params) -> dict:
    """One level's :func:`carotid.flow.simulate.simulate` in a worker process (resumed from a matching checkpoint),
    reporting its fraction of the simulated time done at most every 2 s; returns the summary with
    ``cpu_seconds``, the process time of the whole call (set-up included), s."""
    import time

    from carotid.flow.simulate import simulate

    sent = [-np.inf]

    def progress(info: dict) -> None:
        if time.monotonic() - sent[0] >= 2.0:
            sent[0] = time.monotonic()
            _PROGRESS.put((name, info["time"] / info["end"]))

    cpu = time.process_time()
    summary = simulate(mesh, out, params, resume="auto", progress=progress)
    return {**summary, "cpu_seconds": time.process_time() - cpu}


def _wait(futures: dict, queue, weights: dict, log, progress) -> dict:
    """Wait for the runs of :func:`run_convergence`; returns their summaries by name.

    ``futures`` maps each future to its run name, ``weights`` each name to its estimated cost (any unit);
    ``progress`` receives ``{"fraction": cost-weighted fraction of the study done, "runs": name -> fraction}``
    about every second, ``log`` a line when a run ends.  The first failed run's error is raised.
    """
    import queue as queues
    from concurrent.futures import FIRST_COMPLETED, wait

    fractions = dict.fromkeys(weights, 0.0)
    summaries, pending = {}, set(futures)
    total = sum(weights.values())
    while pending:
        finished, pending = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
        try:
            while True:
                name, fraction = queue.get_nowait()
                fractions[name] = fraction
        except queues.Empty:
            pass
        for future in finished:
            name = futures[future]
            summaries[name] = future.result()
            fractions[name] = 1.0
            if log is not None:
                log(f"{name} done: {summaries[name]['steps']:,} steps in {summaries[name]['seconds']:.0f} s")
        if progress is not None:
            progress({"fraction": sum(weights[n] * f for n, f in fractions.items()) / total, "runs": dict(fractions)})
    return summaries


def run_convergence(case_dir, params, refinement: float = 1.5, time_levels: bool = True, workers: int = 2,
                    case_mesh: bool = True, log=None, progress=None) -> dict:
    """Solution verification of a case: GCI of TAWSS, OSI and RRT per branch and per wall node, in space and time.

    Space: level 0 is the case's own mesh (``mesh.vtu``), so that the GCI is the discretisation uncertainty of
    the case's results; levels 1 and 2 are rebuilt from ``surface.vtp`` remeshed with edges ``refinement`` and
    ``refinement^2`` times as long (:func:`carotid.surface.remesh.coarsened_surface`: the wall, where WSS is
    computed, is coarsened with the rest) and meshed with :func:`coarsened_mesh_parameters` of the case mesh's
    recorded parameters coarsened by the same factors.  Without ``case_mesh`` the three levels are those coarsened by
    ``refinement``, ``refinement^2`` and ``refinement^3``: the case mesh, finer than all of them, is not run
    (a quarter of the cost or less), and the GCI is then that of level 0, a conservative bound of the case
    mesh's error where the convergence is monotonic and asymptotic.  Each level runs
    :func:`carotid.flow.simulate.simulate` with ``params`` (a fixed ``dt``, meant for the case mesh, is scaled
    by the level's representative size h over the case mesh's; the adaptive step scales so by itself) into
    ``flow/convergence/level<k>``.  Per branch region (wall nodes of the nearest centerline branch,
    :func:`carotid.centerline.model.branch_regions`) and over the whole wall, the area-weighted mean TAWSS
    (Pa), OSI and RRT (1/Pa) of each level go through :func:`grid_convergence` (Celik et al. 2008); per node,
    the coarser levels' indices are interpolated linearly to the nodes of level 0's wall
    (:func:`wall_interpolation`).

    Time (``time_levels``): the coarsest mesh is run again with its time step divided by 2 and 4 (the
    adaptive step's safety factor, or the fixed ``dt``, divided) into ``flow/convergence/level2_dt<d>``, and
    the same per-branch means go through :func:`grid_convergence` with h the mean step of each run (s; the
    adaptive step halves only about, as it follows the flow): the apparent temporal order, the extrapolation
    to a zero step and the GCI of the quarter step; each row adds
    ``default_change``, the relative change |phi(dt) / phi(dt/2) - 1| of the study's own step, and
    ``default_e_ext``, its relative distance |phi(dt) / phi_ext - 1| from the extrapolation (the estimated
    temporal error of the coarsest mesh's step, the largest of the study: the steps scale with h).

    The runs go to ``workers`` processes, finest first (with the case mesh, the longest: at ``refinement`` 1.5
    the four others together take about half as long), while the coarser meshes are built.

    Parameters
    ----------
    case_dir : path
        Case with ``surface.vtp``, ``mesh.vtu``, ``mesh_quality.json`` and ``centerlines.vtp``.
    params : FlowParameters
        Settings of every level (``cycles``, ``periodic_tol``, waveform...).
    refinement : float
        Ratio of the edge lengths (wall and core) of consecutive levels, > 1.
    time_levels : bool
        Also run the two temporal levels.
    workers : int
        Processes running the levels side by side (each uses one core).
    case_mesh : bool
        Level 0 is the case mesh (else the case mesh coarsened by ``refinement``).
    log : callable, optional
        Receives a line per level built and per run ended.
    progress : callable, optional
        Receives ``{"fraction", "runs"}`` about every second (see :func:`_wait`).

    Returns
    -------
    dict
        Also written to ``flow/convergence.json``: ``levels`` (0 finest), the per-branch tables ``branches``
        and the map summary ``map`` of the spatial study, and ``time`` (None without temporal levels) with
        its ``levels`` and ``branches``.  The nodal map is ``flow/convergence.vtp`` on level 0's wall (point
        arrays ``<Q>``, ``<Q>_ext``, ``<Q>_GCI`` (fraction), ``<Q>_p`` and ``<Q>_status`` for Q in QUANTITIES,
        and ``branch``).
    """
    import json
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor
    from dataclasses import replace
    from pathlib import Path

    from carotid.centerline import read_centerlines
    from carotid.centerline.model import branch_regions
    from carotid.flow.output import write_wall_vtp
    from carotid.io import write_json
    from carotid.io.vtkfile import read_vtk
    from carotid.mesh.io import write_mesh
    from carotid.mesh.boundary import check_surface
    from carotid.mesh.mesher import build_mesh, median_edge
    from carotid.surface.remesh import coarsened_surface

    if not refinement > 1:
        raise CarotidError(f"--refinement must exceed 1 (got {refinement})")
    if workers < 1:
        raise CarotidError(f"--workers must be at least 1 (got {workers})")
    start = time.perf_counter()
    case_dir = Path(case_dir)
    for name in ("surface.vtp", "mesh.vtu", "mesh_quality.json", "centerlines.vtp"):
        if not (case_dir / name).is_file():
            raise CarotidError(f"the convergence study needs {case_dir / name}: run the earlier stages first")
    surface = read_vtk(case_dir / "surface.vtp", "surface", remedy="rerun `carotid surface`")
    case_quality = json.loads((case_dir / "mesh_quality.json").read_text(encoding="utf-8"))
    recorded = case_quality["parameters"]
    branches = read_centerlines(case_dir / "centerlines.vtp").branches
    names = [b.name for b in branches] + ["whole wall"]
    out = case_dir / "flow" / "convergence"
    h_case = float(representative_size(case_quality["volume"]["mesh_mm3"], case_quality["elements"]["tetrahedra"]))
    levels, weights, futures = [], {}, {}
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init, initargs=(queue,)) as pool:
        try:
            for k in range(3):
                factor = refinement ** (k + (not case_mesh))
                if k == 0 and case_mesh:
                    mesh_path, quality, wall = case_dir / "mesh.vtu", case_quality, surface
                else:
                    wall = coarsened_surface(surface, factor)
                    mesh, quality = build_mesh(wall, **coarsened_mesh_parameters(recorded, factor))
                    write_mesh(mesh, out / f"level{k}", quality)
                    mesh_path = out / f"level{k}" / "mesh.vtu"
                tets = quality["elements"]["tetrahedra"]
                h = float(representative_size(quality["volume"]["mesh_mm3"], tets))
                # no user probes: a point near the wall may lie outside a coarsened mesh (the study is of the wall)
                run = replace(params, dt=None if params.dt is None else params.dt * h / h_case, probes=())
                edge = median_edge(check_surface(wall))
                levels.append({"level": k, "h_mm": h, "tetrahedra": tets, "nodes": quality["elements"]["points"],
                               "wall_edge_mm": edge, "edge_factor": factor,
                               "mesh": coarsened_mesh_parameters(recorded, factor)})
                if log is not None:
                    log(f"level {k}{' (case mesh)' if factor == 1 else ''}: {tets:,} tetrahedra, h = {h:.3f} mm, "
                        f"wall edge {edge:.3f} mm")
                weights[f"level{k}"] = tets / h
                futures[pool.submit(_run_level, f"level{k}", mesh_path, out / f"level{k}", run)] = f"level{k}"
            for divisor in TIME_DIVISORS[1:] if time_levels else ():  # the coarsest level's mesh_path and run
                name = f"level2_dt{divisor}"
                finer = replace(run, safety=run.safety / divisor, dt=None if run.dt is None else run.dt / divisor)
                weights[name] = weights["level2"] * divisor
                futures[pool.submit(_run_level, name, mesh_path, out / name, finer)] = name
            summaries = _wait(futures, queue, weights, log, progress)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            if log is not None and futures:
                log("stopped: waiting for the running levels to end (a rerun resumes them)")
            raise
    for level in levels:
        summary = summaries[f"level{level['level']}"]
        level.update({key: summary[key] for key in ("dt_s", "steps", "seconds", "cpu_seconds", "cycles", "partial",
                                                    "periodic")})
        level["wall_triangles"] = summary["mesh"]["wall_triangles"]
    walls = {}
    for name in summaries:
        path = out / name / "flow" / "indices.vtp"
        if not path.is_file():
            raise CarotidError(f"{name} wrote no wall indices (under two outputs): run longer or output more often")
        walls[name] = read_vtk(path, "wall indices")
    means = {name: _branch_means(w, branch_regions(np.asarray(w.points), branches), len(branches))
             for name, w in walls.items()}  # each (Q, B + 1)
    fine = walls["level0"]
    spatial = [walls[f"level{k}"] for k in range(3)]
    interpolation = [wall_interpolation(w, np.asarray(fine.points)) for w in spatial]
    nodal = {q: np.array([(np.asarray(w[q], dtype=float)[v] * c).sum(axis=1) for w, (v, c) in
                          zip(spatial, interpolation)]) for q in QUANTITIES}
    h = np.array([level["h_mm"] for level in levels])
    spatial_means = np.array([means[f"level{k}"] for k in range(3)])  # (3, Q, B + 1)
    result = {"method": "Celik et al. 2008 (J. Fluids Eng. 130:078001): Richardson extrapolation and the GCI of "
                        "Roache with Fs = 1.25, h = (V/N)^(1/3); the levels are meshed from surface.vtp remeshed with "
                        "edges edge_factor times longer than the case's, with the core size and the layer count "
                        "scaled alike (edge_factor 1: the case mesh itself)",
              "refinement": refinement, "case_level": 0 if case_mesh else None, "workers": workers,
              "levels": levels, "branches": {}, "map": {}, "time": None}
    arrays = {"branch": branch_regions(np.asarray(fine.points), branches)}
    for q, name in enumerate(QUANTITIES):
        result["branches"][name] = _tables(grid_convergence(h, spatial_means[:, q]), names)
        node = grid_convergence(h, nodal[name])
        gci = node["gci_fine21"]
        result["map"][name] = {"median_gci": float(np.nanmedian(gci)) if np.isfinite(gci).any() else None,
                               **{s: float(np.mean(node["status"] == c)) for c, s in enumerate(STATUS)}}
        arrays.update({name: node["phi"][0], f"{name}_ext": node["phi_ext21"], f"{name}_GCI": gci,
                       f"{name}_p": node["p"], f"{name}_status": node["status"]})
    if time_levels:
        runs = ["level2"] + [f"level2_dt{d}" for d in TIME_DIVISORS[1:]]
        step = np.array([summaries[r]["time_s"] / summaries[r]["steps"] for r in runs])  # mean steps, s
        temporal = np.array([means[r] for r in runs])
        result["time"] = {
            "method": "the coarsest mesh (level 2) again with its time step divided by 2 and 4 (the safety factor "
                      "of the adaptive step, or the fixed dt); grid_convergence with h the mean step of each run, "
                      "simulated time / steps",
            "mesh_level": 2,
            "levels": [{"name": r, "divisor": d, "dt_mean_s": float(mean),
                        "dt_s": summaries[r]["dt_s"], "steps": summaries[r]["steps"],
                        "seconds": summaries[r]["seconds"], "cpu_seconds": summaries[r]["cpu_seconds"],
                        "partial": summaries[r]["partial"]}
                       for r, d, mean in zip(runs, TIME_DIVISORS, step)],
            "branches": {}}
        for q, name in enumerate(QUANTITIES):
            study = grid_convergence(step, temporal[:, q])
            with np.errstate(divide="ignore", invalid="ignore"):
                change = np.abs(temporal[0, q] / temporal[1, q] - 1.0)
                error = np.abs(temporal[0, q] / study["phi_ext21"] - 1.0)
            result["time"]["branches"][name] = _tables(study, names, default_change=change, default_e_ext=error)
    result["seconds"] = time.perf_counter() - start
    write_wall_vtp(case_dir / "flow" / "convergence.vtp", np.asarray(fine.points),
                   fine.faces.reshape(-1, 4)[:, 1:], arrays)
    write_json(result, case_dir / "flow" / "convergence.json")
    return result
