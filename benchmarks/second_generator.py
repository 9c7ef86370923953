"""A second carotid angiogram phantom generator, written apart from ``carotid.phantom``.

``carotid phantom`` and the benchmarks built on it share their authors' assumptions: a Gaussian scanner
blur applied on the voxel grid after a partial-volume ramp, a raised-cosine stenosis, its vein and tissue
texture.  A segmentation tuned on them can pass its own family and fail on scans made another way.  This
generator builds the same anatomy class by other means, so that ``bench_second_generator.py`` measures
``segment`` on images it was never developed on:

* **Geometry.**  Each branch (CCA, ICA, ECA) is a sweep of spheres along a polyline (a quadratic Bezier
  curve from the bifurcation, with a sinusoidal wander on the ICA, reduced where it would bring the ICA back
  against the ECA); the lumen is their union.  The CCA runs
  up z; the ICA leaves within 45 degrees of posterior (+y in LPS), the ECA the opposite way.  The ICA's
  stenosis is eccentric: its axial profile is a Gaussian of standard deviation 1.5-5 mm (different
  proximally and distally) narrowing the radius to the drawn area fraction, with the lumen's centre
  pushed away from the plaque.  The plaque fills the unstenosed wall around it; a calcified crescent in it
  touches the lumen (gap 0-0.3 mm) near the throat.  The internal jugular vein is a straight tube beside
  the CCA at a gap of 0.3-2 mm, enhancing at 40-90 % of the artery; a vertebral body (cortex and marrow)
  lies behind the vessels, and fat fills smooth random regions.
* **Image formation.**  Materials are painted on a grid three times finer than the voxels, blurred there
  by an isotropic Gaussian point spread function, integrated over each slice's thickness (which may exceed
  the slice spacing: overlapping reconstructions) and over each pixel, then sampled.  CT noise is white
  noise low-passed in plane; MR images take a multiplicative bias field and Rician noise.

The truth is on the image grid: the lumen mask (the voxel's lumen fraction >= 0.5) and the signed
distance to the sphere sweep (mm, negative inside), whose zero level is the true wall.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from carotid.io import Volume

EXTENT_MM = np.array([64.0, 40.0, 40.0])  # (z, y, x)
FINE = 3  # fine grid: voxel / FINE in every direction
APART_MM = 1.0  # the ICA's and ECA's walls, once apart by this, stay apart (a touching pair is a loop)
CALCIUM_LABEL = 4  # carotid.phantom.LABELS["calcium"], which bench_segmentation.calcium_in_lumen reads


@dataclass
class Branch:
    """A branch's lumen: sphere centres (mm, world x, y, z; shape (n, 3)) and radii (mm, shape (n,))."""

    name: str
    points: np.ndarray
    radii: np.ndarray


@dataclass
class SecondPhantom:
    """Image, truth and the parameters drawn (``info``), in the attribute names the benchmarks score with."""

    image: Volume
    mask: Volume
    sdf: Volume
    labels: Volume
    branches: list
    info: dict


