"""The virtual duplex on phantoms of 50, 70 and 90 % area stenosis, under a fixed split and under RCR outlets.

Each phantom (``make_phantom(stenosis=A, noise=20, seed=0)``, the demo's family) goes through ``carotid run``
at the demo's coarse settings (0.8 mm surface, 2 wall layers; ``--quick``: a tenth of a cycle) with Murray's
split, then the same mesh is run again with RCR outlets calibrated for that split as their mean share (93 mmHg
mean, 40 mmHg pulse); one cycle of the built-in waveform from rest each, the same inflow for all.  Figures per
phantom and outlet model: the ICA share of the inflow, the ICA and CCA PSV and EDV of the Doppler gates, their
ratio, the SRU consensus grade, the pressure drop across the stenosis (mean and at peak systole) and the
pressure ratio (RCR only), beside the NASCET and area reduction of the centerline stage
(``results/duplex.json``).  Issue 16 asks that with RCR outlets the ICA share falls and the PSV rises as the
stenosis tightens.

Usage (from the repository root)::

    .venv/bin/python benchmarks/bench_duplex.py [--quick]
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from _common import parse_args, write_results

STENOSES = (0.5, 0.7, 0.9)
CONFIG = {"surface": {"target_edge_mm": 0.8}, "mesh": {"layers": 2, "thickness_ratio": 0.15},
          "simulate": {"cycles": 1.0, "output_every": 200, "checkpoint_every": 2000}}


def row(case: Path, model: str) -> dict:
    """The figures of one run from its ``flow/summary.json`` and ``geometry.json``."""
    summary = json.loads((case / "flow" / "summary.json").read_text())
    geometry = json.loads((case / "geometry.json").read_text())
    caps = {str(cap["id"]): cap["name"] for cap in geometry["caps"]}
    share = {caps[label]: outlet["fraction_of_inflow_mean"]
             for label, outlet in summary["mass_balance"]["outlets"].items()}
    duplex = summary["duplex"]
    gates, pressure = duplex["gates"], duplex["pressure"]
    return {"outlets": model, "ica_share": share["ICA"], "ica_psv_cm_s": gates["ICA"]["psv_cm_s"],
            "ica_edv_cm_s": gates["ICA"]["edv_cm_s"], "cca_psv_cm_s": gates["CCA"]["psv_cm_s"],
            "cca_edv_cm_s": gates["CCA"]["edv_cm_s"], "psv_ratio": duplex["psv_ratio"],
            "sru_grade": duplex["sru"]["grade"], "pressure_drop_mean_mmhg": pressure["drop_mean_mmhg"],
            "pressure_drop_systole_mmhg": pressure["drop_peak_systole_mmhg"], "pressure_ratio_mean": pressure["ratio_mean"],
            "steps": summary["steps"], "seconds": summary["seconds"], "tetrahedra": summary["mesh"]["tetrahedra"],
            "nascet": geometry["stenosis"]["nascet"], "area_reduction": geometry["stenosis"]["area_reduction"]}


def run_phantom(folder: Path, stenosis: float, cycles: float) -> list[dict]:
    """One phantom through ``carotid run`` (Murray's split), then its mesh with RCR outlets."""
    from carotid.config import Config
    from carotid.flow.simulate import FlowParameters, simulate
    from carotid.phantom import make_phantom, write_phantom
    from carotid.pipeline import run

    write_phantom(make_phantom(stenosis=stenosis, noise=20.0, seed=0), folder / "phantom")
    config = {**CONFIG, "simulate": {**CONFIG["simulate"], "cycles": cycles}}
    run(folder / "phantom" / "image.nii.gz", folder / "split", Config(config))
    (folder / "rcr").mkdir()
    for name in ("mesh.vtu", "centerlines.vtp", "geometry.json"):
        shutil.copy(folder / "split" / name, folder / "rcr" / name)
    simulate(folder / "rcr" / "mesh.vtu", folder / "rcr",
             FlowParameters(cycles=cycles, outlets="rcr", output_every=200, checkpoint_every=2000))
    return [{"area_stenosis": stenosis, **row(folder / model, model)} for model in ("split", "rcr")]


def main() -> None:
    """Run the three phantoms and write ``results/duplex.json``; print the table of the README."""
    args = parse_args(__doc__.splitlines()[0])
    cycles = 0.1 if args.quick else CONFIG["simulate"]["cycles"]
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for stenosis in STENOSES:
            (Path(folder) / str(stenosis)).mkdir()
            rows += run_phantom(Path(folder) / str(stenosis), stenosis, cycles)
    for model in ("split", "rcr"):
        ordered = [r for r in rows if r["outlets"] == model]
        print(f"{model}: ICA share {[round(r['ica_share'], 3) for r in ordered]}, ICA PSV "
              f"{[round(r['ica_psv_cm_s']) for r in ordered]} cm/s")
    print("| area stenosis | NASCET | outlets | ICA share | ICA PSV / EDV (cm/s) | CCA PSV / EDV (cm/s) | ratio | SRU "
          "| drop mean / systole (mmHg) | Pd/Pa |")
    for r in rows:
        ratio = "–" if r["pressure_ratio_mean"] is None else f"{r['pressure_ratio_mean']:.3f}"
        print(f"| {100 * r['area_stenosis']:.0f} % ({100 * r['area_reduction']:.0f} %) | {100 * r['nascet']:.0f} % | "
              f"{r['outlets']} | {100 * r['ica_share']:.1f} % | {r['ica_psv_cm_s']:.0f} / {r['ica_edv_cm_s']:.0f} | "
              f"{r['cca_psv_cm_s']:.0f} / {r['cca_edv_cm_s']:.0f} | {r['psv_ratio']:.2f} | {r['sru_grade']} | "
              f"{r['pressure_drop_mean_mmhg']:.1f} / {r['pressure_drop_systole_mmhg']:.1f} | {ratio} |")
    write_results("duplex", {"config": CONFIG, "cycles": cycles, "rows": rows}, args.quick)


if __name__ == "__main__":
    main()
