"""Synthetic angiograms of a stenosed carotid bifurcation with known truth (CT or MR).

Two models share one function, :func:`make_phantom`.

**Legacy model** (no family keyword given: exactly the arrays of earlier versions for the same
``stenosis``, ``noise``, ``seed``, ``spacing``, ``extent`` and ``blur_fwhm``):

* a common (CCA), internal (ICA, with a sinus bulb) and external (ECA) carotid artery, with a
  graded ICA stenosis in the distal bulb;
* arterial contrast that fades along the neck as the bolus passes (about 450 HU proximally to
  about 320 HU distally);
* an internal jugular vein (a straight, slightly tilted cylinder) 1-2 mm from the CCA wall, with
  venous contrast not far below the arterial one (220-300 HU);
* a vertebra (cortical ring of ~1000 HU around ~280 HU marrow);
* a calcified plaque (1000 HU) touching the lumen at the stenosis;
* partial volume, a Gaussian scanner blur (1 mm FWHM in plane), correlated noise and
  anisotropic voxels (0.45 x 0.45 x 0.625 mm by default).

**Family model** (any of ``FAMILY_KEYWORDS`` given; :func:`carotid.phantom.family.sample_family`
draws them all): the same anatomy and random draws, plus what real inputs vary in and the legacy
model keeps fixed: a jugular vein (a tube of 4-5 mm radius on the lateral to anterolateral side)
that follows the CCA, bulb and proximal ICA at a chosen minimal gap (down to a fraction of a
voxel; the gap is smallest at a random height and grows by 0.01-0.05 mm per mm away from it),
venous and arterial levels, bolus fade, plaque size, position and density, scanner blur, kinked or
coiled ICAs, fat lobules (-110 to -70 HU in CT, brighter than muscle in MR; label 5), and
MR angiography (no HU: bright lumen, dark calcium and cortical bone, bias field, Rician noise), either
contrast-enhanced or time-of-flight.  In 3D time-of-flight MRA the repeated excitations saturate the
stationary tissue: muscle keeps 10-20 % of the inflowing blood's signal and fat, by its short T1,
25-45 %; the blood loses signal as its spins saturate on their way through the slab (the bolus fade
stands for that).  Veins stay as bright as the family draws them (no saturation band, the harder
case); the flow artefacts of time-of-flight (signal loss in the slow flow of the bulb and in the jet
beyond a tight stenosis, which make it overgrade) are left out, since the truth is the geometry.  A
family keyword left at None takes the value the legacy model would use (e.g. the legacy gap of
1-2 mm, 1000 HU calcium, a 1 mm FWHM blur).

The truth is analytic in both: the lumen is a union of spheres along the branch axes minus the
calcium, so the mask and the signed distance are exact at the voxel centres.

Images are float32 in memory with integer values: HU in CT; unitless signal in MR (about 200-350 in
muscle and 1200-2500 in the lumen in contrast-enhanced MRA, 40-200 and 400-1000 in time-of-flight).
:func:`write_phantom` stores both as int16.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from carotid.errors import CarotidError, CarotidWarning
from carotid.io import Volume, atomic_dir, write_image, write_json
from carotid.phantom.geometry import (STEP, Branch, bias_field, coil_tangents, cylinder_sdf, ellipsoid_sdf, frame,
                                      integrate_tangents, kink_tangents, perpendicular, raised_cosine,
                                      spline_axis, tube_gap, tube_sdf, union_of_spheres_sdf)

LABELS = {"background": 0, "lumen": 1, "vein": 2, "bone": 3, "calcium": 4, "fat": 5}

MAX_SPACING_MM = 3.0
"""Coarsest voxel of a phantom, mm: twice an MR angiogram's thickest slices."""
TISSUE_HU = 40.0
CORTICAL_HU = 1000.0
MARROW_HU = 280.0
CALCIUM_HU = 1000.0            # the legacy plaque
MAX_STENOSIS = 0.95            # largest area reduction
MAX_NOISE = 500.0              # noise SD, image units: 12 times the noisiest CTA's; beyond it int16 saturates
ICA_SHAPES = ("smooth", "kink", "loop")
MODALITIES = ("ct", "mr", "tof")
MAGNITUDE = ("mr", "tof")      # magnitude images: bias field, Rician noise, calcium a signal void
MR_TISSUE = (200.0, 350.0)     # muscle signal, MR units (contrast-enhanced MRA)
MR_FAT_RATIO = (1.5, 2.2)      # fat over muscle signal
MR_ARTERIAL = (1200.0, 2500.0)  # proximal lumen signal, MR units
MR_BIAS = 0.3                  # default bias amplitude in MR
TOF_ARTERIAL = (400.0, 1000.0)  # time-of-flight MRA: inflowing blood, proximal, MR units
TOF_TISSUE = (0.1, 0.2)        # saturated muscle, as a fraction of the proximal arterial level
TOF_FAT = (0.25, 0.45)         # fat (short T1, less saturated), as a fraction of the proximal arterial level
MAX_VOXELS = 100_000_000
# Keywords that select the family model (``nascet`` does not: it only restates the stenosis).
FAMILY_KEYWORDS = ("vein_gap_mm", "venous_fraction", "plaque_size", "plaque_angle_deg", "plaque_offset_mm",
                   "calcium_hu", "blur_sigma_mm", "arterial_hu", "bolus_fade", "ica_shape", "modality", "bias")


@dataclass
class Phantom:
    """A generated phantom: the image, the truth and its description.

    Attributes
    ----------
    image : Volume
        float32 with integer values: HU (CT) or unitless MR signal (MR).
    mask : Volume
        uint8 ground-truth lumen (1 inside).
    sdf : Volume
        float32 signed distance to the true lumen wall in mm (negative inside), clipped to +-10 mm.
    labels : Volume
        uint8 structure labels, see ``LABELS`` (fat only in the family model).
    branches : list of Branch
        True centerlines (CCA, ICA, ECA) with lumen radii in mm.
    info : dict
        JSON-ready description: stenosis degrees, bifurcation, seeds, levels, vein gap, parameters
        (``make_phantom(**info["parameters"])`` regenerates the phantom).
    vein : Branch or None
        Axis and (constant) radius of the jugular vein in mm; the legacy model's cylinder is given
        by samples of its tilted axis (its horizontal cross-section is the circle of that radius).
    """

    image: Volume
    mask: Volume
    sdf: Volume
    labels: Volume
    branches: list[Branch] = field(default_factory=list)
    info: dict = field(default_factory=dict)
    vein: Branch | None = None


@dataclass
class _Draws:
    """The legacy model's random draws, in their historical order (do not reorder)."""

    r_cca: float
    r_ica: float
    r_eca: float
    bif: np.ndarray
    spread: float
    s_st: float
    semi0: float
    gap: float
    r_vein: float
    angle: float
    bone_jitter: np.ndarray
    hu_prox: float
    hu_dist: float
    venous: float


