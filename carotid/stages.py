"""The stages after segmentation as ``carotid run`` sees them: TOML-friendly parameters and runners.

Each ``*StageParameters`` dataclass is one section of the run configuration
(``carotid config --show``); each ``run_*`` function reads the stage's input
files from CASE_DIR, calls the stage's plain-function API and writes its
outputs.  Segmentation's own section lives beside it in
``carotid.segment.segmentation``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from carotid.errors import CarotidError, check_ranges


@dataclass
class CenterlineStageParameters:
    """The ``[centerlines]`` section.

    Attributes
    ----------
    prune : float
        Terminal branches shorter than this many radii of their parent vessel are spurs and removed.
    smoothing : float
        Gaussian smoothing of each axis along its arc length, mm (0: none).
    """

    prune: float = 2.0
    smoothing: float = 1.0

    RANGES = {"prune": (0.0, 20.0), "smoothing": (0.0, 20.0)}

    def validate(self) -> "CenterlineStageParameters":
        """Raise CarotidError for values outside their range."""
        check_ranges("centerlines", self, self.RANGES)
        return self


@dataclass
class SurfaceStageParameters:
    """The ``[surface]`` section.

    Attributes
    ----------
    target_edge_mm : float
        Target edge length of the remeshed surface, mm (used when edge_radius_ratio is 0).
    edge_radius_ratio : float
        Target edge length as this fraction of the local radius (0: use target_edge_mm).
    edge_min_mm, edge_max_mm : float
        Bounds of a radius-relative edge length, mm.
    inset_radii : float
        Caps are cut this many end radii inside each open end (the branch's median radius where the end's
        reads less).
    flow_extension_radii : float
        Length of the cylindrical flow extension at each cap, in radii (0: none).
    smoothing_iterations : int
        Taubin smoothing iterations (lambda/mu pairs).
    remesh_iterations : int
        Isotropic remeshing rounds.
    """

    target_edge_mm: float = 0.3
    edge_radius_ratio: float = 0.0
    edge_min_mm: float = 0.15
    edge_max_mm: float = 1.0
    inset_radii: float = 1.5
    flow_extension_radii: float = 0.0
    smoothing_iterations: int = 30
    remesh_iterations: int = 8

    RANGES = {"target_edge_mm": (0.02, 5.0), "edge_radius_ratio": (0.0, 2.0), "edge_min_mm": (0.02, 5.0),
              "edge_max_mm": (0.02, 5.0), "inset_radii": (0.0, 10.0), "flow_extension_radii": (0.0, 50.0),
              "smoothing_iterations": (0, 1000), "remesh_iterations": (0, 100)}

    def validate(self) -> "SurfaceStageParameters":
        """Raise CarotidError for values outside their range."""
        check_ranges("surface", self, self.RANGES)
        if self.edge_min_mm > self.edge_max_mm:
            raise CarotidError("bad surface parameter: edge_min_mm must not exceed edge_max_mm")
        return self


@dataclass
class MeshStageParameters:
    """The ``[mesh]`` section.

    Attributes
    ----------
    layers : int
        Prism sub-layers N at the wall (0: none).
    ratio : float
        Height ratio f between neighbouring sub-layers (thinnest at the wall).
    thickness_mm : float
        Total layer thickness, mm (0: use thickness_ratio).
    thickness_ratio : float
        Total layer thickness as a fraction of the local radius.
    size_mm : float
        Target core edge length, mm (0: the median wall edge).
    core : str
        Core mesher: "gmsh" (HXT) or "tetgen".
    lloyd_iterations : int
        3-D Lloyd smoothing iterations of the interior core nodes.
    """

    layers: int = 10
    ratio: float = 1.2
    thickness_mm: float = 0.0
    thickness_ratio: float = 0.3
    size_mm: float = 0.0
    core: str = "gmsh"
    lloyd_iterations: int = 5

    # A layer thicker than 0.8 of the radius leaves no core; a core element or a layer wider than a few mm is
    # wider than a neck artery.
    RANGES = {"layers": (0, 30), "ratio": (1.0, 3.0), "thickness_mm": (0.0, 5.0), "thickness_ratio": (0.01, 0.8),
              "size_mm": (0.0, 10.0), "lloyd_iterations": (0, 100)}

    def validate(self) -> "MeshStageParameters":
        """Raise CarotidError for values outside their range."""
        check_ranges("mesh", self, self.RANGES)
        if self.core not in ("gmsh", "tetgen"):
            raise CarotidError(f"bad mesh parameter: core must be 'gmsh' or 'tetgen', not {self.core!r}")
        return self


BLOW_UP_FALLBACKS = ("rcr", "none")
# Written in flow/ while the stage runs its RCR fallback: the section and mesh it runs for and why, so that an
# interrupted fallback resumes as a fallback instead of blowing up again under the prescribed split.
FALLBACK_FILE = "outlets_fallback.json"


@dataclass
class FlowStageParameters:
    """The ``[simulate]`` section (SI units).

    Attributes
    ----------
    cycles : float
        Cardiac cycles to run.
    dt : float
        Fixed time step, s (0: adaptive from the convective and diffusive limits).
    waveform : str
        CSV of the inlet flow (time s, flow mL/s); empty: the built-in common carotid waveform.
    split : list of float
        Fraction of the flow leaving each outlet (CellEntityIds 3, 4, ...); empty: Murray's law.
    outlets : str
        Outlet model: "murray" or "split" (a prescribed split), "resistance" or "rcr" (lumped outlets,
        calibrated for that split as the mean share unless ``resistance`` / ``rcr`` give their values).
    mean_pressure_mmhg : float
        Mean pressure the lumped outlets are calibrated for, mmHg.
    pulse_pressure_mmhg : float
        Pulse pressure the RCR outlets are calibrated for, mmHg.
    proximal_fraction : float
        Proximal share R_p / (R_p + R_d) of the calibrated RCR outlets.
    distal_pressure_mmhg : float
        Pressure downstream of the lumped outlets, mmHg.
    resistance : list of float
        Outlet resistances, Pa s/m^3, one per outlet (empty: calibrated).
    rcr : list of [R_p, C, R_d]
        RCR parameters per outlet, Pa s/m^3, m^3/Pa, Pa s/m^3 (empty: calibrated).
    backflow : float
        Coefficient of the directional backflow stabilisation at the outlets (0: none; 0.2 as SimVascular).
    turbulence : str
        "none" or "sa" (Spalart-Allmaras).
    viscous : str
        "explicit" (the paper's CBS: the step is bounded by the thinnest wall layer) or "implicit"
        (backward-Euler viscosity: the step is bounded by convection only).
    pressure : str
        Pressure solver: "auto" (sparse Cholesky up to 300k unknowns, AMG-CG above), "cholesky", "amg",
        "lu" or "jacobi".
    output_every : int
        Steps between outputs of the time series.
    checkpoint_every : int
        Steps between checkpoints.
    flow_ml_s : float
        Constant inflow, mL/s, for a steady case (0: the waveform); each "cycle" is then 1 s.
    rho : float
        Blood density, kg/m^3.
    mu : float
        Blood dynamic viscosity, Pa s (the Newtonian one).
    rheology : str
        "newtonian" (``mu``), "carreau" (Carreau-Yasuda with the blood parameters of Cho & Kensey 1991) or
        "casson" (yield stress 0.005 Pa, high-shear viscosity 0.0035 Pa s).
    force : bool
        Run even when the estimated step count or output size exceeds the sane bounds.
    periodic_tol : float
        Stop at the first whole cycle whose TAWSS changed by less than this area-weighted L2 relative change
        from the previous cycle's, ``cycles`` being the maximum (0: run exactly ``cycles``).
    probes : list of [x, y, z]
        Probe points, mm LPS, named ``probe1``, ``probe2``, ...: velocity and pressure series in
        ``flow/probes.csv`` and ``flow/probes.xdmf`` (with the Doppler gates and the centreline probes).
    probes_file : str
        CSV of further probe points, rows ``x, y, z[, name]`` in mm LPS (empty: none).
    doppler_cca_psv, doppler_cca_edv : float
        Measured CCA peak systolic and end-diastolic velocity, cm/s: the inflow is scaled and shaped so that the
        inlet's Womersley centreline velocity matches them (0 PSV: the waveform as it is).
    blow_up_fallback : str
        What the stage does when the flow blows up under a prescribed split (``outlets`` "murray" or "split"):
        "rcr" reruns it from t = 0 with RCR outlets calibrated for the same split as the mean share
        (:func:`run_simulate`), "none" stops the case.
    """

    cycles: float = 3.0
    dt: float = 0.0
    waveform: str = ""
    split: list = field(default_factory=list)
    outlets: str = "murray"
    mean_pressure_mmhg: float = 93.0
    pulse_pressure_mmhg: float = 40.0
    proximal_fraction: float = 0.09
    distal_pressure_mmhg: float = 0.0
    resistance: list = field(default_factory=list)
    rcr: list = field(default_factory=list)
    backflow: float = 0.2
    turbulence: str = "none"
    viscous: str = "implicit"
    pressure: str = "auto"
    output_every: int = 50
    checkpoint_every: int = 500
    flow_ml_s: float = 0.0
    rho: float = 1060.0
    mu: float = 3.5e-3
    rheology: str = "newtonian"
    force: bool = False
    periodic_tol: float = 0.0
    probes: list = field(default_factory=list)
    probes_file: str = ""
    doppler_cca_psv: float = 0.0
    doppler_cca_edv: float = 0.0
    blow_up_fallback: str = "rcr"

    # Blood and the analogue fluids of flow phantoms (water to glycerol mixtures).
    RANGES = {"cycles": (1e-3, 100.0), "dt": (0.0, 0.01), "output_every": (1, 10**7), "checkpoint_every": (1, 10**7),
              "flow_ml_s": (0.0, 1000.0), "rho": (500.0, 2000.0), "mu": (1e-4, 0.1), "periodic_tol": (0.0, 0.5),
              "mean_pressure_mmhg": (20.0, 200.0), "pulse_pressure_mmhg": (1.0, 150.0),
              "proximal_fraction": (0.01, 0.5), "distal_pressure_mmhg": (0.0, 50.0), "backflow": (0.0, 1.0),
              "doppler_cca_psv": (0.0, 1000.0), "doppler_cca_edv": (0.0, 1000.0)}

    def flow_parameters(self):
        """The solver's ``FlowParameters``, validated."""
        from carotid.flow.simulate import FlowParameters

        from carotid.flow.waveform import ML, check_inflow, constant_waveform, read_waveform_csv

        if self.waveform and self.flow_ml_s:
            raise CarotidError("bad simulate parameter: give a waveform file or a constant flow_ml_s, not both")
        from carotid.flow.probes import read_probe_csv

        if self.flow_ml_s:
            check_inflow(1.0, self.flow_ml_s, "bad simulate parameter: flow_ml_s")

        waveform = (read_waveform_csv(self.waveform) if self.waveform else
                    constant_waveform(self.flow_ml_s * ML) if self.flow_ml_s else None)
        probes = [(f"probe{k + 1}", tuple(float(v) for v in xyz)) for k, xyz in enumerate(self.probes)]
        if self.probes_file:
            probes += read_probe_csv(self.probes_file, start=len(probes) + 1)
        stage_only = ("flow_ml_s", "probes_file", "doppler_cca_psv", "doppler_cca_edv", "blow_up_fallback")
        fields = {k: v for k, v in asdict(self).items() if k not in stage_only}
        fields.update(probes=tuple(probes),
                      doppler_cca=(self.doppler_cca_psv, self.doppler_cca_edv) if self.doppler_cca_psv else None)
        fields.update(dt=self.dt or None, waveform=waveform, split=tuple(self.split) or None,
                      resistance=tuple(self.resistance) or None,
                      rcr=tuple(tuple(float(v) for v in row) for row in self.rcr) or None)
        return FlowParameters(**fields).validate()

    def validate(self) -> "FlowStageParameters":
        """Raise CarotidError for values outside their range, and for what the solver's parameters refuse, so that
        ``carotid run`` stops before its first stage, not at the flow's."""
        check_ranges("simulate", self, self.RANGES)
        if self.blow_up_fallback not in BLOW_UP_FALLBACKS:
            raise CarotidError(f"bad simulate parameter: blow_up_fallback must be one of "
                               f"{', '.join(BLOW_UP_FALLBACKS)} (got {self.blow_up_fallback!r})")
        if self.split and self.outlets == "murray":
            raise CarotidError("bad simulate parameter: split (--split) needs outlets (--outlets) split, resistance "
                               "or rcr; murray shares the flow by Murray's law instead")
        if bool(self.doppler_cca_psv) != bool(self.doppler_cca_edv):
            given, missing = (("doppler_cca_psv", "doppler_cca_edv") if self.doppler_cca_psv else
                              ("doppler_cca_edv", "doppler_cca_psv"))
            raise CarotidError(f"bad simulate parameter: {given} without {missing}: give both measured CCA "
                               "velocities (cm/s) or neither (0 means not measured)")
        if self.split and (any(s <= 0 for s in self.split) or abs(sum(self.split) - 1) > 1e-6):
            raise CarotidError(f"bad simulate parameter: split ratios {self.split} must be positive and sum to 1")
        for xyz in self.probes:
            if not (isinstance(xyz, (list, tuple)) and len(xyz) == 3 and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in xyz)):
                raise CarotidError(f"bad simulate parameter: probes: {xyz!r} is not a point [x, y, z] in mm")
        if self.doppler_cca_psv or self.doppler_cca_edv:
            from carotid.flow.duplex import check_doppler

            try:
                check_doppler(self.doppler_cca_psv, self.doppler_cca_edv)
            except CarotidError as exc:
                raise CarotidError(f"bad simulate parameter: doppler_cca_psv, doppler_cca_edv: {exc}") from None
        self.flow_parameters()  # the solver's own checks (model names, outlet values, the waveform and probe files)
        return self


