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


def coarsened_mesh_parameters(parameters: dict, factor: float) -> dict:
    """Mesh-stage parameters of a mesh ``factor`` times coarser (``factor`` < 1: finer).

    The core edge length ``size_mm`` is multiplied by ``factor``; the wall layer keeps its total thickness
    and grading span while its sub-layer count N becomes ``round(N / factor)``, at least min(N, 2) (the mesher's
    quality report needs two sub-layers), and the growth ratio
    f becomes ``f^(N / N')``, so that f'^N' = f^N and the first-layer height T (f' - 1) / (f'^N' - 1)
    scales by (f' - 1) / (f - 1), about N / N' (the rule of :meth:`carotid.flow.verify.TubeSpec.refined`).
    The wall triangles are those of ``surface.vtp`` on every level: the wall resolution is not scaled.

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


def _tables(result: dict, names: list[str]) -> dict:
    """JSON rows of a vectorised :func:`grid_convergence` result, one per name (the last axis)."""
    keys = ("p", "phi_ext21", "e_a21", "e_ext21", "gci_fine21", "u_num")

    def number(x):
        return float(x) if np.isfinite(x) else None

    return {name: {"phi_fine_to_coarse": [number(v) for v in result["phi"][:, j]],
                   "status": STATUS[int(result["status"][j])], **{k: number(result[k][j]) for k in keys}}
            for j, name in enumerate(names)}


def run_convergence(case_dir, params, refinement: float = 1.5, log=None, progress=None) -> dict:
    """Three-mesh solution verification of a case: GCI of TAWSS, OSI and RRT per branch and per wall node.

    The coarsest level is the case's own mesh (the parameters recorded in ``mesh_quality.json``); the medium
    and finest levels are rebuilt from ``surface.vtp`` with :func:`coarsened_mesh_parameters` refined by
    ``refinement`` and ``refinement^2`` (refined, not coarsened: the core mesher takes its size from the wall
    triangles where the requested core size is larger, so a coarser core request changes nothing).  The GCI is
    the discretisation uncertainty of the finest level's results.  Each level
    runs :func:`carotid.flow.simulate.simulate` with ``params`` (a fixed ``dt``, meant for the case mesh, is
    scaled by the level's representative size h over the case mesh's) into ``flow/convergence/level<k>``
    (0 finest).  Per branch region (wall nodes of
    the nearest centerline branch, :func:`carotid.centerline.model.branch_regions`) and over the whole wall,
    the area-weighted mean TAWSS (Pa), OSI and RRT (1/Pa) of each level go through :func:`grid_convergence`
    (Celik et al. 2008); per node, the coarser levels' indices are taken at the nearest node of their wall
    (the same nodes when, as here, every level keeps the wall triangles of ``surface.vtp``).

    Parameters
    ----------
    case_dir : path
        Case with ``surface.vtp``, ``mesh_quality.json`` and ``centerlines.vtp``.
    params : FlowParameters
        Settings of every level (``cycles``, ``periodic_tol``, waveform...).
    refinement : float
        Ratio of the core sizes of consecutive levels, > 1.
    log : callable, optional
        Receives a line per level.
    progress : callable, optional
        Passed to :func:`simulate`.

    Returns
    -------
    dict
        Also written to ``flow/convergence.json``; the nodal map is ``flow/convergence.vtp`` (point arrays
        ``<Q>``, ``<Q>_ext``, ``<Q>_GCI`` (fraction), ``<Q>_p`` and ``<Q>_status`` for Q in QUANTITIES, and
        ``branch``).
    """
    import json
    from dataclasses import replace
    from pathlib import Path

    import pyvista as pv
    from scipy.spatial import cKDTree

    from carotid.centerline import read_centerlines
    from carotid.centerline.model import branch_regions
    from carotid.flow.output import write_wall_vtp
    from carotid.flow.simulate import simulate
    from carotid.io import write_json
    from carotid.mesh.io import write_mesh
    from carotid.mesh.mesher import build_mesh

    if not refinement > 1:
        raise CarotidError(f"--refinement must exceed 1 (got {refinement})")
    case_dir = Path(case_dir)
    for name in ("surface.vtp", "mesh_quality.json", "centerlines.vtp"):
        if not (case_dir / name).is_file():
            raise CarotidError(f"the convergence study needs {case_dir / name}: run the earlier stages first")
    surface = pv.read(case_dir / "surface.vtp")
    case_quality = json.loads((case_dir / "mesh_quality.json").read_text())
    recorded = case_quality["parameters"]
    h_case = float(representative_size(case_quality["volume"]["mesh_mm3"], case_quality["elements"]["tetrahedra"]))
    branches = read_centerlines(case_dir / "centerlines.vtp").branches
    names = [b.name for b in branches] + ["whole wall"]
    out = case_dir / "flow" / "convergence"
    levels, walls = [], []
    for k in range(3):
        mesh_args = coarsened_mesh_parameters(recorded, refinement ** (k - 2))
        mesh, quality = build_mesh(surface, **mesh_args)
        level_dir = out / f"level{k}"
        write_mesh(mesh, level_dir, quality)
        h = float(representative_size(quality["volume"]["mesh_mm3"], quality["elements"]["tetrahedra"]))
        dt = None if params.dt is None else params.dt * h / h_case
        if log is not None:
            log(f"level {k}: {quality['elements']['tetrahedra']:,} tetrahedra, h = {h:.3f} mm")
        summary = simulate(level_dir / "mesh.vtu", level_dir, replace(params, dt=dt), resume="auto",
                           progress=progress)
        if not (level_dir / "flow" / "indices.vtp").is_file():
            raise CarotidError(f"level {k} wrote no wall indices (under two outputs): run longer or output more often")
        walls.append(pv.read(level_dir / "flow" / "indices.vtp"))
        levels.append({"level": k, "h_mm": h, "tetrahedra": quality["elements"]["tetrahedra"],
                       "nodes": quality["elements"]["points"], "mesh": mesh_args, "dt_s": summary["dt_s"],
                       "steps": summary["steps"], "seconds": summary["seconds"], "cycles": summary["cycles"],
                       "partial": summary["partial"], "periodic": summary["periodic"]})
    h = np.array([lv["h_mm"] for lv in levels])
    fine = walls[0]
    regions = [branch_regions(np.asarray(w.points), branches) for w in walls]
    means = np.array([_branch_means(w, r, len(branches)) for w, r in zip(walls, regions)])  # (3, Q, B + 1)
    nearest = [cKDTree(np.asarray(w.points)).query(np.asarray(fine.points))[1] for w in walls]
    nodal = {name: np.array([np.asarray(w[name], dtype=float)[i] for w, i in zip(walls, nearest)])
             for name in QUANTITIES}
    result = {"method": "Celik et al. 2008 (J. Fluids Eng. 130:078001): Richardson extrapolation and the GCI of "
                        "Roache with Fs = 1.25, h = (V/N)^(1/3); level 2 is the case mesh, levels 1 and 0 "
                        "refined from it",
              "refinement": refinement, "levels": levels, "branches": {}, "map": {}}
    arrays = {"branch": regions[0]}
    for q, name in enumerate(QUANTITIES):
        result["branches"][name] = _tables(grid_convergence(h, means[:, q]), names)
        node = grid_convergence(h, nodal[name])
        gci = node["gci_fine21"]
        result["map"][name] = {"median_gci": float(np.nanmedian(gci)) if np.isfinite(gci).any() else None,
                               **{s: float(np.mean(node["status"] == c)) for c, s in enumerate(STATUS)}}
        arrays.update({name: node["phi"][0], f"{name}_ext": node["phi_ext21"], f"{name}_GCI": gci,
                       f"{name}_p": node["p"], f"{name}_status": node["status"]})
    write_wall_vtp(case_dir / "flow" / "convergence.vtp", np.asarray(fine.points),
                   fine.faces.reshape(-1, 4)[:, 1:], arrays)
    write_json(result, case_dir / "flow" / "convergence.json")
    return result