def _legacy_draws(rng: np.random.Generator) -> _Draws:
    r_cca = rng.uniform(3.0, 3.4)
    r_ica = rng.uniform(2.4, 2.7)
    r_eca = rng.uniform(1.8, 2.1)
    bif = np.array([0.0, 0.0, 30.0]) + rng.uniform(-1.0, 1.0, 3) * [1.0, 1.0, 2.0]
    spread = rng.uniform(0.9, 1.1)
    s_st = rng.uniform(10.0, 13.0)
    semi0 = rng.uniform(0.9, 1.3)
    gap = rng.uniform(1.0, 2.0)
    r_vein = rng.uniform(4.0, 5.0)
    angle = np.deg2rad(rng.uniform(-70.0, -50.0))
    bone_jitter = rng.uniform(-1.0, 1.0, 2)
    hu_prox, hu_dist = rng.uniform(430.0, 480.0), rng.uniform(300.0, 340.0)
    venous = rng.uniform(220.0, 300.0)
    return _Draws(r_cca, r_ica, r_eca, bif, spread, s_st, semi0, gap, r_vein, angle, bone_jitter, hu_prox, hu_dist,
                  venous)


# ----------------------------------------------------------------------------------------------- arteries

def _healthy_ica(s: np.ndarray, r_cca: float, r_ica: float) -> np.ndarray:
    """Healthy ICA radius (mm) along the arc length ``s`` (mm): the sinus bulb tapering to ``r_ica``."""
    r_bulb = 1.12 * r_cca
    bulb = np.where(s < 5.0, 1.0, raised_cosine(s, 5.0, 12.0))
    return r_ica + (r_bulb - r_ica) * bulb


def _arteries(d: _Draws, stenosis: float | None, nascet: float | None, seed: int):
    """The three arterial branches, the stenosis description and the ICA radius model."""
    r_cca, r_ica, r_eca, bif, spread, s_st = d.r_cca, d.r_ica, d.r_eca, d.bif, d.spread, d.s_st
    cca = spline_axis([[0.0, 0.0, -10.0], [0.0, 0.0, 10.0], bif])
    ica_axis = spline_axis(bif + np.array([[0, 0, 0], [1.6, 1.9, 6], [3.6, 4.2, 16], [4.6, 5.0, 30],
                                           [5.0, 5.2, 70]]) * [spread, spread, 1])
    eca_axis = spline_axis(bif + np.array([[0, 0, 0], [-1.8, -2.0, 6], [-3.8, -4.0, 16], [-5.0, -4.6, 30],
                                           [-5.6, -4.8, 70]]) * [spread, spread, 1])

    cca_b = Branch("CCA", cca, np.full(len(cca), r_cca))
    s = Branch("ICA", ica_axis, np.zeros(len(ica_axis))).arclength
    healthy = _healthy_ica(s, r_cca, r_ica)
    bump = raised_cosine(s, s_st, 4.0)
    k = int(np.argmin(np.abs(s - s_st)))
    r_local = float(np.interp(s_st, s, healthy))
    if nascet is None:
        depth = 1.0 - np.sqrt(1.0 - stenosis)  # area reduction -> radius reduction at the lesion
        area = float(stenosis)
    else:
        depth_max = 1.0 - math.sqrt(1.0 - MAX_STENOSIS)
        highest = 1.0 - healthy[k] * (1.0 - depth_max * bump[k]) / r_ica
        if not 0.0 <= nascet < highest:
            raise CarotidError(f"NASCET stenosis {nascet} is outside the range this anatomy can have, "
                               f"[0, {highest:.3f}) for seed {seed} (NASCET 0 is an area reduction of "
                               f"{1 - (r_ica / r_local) ** 2:.2f} in the bulb; area reduction must stay < "
                               f"{MAX_STENOSIS})")
        depth = (1.0 - (1.0 - nascet) * r_ica / healthy[k]) / bump[k]  # exact at the throat sample
        area = float(1.0 - (1.0 - depth) ** 2)
    radii = healthy * (1.0 - depth * bump)
    ica_b = Branch("ICA", ica_axis, radii)

    s_e = Branch("ECA", eca_axis, np.zeros(len(eca_axis))).arclength
    eca_b = Branch("ECA", eca_axis, r_eca + 0.3 * raised_cosine(s_e, 0.0, 8.0))

    def radius_of(arc: np.ndarray) -> np.ndarray:
        return _healthy_ica(arc, r_cca, r_ica) * (1.0 - depth * raised_cosine(arc, s_st, 4.0))

    r_min = float(radii[k])
    sten = {
        "area_reduction": area,
        "nascet": 1.0 - r_min / r_ica,
        "ecst": 1.0 - r_min / r_local,
        "location_mm": ica_axis[k].tolist(),
        "arclength_from_bifurcation_mm": float(s[k]),
        "min_diameter_mm": 2 * r_min,
        "distal_diameter_mm": 2 * r_ica,
        "local_diameter_mm": 2 * r_local,
        "specified_as": "area" if nascet is None else "nascet",
    }
    return [cca_b, ica_b, eca_b], {"bifurcation_mm": bif.tolist(), "stenosis": sten}, k, radius_of


@dataclass
class _Plaque:
    """A calcified plaque: an ellipsoid with orthonormal ``axes`` (rows: radial, circumferential,
    axial) and semi-axes ``semi`` (mm), touching the lumen sphere of ICA sample ``k``."""

    centre: np.ndarray
    axes: np.ndarray
    semi: np.ndarray
    k: int

    def sdf(self, points: np.ndarray) -> np.ndarray:
        return ellipsoid_sdf(points, self.centre, self.axes, self.semi)

    def surface(self, n: int = 300) -> np.ndarray:
        """Points (n, 3) on the surface (a Fibonacci lattice)."""
        i = np.arange(n) + 0.5
        polar, azim = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
        unit = np.stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar), np.cos(polar)], axis=1)
        return self.centre + (unit * self.semi) @ self.axes


def _plaque(ica: Branch, s: np.ndarray, s_st: float, semi0: float, size: float, angle_deg: float,
            offset_mm: float) -> _Plaque | None:
    """The calcified plaque at the throat (legacy: size 1, angle 0, offset 0) or ``offset_mm`` along
    the axis from it, ``angle_deg`` around the axis from the side away from the ECA."""
    if size == 0:
        return None
    k = int(np.argmin(np.abs(s - (s_st + offset_mm))))
    n = len(ica.points)
    t = ica.points[min(k + 1, n - 1)] - ica.points[max(k - 1, 0)]
    t /= np.linalg.norm(t)
    u = perpendicular(t, np.array([1.0, 0.3, 0.0]))
    if angle_deg:
        a = np.deg2rad(angle_deg)
        u = np.cos(a) * u + np.sin(a) * np.cross(t, u)
    semi = np.array([semi0, 1.4, 2.2])
    if size != 1:
        semi = semi * size
    axes = np.stack([u, np.cross(t, u), t])
    centre = ica.points[k] + (ica.radii[k] + semi[0] + 0.05) * u
    return _Plaque(centre, axes, semi, k)


