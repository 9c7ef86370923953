"""Surface stage on the demo phantom: seconds for marching cubes + clipping + Taubin + remeshing at 0.3 mm,
and pymeshlab's isotropic explicit remeshing (target 0.3 mm absolute) of the same clipped, smoothed input,
with the same quality figures for both.  Run as ``python benchmarks/bench_surface.py [--quick]``."""

from __future__ import annotations

import numpy as np
from _common import parse_args, run_isolated, timed, write_results

TARGET = 0.3


def _inputs(quick: bool):
    from carotid.centerline.model import Branch, Centerlines
    from carotid.phantom import make_phantom

    ph = make_phantom(stenosis=0.7, noise=20, seed=0, extent=(44, 44, 40) if quick else (44, 44, 75))
    branches = [Branch(b.name, b.points[ph.sdf.contains(b.points)], b.radii[ph.sdf.contains(b.points)])
                for b in ph.branches]
    return ph.sdf, Centerlines(branches, np.asarray(ph.info["bifurcation_mm"]))


def _carotid(quick: bool) -> dict:
    from carotid.surface.clip import clip_surface
    from carotid.surface.extract import extract_surface
    from carotid.surface.quality import surface_quality
    from carotid.surface.remesh import remesh
    from carotid.surface.smooth import taubin_smooth

    levelset, centerlines = _inputs(quick)
    times = {}
    surf, times["marching_cubes"] = timed(extract_surface, levelset)
    (clipped, _), times["clip"] = timed(clip_surface, surf, centerlines, domain=levelset)
    smoothed, times["taubin"] = timed(taubin_smooth, clipped, 30)
    out, times["remesh"] = timed(remesh, smoothed, TARGET, iterations=8)
    times["total"] = sum(times.values())
    smoothed.save("/tmp/_bench_surface_input.vtp")
    return {"seconds": times, "quality": surface_quality(out, TARGET)}


def _pymeshlab() -> dict:
    import pymeshlab
    import pyvista as pv

    from carotid.surface.mesh import from_polydata, to_polydata
    from carotid.surface.quality import surface_quality

    points, faces, _ = from_polydata(pv.read("/tmp/_bench_surface_input.vtp"))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(points, faces))

    def run():
        ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(TARGET), iterations=8)

    _, seconds = timed(run)
    m = ms.current_mesh()
    return {"seconds": {"remesh": seconds},
            "quality": surface_quality(to_polydata(m.vertex_matrix(), m.face_matrix()), TARGET)}


def main() -> None:
    args = parse_args(__doc__)
    ours = run_isolated(_carotid, args.quick)
    peer = run_isolated(_pymeshlab)
    figures = {"target_edge_mm": TARGET, "input": "make_phantom(stenosis=0.7, noise=20, seed=0), true SDF",
               "carotid": {**ours["result"], "peak_rss_mb": ours["peak_rss_mb"]},
               "pymeshlab": {**peer["result"], "peak_rss_mb": peer["peak_rss_mb"],
                             "note": "same clipped, Taubin-smoothed input; caps not kept planar or labelled"}}
    write_results("surface", figures, quick=args.quick)


if __name__ == "__main__":
    main()
