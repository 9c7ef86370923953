"""The ``carotid`` command line: one subcommand per pipeline stage.

Bad input ends with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from carotid import __version__
from carotid.errors import CarotidError, CarotidWarning

# Stage packages that register their own subcommands (``register(subparsers)``), imported lazily.
STAGE_COMMANDS = ("carotid.centerline.command", "carotid.surface.command", "carotid.mesh.command",
                  "carotid.flow.command")


def _progress_bar(label: str):
    """The progress report on stderr (:class:`carotid.pipeline.StageProgress`: a bar on a terminal, a line every
    few seconds elsewhere) and its level-set callback."""
    from carotid.pipeline import StageProgress

    report = StageProgress(label, sys.stderr)

    def update(iterations: int, changed: int, front: int) -> None:
        report(iterations, None, iterations=iterations, front=front, changed=changed)

    return report, update


def _segment_parameters(args):
    from carotid.segment import SegmentParameters

    fields = {
        "alpha": args.alpha, "kernel_radius_mm": args.kernel_radius, "sigma_mm": args.sigma,
        "refine_radius_mm": args.refine_radius, "denoise_iterations": args.denoise,
        "seed_radius_mm": args.seed_radius, "max_iterations": args.max_iterations,
        "chamber_ratio": args.chamber_ratio, "companion_depth": args.companion_depth, "handle_mm": args.handles,
        "join_contrast": args.join_contrast,
        "wall_trunk_mm": args.wall_trunk, "slice_thickness_mm": args.slice_thickness,
        "measure_slice_blur": args.measure_slice_blur,
    }
    if args.hu_window:
        fields["window"] = list(args.hu_window)
    if args.wall or args.wall_morphology or args.wall_trunk:
        fields["wall"] = True
    if args.wall_morphology:
        fields["wall_close_mm"], fields["wall_open_mm"] = args.wall_morphology
    return SegmentParameters(**{k: v for k, v in fields.items() if v is not None}).validate()


def cmd_phantom(args) -> int:
    from carotid.phantom import make_phantom, sample_family, write_phantom

    kwargs = sample_family(args.seed, modality=args.modality) if args.family else {}
    explicit = {
        "stenosis": args.stenosis, "nascet": args.nascet, "noise": args.noise, "seed": args.seed,
        "spacing": args.spacing, "extent": args.extent, "vein_gap_mm": args.vein_gap,
        "venous_fraction": args.venous_fraction, "calcium_hu": args.calcium_hu, "blur_sigma_mm": args.blur_sigma,
        "arterial_hu": args.arterial_hu, "bolus_fade": args.bolus_fade, "ica_shape": args.ica_shape,
        "modality": args.modality, "bias": args.bias, "noise_seed": args.noise_seed,
    }
    explicit = {k: v for k, v in explicit.items() if v is not None}
    if "nascet" in explicit:
        kwargs.pop("stenosis", None)
    kwargs.update(explicit)
    for key in ("spacing", "extent"):
        if key in kwargs:
            kwargs[key] = tuple(kwargs[key])
    phantom = make_phantom(**kwargs)
    out = write_phantom(phantom, args.out_dir)
    info = phantom.info
    sten = info["stenosis"]
    vein = info["vein"]
    print(f"phantom written to {out} ({info['modality'].upper()}, {info['model']} model; ICA stenosis: "
          f"area stenosis {100 * sten['area_reduction']:.0f}%, NASCET {100 * sten['nascet']:.0f}% (diameter); "
          f"{info['ica_shape']['shape']} ICA; vein gap {vein['min_gap_to_lumen_mm']:.2f} mm; "
          f"CCA seed {np.round(info['seeds_mm']['CCA'], 1).tolist()} mm)")
    return 0


def run_segmentation(image_path, case_dir, seeds=None, init_mask_path=None, params=None, stops=None):
    """Read an image, segment it with a progress bar and write ``CASE_DIR/segmentation``.

    Returns
    -------
    (Segmentation, Path)
    """
    from carotid.io import read_image
    from carotid.segment import segment, write_segmentation

    volume = read_image(image_path)
    init_mask = None
    if init_mask_path is not None:
        mask = read_image(init_mask_path, dtype=None)
        if not mask.same_grid(volume):
            raise CarotidError(f"{init_mask_path}: the initial region is not on the image's grid ({mask.grid()}; "
                               f"the image: {volume.grid()})")
        init_mask = mask.array > 0
    bar, update = _progress_bar("segment")
    try:
        result = segment(volume, seeds_xyz=seeds, init_mask=init_mask, params=params, progress=update,
                         stops_xyz=stops)
    finally:
        bar.close()
    return result, write_segmentation(result, case_dir, image_path)


def cmd_segment(args) -> int:
    result, out = run_segmentation(args.image, args.output, seeds=args.seed, init_mask_path=args.init_mask,
                                   params=_segment_parameters(args), stops=args.stop)
    rep = result.report
    state = "converged" if rep["converged"] else "NOT converged (raise --max-iterations)"
    wall = "" if rep["wall"] is None else f"whole vessel {rep['wall']['volume_mm3']:.0f} mm^3, "
    print(f"segmentation written to {out}: lumen {rep['lumen_volume_mm3']:.0f} mm^3, {wall}"
          f"{sum(rep['iterations'])} iterations, {state}, {rep['seconds']['total_s']:.1f} s")
    quality = rep["intensity"]
    if quality.get("contrast_to_noise") is None:
        warnings.warn("the lumen's contrast-to-noise ratio could not be measured (its core, two blur widths inside "
                      "the wall, holds under 100 voxels): the region segmented may not be a vessel's lumen; check the "
                      "seeds or the initial region", CarotidWarning)
    elif quality["contrast_to_noise"] < quality["contrast_to_noise_validated"]:
        warnings.warn(f"the lumen's contrast-to-noise ratio is {quality['contrast_to_noise']:.1f} (contrast "
                      f"{quality['contrast']:.4g}, noise {quality['noise']:.3g}), below "
                      f"{quality['contrast_to_noise_validated']:g}, the lowest the segmentation's accuracy was "
                      "measured at: the wall may follow the noise, and a stenosis grade tight or loose", CarotidWarning)
    if rep["topology"]["handles"]:
        warnings.warn(f"the lumen has {rep['topology']['handles']} handle(s), where a vessel tree has none: vessels "
                      "bridged where the image does not resolve the gap between them, or tunnels through the lumen; "
                      "check the centerlines and the grade", CarotidWarning)
    for change in rep["handles_removed"]:
        what = "cut a bridge" if change["kind"] == "cut" else "filled a tunnel"
        print(f"removed {change['handles_removed']} handle(s) of the lumen: {what} up to "
              f"{2 * change['scale_mm']:.2f} mm wide, {change['voxels']} voxels at {change['centre_mm']} mm "
              "(--handles 0 keeps them)")
    for found in rep["chambers"] or []:
        ratio = rep["parameters"]["chamber_ratio"]
        if found["cores"]:
            print(f"kept out of the lumen: {found['cores']} chamber(s) wider than {ratio:g} x the vessel's "
                  f"{found['vessel_radius_mm']:.1f} mm radius (--chamber-ratio 0 keeps them)")
        if found["companions"]:
            print(f"kept out of the lumen: {found['companions']} bright vessel(s) running beside the seeded one "
                  "behind a thin gap (--companion-depth 0 keeps them)")
        print(f"  {found['excluded_mm3']:.0f} mm^3 kept out, centred at {found['centres_mm']} mm")
    return 0


# Coarse settings of `carotid demo`: a 0.8 mm surface, 2 wall layers, one cardiac cycle (the WSS indices
# are cycle averages).
DEMO_CONFIG = {
    "surface": {"target_edge_mm": 0.8},
    "mesh": {"layers": 2, "thickness_ratio": 0.15},
    "simulate": {"cycles": 1.0, "output_every": 50, "checkpoint_every": 500},
}


def cmd_demo(args) -> int:
    from carotid.config import Config
    from carotid.io import read_image
    from carotid.phantom import make_phantom, write_phantom
    from carotid.pipeline import run
    from carotid.segment.metrics import dice

    out = Path(args.output)
    print(f"1. phantom: a stenosed carotid bifurcation CTA with vein, bone and calcium -> {out / 'phantom'}")
    write_phantom(make_phantom(stenosis=0.7, noise=20.0, seed=0), out / "phantom")
    print(f"2. carotid run on it (automatic initialisation, coarse settings) -> {out / 'case'}")
    run(out / "phantom" / "image.nii.gz", out / "case", Config(DEMO_CONFIG), log=lambda line: print(f"   {line}"))
    case = out / "case"
    truth = read_image(out / "phantom" / "truth_mask.nii.gz", dtype=np.uint8).array > 0
    mask = read_image(case / "segmentation" / "mask.nii.gz", dtype=np.uint8).array > 0
    report = json.loads((case / "segmentation" / "report.json").read_text(encoding="utf-8"))
    print(f"   segmentation: lumen {report['lumen_volume_mm3']:.0f} mm^3, "
          f"Dice against the truth {dice(mask, truth):.3f}, {report['seconds']['total_s']:.1f} s")
    print(f"results are in {out.resolve()}; open {(case / 'report.html').resolve()}")
    return 0


def _config(args):
    from carotid.config import Config

    return Config.from_toml(args.config) if args.config else Config()


def cmd_run(args) -> int:
    from carotid.pipeline import run

    record = run(args.image, args.output, _config(args))
    total = sum(stage["seconds"] for stage in record["stages"].values())
    print(f"case written to {args.output} (case.json: {len(record['stages'])} stages finished, {total:.1f} s of work)")
    return 0


def cmd_batch(args) -> int:
    from carotid.batch import run_batch

    rows = run_batch(args.manifest, args.output, scheduler=args.scheduler, workers=args.workers,
                     retries=args.retries, config=args.config)
    failed = [row for row in rows if row["status"] != "ok"]
    for row in rows:
        print(f"{row['case_id']}: {row['status']}" + (f" at {row['failed_stage']}: {row['reason']}"
                                                       if row["status"] != "ok" else ""))
    print(f"{len(rows) - len(failed)} of {len(rows)} cases finished; cohort.csv in {args.output}")
    if failed:
        print(f"carotid: {len(failed)} of {len(rows)} cases failed (reasons in cohort.csv)", file=sys.stderr)
        return 3
    return 0


# Any of these makes a folder a case the report can describe.
REPORTED_OUTPUTS = ("segmentation", "centerlines.vtp", "surface.vtp", "mesh.vtu", "flow/summary.json")


def cmd_report(args) -> int:
    from carotid.report import build_report

    case = Path(args.case_dir)
    if not any((case / name).exists() for name in REPORTED_OUTPUTS):
        raise CarotidError(f"{case}: no stage output in this folder ({', '.join(REPORTED_OUTPUTS)}): "
                           "nothing to report")
    print(f"report written to {build_report(args.case_dir)}")
    return 0


def cmd_config(args) -> int:
    print(_config(args).to_toml(), end="")
    return 0


def _add_segment_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", nargs=3, type=float, action="append", metavar=("X", "Y", "Z"),
                   help="seed point in world mm (LPS), repeatable (one per branch is safest); none: automatic "
                        "initialisation")
    p.add_argument("--stop", nargs=3, type=float, action="append", metavar=("X", "Y", "Z"),
                   help="stop point in world mm (LPS), repeatable: the bright structure around it (a vein the front "
                        "leaked into) is kept out of the lumen")
    p.add_argument("--init-mask", type=Path, metavar="FILE",
                   help="initial region (image on the same grid, nonzero inside); may cross the boundary")
    p.add_argument("--alpha", type=float, help="curvature weight of eq. (1), 0..1 (default 0.2)")
    p.add_argument("--hu-window", nargs=2, type=float, metavar=("LOW", "HIGH"),
                   help="intensity window in the image's units (HU for CT); brighter voxels are folded dark "
                        "(default: estimated from the lumen at the seeds and the tissue around it)")
    p.add_argument("--kernel-radius", type=float, metavar="MM", help="GPF kernel support (default 10 mm)")
    p.add_argument("--sigma", type=float, metavar="MM", help="pre-smoothing in mm (default 0.6)")
    p.add_argument("--refine-radius", type=float, metavar="MM",
                   help="kernel of the refining stage, 0 to skip it (default 1.5 mm)")
    p.add_argument("--denoise", type=int, metavar="N",
                   help="curvature anisotropic diffusion iterations before the potential (default 0: off)")
    p.add_argument("--seed-radius", type=float, metavar="MM", help="radius of each seed sphere (default 1.5)")
    p.add_argument("--chamber-ratio", type=float, metavar="R",
                   help="a region wider than R times the vessel at the seeds (a heart chamber) is kept out of the "
                        "lumen; 0 keeps it, e.g. an aneurysm (default 2)")
    p.add_argument("--companion-depth", type=float, metavar="C",
                   help="a bright vessel running beside the seeded one, behind a gap that dips by at least C of the "
                        "lumen's contrast (a vein as bright as the artery), is kept out of the lumen; 0 keeps it "
                        "(default 0.05)")
    p.add_argument("--join-contrast", type=float, metavar="C",
                   help="seeds left in separate pieces (the front pinched at a string-sign stenosis) are joined "
                        "along the minimal path through the image when it stays at C or more of the lumen's "
                        "contrast all along; 0 never joins them (default 0.25)")
    p.add_argument("--handles", type=float, metavar="MM",
                   help="remove the lumen's handles (vessels bridged where the image does not resolve the gap "
                        "between them, tunnels through the mask) by cutting bridges or filling tunnels up to 2 MM "
                        "wide; 0 keeps them (default 1.5)")
    p.add_argument("--slice-thickness", type=float, metavar="MM",
                   help="reconstructed slice thickness, when the image file does not record it (DICOM and "
                        "dcm2niix's JSON sidecar do): the blur model spreads each slice over it (default: the "
                        "recorded thickness, else the slice spacing)")
    p.add_argument("--measure-slice-blur", action=argparse.BooleanOptionalAction,
                   help="measure the blur along the slice axis on the image, from how the width of the tissue "
                        "edges grows as they tilt out of the slices (default), or take it from the slice "
                        "thickness (--no-measure-slice-blur); --slice-thickness overrides it")
    p.add_argument("--max-iterations", type=int, metavar="N", help="per stage (default 4000)")
    p.add_argument("--wall", action="store_true",
                   help="also segment the whole vessel (lumen, thrombus, wall): segmentation/wall_mask.nii.gz")
    p.add_argument("--wall-morphology", nargs=2, type=float, metavar=("CLOSE", "OPEN"),
                   help="radii in mm of the closing and opening of that whole-vessel mask (default 0 0: none; "
                        "implies --wall)")
    p.add_argument("--wall-trunk", type=float, metavar="MM",
                   help="keep only the trunk of that mask (e.g. the aorta without its branches): within MM of the "
                        "balls along its main axis (default 0: off; implies --wall)")


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (and exit status 2), not the usage block first."""

    def error(self, message: str):
        self.exit(2, f"carotid: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``carotid`` command (its subcommands' parsers are of the same class)."""
    parser = OneLineParser(prog="carotid", description="CT angiogram of the neck -> carotid blood flow.")
    parser.add_argument("--version", action="version", version=f"carotid {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="run every available stage on a built-in synthetic case")
    p.add_argument("-o", "--output", default="carotid-demo", help="output folder (default ./carotid-demo)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("phantom", help="write a synthetic carotid CTA (or MRA) with its ground truth")
    p.add_argument("out_dir", type=Path)
    grade = p.add_mutually_exclusive_group()
    grade.add_argument("--area-stenosis", "--stenosis", dest="stenosis", type=float, metavar="FRACTION",
                       help="ICA stenosis as the AREA reduction 1-(d_min/d_local)^2, 0..0.95 (default 0.7); "
                            "--stenosis is an alias")
    grade.add_argument("--nascet", type=float, metavar="FRACTION",
                       help="ICA stenosis by NASCET, 1 - d_min/d_distal ICA (diameters), instead of the area "
                            "reduction; at most about 0.7 (the area reduction stays < 0.95)")
    p.add_argument("--noise", type=float, help="noise standard deviation, HU in CT (default 20), MR units in MR")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--noise-seed", type=int, metavar="N",
                   help="draw the image noise alone from N: the same anatomy rescanned (default: from --seed)")
    p.add_argument("--spacing", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="voxel size in mm (default 0.45 0.45 0.625)")
    p.add_argument("--extent", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="field of view in mm (default 44 44 75)")
    family = p.add_argument_group("family model (any of these selects it; see carotid.phantom.sample_family)")
    family.add_argument("--family", action="store_true",
                        help="draw every parameter from the phantom family with --seed; explicit options override")
    family.add_argument("--vein-gap", type=float, metavar="MM",
                        help="smallest gap between the jugular vein and the arterial lumen walls (family 0.3-2)")
    family.add_argument("--venous-fraction", type=float, metavar="F",
                        help="venous enhancement / proximal arterial enhancement above tissue, 0..1 (family 0.4-0.9)")
    family.add_argument("--calcium-hu", type=float, metavar="HU", help="calcium density, CT only (family 300-1500)")
    family.add_argument("--blur-sigma", type=float, metavar="MM",
                        help="scanner blur standard deviation in plane (family 0.4-0.8; default 1 mm FWHM)")
    family.add_argument("--arterial-hu", type=float, metavar="LEVEL",
                        help="proximal lumen level: HU in CT (family 250-600), MR units in MR (1200-2500; "
                             "time-of-flight 400-1000)")
    family.add_argument("--bolus-fade", type=float, metavar="F",
                        help="fraction of the arterial enhancement lost from proximal CCA to distal ICA (family 0-0.3)")
    family.add_argument("--ica-shape", choices=("smooth", "kink", "loop"), help="ICA course distal to the stenosis")
    family.add_argument("--modality", choices=("ct", "mr", "tof"),
                        help="CT angiogram (HU), contrast-enhanced MRA or time-of-flight MRA")
    family.add_argument("--bias", type=float, metavar="A", help="MR bias field amplitude, 0..1 (default 0.3 in MR)")
    p.set_defaults(func=cmd_phantom)

    p = sub.add_parser("segment", help="segment the arterial lumen (GPF level set)")
    p.add_argument("image", type=Path, help="CT image: DICOM folder, NIfTI, NRRD or MHA")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CASE_DIR")
    _add_segment_options(p)
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser("run", help="every stage from scan to report, skipping stages already done")
    p.add_argument("image", type=Path, help="CT image: DICOM folder, NIfTI, NRRD or MHA")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CASE_DIR")
    p.add_argument("--config", type=Path, metavar="TOML", help="parameters of every stage (see `carotid config`)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("batch", help="run a cohort (manifest CSV: case_id,image[,config][,doppler_cca_psv,"
                                     "doppler_cca_edv]) on Dask; exit 3 when some cases failed")
    p.add_argument("manifest", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT_DIR")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (default: a LocalCluster)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    p.add_argument("--retries", type=int, default=1, help="retries of a stage after an unexpected error (default 1)")
    p.add_argument("--config", type=Path, metavar="TOML", help="config for cases without their own")
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("report", help="write CASE_DIR/report.html from the stages that have run")
    p.add_argument("case_dir", type=Path, metavar="CASE_DIR")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("config", help="print the effective configuration of `carotid run` as TOML")
    p.add_argument("--show", action="store_true", help="print it (the default action)")
    p.add_argument("--config", type=Path, metavar="TOML", help="a config file to validate and merge")
    p.set_defaults(func=cmd_config)

    for module in STAGE_COMMANDS:
        importlib.import_module(module).register(sub)

    return parser


# Arguments that name a folder the command writes into.
OUTPUT_FOLDERS = ("output", "out_dir", "case_dir")


def check_output_folders(args) -> None:
    """Raise CarotidError when an output folder argument names an existing file or a place nothing can be
    written to, before any work is done."""
    for name in OUTPUT_FOLDERS:
        value = getattr(args, name, None)
        if value is None:
            continue
        path = Path(value).absolute()
        if path.exists() and not path.is_dir():
            raise CarotidError(f"{value}: exists and is a file, not a folder")
        existing = next(p for p in (path, *path.parents) if p.exists())
        if not existing.is_dir():
            raise CarotidError(f"{value}: cannot be created, {existing} is a file")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise CarotidError(f"{value}: cannot be written, {existing} is not writable")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line on stderr, like the errors."""
    print(f"carotid: warning: {message}", file=sys.stderr)


def main(argv=None) -> int:
    """Entry point of the ``carotid`` console script."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # a usage error (one line, status 2), --help or --version
        return exc.code
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            check_output_folders(args)
            return args.func(args)
    except CarotidError as exc:
        print(f"carotid: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print("carotid: error: out of memory (try a smaller region of interest)", file=sys.stderr)
        return 2
    except OSError as exc:  # the file system refused (a folder that cannot be made, a full disk)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"carotid: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("carotid: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # an internal error: one line, the traceback on request
        if os.environ.get("CAROTID_DEBUG"):
            raise
        print(f"carotid: internal error: {type(exc).__name__}: {exc} (set CAROTID_DEBUG=1 for the traceback)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