# ------------------------------------------------------------------------------------ tortuous ICA

def _tortuous_ica(ica: Branch, radius_of, s_st: float, shape: str, rng: np.random.Generator,
                  others: list[Branch], plaque: _Plaque | None, bone_centre: np.ndarray,
                  vein_dir: np.ndarray, extent: tuple[float, float, float]) -> tuple[Branch, dict]:
    """Replace the ICA distal to the lesion by a kink or a coil, inside the field of view, clear of
    the other arteries, the vertebra, the plaque and itself; the radius model is kept."""
    s = ica.arclength
    r = float(ica.radii[-1])
    obstacles = np.concatenate([b.points for b in others])
    obstacle_r = np.concatenate([b.radii for b in others])
    tree = cKDTree(obstacles)
    half = np.array(extent[:2]) / 2 - r - 1.0
    z_top = max(float(ica.points[-1, 2]), extent[2] + 15.0)
    for attempt in range(40):
        shrink = 1.0 - 0.015 * attempt
        if shape == "kink":
            s_l = s_st + 4.0 + rng.uniform(2.0, 6.0)
            angle = np.deg2rad(rng.uniform(60.0, 100.0))
            r1, straight, r2 = r + rng.uniform(0.6, 1.4), rng.uniform(2.0, 5.0) * shrink, rng.uniform(5.0, 8.0) * shrink
            hands = [1.0]
        else:
            s_l = s_st + 4.0 + rng.uniform(2.0, 4.0)
            r_bend, r_coil = r + rng.uniform(1.0, 2.0) * shrink, rng.uniform(4.0, 5.5) * shrink
            pitch = 2 * r + rng.uniform(1.5, 3.0)
            hands = [1.0, -1.0]
        k0 = int(np.searchsorted(s, s_l))
        p0 = ica.points[k0]
        t0 = ica.points[k0 + 1] - ica.points[k0 - 1]
        t0 /= np.linalg.norm(t0)
        e1, e2 = frame(t0, np.array([1.0, 0.0, 0.0]))
        first = rng.uniform(0.0, 2 * np.pi)
        candidates = []
        for phi in first + np.arange(24) * (2 * np.pi / 24):
            bend = np.cos(phi) * e1 + np.sin(phi) * e2
            for hand in hands:
                if shape == "kink":
                    tangents = kink_tangents(t0, bend, angle, r1, straight, r2)
                else:
                    tangents = coil_tangents(t0, bend, hand, r_bend, r_coil, pitch)
                seg = integrate_tangents(p0, tangents)
                n_on = max(int(np.ceil((z_top - seg[-1, 2]) / (STEP * t0[2]))), 1)
                tail = seg[-1] + np.arange(1, n_on + 1)[:, None] * STEP * t0
                new = np.concatenate([seg, tail])
                inside = (new[:, 2] > -r) & (new[:, 2] < extent[2] + r)
                if np.any(np.abs(new[inside, :2]) > half) or seg[:, 2].max() > extent[2] - 8.0:
                    continue
                dist, idx = tree.query(new, k=16)
                clearance = float(np.min(dist - obstacle_r[idx])) - r
                if clearance < 1.5:
                    continue
                if np.min(np.linalg.norm(new[:, :2] - bone_centre, axis=1)) - 7.5 - r < 1.5:
                    continue
                if plaque is not None and np.min(plaque.sdf(new)) - r < 1.0:
                    continue
                points = np.concatenate([ica.points[:k0 + 1], new])
                arc = Branch("ICA", points, np.zeros(len(points))).arclength
                radii = radius_of(arc)
                pairs = cKDTree(points).query_pairs(2 * radii.max() + 1.0, output_type="ndarray")
                far = np.abs(arc[pairs[:, 0]] - arc[pairs[:, 1]]) > 12.0
                gaps = (np.linalg.norm(points[pairs[far, 0]] - points[pairs[far, 1]], axis=1)
                        - radii[pairs[far, 0]] - radii[pairs[far, 1]])
                if len(gaps) and gaps.min() < 1.0:
                    continue
                towards_vein = float(np.max((seg[:, :2] - p0[:2]) @ vein_dir))
                meta = {"shape": shape, "start_arclength_mm": float(arc[k0]),
                        "end_arclength_mm": float(arc[k0 + len(seg)]), "bend_direction": bend.tolist(),
                        "lowest_self_gap_mm": float(gaps.min()) if len(gaps) else None}
                if shape == "kink":
                    meta.update(angle_deg=float(np.rad2deg(angle)), sharp_bend_radius_mm=r1, straight_mm=straight,
                                return_bend_radius_mm=r2)
                else:
                    meta.update(coil_radius_mm=r_coil, pitch_mm=pitch, bend_radius_mm=r_bend, handedness=hand)
                candidates.append((towards_vein, clearance, Branch("ICA", points, radii), meta))
        if candidates:
            # Prefer courses that keep off the vein's side and well away from the ECA and CCA.
            pools = ([c for c in candidates if c[0] <= r + 1.0 and c[1] >= 4.0],
                     [c for c in candidates if c[0] <= r + 1.0], candidates)
            pool = next(p for p in pools if p)
            _, _, branch, meta = pool[int(rng.integers(len(pool)))]
            return branch, meta
    raise CarotidError(f"an ICA {shape} does not fit in a field of view of {extent[0]:g} x {extent[1]:g} x "
                       f"{extent[2]:g} mm with this anatomy; enlarge the extent (44 x 44 x 75 mm always fits)")


# ------------------------------------------------------------------------------------------ vein

