"""What the report judges: the stenosis category, the quality checks of each stage and stale results.

Every function here reads the JSON records the stages wrote (and, for staleness, the current files) and
returns plain values, so the HTML layer only lays them out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carotid.mesh.mesher import CORE_MIN_DIHEDRAL

# Near-occlusion on CTA (Bartlett et al., AJNR 2006;27:632-637): a residual lumen of at most 1.3 mm with a
# collapsed distal ICA of at most 3.5 mm.  NASCET underestimates such a stenosis (its reference collapses),
# so the category overrides the percentage.
NEAR_OCCLUSION_RESIDUAL_MM = 1.3
NEAR_OCCLUSION_DISTAL_MM = 3.5

# Mesh quality limits.  Tetrahedra of the core flatter than the mesher's floor (``CORE_MIN_DIHEDRAL``, which
# it repairs by thinning the layer) degrade the pressure solve.  The wall layers are flat by design: a right
# prism split into three tetrahedra has a smallest dihedral angle of about its height over its edge (2.6
# degrees at 0.04, the first of ten layers), and its largest is 90-100 degrees.  What spoils the wall
# gradients is a dihedral angle near 180 degrees (the maximum angle condition of linear elements), from
# columns that twist or fan; 165 degrees is TetGen's default bound on it (``-q``).
MAX_DIHEDRAL_LAYER_DEG = 165.0
MIN_SURFACE_ANGLE_DEG = 15.0
MAX_SPLIT_ERROR = 0.01  # absolute error of an outlet's flow fraction
# Outputs that later stages rewrite by design (the surface stage adds the caps to geometry.json; the report
# is rebuilt at will): their recorded hashes say nothing about staleness.
AMENDED = ("geometry.json", "report.html")


def stenosis_category(nascet: float, min_diameter_mm: float, distal_diameter_mm: float) -> str:
    """NASCET category of a carotid stenosis.

    Parameters
    ----------
    nascet : float
        NASCET grade, fraction: 1 - minimal diameter / distal ICA diameter.
    min_diameter_mm, distal_diameter_mm : float
        Minimal lumen diameter and distal reference diameter, mm.

    Returns
    -------
    str
        ``"near-occlusion"`` when the residual lumen is at most 1.3 mm and the distal ICA at most
        3.5 mm (whatever the percentage), else ``"<50 %"``, ``"50-69 %"`` or ``">=70 %"``.
    """
    if min_diameter_mm <= NEAR_OCCLUSION_RESIDUAL_MM and distal_diameter_mm <= NEAR_OCCLUSION_DISTAL_MM:
        return "near-occlusion"
    if nascet >= 0.70:
        return ">=70 %"
    if nascet >= 0.50:
        return "50-69 %"
    return "<50 %"


@dataclass
class Check:
    """One quality criterion of one stage and whether the stage's record meets it."""

    stage: str
    quantity: str
    value: object
    criterion: str
    passed: bool


def _get(data: dict, dotted: str):
    """``data["a"]["b"]`` for ``"a.b"``; None when a key is missing."""
    for key in dotted.split("."):
        if not isinstance(data, dict) or key not in data:
            return None
        data = data[key]
    return data


def quality_checks(segmentation: dict, surface: dict, mesh: dict, flow: dict) -> list[Check]:
    """The pass/fail criteria of every stage whose record is present.

    Parameters
    ----------
    segmentation, surface, mesh, flow : dict
        ``segmentation/report.json``, ``surface_quality.json``, ``mesh_quality.json`` and
        ``flow/summary.json`` (empty when the stage has not run).

    Returns
    -------
    list of Check
        Criteria whose quantity is recorded; absent quantities are not judged, nor the cycle-to-cycle TAWSS
        change of a flow run without a periodicity tolerance (``periodic.status`` "not assessed").
    """
    validated = _get(segmentation, "intensity.contrast_to_noise_validated")  # the ratio's bound, as recorded
    rows = [
        ("segmentation", "level set converged", _get(segmentation, "converged"), "yes", lambda v: bool(v)),
        ("segmentation", "handles of the lumen (a vessel tree has none)", _get(segmentation, "topology.handles"), "0",
         lambda v: v == 0),
        ("segmentation", "lumen contrast-to-noise ratio (validated down to the criterion)",
         _get(segmentation, "intensity.contrast_to_noise"), f">= {validated}", lambda v: v >= validated),
        ("surface", "watertight", _get(surface, "watertight"), "yes", lambda v: bool(v)),
        ("surface", "self-intersections", _get(surface, "self_intersections"), "0", lambda v: v == 0),
        ("surface", "non-manifold edges", _get(surface, "nonmanifold_edges"), "0", lambda v: v == 0),
        ("surface", "smallest triangle angle (deg)", _get(surface, "min_angle_deg.min"),
         f">= {MIN_SURFACE_ANGLE_DEG:g}", lambda v: v >= MIN_SURFACE_ANGLE_DEG),
        ("mesh", "smallest dihedral angle, core (deg)", _get(mesh, "core.min_dihedral.min_deg"),
         f">= {CORE_MIN_DIHEDRAL:g}", lambda v: v >= CORE_MIN_DIHEDRAL),
        ("mesh", "largest dihedral angle, wall layers (deg)", _get(mesh, "layer.max_dihedral_deg"),
         f"<= {MAX_DIHEDRAL_LAYER_DEG:g}", lambda v: v <= MAX_DIHEDRAL_LAYER_DEG),
        ("mesh", "wall layers found under every wall node, fewest",
         _get(mesh, "boundary_layer.read_back_from_mesh.layers_found.min"), ">= 1", lambda v: v >= 1),
        ("mesh", "volume error against the surface", _get(mesh, "volume.relative_error"), "<= 0.001",
         lambda v: abs(v) <= 1e-3),
    ]
    checks = [Check(stage, quantity, value, criterion, bool(test(value)))
              for stage, quantity, value, criterion, test in rows if value is not None]
    for label, outlet in (_get(flow, "mass_balance.outlets") or {}).items():
        error = outlet.get("error_max")
        if error is not None:
            checks.append(Check("flow", f"outlet {label}: flow-split error, largest", error,
                                f"<= {MAX_SPLIT_ERROR:g}", error <= MAX_SPLIT_ERROR))
    fallback = _get(flow, "outlets.fallback")
    if fallback:  # the configured prescribed split blew up and the stage reran with RCR outlets
        checks.append(Check("flow", "outlet model as configured (no RCR fallback after a blow-up)",
                            f"rcr, since {fallback['from']} {fallback['reason']}", "as configured", False))
    periodic = flow.get("periodic") or {}
    if periodic.get("status") in ("periodic", "not periodic"):  # "not assessed": no tolerance or under two cycles
        checks.append(Check("flow", "TAWSS change of the last cycle from the previous (L2, relative)",
                            periodic["last_relative_change"], f"< {periodic['tolerance']:g}",
                            periodic["status"] == "periodic"))
    return checks


