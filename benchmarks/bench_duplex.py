"""The virtual duplex on phantoms of 50, 70 and 90 % area stenosis, under a fixed split and under RCR outlets.

Each phantom (``make_phantom(stenosis=A, noise=20, seed=0)``, the demo's family) goes through segment,
centerlines, surface and mesh at the demo's coarse settings (0.8 mm surface, 2 wall layers).  Its mesh is then
simulated twice, from rest, for three cycles of the built-in waveform (``--quick``: a tenth of a cycle): with
Murray's split, and with RCR outlets calibrated for that split as their mean share (93 mmHg mean, 40 mmHg
pulse); the same inflow for all.  The six runs share the two cores, two at a time.

Figures per phantom and outlet model: the ICA share of the inflow volume in each cycle (the share of the mean
flow), the ICA and CCA PSV and EDV of the Doppler gates over the last cycle, their ratio, the SRU consensus
grade, the pressure drop across the stenosis (mean and at peak systole) and the pressure ratio (RCR only),
beside the NASCET and area reduction of the centerline stage (``results/duplex.json``).  Issue 16 asks that
with RCR outlets the ICA share falls and the PSV rises as the stenosis tightens.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_duplex.py [--quick]
"""

from __future__ import annotations

import json
import shutil
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from _common import parse_args, write_results

STENOSES = (0.5, 0.7, 0.9)
MODELS = {"split": "murray", "rcr": "rcr"}
CONFIG = {"surface": {"target_edge_mm": 0.8}, "mesh": {"layers": 2, "thickness_ratio": 0.15}}
SIMULATE = {"cycles": 3.0, "output_every": 200, "checkpoint_every": 2000}
MESH_FILES = ("mesh.vtu", "centerlines.vtp", "geometry.json")


def prepare(folder: Path, stenosis: float) -> Path:
    """Phantom of ``stenosis`` (area fraction) through segment, centerlines, surface and mesh; the case folder."""
    from carotid.config import Config
    from carotid.phantom import make_phantom, write_phantom
    from carotid.pipeline import STAGES, run_stage

    write_phantom(make_phantom(stenosis=stenosis, noise=20.0, seed=0), folder / "phantom")
    case = folder / "case"
    for stage in STAGES[:[s.name for s in STAGES].index("mesh") + 1]:
        print(f"{100 * stenosis:.0f} %: {run_stage(stage, folder / 'phantom' / 'image.nii.gz', case, Config(CONFIG))}",
              flush=True)
    return case


def simulate_case(case: Path, model: str, cycles: float) -> Path:
    """Run the mesh of ``case`` with the outlet ``model`` ("split" or "rcr") in a folder of its own."""
    from carotid.flow.simulate import FlowParameters, simulate

    folder = case.parent / model
    folder.mkdir()
    for name in MESH_FILES:
        shutil.copy(case / name, folder / name)
    simulate(folder / "mesh.vtu", folder, FlowParameters(**{**SIMULATE, "cycles": cycles}, outlets=MODELS[model]))
    print(f"{folder}: done", flush=True)
    return folder


def row(folder: Path, model: str) -> dict:
    """The figures of one run from its ``flow/summary.json`` and ``geometry.json``."""
    summary = json.loads((folder / "flow" / "summary.json").read_text())
    geometry = json.loads((folder / "geometry.json").read_text())
    caps = {str(cap["id"]): cap["name"] for cap in geometry["caps"]}
    labels = list(summary["mass_balance"]["outlets"])
    ica = labels.index(next(label for label in labels if caps[label] == "ICA"))
    share = {caps[label]: outlet["fraction_of_inflow_mean"]
             for label, outlet in summary["mass_balance"]["outlets"].items()}
    duplex = summary["duplex"]
    gates, pressure = duplex["gates"], duplex["pressure"]
    return {"outlets": model, "ica_share": share["ICA"],
            "ica_share_per_cycle": [entry["outlet_share"][ica] for entry in summary["periodicity"]],
            "ica_psv_cm_s": gates["ICA"]["psv_cm_s"],
            "ica_edv_cm_s": gates["ICA"]["edv_cm_s"], "cca_psv_cm_s": gates["CCA"]["psv_cm_s"],
            "cca_edv_cm_s": gates["CCA"]["edv_cm_s"], "psv_ratio": duplex["psv_ratio"],
            "sru_grade": duplex["sru"]["grade"], "pressure_drop_mean_mmhg": pressure["drop_mean_mmhg"],
            "pressure_drop_systole_mmhg": pressure["drop_peak_systole_mmhg"], "pressure_ratio_mean": pressure["ratio_mean"],
            "steps": summary["steps"], "seconds": summary["seconds"], "tetrahedra": summary["mesh"]["tetrahedra"],
            "nascet": geometry["stenosis"]["nascet"], "area_reduction": geometry["stenosis"]["area_reduction"]}


def main() -> None:
    """Prepare the three phantoms, run the six simulations and write ``results/duplex.json``; print the
    README's table."""
    args = parse_args(__doc__.splitlines()[0])
    cycles = 0.1 if args.quick else SIMULATE["cycles"]
    with tempfile.TemporaryDirectory() as tmp:
        cases = {}
        for stenosis in STENOSES:
            (Path(tmp) / str(stenosis)).mkdir()
            cases[stenosis] = prepare(Path(tmp) / str(stenosis), stenosis)
        jobs = [(s, m) for s in sorted(STENOSES, reverse=True) for m in MODELS]  # the longest runs first
        with ProcessPoolExecutor(max_workers=2) as pool:
            done = {job: pool.submit(simulate_case, cases[job[0]], job[1], cycles) for job in jobs}
            rows = [{"area_stenosis": s, **row(done[(s, m)].result(), m)} for s in STENOSES for m in MODELS]
    for model in MODELS:
        ordered = [r for r in rows if r["outlets"] == model]
        print(f"{model}: ICA share {[round(r['ica_share'], 4) for r in ordered]}, ICA PSV "
              f"{[round(r['ica_psv_cm_s']) for r in ordered]} cm/s")
    print("| area stenosis | NASCET | outlets | ICA share, cycles 1 / 2 / 3 | ICA PSV / EDV (cm/s) | CCA PSV / EDV "
          "(cm/s) | ratio | SRU | drop mean / systole (mmHg) | Pd/Pa |")
    for r in rows:
        ratio = "–" if r["pressure_ratio_mean"] is None else f"{r['pressure_ratio_mean']:.3f}"
        cycles_text = " / ".join(f"{100 * s:.2f}" for s in r["ica_share_per_cycle"]) or f"{100 * r['ica_share']:.2f}"
        print(f"| {100 * r['area_stenosis']:.0f} % ({100 * r['area_reduction']:.0f} %) | {100 * r['nascet']:.0f} % | "
              f"{r['outlets']} | {cycles_text} % | {r['ica_psv_cm_s']:.0f} / {r['ica_edv_cm_s']:.0f} | "
              f"{r['cca_psv_cm_s']:.0f} / {r['cca_edv_cm_s']:.0f} | {r['psv_ratio']:.2f} | {r['sru_grade']} | "
              f"{r['pressure_drop_mean_mmhg']:.1f} / {r['pressure_drop_systole_mmhg']:.1f} | {ratio} |")
    write_results("duplex", {"config": {**CONFIG, "simulate": SIMULATE}, "cycles": cycles, "rows": rows},
                  args.quick)


if __name__ == "__main__":
    main()