def _follow_vein(arteries: list[Branch], follow: int, plaque: _Plaque | None, direction: np.ndarray,
                 r_vein: float, gap: float, z0: float, slope: float, extent_z: float) -> tuple[Branch, dict]:
    """An internal jugular vein of radius ``r_vein`` beside the CCA, bulb and ICA (up to ICA sample
    ``follow``, then straight on), on the side ``direction`` (unit, in plane), whose smallest
    wall-to-wall gap to the arterial lumen in the field of view is exactly ``gap`` mm, reached near
    height ``z0`` (mm); elsewhere the gap grows by about ``slope`` mm per mm of height."""
    cca, ica, _ = arteries
    ref = np.concatenate([cca.points, ica.points[1:follow + 1]])
    ref[:, 2] = np.maximum.accumulate(ref[:, 2])
    t_end = ica.points[follow] - ica.points[max(follow - 20, 0)]
    t_end /= np.linalg.norm(t_end)
    heights = np.arange(-25.0, extent_z + 25.0 + 1e-9, 0.5)
    xy = np.stack([np.interp(heights, ref[:, 2], ref[:, i]) for i in (0, 1)], axis=1)
    above = heights > ref[-1, 2]
    xy[above] = ref[-1, :2] + (heights[above, None] - ref[-1, 2]) * t_end[:2] / t_end[2]
    xy = ndimage.gaussian_filter1d(xy, 6.0, axis=0, mode="nearest")  # 3 mm

    # The offset along `direction` that keeps every arterial cross-section (and the plaque, with a
    # margin) at least the wanted gap away at each height, as a smooth upper envelope.
    wanted = gap + slope * (np.sqrt((heights - z0) ** 2 + 16.0) - 4.0)
    centres = np.concatenate([b.points[::2] for b in arteries])
    radii = np.concatenate([b.radii[::2] for b in arteries])
    margin = np.zeros(len(centres))
    if plaque is not None:
        shell = plaque.surface(400)
        centres = np.concatenate([centres, shell])
        radii = np.concatenate([radii, np.full(len(shell), 0.3)])
        margin = np.concatenate([margin, np.full(len(shell), 0.6)])
    dz = heights[:, None] - centres[None, :, 2]
    disc = np.sqrt(np.clip(radii ** 2 - dz ** 2, 0.0, None))
    w = centres[None, :, :2] - xy[:, None, :]
    along = w @ direction
    perp2 = np.sum(w ** 2, axis=2) - along ** 2
    need = disc + r_vein + wanted[:, None] + margin
    ok = (np.abs(dz) < radii) & (need ** 2 > perp2)
    offset = np.where(ok, along + np.sqrt(np.clip(need ** 2 - perp2, 0.0, None)), -np.inf).max(axis=1)
    # Never closer than beside a vessel of the distal ICA's radius on the reference line (which, above the
    # followed part, no artery occupies), so that the vein stays on its side.
    offset = np.maximum(offset, float(ica.radii[-1]) + r_vein + wanted)
    # A maximum over +-6 mm, then a Gaussian of 2 mm: smooth and (to 0.3 % of a bump) above the envelope.
    offset = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(offset, 25), 4.0, mode="nearest")
    axis = spline_axis(np.column_stack([xy + offset[:, None] * direction, heights]))

    # Exact minimal gap to the lumen in the field of view: shift the vein along `direction` until
    # it equals the requested one.
    infov = [(b.points[:, 2] >= 0) & (b.points[:, 2] <= extent_z) for b in arteries]
    c_fov = np.concatenate([b.points[m] for b, m in zip(arteries, infov)])
    r_fov = np.concatenate([b.radii[m] for b, m in zip(arteries, infov)])
    for _ in range(12):
        realised, i, j = tube_gap(c_fov, r_fov, axis, r_vein)
        delta = gap - realised
        if abs(delta) < 2e-4:
            break
        normal = axis[j] - c_fov[i]
        cos = max(float(normal[:2] @ direction) / float(np.linalg.norm(normal)), 0.3)
        axis[:, :2] += (delta / cos) * direction
    realised, i, j = tube_gap(c_fov, r_fov, axis, r_vein)
    m = infov[0]
    to_cca = tube_gap(cca.points[m], cca.radii[m], axis, r_vein)[0]
    meta = {"requested_gap_mm": gap, "min_gap_to_lumen_mm": realised, "gap_to_cca_mm": to_cca,
            "height_of_min_gap_mm": float(0.5 * (c_fov[i, 2] + axis[j, 2])), "radius_mm": r_vein,
            "side": direction.tolist(), "gap_growth_mm_per_mm": slope}
    if plaque is not None:
        d, _ = cKDTree(axis).query(plaque.surface(600))
        meta["gap_to_calcium_mm"] = float(d.min() - r_vein)
    return Branch("vein", axis, np.full(len(axis), r_vein)), meta


def _legacy_vein(draws: _Draws, r_cca: float, arteries: list[Branch], extent_z: float):
    """The legacy vein: centre at z = 0, tilt (mm per mm of z), radius, and its realised gaps."""
    direction = np.array([np.cos(draws.angle), np.sin(draws.angle)])
    vein_centre = direction * (r_cca + draws.gap + draws.r_vein)
    tilt = 0.04 * direction
    z = np.arange(-15.0, extent_z + 15.0, STEP)
    axis = np.column_stack([vein_centre + z[:, None] * tilt, z])
    infov = [(b.points[:, 2] >= 0) & (b.points[:, 2] <= extent_z) for b in arteries]
    c_fov = np.concatenate([b.points[m] for b, m in zip(arteries, infov)])
    r_fov = np.concatenate([b.radii[m] for b, m in zip(arteries, infov)])
    realised, i, j = tube_gap(c_fov, r_fov, axis, draws.r_vein)
    meta = {"gap_to_cca_mm": draws.gap, "radius_mm": draws.r_vein, "requested_gap_mm": None,
            "min_gap_to_lumen_mm": realised, "height_of_min_gap_mm": float(0.5 * (c_fov[i, 2] + axis[j, 2])),
            "side": direction.tolist()}
    return vein_centre, tilt, Branch("vein", axis, np.full(len(axis), draws.r_vein)), meta


# ------------------------------------------------------------------------------------ parameters

def rescale(value: float, source: tuple[float, float], target: tuple[float, float]) -> float:
    """``value`` moved from the range ``source`` to the same relative place in ``target``."""
    return target[0] + (value - source[0]) / (source[1] - source[0]) * (target[1] - target[0])


def _number(name: str, value, low: float | None = None, high: float | None = None, low_open: bool = False,
            high_open: bool = False) -> float | None:
    """``value`` as a float checked against [low, high] (open ends on request), or None."""
    if value is None:
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise CarotidError(f"{name} must be a number, not {value!r}") from None
    if not math.isfinite(x):
        raise CarotidError(f"{name} must be a finite number, not {value}")
    bad = False
    if low is not None:
        bad |= x <= low if low_open else x < low
    if high is not None:
        bad |= x >= high if high_open else x > high
    if bad:
        lo = "(" if low_open else "["
        hi = ")" if high_open else "]"
        raise CarotidError(f"{name} {value} is outside {lo}{'-inf' if low is None else f'{low:g}'}, "
                           f"{'inf' if high is None else f'{high:g}'}{hi}")
    return x


def _check_seed(name: str, value) -> None:
    """Raise ``CarotidError`` unless ``value`` is a non-negative integer (a bool is not one)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise CarotidError(f"{name} {value!r} must be a non-negative integer")


def _triple(name: str, value) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise CarotidError(f"{name} must be three numbers in mm, not {value!r}") from None
    if len(out) != 3 or not all(math.isfinite(v) and v > 0 for v in out):
        raise CarotidError(f"{name} {list(value)} must be three positive numbers in mm (x y z)")
    return out


def _occupancy(sdf: np.ndarray, width: float) -> np.ndarray:
    """Partial-volume fraction (0..1) from a signed distance (mm) over a ramp of ``width`` mm."""
    return np.clip(0.5 - sdf / width, 0.0, 1.0).astype(np.float32)


def bolus_level(z_mm: np.ndarray, tissue: float, proximal: float, fade: float, extent_z: float) -> np.ndarray:
    """The family's lumen level at heights ``z_mm``: ``proximal`` up to z = 10 mm, falling linearly by the
    fraction ``fade`` of the contrast over the image's height ``extent_z`` less 10 mm at either end (float32,
    ``z_mm``'s shape)."""
    ramp = np.clip((np.asarray(z_mm) - 10.0) / (extent_z - 20.0), 0.0, 1.0).astype(np.float32)
    return (tissue + (proximal - tissue) * (1.0 - fade * ramp)).astype(np.float32)