def stale_warnings(case_dir: Path, record: dict, geometry: dict, segmentation: dict, mesh_quality: dict,
                   flow: dict, surface=None, mesh=None) -> list[str]:
    """Results that no longer match the files they were computed from.

    Each stage's record holds a fingerprint of its input: the flow summary the node and tetrahedron
    counts of the mesh it ran on, the mesh record the volume of the surface it filled, ``geometry.json``
    the lumen volume of the segmentation and (once the surface stage has run on these centerlines) the
    caps.  ``case.json`` of ``carotid run`` adds the content hash of every output as it was written.

    Parameters
    ----------
    case_dir : Path
    record, geometry, segmentation, mesh_quality, flow : dict
        The case's records (empty when missing).
    surface, mesh : pyvista.PolyData, pyvista.UnstructuredGrid, optional
        ``surface.vtp`` and ``mesh.vtu`` as the report read them; None when missing or unreadable.

    Returns
    -------
    list of str
        One sentence per stale result; empty when everything is consistent.  A mesh or surface file that
        cannot be read is left out here: the report names it among the unreadable files.
    """
    import pyvista as pv

    from carotid.pipeline import file_hash

    warnings = []
    flow_mesh = flow.get("mesh", {})
    if mesh is not None and flow_mesh:
        tets = int(np.count_nonzero(np.asarray(mesh.celltypes) == pv.CellType.TETRA))
        if (flow_mesh.get("tetrahedra"), flow_mesh.get("nodes")) != (tets, mesh.n_points):
            warnings.append(f"The flow results were computed on a mesh of {flow_mesh.get('tetrahedra', 0):,} "
                            f"tetrahedra and {flow_mesh.get('nodes', 0):,} nodes; mesh.vtu now holds {tets:,} "
                            f"tetrahedra and {mesh.n_points:,} nodes. Flow, WSS maps and indices are stale: "
                            "rerun the simulate stage.")
    recorded_surface = mesh_quality.get("volume", {}).get("surface_mm3")
    if surface is not None and recorded_surface:
        volume = abs(surface.volume)
        if abs(volume - recorded_surface) > 1e-6 * recorded_surface:
            warnings.append(f"mesh.vtu was built from a surface of {recorded_surface:.1f} mm³; surface.vtp now "
                            f"encloses {volume:.1f} mm³. The mesh (and the flow) are stale: rerun the mesh stage.")
    lumen = geometry.get("lumen", {}).get("lumen_volume_mm3")
    segmented = segmentation.get("lumen_volume_mm3")
    if lumen is not None and segmented is not None and abs(lumen - segmented) > 1e-6 * segmented:
        warnings.append(f"The centerlines were computed from a lumen of {lumen:.1f} mm³; the segmentation now "
                        f"holds {segmented:.1f} mm³. Centerlines, stenosis grade and later stages are stale.")
    if geometry and (case_dir / "surface.vtp").exists() and "caps" not in geometry:
        warnings.append("surface.vtp was built on earlier centerlines (geometry.json records no caps): "
                        "the surface and later stages may be stale.")
    for stage, done in record.get("stages", {}).items():
        changed = [name for name, digest in done.get("outputs", {}).items()
                   if name not in AMENDED and (case_dir / name).exists() and file_hash(case_dir / name) != digest]
        if changed:
            warnings.append(f"{', '.join(changed)} changed after `carotid run` recorded the {stage} stage: "
                            "results of later stages may not match them.")
    return warnings