def draw(seed: int) -> dict:
    """Random parameters of case ``seed``: CT (three in four cases) or contrast-enhanced MR."""
    rng = np.random.default_rng([seed, 2026])
    mr = rng.random() < 0.25
    h = rng.uniform(0.35, 0.6)
    hz = rng.uniform(h, 1.0) if not mr else rng.uniform(0.6, 1.5)
    ica_azimuth = rng.uniform(45.0, 135.0)  # the ICA leaves posteriorly (+y in LPS), to the left or right
    return {
        "seed": seed, "modality": "mr" if mr else "ct",
        "spacing_xyz": [round(h, 3), round(h, 3), round(hz, 3)],
        "thickness_mm": round(hz * (rng.uniform(1.0, 1.6) if not mr else 1.0), 3),
        "psf_sigma_mm": round(rng.uniform(0.3, 0.7), 3),
        "cca_radius_mm": rng.uniform(2.8, 3.8), "ica_ratio": rng.uniform(0.62, 0.8),
        "eca_ratio": rng.uniform(0.5, 0.65), "bifurcation_z_mm": rng.uniform(20.0, 28.0),
        "ica_angle_deg": rng.uniform(10.0, 35.0), "eca_angle_deg": rng.uniform(15.0, 40.0),
        "ica_azimuth_deg": ica_azimuth, "ica_wander_mm": rng.uniform(0.0, 3.0),
        "stenosis_area": rng.uniform(0.3, 0.9), "stenosis_position_mm": rng.uniform(5.0, 12.0),
        "stenosis_sd_mm": [rng.uniform(1.5, 5.0), rng.uniform(1.5, 5.0)],
        "eccentricity": rng.uniform(0.0, 0.8), "plaque_azimuth_deg": rng.uniform(0.0, 360.0),
        "calcium": bool(rng.random() < 0.75),
        "calcium_gap_mm": rng.uniform(0.0, 0.3), "calcium_length_mm": rng.uniform(1.0, 5.0),
        "calcium_halfangle_deg": rng.uniform(30.0, 100.0), "calcium_offset_mm": rng.uniform(-2.0, 2.0),
        "calcium_hu": rng.uniform(400.0, 1600.0),
        "vein_gap_mm": rng.uniform(0.3, 2.0), "vein_radius_mm": rng.uniform(3.0, 6.0),
        "vein_fraction": rng.uniform(0.4, 0.9),
        "vein_azimuth_deg": ica_azimuth + rng.choice([-90.0, 90.0]) + rng.uniform(-30.0, 30.0),
        "vertebra_gap_mm": rng.uniform(2.0, 8.0),
        "arterial": rng.uniform(200.0, 600.0) if not mr else rng.uniform(1000.0, 2000.0),
        "fade": rng.uniform(0.0, 0.3),
        "muscle": rng.uniform(30.0, 70.0) if not mr else rng.uniform(200.0, 350.0),
        "fat_ratio": rng.uniform(0.5, 2.0),
        "noise": rng.uniform(10.0, 40.0) if not mr else rng.uniform(0.02, 0.08),
        "bias": rng.uniform(0.1, 0.3) if mr else 0.0,
        "texture_seed": int(rng.integers(1 << 30)),
    }


def _curve(start, direction, end_z, bend, wander=0.0, period=20.0, step=0.2):
    """Points (mm, shape (n, 3), x y z) of a quadratic Bezier from ``start`` leaving along ``direction``
    and ending vertical at ``end_z``, with a sinusoidal ``wander`` (mm, period ``period`` mm) in the plane
    of the bend."""
    start, direction = np.asarray(start, float), np.asarray(direction, float) / np.linalg.norm(direction)
    height = end_z - start[2]
    control = start + direction * (bend * height / max(direction[2], 0.2))
    end = control + np.array([0.0, 0.0, height * (1 - bend)])
    n = int(np.ceil(1.5 * (height + np.linalg.norm(control - start)) / step))
    t = np.linspace(0.0, 1.0, n)[:, None]
    points = (1 - t) ** 2 * start + 2 * t * (1 - t) * control + t ** 2 * end
    if wander:
        side = np.array([direction[0], direction[1], 0.0]) / max(np.hypot(direction[0], direction[1]), 1e-9)
        points += wander * np.sin(2 * np.pi * (points[:, 2] - start[2]) / period)[:, None] * side
    return points


