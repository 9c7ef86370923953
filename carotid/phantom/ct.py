"""A synthetic neck CT angiogram of a stenosed carotid bifurcation with known truth.

The phantom is built so that segmentation is tested where it fails in practice:

* a common (CCA), internal (ICA, with a sinus bulb) and external (ECA) carotid
  artery, with a graded ICA stenosis in the distal bulb;
* arterial contrast that fades along the neck as the bolus passes (about 450 HU
  proximally to about 320 HU distally);
* an internal jugular vein 1-2 mm from the CCA wall, with venous contrast not
  far below the arterial one (220-300 HU);
* a vertebra (cortical ring of ~1000 HU around ~280 HU marrow);
* a calcified plaque (~1000 HU) touching the lumen at the stenosis;
* partial volume, a Gaussian scanner blur (about 1 mm FWHM in plane), correlated
  noise and anisotropic voxels (0.45 x 0.45 x 0.625 mm by default).

Values are Hounsfield units; the image is stored as int16 like a scanner's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.io import Volume, atomic_dir, write_image, write_json
from carotid.phantom.geometry import (Branch, cylinder_sdf, ellipsoid_sdf, perpendicular, raised_cosine,
                                      spline_axis, union_of_spheres_sdf)

LABELS = {"background": 0, "lumen": 1, "vein": 2, "bone": 3, "calcium": 4}

TISSUE_HU = 40.0
CORTICAL_HU = 1000.0
MARROW_HU = 280.0


@dataclass
class Phantom:
    """A generated phantom: the CT image, the truth and its description.

    Attributes
    ----------
    image : Volume
        float32 HU.
    mask : Volume
        uint8 ground-truth lumen (1 inside).
    sdf : Volume
        float32 signed distance to the true lumen wall in mm (negative inside).
    labels : Volume
        uint8 structure labels, see ``LABELS``.
    branches : list of Branch
        True centerlines with lumen radii.
    info : dict
        JSON-ready description: stenosis degrees, bifurcation, seeds, parameters.
    """

    image: Volume
    mask: Volume
    sdf: Volume
    labels: Volume
    branches: list[Branch] = field(default_factory=list)
    info: dict = field(default_factory=dict)


def _branches(rng: np.random.Generator, stenosis: float) -> tuple[list[Branch], dict]:
    """The three arterial branches and the stenosis description."""
    r_cca = rng.uniform(3.0, 3.4)
    r_ica = rng.uniform(2.4, 2.7)
    r_eca = rng.uniform(1.8, 2.1)
    bif = np.array([0.0, 0.0, 30.0]) + rng.uniform(-1.0, 1.0, 3) * [1.0, 1.0, 2.0]
    spread = rng.uniform(0.9, 1.1)

    cca = spline_axis([[0.0, 0.0, -10.0], [0.0, 0.0, 10.0], bif])
    ica_axis = spline_axis(bif + np.array([[0, 0, 0], [1.6, 1.9, 6], [3.6, 4.2, 16], [4.6, 5.0, 30],
                                           [5.0, 5.2, 70]]) * [spread, spread, 1])
    eca_axis = spline_axis(bif + np.array([[0, 0, 0], [-1.8, -2.0, 6], [-3.8, -4.0, 16], [-5.0, -4.6, 30],
                                           [-5.6, -4.8, 70]]) * [spread, spread, 1])

    cca_b = Branch("CCA", cca, np.full(len(cca), r_cca))
    s = Branch("ICA", ica_axis, np.zeros(len(ica_axis))).arclength
    r_bulb = 1.12 * r_cca
    bulb = np.where(s < 5.0, 1.0, raised_cosine(s, 5.0, 12.0))
    healthy = r_ica + (r_bulb - r_ica) * bulb
    s_st = rng.uniform(10.0, 13.0)
    r_local = float(np.interp(s_st, s, healthy))
    depth = 1.0 - np.sqrt(1.0 - stenosis)  # area reduction -> radius reduction at the lesion
    radii = healthy * (1.0 - depth * raised_cosine(s, s_st, 4.0))
    ica_b = Branch("ICA", ica_axis, radii)

    s_e = Branch("ECA", eca_axis, np.zeros(len(eca_axis))).arclength
    eca_b = Branch("ECA", eca_axis, r_eca + 0.3 * raised_cosine(s_e, 0.0, 8.0))

    k = int(np.argmin(np.abs(s - s_st)))
    r_min = float(radii[k])
    sten = {
        "area_reduction": float(stenosis),
        "nascet": 1.0 - r_min / r_ica,
        "ecst": 1.0 - r_min / r_local,
        "location_mm": ica_axis[k].tolist(),
        "arclength_from_bifurcation_mm": float(s[k]),
        "min_diameter_mm": 2 * r_min,
        "distal_diameter_mm": 2 * r_ica,
        "local_diameter_mm": 2 * r_local,
    }
    return [cca_b, ica_b, eca_b], {"bifurcation_mm": bif.tolist(), "stenosis": sten, "_k": k}


def _occupancy(sdf: np.ndarray, width: float) -> np.ndarray:
    """Partial-volume fraction (0..1) from a signed distance (mm) over a ramp of ``width`` mm."""
    return np.clip(0.5 - sdf / width, 0.0, 1.0).astype(np.float32)


def make_phantom(stenosis: float = 0.7, noise: float = 20.0, seed: int = 0,
                 spacing: tuple[float, float, float] = (0.45, 0.45, 0.625),
                 extent: tuple[float, float, float] = (44.0, 44.0, 75.0),
                 blur_fwhm: float = 1.0) -> Phantom:
    """Generate a carotid CTA phantom with its ground truth.

    Parameters
    ----------
    stenosis : float
        ICA area reduction at the lesion, 0 <= stenosis < 0.95.
    noise : float
        Standard deviation of the image noise in HU.
    seed : int
        Random seed: anatomy, contrast, distractor placement and noise.
    spacing : tuple of 3 float
        Voxel size (x, y, z) in mm.
    extent : tuple of 3 float
        Field of view (x, y, z) in mm; the bifurcation sits near z = 30 mm.
    blur_fwhm : float
        In-plane full width at half maximum of the scanner blur in mm (1.25 x along z).

    Returns
    -------
    Phantom
    """
    if not 0.0 <= stenosis < 0.95:
        raise CarotidError(f"stenosis {stenosis} must be an area fraction in [0, 0.95)")
    if noise < 0:
        raise CarotidError(f"noise {noise} HU must not be negative")
    rng = np.random.default_rng(seed)
    branches, desc = _branches(rng, stenosis)

    spacing = tuple(float(s) for s in spacing)
    shape = tuple(int(round(e / s)) for e, s in zip(extent[::-1], spacing[::-1]))
    origin = (-extent[0] / 2, -extent[1] / 2, 0.0)
    grid = Volume(np.zeros(shape, np.float32), spacing, origin)
    kji = np.indices(shape, dtype=np.float32).reshape(3, -1).T
    xyz = grid.index_to_world(kji)
    del kji

    lumen = union_of_spheres_sdf(xyz, branches)

    # Calcified plaque: an ellipsoid touching the lumen at the stenosis, on the side away from the ECA.
    ica = branches[1]
    k = desc.pop("_k")
    t = ica.points[min(k + 1, len(ica.points) - 1)] - ica.points[max(k - 1, 0)]
    t /= np.linalg.norm(t)
    u = perpendicular(t, np.array([1.0, 0.3, 0.0]))
    semi = np.array([rng.uniform(0.9, 1.3), 1.4, 2.2])
    axes = np.stack([u, np.cross(t, u), t])
    calc_centre = ica.points[k] + (ica.radii[k] + semi[0] + 0.05) * u
    calcium = ellipsoid_sdf(xyz, calc_centre, axes, semi)
    lumen = np.maximum(lumen, -calcium)

    # Jugular vein: lateral-anterior of the CCA, gap of 1-2 mm at the CCA.
    gap = rng.uniform(1.0, 2.0)
    r_vein = rng.uniform(4.0, 5.0)
    angle = np.deg2rad(rng.uniform(-70.0, -50.0))
    direction = np.array([np.cos(angle), np.sin(angle)])
    r_cca = branches[0].radii[0]
    vein_centre = direction * (r_cca + gap + r_vein)
    vein = cylinder_sdf(xyz, vein_centre, 0.04 * direction, r_vein)

    # Vertebra: cortical ring around marrow, posterior-medial.
    bone_centre = np.array([-5.0, 16.5]) + rng.uniform(-1.0, 1.0, 2)
    bone_outer = cylinder_sdf(xyz, bone_centre, np.zeros(2), 7.5)
    bone_inner = bone_outer + 1.6

    z = xyz[:, 2]
    hu_prox, hu_dist = rng.uniform(430.0, 480.0), rng.uniform(300.0, 340.0)
    arterial = hu_prox + (hu_dist - hu_prox) * np.clip((z - 10.0) / 55.0, 0.0, 1.0)
    venous = rng.uniform(220.0, 300.0)
    del xyz

    width = float(np.mean(spacing))
    hu = np.full(lumen.shape, TISSUE_HU, np.float32)
    for sdf, value in ((bone_outer, CORTICAL_HU), (bone_inner, MARROW_HU), (vein, venous),
                       (lumen, arterial), (calcium, 1000.0)):
        occ = _occupancy(sdf, width)
        hu += occ * (value - hu)
    hu = hu.reshape(shape)
    texture = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 6.0)
    hu += TISSUE_HU * 0.25 * texture / max(float(texture.std()), 1e-6) * (hu < 100)

    sigma_mm = np.array([1.25, 1.0, 1.0]) * blur_fwhm / 2.355
    hu = ndimage.gaussian_filter(hu, sigma_mm / grid.spacing_kji)
    if noise > 0:
        white = ndimage.gaussian_filter(rng.standard_normal(shape).astype(np.float32), 0.6)
        hu += noise * white / white.std()
    hu = np.round(hu).astype(np.float32)

    labels = np.zeros(shape, np.uint8)
    labels[(bone_outer < 0).reshape(shape)] = LABELS["bone"]
    labels[(vein < 0).reshape(shape)] = LABELS["vein"]
    labels[(lumen < 0).reshape(shape)] = LABELS["lumen"]
    labels[(calcium < 0).reshape(shape)] = LABELS["calcium"]

    seeds = {
        "CCA": branches[0].points[np.argmin(np.abs(branches[0].points[:, 2] - 10.0))].tolist(),
        "ICA": ica.points[np.argmin(np.abs(ica.points[:, 2] - 60.0))].tolist(),
        "ECA": branches[2].points[np.argmin(np.abs(branches[2].points[:, 2] - 60.0))].tolist(),
    }
    info = {
        "parameters": {"stenosis": stenosis, "noise_hu": noise, "seed": seed, "spacing_mm": list(spacing),
                       "extent_mm": list(extent), "blur_fwhm_mm": blur_fwhm},
        **desc,
        "seeds_mm": seeds,
        "contrast_hu": {"arterial_proximal": hu_prox, "arterial_distal": hu_dist, "venous": venous,
                        "tissue": TISSUE_HU, "calcium": 1000.0, "cortical_bone": CORTICAL_HU},
        "vein": {"gap_to_cca_mm": gap, "radius_mm": r_vein},
        "calcium_centre_mm": calc_centre.tolist(),
        "labels": LABELS,
    }
    return Phantom(image=grid.with_array(hu),
                   mask=grid.with_array((labels == LABELS["lumen"]).astype(np.uint8)),
                   sdf=grid.with_array(np.clip(lumen, -10, 10).reshape(shape).astype(np.float32)),
                   labels=grid.with_array(labels), branches=branches, info=info)


def write_phantom(phantom: Phantom, out_dir: str | Path) -> Path:
    """Write a phantom to ``out_dir`` (replaced as a whole, atomically).

    Files: ``image.nii.gz`` (int16 HU), ``truth_mask.nii.gz`` (uint8),
    ``truth_sdf.nii.gz`` (float32 mm), ``labels.nii.gz`` (uint8),
    ``centerlines.json`` (per branch: points in mm and radii in mm) and
    ``phantom.json`` (stenosis degrees, bifurcation, seeds, parameters).
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
