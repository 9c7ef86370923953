"""``carotid simulate`` and ``carotid verify``: argparse registration and handlers."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from carotid.errors import CarotidError


def _split(values: list[str] | None) -> tuple | None:
    """``["0.65:0.35"]`` or ``["0.65", "0.35"]`` -> (0.65, 0.35)."""
    if not values:
        return None
    try:
        return tuple(float(v) for item in values for v in item.split(":") if v)
    except ValueError as exc:
        raise CarotidError(f"--split takes numbers like 0.65:0.35 ({exc})") from exc


def cmd_simulate(args) -> int:
    from carotid.flow.mesh import FlowMesh
    from carotid.flow.simulate import simulate
    from carotid.pipeline import StageProgress
    from carotid.stages import FlowStageParameters

    case = Path(args.case_dir)
    if args.flow is not None and not args.flow > 0:
        raise CarotidError(f"--flow {args.flow:g}: a steady inflow must be positive (mL/s); leave --flow out for "
                           "the built-in pulsatile waveform")
    if args.doppler_cca:
        from carotid.flow.duplex import check_doppler

        check_doppler(*args.doppler_cca)
    cycles = args.cycles if args.cycles is not None else 1.0 if args.convergence else 3.0
    stage = FlowStageParameters(cycles=cycles, dt=args.dt or 0.0, waveform=str(args.waveform or ""),
                                split=list(_split(args.split) or []), turbulence=args.turbulence,
                                outlets=args.outlets or ("split" if args.split else "murray"),
                                mean_pressure_mmhg=args.mean_pressure, pulse_pressure_mmhg=args.pulse_pressure,
                                viscous=args.viscous, pressure=args.pressure, output_every=args.output_every,
                                checkpoint_every=args.checkpoint_every, force=args.force,
                                flow_ml_s=args.flow or 0.0, rho=args.density, mu=args.viscosity,
                                rheology=args.rheology,
                                periodic_tol=args.periodic_tol, probes=[list(xyz) for xyz in args.probe or []],
                                probes_file=str(args.probes or ""),
                                doppler_cca_psv=args.doppler_cca[0] if args.doppler_cca else 0.0,
                                doppler_cca_edv=args.doppler_cca[1] if args.doppler_cca else 0.0)
    params = stage.validate().flow_parameters()
    mesh = FlowMesh.from_vtu(case / "mesh.vtu")
    if args.convergence:
        return _convergence(case, params, args)
    with StageProgress("simulate", sys.stderr) as report:
        def progress(info: dict) -> None:
            report(info["time"], info["end"], step=info["step"], cycle=f"{info['cycle']:.3f}",
                   CFL=f"{info['cfl']:.2f}", imbalance=f"{100 * info['imbalance']:+.3f}%")

        summary = simulate(mesh, case, params, resume=args.resume, progress=progress, log=report.write)
    mb = summary["mass_balance"]
    print(f"flow written to {case / 'flow'}: {summary['steps']} steps, {summary['seconds']:.0f} s, "
          f"max CFL {summary['cfl_max']:.2f}, max mass imbalance (P1 flux) {100 * mb['imbalance_p1_max_abs']:.3f}%, "
          f"pressure drop {summary['pressure_drop_pa']['cycle_mean']:.1f} Pa")
    changes = [f"{e['relative_change']:.2%}" for e in summary["periodicity"] if e["relative_change"] is not None]
    if changes:
        periodic = summary["periodic"]
        print(f"TAWSS change from the previous cycle: {', '.join(changes)} ({periodic['status']}"
              + (f", tolerance {periodic['tolerance']:.2%})" if periodic["tolerance"] else ")"))
    duplex = summary["duplex"]
    if "gates" in duplex:
        gates = duplex["gates"]
        print(f"virtual duplex: ICA PSV {gates['ICA']['psv_cm_s']:.0f} cm/s, EDV {gates['ICA']['edv_cm_s']:.0f} cm/s; "
              f"CCA PSV {gates['CCA']['psv_cm_s']:.0f} cm/s; ICA/CCA {duplex['psv_ratio']:.2f}: SRU "
              f"{duplex['sru']['grade']} (NASCET {100 * duplex['nascet']:.0f} % from the geometry); pressure drop "
              f"{duplex['pressure']['drop_mean_mmhg']:.2f} mmHg mean")
    if summary["probes"]:
        print(f"probes: {len(summary['probes']['points'])} series in {case / 'flow' / 'probes.csv'}")
    if summary["partial"]:
        print(f"warning: {summary['indices_note']}", file=sys.stderr)
    return 0


def _convergence(case: Path, params, args) -> int:
    """``--convergence``: the study of :func:`carotid.flow.convergence.run_convergence`, printed."""
    from carotid.flow.convergence import run_convergence
    from carotid.pipeline import StageProgress

    with StageProgress("convergence", sys.stderr) as report:
        def progress(info: dict) -> None:
            report(info["fraction"], 1.0, **{name: f"{100 * f:.0f}%" for name, f in info["runs"].items()})

        result = run_convergence(case, params, args.refinement, time_levels=args.time_levels, workers=args.workers,
                                 case_mesh=args.case_mesh, progress=progress, log=report.write)
    sizes = ", ".join(f"{level['h_mm']:.3f}" for level in result["levels"])
    finest = "the case mesh" if args.case_mesh else f"the case mesh coarsened by {args.refinement:g}"
    print(f"convergence study written to {case / 'flow' / 'convergence.json'} in {result['seconds'] / 60:.1f} min; "
          f"mean TAWSS per branch on the meshes of h = {sizes} mm (the first is {finest}):")
    _print_rows(result["branches"]["TAWSS"])
    if result["time"] is not None:
        print("time step on the coarsest mesh (its step, then 1/2 and 1/4 of it): mean TAWSS per branch")
        for name, row in result["time"]["branches"]["TAWSS"].items():
            print(f"  {name}: {row['phi_fine_to_coarse'][2]:.4g} Pa, {_percent(row['default_change'])} change at half "
                  f"the step, {_percent(row['default_e_ext'])} from the extrapolation to a zero step, "
                  f"p = {row['p'] if row['p'] is None else round(row['p'], 2)} ({row['status']})")
    return 0


def _print_rows(rows: dict) -> None:
    """One line per branch of a :func:`carotid.flow.convergence.run_convergence` table: the finest value, the
    extrapolated one, the GCI and the apparent order."""
    for name, row in rows.items():
        ext = "n/a" if row["phi_ext21"] is None else f"{row['phi_ext21']:.4g}"
        print(f"  {name}: {row['phi_fine_to_coarse'][0]:.4g} Pa, extrapolated {ext} Pa, "
              f"GCI {_percent(row['gci_fine21'])}, p = {row['p'] if row['p'] is None else round(row['p'], 2)} "
              f"({row['status']})")


def _percent(fraction: float | None) -> str:
    """A fraction as a percentage with two decimals, "n/a" for None."""
    return "n/a" if fraction is None else f"{100 * fraction:.2f}%"


def cmd_verify(args) -> int:
    from carotid.flow.verify import run_verification

    results = run_verification(quick=args.quick, out=sys.stdout)
    return 0 if all(r["passed"] for r in results) else 1


def register(subparsers) -> None:
    """Add ``simulate`` and ``verify`` to an argparse subparsers object."""
    p = subparsers.add_parser("simulate", help="CBS blood-flow simulation on CASE_DIR/mesh.vtu")
    p.add_argument("case_dir", type=Path, metavar="CASE_DIR")
    p.add_argument("--cycles", type=float, help="cardiac cycles (default 3; 1 per level with --convergence)")
    p.add_argument("--dt", type=float, help="fixed time step in s (default: adaptive)")
    p.add_argument("--periodic-tol", type=float, default=0.0, metavar="TOL",
                   help="run whole cycles until the TAWSS changes by less than TOL (area-weighted L2, relative) "
                        "from the previous cycle, --cycles being the maximum (default 0: exactly --cycles)")
    inflow = p.add_mutually_exclusive_group()
    inflow.add_argument("--waveform", type=Path, metavar="FILE", help="inlet flow CSV: time s, flow mL/s")
    inflow.add_argument("--flow", type=float, metavar="ML_S",
                        help="constant inflow in mL/s, for a steady case (each cycle is then 1 s)")
    p.add_argument("--doppler-cca", nargs=2, type=float, metavar=("PSV", "EDV"),
                   help="measured CCA peak systolic and end-diastolic velocity in cm/s: the inflow waveform is scaled "
                        "and shaped (a q + b) so that the inlet's Womersley centreline velocity matches them")
    p.add_argument("--probe", nargs=3, type=float, action="append", metavar=("X", "Y", "Z"),
                   help="probe point in world mm (LPS), repeatable: velocity and pressure series in flow/probes.csv "
                        "and flow/probes.xdmf")
    p.add_argument("--probes", type=Path, metavar="FILE", help="CSV of probe points: x, y, z[, name] in mm (LPS)")
    p.add_argument("--density", type=float, default=1060.0, metavar="KG_M3", help="fluid density (default 1060)")
    p.add_argument("--viscosity", type=float, default=3.5e-3, metavar="PA_S",
                   help="dynamic viscosity (default 3.5e-3)")
    p.add_argument("--rheology", choices=("newtonian", "carreau", "casson"), default="newtonian",
                   help="blood viscosity law: Newtonian (--viscosity), Carreau-Yasuda or Casson with published "
                        "blood parameters")
    p.add_argument("--split", nargs="+", metavar="RATIO",
                   help="outflow fraction per outlet in label order, e.g. 0.65:0.35 (default: Murray's law)")
    p.add_argument("--outlets", choices=("murray", "split", "resistance", "rcr"),
                   help="outlet model: a prescribed split (Murray's law by default, or --split), or resistance / "
                        "three-element Windkessel (RCR) outlets calibrated for that split as the mean share, the "
                        "mean pressure and (RCR) the pulse pressure")
    p.add_argument("--mean-pressure", type=float, default=93.0, metavar="MMHG",
                   help="mean pressure the lumped outlets are calibrated for (default 93 mmHg)")
    p.add_argument("--pulse-pressure", type=float, default=40.0, metavar="MMHG",
                   help="pulse pressure the RCR outlets are calibrated for (default 40 mmHg)")
    p.add_argument("--turbulence", choices=("none", "sa"), default="none", help="Spalart-Allmaras or none")
    p.add_argument("--viscous", choices=("explicit", "implicit"), default="implicit",
                   help="viscous term: explicit (the paper's CBS) or implicit (larger steps on thin wall layers)")
    p.add_argument("--pressure", default="auto", metavar="SOLVER",
                   help="pressure solver: auto (sparse Cholesky up to 300k unknowns, AMG-CG above), cholesky, amg, "
                        "lu or jacobi")
    p.add_argument("--output-every", type=int, default=50, metavar="K", help="steps between outputs (50)")
    p.add_argument("--checkpoint-every", type=int, default=500, metavar="M", help="steps between checkpoints")
    p.add_argument("--resume", action="store_true", help="continue from CASE_DIR/flow/checkpoint.npz")
    p.add_argument("--convergence", action="store_true",
                   help="solution verification: run the case mesh and two coarser meshes rebuilt from surface.vtp "
                        "(wall, core and layers coarsened), and the coarsest again at 1/2 and 1/4 of its time step; "
                        "write the GCI of TAWSS/OSI/RRT per branch and per node to flow/convergence.json/.vtp")
    p.add_argument("--refinement", type=float, default=1.5, metavar="R",
                   help="edge-length ratio between consecutive --convergence levels (default 1.5)")
    p.add_argument("--time-levels", action=argparse.BooleanOptionalAction, default=True,
                   help="with --convergence: the two time-step levels on the coarsest mesh (default: on)")
    p.add_argument("--case-mesh", action=argparse.BooleanOptionalAction, default=True,
                   help="with --convergence: the finest level is the case mesh (default), so that the GCI is the "
                        "case's; --no-case-mesh: the three levels are the case mesh coarsened by R, R^2 and R^3 "
                        "(a quarter of the cost or less; the GCI is then that of a coarser mesh than the case's)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="with --convergence: processes running the levels side by side, one core each (default 2)")
    p.add_argument("--force", action="store_true",
                   help="run even when the estimated steps (over 5 million) or output exceed the sane bounds")
    p.set_defaults(func=cmd_simulate)

    p = subparsers.add_parser("verify", help="run the analytic flow verification cases (Poiseuille, Womersley, "
                                             "mass split) and print pass/fail")
    p.add_argument("--quick", action="store_true", help="coarse meshes and short runs (about a minute)")
    p.set_defaults(func=cmd_verify)


def build_parser() -> argparse.ArgumentParser:
    """A stand-alone parser with only these subcommands (tests)."""
    parser = argparse.ArgumentParser(prog="carotid")
    register(parser.add_subparsers(dest="command", required=True))
    return parser