def _arclength(points):
    """Cumulative length (mm) along a polyline, shape (n,)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _sweep(step, points, radii, out):
    """``out`` (fine grid, z y x, spacing ``step`` (z, y, x) mm) := min(out, |x - c| - r) over the spheres
    (c, r): the signed distance of their union outside, an approximation of it inside.  Loops over the
    spheres, each on its own box."""
    shape = np.array(out.shape)
    for c, r in zip(points, radii):
        centre = c[::-1] / step
        reach = (r + 2.0) / step
        lo = np.maximum(np.floor(centre - reach).astype(int), 0)
        hi = np.minimum(np.ceil(centre + reach).astype(int) + 1, shape)
        if np.any(hi <= lo):
            continue
        z, y, x = np.ogrid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        d = np.sqrt((z * step[0] - c[2]) ** 2 + (y * step[1] - c[1]) ** 2 + (x * step[2] - c[0]) ** 2) - r
        box = out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        np.minimum(box, d.astype(np.float32), out=box)


def _line(a, b, step=0.2):
    """Points (mm, shape (n, 3)) from ``a`` to ``b`` every ``step`` mm or less."""
    n = int(np.ceil(np.linalg.norm(np.subtract(b, a)) / step)) + 1
    return np.asarray(a, float) + np.linspace(0.0, 1.0, n)[:, None] * np.subtract(b, a)


def make_second_phantom(seed: int, calcium_hu: float | None = None) -> SecondPhantom:
    """Build case ``seed`` (see the module docstring); 5-30 s and 1-3 GB on the fine grid.  ``calcium_hu``
    replaces the calcium's drawn level (the same case and noise otherwise)."""
    p = draw(seed)
    if calcium_hu is not None:
        p["calcium_hu"] = float(calcium_hu)
    hx, _, hz = p["spacing_xyz"]
    fz = int(np.ceil(FINE * hz / hx))
    step = np.array([hz / fz, hx / FINE, hx / FINE])  # fine grid (z, y, x), mm
    nz = int(EXTENT_MM[0] // hz)
    ny, nx = (int(EXTENT_MM[a] // hx) for a in (1, 2))
    shape_fine = (nz * fz, ny * FINE, nx * FINE)
    top = nz * hz - 1.0
    rc = p["cca_radius_mm"]
    az = np.radians(p["ica_azimuth_deg"])
    outward = np.array([np.cos(az), np.sin(az), 0.0])
    bif = np.array([EXTENT_MM[2] / 2 - 0.15 * rc * outward[0], EXTENT_MM[1] / 2 - 0.15 * rc * outward[1],
                    p["bifurcation_z_mm"]])
    cca = _line(bif - [0, 0, bif[2] + 2.0], bif)
    ti, te = np.radians(p["ica_angle_deg"]), np.radians(p["eca_angle_deg"])
    eca = _curve(bif, -outward * np.sin(te) + [0, 0, np.cos(te)], top + 3, 0.35)
    # radii: the ICA's bulb tapering to its distal radius, the ECA past a short taper
    s_e = _arclength(eca)
    r_far = p["ica_ratio"] * rc
    r_eca = p["eca_ratio"] * rc + (0.8 - p["eca_ratio"]) * rc * np.exp(-(s_e / 3.0) ** 2)
    while True:  # a wander that brings the ICA back against the ECA would make the lumen a loop: reduce it
        ica = _curve(bif, outward * np.sin(ti) + [0, 0, np.cos(ti)], top + 3, 0.4, p["ica_wander_mm"])
        s_i = _arclength(ica)
        r_ica = r_far + (1.05 * rc - r_far) * np.exp(-(s_i / 9.0) ** 2)
        lumen_c, lumen_r, side = _stenosis(ica, s_i, r_ica, p)
        if p["ica_wander_mm"] < 0.05 or _apart(lumen_c, lumen_r, eca, r_eca, APART_MM):
            break
        p["ica_wander_mm"] *= 0.8
    lumen = np.full(shape_fine, np.float32(1e3))
    for points, radii in ((cca, np.full(len(cca), rc)), (lumen_c, lumen_r), (eca, r_eca)):
        _sweep(step, points, radii, lumen)
    vessel = lumen.copy()
    _sweep(step, ica, r_ica, vessel)  # the unstenosed ICA: lumen and plaque
    z, y, x = (np.arange(n, dtype=np.float32) * s for n, s in zip(shape_fine, step))
    # vein beside the CCA, vertebra on the other side, both straight along z
    vaz = np.radians(p["vein_azimuth_deg"])
    vdir = np.array([np.cos(vaz), np.sin(vaz)])
    rv = p["vein_radius_mm"]
    vc = bif[:2] + vdir * (rc + p["vein_gap_mm"] + rv)
    vein = np.broadcast_to(np.hypot(x[None, None, :] - vc[0], y[None, :, None] - vc[1]) - rv, shape_fine)
    vb = bif[:2] - vdir * (rc + p["vertebra_gap_mm"] + 8.0)
    bone = np.broadcast_to(np.hypot(x[None, None, :] - vb[0], y[None, :, None] - vb[1]) - 8.0, shape_fine)
    # materials: muscle, fat in smooth random regions, vertebra (cortex, marrow), vein, plaque, calcium, lumen
    mr = p["modality"] == "mr"
    muscle = p["muscle"]
    rng = np.random.default_rng(p["texture_seed"])
    coarse = ndimage.gaussian_filter(rng.standard_normal(tuple(max(n // 12, 4) for n in shape_fine)), 1.5)
    fat = ndimage.zoom(coarse.astype(np.float32), np.array(shape_fine) / np.array(coarse.shape), order=1,
                       grid_mode=True, mode="nearest") > np.quantile(coarse, 0.65)
    img = np.where(fat, np.float32(-100.0 if not mr else muscle * p["fat_ratio"]), np.float32(muscle))
    del fat, coarse
    img[bone < 0] = 900.0 if not mr else 30.0
    img[bone < -1.2] = 250.0 if not mr else 1.2 * muscle
    img[vein < 0] = muscle + p["vein_fraction"] * (p["arterial"] - muscle)
    gap = float(lumen[vein < 0.5 * step[1]].min()) if np.any(vein < 0.5 * step[1]) else None
    plaque = (vessel < 0) & (lumen >= 0)
    img[plaque] = 60.0 if not mr else 0.9 * muscle
    del vessel
    calcium = np.zeros(shape_fine, bool)
    if p["calcium"]:
        calcium = _calcium(plaque, lumen, ica, s_i, side, p, step)
        img[calcium] = p["calcium_hu"] if not mr else 20.0
    del plaque
    inside = lumen < 0
    arterial_z = p["arterial"] * (1.0 - p["fade"] * np.clip(z / EXTENT_MM[0], 0, 1))
    img = np.where(inside, arterial_z[:, None, None].astype(np.float32), img)
    # image formation: point spread function, slice profile and pixel, sampling at the voxel centres
    img = ndimage.gaussian_filter(img, p["psf_sigma_mm"] / step, truncate=3.0)
    width = 2 * int(round((p["thickness_mm"] / step[0] - 1) / 2)) + 1  # odd: centred on the slice
    p["thickness_mm"] = round(width * step[0], 4)
    img = _integrate(img, (fz, FINE, FINE), width)
    frac = _integrate(inside.astype(np.float32), (fz, FINE, FINE), fz + 1 - fz % 2)
    calcium = _integrate(calcium.astype(np.float32), (fz, FINE, FINE), fz + 1 - fz % 2) >= 0.5
    sdf = _centre(lumen, (fz, FINE, FINE))
    del lumen, inside
    img = _noise(img, p, np.random.default_rng([seed, 99]))
    origin = (step[2] * (FINE - 1) / 2, step[1] * (FINE - 1) / 2, step[0] * (fz - 1) / 2)
    image = Volume(img.astype(np.float32), spacing=(hx, hx, hz), origin=origin)
    s0 = p["stenosis_position_mm"]
    lesion = np.abs(s_i - s0) <= 2.0 * np.where(s_i < s0, p["stenosis_sd_mm"][0], p["stenosis_sd_mm"][1])
    throat = np.flatnonzero(lesion)[np.argmin(lumen_r[lesion])]
    info = {"parameters": p, "vein_gap_measured_mm": gap, "bifurcation_mm": bif.tolist(),
            "lesion": {"throat_mm": lumen_c[throat].tolist(), "min_diameter_mm": 2.0 * float(lumen_r[throat])},
            "seeds_mm": {"CCA": cca[len(cca) // 5], "ICA": _at_z(lumen_c, top - 6.0),
                         "ECA": _at_z(eca, top - 6.0)}}
    return SecondPhantom(
        image=image, mask=image.with_array((frac >= 0.5).astype(np.uint8)), sdf=image.with_array(sdf),
        labels=image.with_array(np.where(calcium, CALCIUM_LABEL, 0).astype(np.uint8)),
        branches=[Branch("CCA", cca, np.full(len(cca), rc)), Branch("ICA", lumen_c, lumen_r),
                  Branch("ECA", eca, r_eca)], info=info)


def _stenosis(ica, s, r, p):
    """The ICA's lumen (centres (n, 3) and radii (n,), mm) narrowed by the eccentric stenosis: the radius
    ``r`` by a two-sided Gaussian in arc length ``s`` (n,), the centre pushed from the plaque; and the unit
    vectors (n, 3) across the ICA towards the plaque."""
    s0 = p["stenosis_position_mm"]
    sd = np.where(s < s0, p["stenosis_sd_mm"][0], p["stenosis_sd_mm"][1])
    narrowing = (1.0 - np.sqrt(1.0 - p["stenosis_area"])) * np.exp(-0.5 * ((s - s0) / sd) ** 2)
    lumen_r = r * (1.0 - narrowing)
    tangent = np.gradient(ica, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    paz = np.radians(p["plaque_azimuth_deg"])
    towards = np.array([np.cos(paz), np.sin(paz), 0.0])
    side = towards - (tangent @ towards)[:, None] * tangent
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    return ica - (p["eccentricity"] * (r - lumen_r))[:, None] * side, lumen_r, side


def _apart(a, r_a, b, r_b, gap):
    """Whether two branches leaving one point, once their walls are ``gap`` mm apart, stay so: polylines
    ``a`` (n, 3) and ``b`` (m, 3) mm with radii ``r_a`` (n,) and ``r_b`` (m,) mm."""
    distance, nearest = cKDTree(b).query(a)
    clearance = distance - r_a - r_b[nearest]
    parted = np.flatnonzero(clearance > gap)
    return len(parted) == 0 or bool(np.all(clearance[parted[0]:] > gap))


def _at_z(points, z):
    """The point of a polyline nearest the height ``z`` (mm)."""
    return points[np.argmin(np.abs(points[:, 2] - z))]


def _calcium(plaque, lumen, axis, s, side, p, step):
    """Calcified crescent of the plaque: within ``calcium_length_mm / 2`` along the ICA of the throat
    (shifted by ``calcium_offset_mm``), within ``calcium_halfangle_deg`` of the plaque's direction, and at
    least ``calcium_gap_mm`` from the lumen."""
    idx = np.nonzero(plaque)
    pts = np.column_stack(idx)[:, ::-1] * step[::-1]  # x y z, mm
    near = cKDTree(axis).query(pts)[1]
    along = s[near] - (p["stenosis_position_mm"] + p["calcium_offset_mm"])
    radial = pts - axis[near]
    cos = np.einsum("ij,ij->i", radial, side[near]) / np.maximum(np.linalg.norm(radial, axis=1), 1e-6)
    keep = ((np.abs(along) <= 0.5 * p["calcium_length_mm"])
            & (cos >= np.cos(np.radians(p["calcium_halfangle_deg"])))
            & (lumen[idx] >= p["calcium_gap_mm"]))
    out = np.zeros(plaque.shape, bool)
    out[tuple(i[keep] for i in idx)] = True
    return out


def _integrate(fine, factors, width):
    """Voxel values: the mean of the fine grid over each pixel (``factors[1:]`` fine cells) and over
    ``width`` (odd) fine cells along z centred on the slice, shape ``fine.shape // factors``."""
    fz, fy, fx = factors
    along = ndimage.uniform_filter1d(fine, width, axis=0, mode="nearest")
    if fz % 2 == 0:
        along = 0.5 * (along + np.roll(along, -1, axis=0))  # centre of an even block lies between cells
    along = along[(fz - 1) // 2::fz]
    n = [s // f for s, f in zip(fine.shape, factors)]
    return along[: n[0], : n[1] * fy, : n[2] * fx].reshape(n[0], n[1], fy, n[2], fx).mean(axis=(2, 4)).astype(
        np.float32)


def _centre(fine, factors):
    """Values at the voxels' centres (the mean of the two middle cells along an even block)."""
    fz, fy, fx = factors
    a = fine[(fz - 1) // 2::fz]
    b = fine[fz // 2::fz]
    n = min(len(a), len(b), fine.shape[0] // fz)
    return (0.5 * (a[:n] + b[:n]))[:, fy // 2::fy, fx // 2::fx][:, : fine.shape[1] // fy, : fine.shape[2] // fx].astype(
        np.float32)


def _noise(img, p, rng):
    """CT: white noise low-passed in plane (0.6 pixel), scaled to ``noise`` HU.  MR: a multiplicative bias
    field (a random quadratic spanning +- ``bias``) and Rician noise of ``noise`` times the lumen-muscle
    contrast."""
    if p["modality"] == "ct":
        n = ndimage.gaussian_filter(rng.standard_normal(img.shape).astype(np.float32), (0, 0.6, 0.6))
        return img + p["noise"] * n / n.std()
    grids = np.meshgrid(*(np.linspace(-1, 1, n, dtype=np.float32) for n in img.shape), indexing="ij")
    field = sum(rng.uniform(-1, 1) * t for t in list(grids) + [a * b for a in grids for b in grids])
    field = 1.0 + p["bias"] * field / np.abs(field).max()
    sigma = p["noise"] * (p["arterial"] - p["muscle"])
    real = img * field + sigma * rng.standard_normal(img.shape).astype(np.float32)
    imag = sigma * rng.standard_normal(img.shape).astype(np.float32)
    return np.sqrt(real ** 2 + imag ** 2).astype(np.float32)