def _unit_noise(rng: np.random.Generator, shape: tuple[int, int, int]) -> np.ndarray:
    """Correlated Gaussian noise of unit standard deviation (float32)."""
    white = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 0.6)
    return white / white.std()


# ------------------------------------------------------------------------------------ the phantom

def make_phantom(stenosis: float | None = None, noise: float | None = None, seed: int = 0,
                 spacing: tuple[float, float, float] = (0.45, 0.45, 0.625),
                 extent: tuple[float, float, float] = (44.0, 44.0, 75.0),
                 blur_fwhm: float | None = None, *,
                 nascet: float | None = None,
                 vein_gap_mm: float | None = None,
                 venous_fraction: float | None = None,
                 plaque_size: float | None = None,
                 plaque_angle_deg: float | None = None,
                 plaque_offset_mm: float | None = None,
                 calcium_hu: float | None = None,
                 blur_sigma_mm: float | None = None,
                 arterial_hu: float | None = None,
                 bolus_fade: float | None = None,
                 ica_shape: str | None = None,
                 modality: str | None = None,
                 bias: float | None = None,
                 noise_seed: int | None = None) -> Phantom:
    """Generate a carotid angiogram phantom (CTA, contrast-enhanced or time-of-flight MRA) with its ground truth.

    With none of the keyword-only family parameters (``nascet`` excepted) the legacy model is used
    and ``make_phantom(stenosis, noise, seed, spacing, extent, blur_fwhm)`` returns exactly the
    arrays of earlier versions.  Any family parameter selects the family model; the others then
    default to the values the legacy model would draw or use.  New randomness comes from
    ``np.random.default_rng([seed, n])`` streams, one per feature, so that changing one option
    does not move the others.  Family ranges: see :func:`carotid.phantom.family.sample_family`.

    Parameters
    ----------
    stenosis : float, optional
        ICA stenosis as the AREA reduction at the lesion, 1 - (d_min / d_local)^2, in [0, 0.95).
        Give ``stenosis`` or ``nascet``, not both; neither: 0.7.
    noise : float, optional
        Standard deviation of the image noise: HU in CT (default 20); MR units in MR (default 4 %
        of the lumen-tissue contrast), where it is the sigma of each Rician component.
    seed : int
        Random seed (>= 0): anatomy, contrast, distractor placement and noise.
    noise_seed : int, optional
        Seed (>= 0) of the image noise alone: the same anatomy, contrast, texture and bias field
        with an independent noise draw, as a rescan of the same patient (test-retest). None: the
        noise is drawn with the anatomy, from ``seed``.
    spacing : tuple of 3 float
        Voxel size (x, y, z) in mm, e.g. (0.4, 0.4, 0.4) to (0.5, 0.5, 1.0).
    extent : tuple of 3 float
        Field of view (x, y, z) in mm; the bifurcation sits near z = 30 mm.
    blur_fwhm : float, optional
        In-plane full width at half maximum of the scanner blur in mm (1.25 x along z); default 1.
    nascet : float, optional
        ICA stenosis by NASCET, 1 - d_min / d_distal ICA (diameters), instead of ``stenosis``; it
        must be in [0, highest) where the highest value (about 0.7) keeps the area reduction below
        0.95 with the seed's bulb.  The throat radius is then exact: 1 - r_min / r_distal = nascet.
    vein_gap_mm : float, optional
        Family: smallest wall-to-wall gap (mm, > 0) between the jugular vein and the arterial lumen
        in the field of view.  The vein runs beside the CCA, bulb and proximal ICA; the gap is
        smallest at a random height and grows slowly away from it.  Realised exactly (to 0.001 mm).
    venous_fraction : float, optional
        Family: venous enhancement above tissue as a fraction of the proximal arterial one, [0, 1).
    plaque_size : float, optional
        Family: scale of the calcified plaque's semi-axes (legacy: 1 = about 1.1 x 1.4 x 2.2 mm),
        [0, 2.5]; 0: no calcium.
    plaque_angle_deg : float, optional
        Family: position of the plaque around the ICA axis in degrees (0: the legacy side, away
        from the ECA).
    plaque_offset_mm : float, optional
        Family: position of the plaque along the ICA axis relative to the throat, [-4, 4] mm.  The
        calcium always touches (within 0.05 mm) the lumen of the axis sample it sits on.
    calcium_hu : float, optional
        Family, CT only: calcium density in HU, (40, 3000] (legacy 1000).  In MR calcium is a
        signal void.
    blur_sigma_mm : float, optional
        Family: Gaussian scanner blur as a standard deviation in mm in plane (1.25 x along z, plus
        the part of the slice profile the partial-volume ramp misses on thick slices); give at
        most one of ``blur_fwhm`` and ``blur_sigma_mm``.
    arterial_hu : float, optional
        Family: proximal arterial lumen level in the image's units: HU in CT, (90, 1500]; MR
        units in MR, (400, 10000] (default drawn from 1200-2500); in time-of-flight (100, 10000]
        (default drawn from 400-1000), and the tissues' levels are fractions of it.
    bolus_fade : float, optional
        Family: fraction of the arterial enhancement above tissue lost from the proximal CCA
        (z = 10 mm) to the distal ICA (z = extent - 10 mm), [0, 1).
    ica_shape : {"smooth", "kink", "loop"}, optional
        Family: "kink" adds a sharp bend of 60-100 degrees distal to the stenosis (and a gentler
        one back), "loop" a full helical coil; both stay in the field of view, clear of the other
        vessels, the vertebra, the plaque and themselves, and keep the radius model.
    modality : {"ct", "mr", "tof"}, optional
        Family: "ct" (HU), "mr" (contrast-enhanced MR angiography: muscle 200-350, fat 1.5-2.2 times
        brighter, lumen 1200-2500, cortical bone and calcium dark, multiplicative bias field, Rician
        noise) or "tof" (time-of-flight MR angiography: as "mr", with inflowing blood 400-1000 and the
        saturated muscle at 10-20 % of it, fat at 25-45 %; see the module's docstring).
    bias : float, optional
        Family: amplitude of the smooth random multiplicative bias field (a polynomial of degree
        <= 2 spanning 1 - bias to 1 + bias over the field of view), [0, 1); default 0.3 in MR (either
        kind), and it must be 0 in CT.

    Returns
    -------
    Phantom
        ``image`` float32 (nk, nj, ni) with integer values (HU, or MR units), ``mask``, ``sdf``,
        ``labels`` on the same grid; ``info`` holds the truth description.

    Raises
    ------
    CarotidError
        On any parameter outside its range (one line saying which and why).
    """
    family_values = {"vein_gap_mm": vein_gap_mm, "venous_fraction": venous_fraction, "plaque_size": plaque_size,
                     "plaque_angle_deg": plaque_angle_deg, "plaque_offset_mm": plaque_offset_mm,
                     "calcium_hu": calcium_hu, "blur_sigma_mm": blur_sigma_mm, "arterial_hu": arterial_hu,
                     "bolus_fade": bolus_fade, "ica_shape": ica_shape, "modality": modality, "bias": bias}
    family = any(v is not None for v in family_values.values())

    # --- parameters
    if stenosis is not None and nascet is not None:
        raise CarotidError("give the stenosis either as an area reduction (stenosis) or as NASCET (nascet), not both")
    if nascet is None and stenosis is None:
        stenosis = 0.7
    if stenosis is not None:
        s_val = _number("stenosis", stenosis)
        if not 0.0 <= s_val < MAX_STENOSIS:
            raise CarotidError(f"stenosis {stenosis} must be an area fraction in [0, {MAX_STENOSIS})")
    nascet = _number("NASCET stenosis", nascet)
    _check_seed("seed", seed)
    if noise_seed is not None:
        _check_seed("noise seed", noise_seed)
    spacing = _triple("spacing", spacing)
    if max(spacing) > MAX_SPACING_MM:
        raise CarotidError(f"spacing {list(spacing)} mm: a phantom's voxels must be at most {MAX_SPACING_MM:g} mm "
                           "(coarser ones cannot resolve a carotid a few millimetres across)")
    extent = _triple("extent", extent)
    if blur_fwhm is not None and blur_sigma_mm is not None:
        raise CarotidError("give the scanner blur as blur_fwhm or as blur_sigma_mm, not both")
    blur_fwhm_v = _number("blur FWHM (mm)", blur_fwhm, 0.0, 10.0)
    blur_sigma_v = _number("blur sigma (mm)", blur_sigma_mm, 0.0, 5.0)
    modality = "ct" if modality is None else str(modality).lower()
    if modality not in MODALITIES:
        raise CarotidError(f"modality {modality!r} must be one of {', '.join(MODALITIES)}")
    mr = modality in MAGNITUDE
    tof = modality == "tof"
    shape_kind = "smooth" if ica_shape is None else str(ica_shape).lower()
    if shape_kind not in ICA_SHAPES:
        raise CarotidError(f"ica_shape {ica_shape!r} must be one of {', '.join(ICA_SHAPES)}")
    gap_v = _number("vein gap (mm)", vein_gap_mm, 0.0, 10.0, low_open=True)
    vf_v = _number("venous fraction", venous_fraction, 0.0, 1.0, high_open=True)
    size_v = _number("plaque size", plaque_size, 0.0, 2.5)
    angle_v = _number("plaque angle (degrees)", plaque_angle_deg)
    offset_v = _number("plaque offset (mm)", plaque_offset_mm, -4.0, 4.0)
    if calcium_hu is not None and mr:
        raise CarotidError("calcium_hu applies to CT only: in MR calcium is a signal void")
    calcium_v = _number("calcium (HU)", calcium_hu, TISSUE_HU, 3000.0, low_open=True)
    arterial_v = (_number("arterial level (MR units)", arterial_hu, 100.0 if tof else 400.0, 10000.0,
                          low_open=True) if mr else
                  _number("arterial level (HU)", arterial_hu, TISSUE_HU + 50.0, 1500.0, low_open=True))
    fade_v = _number("bolus fade", bolus_fade, 0.0, 1.0, high_open=True)
    bias_v = _number("bias", bias, 0.0, 1.0, high_open=True)
    if bias_v and not mr:
        raise CarotidError("bias (a multiplicative MR intensity field) must be 0 in CT")
    noise_v = _number("noise", noise, 0.0, MAX_NOISE)
    if noise_v is None and not mr:
        noise_v = 20.0
    shape = tuple(int(round(e / s)) for e, s in zip(extent[::-1], spacing[::-1]))
    if min(shape) < 1 or math.prod(shape) > MAX_VOXELS:
        raise CarotidError(f"extent {list(extent)} mm at spacing {list(spacing)} mm gives {list(shape)} voxels; "
                           f"need at least one and at most {MAX_VOXELS:,} voxels")

    parameters = {"stenosis": stenosis, "nascet": nascet, "noise": noise, "seed": int(seed), "noise_seed": noise_seed,
                  "spacing": list(spacing), "extent": list(extent), "blur_fwhm": blur_fwhm, **family_values}
    parameters = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in parameters.items() if v is not None}

    # --- anatomy
    rng = np.random.default_rng(seed)
    draws = _legacy_draws(rng)
    # the noise's streams: the anatomy's own, or independent ones for a rescan
    noise_rng = rng if noise_seed is None else np.random.default_rng([seed, 7, noise_seed])
    rician_rng = np.random.default_rng([seed, 6] if noise_seed is None else [seed, 8, noise_seed])
    branches, desc, k, radius_of = _arteries(draws, None if stenosis is None else s_val, nascet, seed)
    if family:
        if shape_kind != "smooth" and extent[2] < 60.0:
            raise CarotidError(f"an ICA {shape_kind} needs a field of view at least 60 mm high, not {extent[2]:g}")
        if extent[2] < draws.bif[2] + 12.0:
            raise CarotidError(f"extent z {extent[2]:g} mm is too short: the family model needs the ICA and ECA "
                               f"seeds above the bifurcation (at least {draws.bif[2] + 12.0:.0f} mm)")

    origin = (-extent[0] / 2, -extent[1] / 2, 0.0)
    grid = Volume(np.zeros(shape, np.float32), spacing, origin)
    kji = np.indices(shape, dtype=np.float32).reshape(3, -1).T
    xyz = grid.index_to_world(kji)
    del kji

    ica = branches[1]
    s_ica = ica.arclength
    plaque = _plaque(ica, s_ica, draws.s_st, draws.semi0, 1.0 if size_v is None else size_v,
                     angle_v or 0.0, offset_v or 0.0)
    bone_centre = np.array([-5.0, 16.5]) + draws.bone_jitter
    shape_meta = {"shape": "smooth"}
    vein_rng = np.random.default_rng([seed, 1])
    vein_dir = None
    if family:
        vein_angle = np.deg2rad(vein_rng.uniform(-75.0, 0.0))
        vein_dir = np.array([np.cos(vein_angle), np.sin(vein_angle)])
        if shape_kind != "smooth":
            ica, shape_meta = _tortuous_ica(ica, radius_of, draws.s_st, shape_kind, np.random.default_rng([seed, 2]),
                                            [branches[0], branches[2]], plaque, bone_centre, vein_dir, extent)
            branches[1] = ica

    lumen = union_of_spheres_sdf(xyz, branches)
    if plaque is not None:
        calcium = plaque.sdf(xyz)
        lumen = np.maximum(lumen, -calcium)
    else:
        calcium = None

    if family:
        follow = len(ica.points) - 1 if shape_kind == "smooth" else int(
            np.searchsorted(ica.arclength, shape_meta["start_arclength_mm"]))
        z0 = vein_rng.uniform(5.0, draws.bif[2] + 8.0)
        slope = vein_rng.uniform(0.01, 0.05)
        vein_branch, vein_meta = _follow_vein(branches, follow, plaque, vein_dir, draws.r_vein,
                                              draws.gap if gap_v is None else gap_v, z0, slope, extent[2])
        vein = tube_sdf(xyz, vein_branch.points, draws.r_vein)
        axis = vein_branch.points
        low = (axis[:, 2] > -draws.r_vein) & (axis[:, 2] < extent[2] + draws.r_vein)
        vein_meta["gap_to_vertebra_mm"] = float(np.min(np.linalg.norm(axis[low, :2] - bone_centre, axis=1))
                                                - 7.5 - draws.r_vein)
    else:
        vein_centre, tilt, vein_branch, vein_meta = _legacy_vein(draws, branches[0].radii[0], branches, extent[2])
        vein = cylinder_sdf(xyz, vein_centre, tilt, draws.r_vein)

    bone_outer = cylinder_sdf(xyz, bone_centre, np.zeros(2), 7.5)
    bone_inner = bone_outer + 1.6

    # --- intensities
    if not family:
        z = xyz[:, 2]
        hu_prox, hu_dist, venous = draws.hu_prox, draws.hu_dist, draws.venous
        arterial = hu_prox + (hu_dist - hu_prox) * np.clip((z - 10.0) / 55.0, 0.0, 1.0)
        del xyz
        width = float(np.mean(spacing))
        hu = np.full(lumen.shape, TISSUE_HU, np.float32)
        for sdf, value in ((bone_outer, CORTICAL_HU), (bone_inner, MARROW_HU), (vein, venous),
                           (lumen, arterial), (calcium, CALCIUM_HU)):
            occ = _occupancy(sdf, width)
            hu += occ * (value - hu)
        hu = hu.reshape(shape)
        texture = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 6.0)
        hu += TISSUE_HU * 0.25 * texture / max(float(texture.std()), 1e-6) * (hu < 100)

        sigma_mm = np.array([1.25, 1.0, 1.0]) * (1.0 if blur_fwhm_v is None else blur_fwhm_v) / 2.355
        hu = ndimage.gaussian_filter(hu, sigma_mm / grid.spacing_kji)
        if noise_v > 0:
            white = ndimage.gaussian_filter(noise_rng.standard_normal(shape).astype(np.float32), 0.6)
            hu += noise_v * white / white.std()
        image = np.round(hu).astype(np.float32)
        fat_occ = None
        levels = {"units": "HU", "tissue": TISSUE_HU, "arterial_proximal": hu_prox, "arterial_distal": hu_dist,
                  "venous": venous, "venous_fraction": (venous - TISSUE_HU) / (hu_prox - TISSUE_HU),
                  "bolus_fade": 1.0 - (hu_dist - TISSUE_HU) / (hu_prox - TISSUE_HU), "calcium": CALCIUM_HU,
                  "cortical_bone": CORTICAL_HU, "marrow": MARROW_HU, "fat": None}
        sigma_info = sigma_mm
        field_info = None
        calcium_level = CALCIUM_HU
    else:
        level_rng = np.random.default_rng([seed, 3])
        tissue_mr, fat_ratio, arterial_mr = (level_rng.uniform(*MR_TISSUE), level_rng.uniform(*MR_FAT_RATIO),
                                             level_rng.uniform(*MR_ARTERIAL))
        fat_ct = level_rng.uniform(-110.0, -70.0)
        if tof:  # the same draws, placed in the time-of-flight ranges (tissues relative to the inflow)
            arterial_mr = arterial_v if arterial_v is not None else rescale(arterial_mr, MR_ARTERIAL, TOF_ARTERIAL)
            muscle, fat_fraction = rescale(tissue_mr, MR_TISSUE, TOF_TISSUE), rescale(fat_ratio, MR_FAT_RATIO, TOF_FAT)
            tissue_mr, fat_ratio = arterial_mr * muscle, fat_fraction / muscle
        if mr:
            tissue = tissue_mr
            fat = tissue * fat_ratio
            prox = arterial_v if arterial_v is not None else arterial_mr
            cortical, marrow, calcium_level = 0.08 * tissue, 0.7 * fat, 0.08 * tissue
        else:
            tissue, fat = TISSUE_HU, fat_ct
            prox = arterial_v if arterial_v is not None else draws.hu_prox
            cortical, marrow = CORTICAL_HU, MARROW_HU
            calcium_level = calcium_v if calcium_v is not None else CALCIUM_HU
        legacy_fraction = (draws.venous - TISSUE_HU) / (draws.hu_prox - TISSUE_HU)
        legacy_fade = 1.0 - (draws.hu_dist - TISSUE_HU) / (draws.hu_prox - TISSUE_HU)
        fraction = legacy_fraction if vf_v is None else vf_v
        fade = legacy_fade if fade_v is None else fade_v
        if prox <= tissue:
            raise CarotidError(f"arterial level {prox:g} must be above the tissue level {tissue:g}")
        venous = tissue + fraction * (prox - tissue)
        arterial = bolus_level(xyz[:, 2], tissue, prox, fade, extent[2])
        del xyz
        spacing_kji = grid.spacing_kji
        texture = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 2.7 / spacing_kji)
        texture /= max(float(texture.std()), 1e-6)
        fat_field = ndimage.gaussian_filter(np.random.default_rng([seed, 4]).standard_normal(shape)
                                            .astype(np.float32), 3.0 / spacing_kji)
        fat_field /= max(float(fat_field.std()), 1e-6)
        fat_occ = np.clip(0.5 + (fat_field - 0.7) / 0.25, 0.0, 1.0).reshape(-1)
        del fat_field
        if mr:
            base = tissue * (1.0 + 0.06 * texture.reshape(-1))
            fat_value = fat * (1.0 + 0.04 * texture.reshape(-1))
        else:
            base = tissue + 0.25 * TISSUE_HU * texture.reshape(-1)
            fat_value = fat + 0.25 * TISSUE_HU * texture.reshape(-1)
        del texture
        img = base + fat_occ * (fat_value - base)
        del base, fat_value
        width = float(np.mean(spacing))
        for sdf, value in ((bone_outer, cortical), (bone_inner, marrow), (vein, venous), (lumen, arterial),
                           (calcium, calcium_level)):
            if sdf is not None:
                occ = _occupancy(sdf, width)
                img += occ * (value - img)
        del arterial
        img = img.reshape(shape).astype(np.float32)
        sigma = blur_sigma_v if blur_sigma_v is not None else (1.0 if blur_fwhm_v is None else blur_fwhm_v) / 2.355
        slice_extra = max(spacing[2] ** 2 - width ** 2, 0.0) / 12.0 if sigma > 0 else 0.0
        sigma_info = np.array([math.sqrt((1.25 * sigma) ** 2 + slice_extra), sigma, sigma])
        img = ndimage.gaussian_filter(img, sigma_info / spacing_kji)
        field_info = None
        amplitude = (MR_BIAS if bias_v is None else bias_v) if mr else 0.0
        if amplitude > 0:
            bias_map = bias_field(shape, np.random.default_rng([seed, 5]), amplitude)
            img *= bias_map
            field_info = {"amplitude": amplitude, "min": float(bias_map.min()), "max": float(bias_map.max())}
            del bias_map
        if noise_v is None:
            noise_v = 0.04 * (prox - tissue)
        if noise_v > 0:
            img += noise_v * _unit_noise(noise_rng, shape)
            if mr:  # Rician magnitude: the second (imaginary) component
                img = np.sqrt(img ** 2 + (noise_v * _unit_noise(rician_rng, shape)) ** 2)
        elif mr:
            img = np.abs(img)
        image = np.round(img).astype(np.float32)
        del img
        levels = {"units": "MR arbitrary units" if mr else "HU", "tissue": tissue, "arterial_proximal": prox,
                  "arterial_distal": tissue + (1.0 - fade) * (prox - tissue), "venous": venous,
                  "venous_fraction": fraction, "bolus_fade": fade,
                  "calcium": None if plaque is None else calcium_level, "cortical_bone": cortical, "marrow": marrow,
                  "fat": fat}

    # --- truth
    labels = np.zeros(shape, np.uint8)
    if fat_occ is not None:
        labels[(fat_occ >= 0.5).reshape(shape)] = LABELS["fat"]
        del fat_occ
    labels[(bone_outer < 0).reshape(shape)] = LABELS["bone"]
    labels[(vein < 0).reshape(shape)] = LABELS["vein"]
    labels[(lumen < 0).reshape(shape)] = LABELS["lumen"]
    if calcium is not None:
        labels[(calcium < 0).reshape(shape)] = LABELS["calcium"]

    if not family:
        seeds = {
            "CCA": branches[0].points[np.argmin(np.abs(branches[0].points[:, 2] - 10.0))].tolist(),
            "ICA": ica.points[np.argmin(np.abs(ica.points[:, 2] - 60.0))].tolist(),
            "ECA": branches[2].points[np.argmin(np.abs(branches[2].points[:, 2] - 60.0))].tolist(),
        }
    else:
        z_seed = max(extent[2] - 15.0, draws.bif[2] + 10.0)
        distal = np.arange(len(ica.points))
        if shape_kind != "smooth":
            end = shape_meta["end_arclength_mm"]
            distal = distal[ica.arclength >= end]
            z_seed = max(z_seed, float(ica.points[distal[0], 2]) + 3.0)
        z_seed = min(z_seed, extent[2] - 3.0)
        seeds = {
            "CCA": branches[0].points[np.argmin(np.abs(branches[0].points[:, 2] - 10.0))].tolist(),
            "ICA": ica.points[distal[np.argmin(np.abs(ica.points[distal, 2] - z_seed))]].tolist(),
            "ECA": branches[2].points[np.argmin(np.abs(branches[2].points[:, 2] - z_seed))].tolist(),
        }

    info = {
        "parameters": parameters,
        "model": "family" if family else "legacy",
        "modality": modality,
        **desc,
        "seeds_mm": seeds,
        "levels": levels,
        "arterial_level": levels["arterial_proximal"],
        "venous_level": levels["venous"],
        "calcium_hu": None if (mr or plaque is None) else calcium_level,
        "vein": vein_meta,
        "ica_shape": shape_meta,
        "blur_sigma_mm": {"in_plane": float(sigma_info[1]), "z": float(sigma_info[0])},
        "bias_field": field_info,
        "noise": noise_v,
        "calcium_centre_mm": None if plaque is None else plaque.centre.tolist(),
        "plaque": None if plaque is None else {
            "centre_mm": plaque.centre.tolist(), "semi_axes_mm": plaque.semi.tolist(),
            "axes": plaque.axes.tolist(), "arclength_from_bifurcation_mm": float(s_ica[plaque.k]),
            "offset_from_throat_mm": float(s_ica[plaque.k] - desc["stenosis"]["arclength_from_bifurcation_mm"])},
        "labels": LABELS,
    }
    if not mr:
        info["contrast_hu"] = {"arterial_proximal": levels["arterial_proximal"],
                               "arterial_distal": levels["arterial_distal"], "venous": levels["venous"],
                               "tissue": levels["tissue"], "calcium": levels["calcium"],
                               "cortical_bone": levels["cortical_bone"]}
    fov = f"a field of view of {extent[0]:g} x {extent[1]:g} x {extent[2]:g} mm"
    landmarks = {**{f"{name} seed": xyz for name, xyz in seeds.items()}, "bifurcation": desc["bifurcation_mm"],
                 "ICA stenosis": desc["stenosis"]["location_mm"]}
    outside = [name for name, xyz in landmarks.items() if not grid.contains(np.asarray(xyz, float))]
    if outside:
        warnings.warn(f"{fov} does not hold the phantom's {', '.join(outside)}: the image does not show "
                      f"{'them' if len(outside) > 1 else 'it'}", CarotidWarning, stacklevel=2)
    return Phantom(image=grid.with_array(image),
                   mask=grid.with_array((labels == LABELS["lumen"]).astype(np.uint8)),
                   sdf=grid.with_array(np.clip(lumen, -10, 10).reshape(shape).astype(np.float32)),
                   labels=grid.with_array(labels), branches=branches, info=_jsonable(info), vein=vein_branch)