def run_centerlines(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``centerlines`` stage: ``segmentation/`` -> ``centerlines.vtp``, ``geometry.json``."""
    from carotid.centerline.command import run_centerlines as compute

    p = CenterlineStageParameters(**params).validate()
    compute(case_dir, prune=p.prune, smoothing=p.smoothing)


def run_surface(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``surface`` stage: level set and centerlines -> ``surface.vtp``, ``surface_quality.json``."""
    from carotid.centerline import read_centerlines
    from carotid.io import read_image
    from carotid.surface.pipeline import build_surface, write_surface

    p = SurfaceStageParameters(**params).validate()
    levelset = read_image(case_dir / "segmentation" / "levelset.nii.gz")
    surface, caps, quality = build_surface(
        levelset, read_centerlines(case_dir / "centerlines.vtp"), target_edge_mm=p.target_edge_mm,
        edge_radius_ratio=p.edge_radius_ratio or None, edge_bounds_mm=(p.edge_min_mm, p.edge_max_mm),
        inset_radii=p.inset_radii, flow_extension_radii=p.flow_extension_radii,
        smoothing_iterations=p.smoothing_iterations, remesh_iterations=p.remesh_iterations)
    write_surface(surface, case_dir, quality=quality, caps=caps)


def run_mesh(case_dir: Path, params: dict, inputs: list[Path]) -> None:
    """The ``mesh`` stage: ``surface.vtp`` -> ``mesh.vtu`` (+ .msh, XDMF), ``mesh_quality.json``."""
    from carotid.io.vtkfile import read_vtk
    from carotid.mesh.io import write_mesh
    from carotid.mesh.mesher import build_mesh

    p = MeshStageParameters(**params).validate()
    surface = read_vtk(case_dir / "surface.vtp", "surface", remedy="rerun the surface stage")
    mesh, quality = build_mesh(surface, layers=p.layers, ratio=p.ratio,
                               thickness=p.thickness_mm or None, thickness_ratio=p.thickness_ratio,
                               size=p.size_mm or None, core=p.core, lloyd_iterations=p.lloyd_iterations)
    write_mesh(mesh, case_dir, quality)


def run_simulate(case_dir: Path, params: dict, inputs: list[Path], progress=None) -> None:
    """The ``simulate`` stage: ``mesh.vtu`` -> ``flow/``.

    The run continues from ``flow/checkpoint.npz`` when that was made with the same mesh and solution
    settings (:meth:`carotid.flow.simulate.FlowParameters.fingerprint`), else it starts at t = 0.

    A prescribed split (Murray's law or ``split``) forces each outlet's share through the lumen at whatever
    pressure it takes, and behind a tight stenosis the run can blow up however small the step.  With
    ``blow_up_fallback = "rcr"`` the stage then warns and reruns from t = 0 with RCR outlets calibrated for
    the same split as the mean share, as a SimVascular user would by hand: the flow redistributes under a
    physiological outlet pressure instead.  ``flow/summary.json`` records it under ``outlets.fallback`` (the
    configured model and where and when it blew up), and ``flow/outlets_fallback.json``, kept until the
    fallback has finished, lets an interrupted one resume as a fallback for the same section and mesh.

    Parameters
    ----------
    case_dir : Path
    params : dict
        The ``[simulate]`` section.
    inputs : list of Path
        ``mesh.vtu``.
    progress : carotid.pipeline.StageProgress, optional
        Receives after every step the simulated time as a fraction of the run's end time, with the cycle,
        the time (s), the CFL number and the mass imbalance (%), and the solver's estimate of the run as a line.
    """
    import json
    import warnings
    from dataclasses import replace

    from carotid.errors import CarotidWarning
    from carotid.flow.simulate import FlowBlowUp, simulate
    from carotid.io import read_json, write_json
    from carotid.pipeline import file_hash

    stage = FlowStageParameters(**params).validate()
    flow = stage.flow_parameters()
    marker = case_dir / "flow" / FALLBACK_FILE

    def report(info: dict) -> None:
        progress(info["time"] / info["end"], 1.0, cycle=f"{info['cycle']:.3f}", t=f"{info['time']:.4f}s",
                 CFL=f"{info['cfl']:.2f}", imbalance=f"{100 * info['imbalance']:+.3f}%")

    def run(parameters) -> dict:
        return simulate(inputs[0], case_dir, parameters, resume="auto", progress=None if progress is None else report,
                        log=None if progress is None else progress.write)

    key = {"params": json.loads(json.dumps(params)), "mesh": file_hash(inputs[0])}
    record = read_json(marker)  # a fallback started for this section and mesh resumes as one
    fallback = record.get("fallback") if isinstance(record, dict) and record.get("key") == key else None
    marker.unlink(missing_ok=True)
    if fallback is None:
        try:
            run(flow)
            return
        except FlowBlowUp as exc:
            if stage.blow_up_fallback != "rcr" or flow.outlets not in ("murray", "split"):
                raise
            fallback = {"from": flow.outlets, "reason": f"blew up at {exc.detail}"}
            warnings.warn(f"the flow blew up under the prescribed split ({flow.outlets}) at t = {exc.time_s:.4f} s: "
                          "rerunning from t = 0 with RCR outlets calibrated for the same split", CarotidWarning,
                          stacklevel=2)
    marker.parent.mkdir(parents=True, exist_ok=True)
    write_json({"key": key, "fallback": fallback}, marker)
    try:
        summary = run(replace(flow, outlets="rcr", rcr=None))
    except FlowBlowUp as exc:
        raise FlowBlowUp(f"the flow {fallback['reason']} under the prescribed split ({fallback['from']}) and again "
                         f"under the RCR outlets of the fallback, at {exc.detail}: try a smaller --dt or a finer mesh",
                         exc.time_s, exc.detail) from None
    summary["outlets"]["fallback"] = fallback
    write_json(summary, case_dir / "flow" / "summary.json")
    marker.unlink()