def _jsonable(obj):
    """``obj`` with numpy scalars and arrays turned into Python numbers and lists."""
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def write_phantom(phantom: Phantom, out_dir: str | Path) -> Path:
    """Write a phantom to ``out_dir`` (replaced as a whole, atomically).

    Files: ``image.nii.gz`` (int16: HU in CT, unitless signal in MR), ``truth_mask.nii.gz``
    (uint8), ``truth_sdf.nii.gz`` (float32 mm), ``labels.nii.gz`` (uint8), ``centerlines.json``
    (per artery: points in mm and radii in mm) and ``phantom.json`` (stenosis degrees,
    bifurcation, seeds, levels, vein gap, parameters).
    """
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        write_image(phantom.image.with_array(phantom.image.array.astype(np.int16)), tmp / "image.nii.gz")
        write_image(phantom.mask, tmp / "truth_mask.nii.gz")
        write_image(phantom.sdf, tmp / "truth_sdf.nii.gz")
        write_image(phantom.labels, tmp / "labels.nii.gz")
        write_json({b.name: {"points_mm": np.round(b.points, 4).tolist(), "radius_mm": np.round(b.radii, 4).tolist()}
                    for b in phantom.branches}, tmp / "centerlines.json")
        write_json(phantom.info, tmp / "phantom.json")
    return out_dir
