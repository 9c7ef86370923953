"""The synthetic CTA phantom: its truth is self-consistent and its distractors are where promised."""

import functools
import hashlib
import json

import numpy as np
import pytest
from scipy import ndimage

from carotid.cli import main
from carotid.errors import CarotidError, CarotidWarning
from carotid.phantom import FAMILY_RANGES, LABELS, make_phantom, sample_family, write_phantom
from carotid.phantom.geometry import tube_sdf, union_of_spheres_sdf
from conftest import phantom


def test_truth_is_consistent():
    p = phantom()
    assert np.array_equal(p.mask.array > 0, p.sdf.array < 0)
    assert np.array_equal(p.mask.array > 0, p.labels.array == LABELS["lumen"])
    assert p.image.array.dtype == np.float32 and p.image.spacing == (0.45, 0.45, 0.625)
    # Arterial contrast is inside the lumen, fading along the neck (z).
    lumen = p.image.array[p.sdf.array < -1.0]
    assert 250 < np.median(lumen) < 500
    z = np.nonzero(p.sdf.array < -1.0)[0]
    assert np.median(lumen[z < 30]) > np.median(lumen[z > 90]) + 60


def test_stenosis_degree_matches_the_geometry():
    p = phantom(0.75, 10.0, 3)
    ica = p.branches[1]
    sten = p.info["stenosis"]
    assert sten["area_reduction"] == 0.75
    r_min = ica.radii[np.argmin(np.abs(ica.arclength - sten["arclength_from_bifurcation_mm"]))]
    assert np.isclose(1 - (2 * r_min / sten["local_diameter_mm"]) ** 2, 0.75, atol=0.01)
    assert np.isclose(sten["nascet"], 1 - sten["min_diameter_mm"] / sten["distal_diameter_mm"])
    # The narrowest lumen cross-section of the truth mask near the lesion has the stenosed area.
    centre = p.image.world_to_index(np.array(sten["location_mm"]))
    k = int(round(centre[0]))
    ks = range(k - 6, k + 7)
    # The ICA is tilted: its axial cross-section area is the true area / cos(tilt).
    tangent = np.gradient(ica.points, axis=0)[np.argmin(np.linalg.norm(ica.points - sten["location_mm"], axis=1))]
    cos_tilt = abs(tangent[2]) / np.linalg.norm(tangent)
    areas = []
    for kk in ks:
        labels, _ = ndimage.label(p.mask.array[kk])
        axis_point = ica.points[np.argmin(np.abs(ica.points[:, 2] - kk * 0.625))]
        j, i = np.round(p.image.world_to_index(axis_point)[1:]).astype(int)
        if labels[j, i]:
            areas.append(np.count_nonzero(labels == labels[j, i]) * 0.45 * 0.45 * cos_tilt)
    expected = np.pi * (sten["min_diameter_mm"] / 2) ** 2
    assert abs(min(areas) - expected) < 0.2 * expected


def test_distractors_are_present_and_placed():
    p = phantom()
    labels = p.labels.array
    for name in ("vein", "bone", "calcium"):
        assert np.count_nonzero(labels == LABELS[name]) > 50, name
    hu = p.image.array
    assert 180 < np.median(hu[ndimage.binary_erosion(labels == LABELS["vein"], iterations=3)]) < 320
    # The vein runs 1-2 mm from the CCA wall: measured between the true surfaces in the lower neck.
    low = slice(0, 40)
    gap = ndimage.distance_transform_edt(labels[low] != LABELS["lumen"], sampling=(0.625, 0.45, 0.45))
    measured = gap[labels[low] == LABELS["vein"]].min()
    assert abs(measured - p.info["vein"]["gap_to_cca_mm"]) < 0.5
    assert 1.0 <= p.info["vein"]["gap_to_cca_mm"] <= 2.0
    # The calcium touches the lumen.
    grown = ndimage.binary_dilation(labels == LABELS["calcium"], iterations=2)
    assert np.any(grown & (labels == LABELS["lumen"]))


def test_noise_and_seed_are_honoured():
    a = make_phantom(0.6, 0.0, 5, extent=(30, 30, 40))
    b = make_phantom(0.6, 0.0, 5, extent=(30, 30, 40))
    c = make_phantom(0.6, 30.0, 5, extent=(30, 30, 40))
    assert np.array_equal(a.image.array, b.image.array)
    tissue = (a.labels.array == 0) & (np.abs(a.sdf.array) > 5)
    tissue &= ndimage.binary_erosion(a.labels.array == 0, iterations=8)
    assert 25 < np.std(c.image.array[tissue] - a.image.array[tissue]) < 35


@pytest.mark.parametrize("kwargs", [dict(stenosis=0.6, noise=30.0, seed=5),
                                    dict(modality="mr", noise=150.0, seed=5, spacing=(0.6, 0.6, 0.8),
                                         extent=(30, 30, 48))])
def test_noise_seed_rescans_the_same_anatomy(kwargs):
    """A noise seed redraws the noise alone: anatomy, levels, texture and bias field stay; the noise is as
    strong as the first draw's and independent of it, in MR both Rician components (the second one is what
    the dark cortical bone shows)."""
    kwargs = {"extent": (30, 30, 40), **kwargs}
    first, again, other = (make_phantom(**kwargs, noise_seed=n) for n in (None, None, 1))
    clean = make_phantom(**dict(kwargs, noise=1e-6))
    assert np.array_equal(first.image.array, again.image.array)
    for name in ("mask", "sdf", "labels"):
        assert np.array_equal(getattr(first, name).array, getattr(other, name).array)
    tissue = (first.labels.array == 0) & ndimage.binary_erosion(first.labels.array == 0, iterations=8)
    lumen = first.sdf.array < -1.5
    noise = kwargs["noise"]
    for region in (tissue, lumen):
        a = first.image.array[region] - clean.image.array[region]
        b = other.image.array[region] - clean.image.array[region]
        assert 0.85 * noise < np.std(b) < 1.15 * noise
        assert abs(np.corrcoef(a, b)[0, 1]) < 0.1
        assert abs(np.mean(b) - np.mean(a)) < 0.1 * noise
    if kwargs.get("modality") == "mr":
        bone = first.labels.array == LABELS["bone"]
        a, b = (p.image.array[bone] - clean.image.array[bone] for p in (first, other))
        assert abs(np.corrcoef(a, b)[0, 1]) < 0.2
    assert other.info["parameters"]["noise_seed"] == 1 and "noise_seed" not in first.info["parameters"]
    assert np.array_equal(make_phantom(**json.loads(json.dumps(other.info["parameters"]))).image.array,
                          other.image.array)


def test_bad_parameters_are_refused():
    with pytest.raises(CarotidError):
        make_phantom(stenosis=0.99)
    with pytest.raises(CarotidError):
        make_phantom(noise=-1)
    bad = [dict(spacing=(0, 0.5, 0.5)), dict(spacing=(0.5, 0.5, float("nan"))), dict(extent=(40, -1, 60)),
           dict(vein_gap_mm=-0.5), dict(vein_gap_mm=0), dict(venous_fraction=1.0), dict(venous_fraction=-0.1),
           dict(stenosis=0.5, nascet=0.3), dict(nascet=0.95), dict(nascet=-0.1), dict(blur_fwhm=1, blur_sigma_mm=0.5),
           dict(blur_sigma_mm=-1), dict(bolus_fade=1.0), dict(ica_shape="spiral"), dict(modality="pet"),
           dict(modality="mr", calcium_hu=800), dict(bias=0.2), dict(modality="mr", bias=1.0),
           dict(plaque_size=-1), dict(plaque_offset_mm=9), dict(arterial_hu=20), dict(calcium_hu=-5), dict(seed=-1),
           dict(noise_seed=-1), dict(noise_seed=1.5), dict(ica_shape="loop", extent=(44, 44, 50)),
           dict(spacing=(10.0, 10.0, 10.0))]
    for kwargs in bad:
        with pytest.raises(CarotidError):
            make_phantom(**kwargs)
    with pytest.raises(CarotidError, match="outside"):
        make_phantom(noise=1e9)  # saturated int16 before the bound
    for kwargs in (dict(stenosis=float("nan")), dict(nascet=float("inf")), dict(plaque_angle_deg=float("nan"))):
        with pytest.raises(CarotidError, match="must be a finite number"):
            make_phantom(**kwargs)
    with pytest.warns(CarotidWarning, match="does not hold the phantom's CCA seed, ICA seed, ECA seed, bifurcation"):
        make_phantom(extent=(2, 2, 2), spacing=(0.5, 0.5, 0.5))
    with pytest.warns(CarotidWarning, match="does not hold the phantom's ICA seed, ECA seed, ICA stenosis"):
        make_phantom(extent=(20, 20, 30), spacing=(0.6, 0.6, 0.8), seed=1)


def _digest(array):
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]


def test_default_output_is_unchanged():
    """The legacy phantoms are bit for bit those of the version before the family model (digests taken
    from that version)."""
    expected = {
        (0.7, 20.0, 1): ("e18e3dc49edb8441", "505adbe818706b12", "97aefeeda57c111c", "b9ae4bcf7c9a6416"),
        (0.6, 0.0, 5): ("9f8eead8cab21f83", "f604984348d73dc2", "e64f728fbcd1c140", "8a78a4be7b6a6550"),
    }
    for (stenosis, noise, seed), digests in expected.items():
        p = phantom() if seed == 1 else make_phantom(stenosis, noise, seed, extent=(30, 30, 40))
        assert tuple(_digest(a.array) for a in (p.image, p.mask, p.sdf, p.labels)) == digests
        assert p.info["model"] == "legacy" and p.info["modality"] == "ct"
    p = phantom()
    branches = np.concatenate([np.c_[b.points, b.radii] for b in p.branches])
    assert _digest(branches) == "ef67d4d7de75cc63"
    assert p.info["vein"]["requested_gap_mm"] is None and 1.0 <= p.info["vein"]["gap_to_cca_mm"] <= 2.0
    # The parameters regenerate it.
    again = make_phantom(**json.loads(json.dumps(p.info["parameters"])))
    assert np.array_equal(again.image.array, p.image.array)


@functools.lru_cache(maxsize=None)
def family_phantom(**kwargs):
    return make_phantom(**kwargs)


def _world(volume):
    kji = np.indices(volume.array.shape).reshape(3, -1).T
    return volume.index_to_world(kji)


def test_vein_gap_is_exact_with_thick_slices():
    gap = 0.3
    p = family_phantom(stenosis=0.6, seed=11, vein_gap_mm=gap, spacing=(0.5, 0.5, 1.0), noise=15.0)
    vein = p.info["vein"]
    assert p.info["model"] == "family" and p.image.spacing == (0.5, 0.5, 1.0)
    assert abs(vein["min_gap_to_lumen_mm"] - gap) < 0.15
    assert abs(vein["min_gap_to_lumen_mm"] - gap) < 0.005  # in fact exact
    assert 0.0 <= vein["height_of_min_gap_mm"] <= 75.0
    # Independently, from the true signed distances at the voxel centres: sdf_lumen + sdf_vein >= gap
    # everywhere, with equality on the segment between the closest points.
    vein_sdf = tube_sdf(_world(p.sdf), p.vein.points, p.vein.radii[0]).reshape(p.sdf.array.shape)
    total = p.sdf.array + vein_sdf
    assert gap - 0.002 < total.min() < gap + 0.05
    assert not np.any((p.sdf.array < 0) & (vein_sdf < 0))
    # In the voxels too: the closest vein and lumen voxel centres are one in-plane voxel apart.
    labels = p.labels.array
    edt = ndimage.distance_transform_edt(labels != LABELS["lumen"], sampling=p.image.spacing_kji)
    assert edt[labels == LABELS["vein"]].min() <= gap + 0.5
    # The vein is beside the CCA / bulb: the gap to the CCA alone grows by less than 1 mm.
    assert vein["gap_to_cca_mm"] < gap + 1.0


def test_levels_in_the_image_match_the_request():
    p = family_phantom(seed=4, arterial_hu=350.0, venous_fraction=0.7, bolus_fade=0.2, noise=10.0,
                       calcium_hu=900.0, plaque_offset_mm=2.0, plaque_angle_deg=90.0, plaque_size=1.3,
                       spacing=(0.6, 0.6, 0.6), extent=(40.0, 40.0, 70.0))
    lv = p.info["levels"]
    assert lv["arterial_proximal"] == 350.0 and lv["venous"] == pytest.approx(40 + 0.7 * 310)
    assert lv["arterial_distal"] == pytest.approx(40 + 0.8 * 310) and p.info["calcium_hu"] == 900.0
    img, sdf = p.image.array, p.sdf.array
    z = _world(p.sdf)[:, 2].reshape(sdf.shape)
    expected = 40.0 + 310.0 * (1.0 - 0.2 * np.clip((z - 10.0) / 50.0, 0.0, 1.0))
    core = sdf < -1.2
    assert abs(np.median((img - expected)[core])) < 6.0
    assert abs(np.median(img[core & (z < 12)]) - 350.0) < 8.0
    assert abs(np.median(img[core & (z > 60)]) - 288.0) < 8.0
    vein_core = tube_sdf(_world(p.sdf), p.vein.points, p.vein.radii[0]).reshape(sdf.shape) < -1.5
    assert abs(np.median(img[vein_core]) - (40 + 0.7 * 310)) < 6.0
    calcium = p.labels.array == LABELS["calcium"]
    assert np.max(img[calcium]) > 600
    # The plaque sits where asked and touches the lumen.
    plaque = p.info["plaque"]
    assert abs(plaque["offset_from_throat_mm"] - 2.0) < 0.1
    assert plaque["semi_axes_mm"][1:] == pytest.approx([1.4 * 1.3, 2.2 * 1.3])
    ica = p.branches[1]
    k = int(np.argmin(np.abs(ica.arclength - plaque["arclength_from_bifurcation_mm"])))
    radial = np.asarray(plaque["centre_mm"]) - ica.points[k]
    assert np.linalg.norm(radial) == pytest.approx(ica.radii[k] + plaque["semi_axes_mm"][0] + 0.05, abs=1e-6)
    assert np.any(ndimage.binary_dilation(calcium, iterations=1) & (p.labels.array == LABELS["lumen"]))
    legacy_side = make_phantom(seed=4, plaque_offset_mm=2.0, spacing=(1.0, 1.0, 1.0), extent=(40.0, 40.0, 70.0))
    u0 = np.asarray(legacy_side.info["plaque"]["axes"][0])
    assert abs(np.dot(u0, np.asarray(plaque["axes"][0]))) < 1e-6  # a quarter turn around the axis
    fat = ndimage.binary_erosion(p.labels.array == LABELS["fat"], iterations=2)
    assert np.median(img[fat]) < -50


def test_nascet_round_trips():
    small = dict(seed=2, noise=0.0, spacing=(1.0, 1.0, 1.0), extent=(24.0, 24.0, 50.0))
    p = make_phantom(nascet=0.5, **small)
    ica = p.branches[1]
    sten = p.info["stenosis"]
    k = int(np.argmin(np.abs(ica.arclength - sten["arclength_from_bifurcation_mm"])))
    assert 1 - ica.radii[k] / ica.radii[-1] == pytest.approx(0.5, abs=1e-9)
    assert sten["nascet"] == pytest.approx(0.5, abs=1e-9) and sten["specified_as"] == "nascet"
    lesion = np.abs(ica.arclength - ica.arclength[k]) < 4.0
    assert 1 - ica.radii[lesion].min() / ica.radii[-1] == pytest.approx(0.5, abs=0.01)
    # Its area reduction, given back as `stenosis`, makes the same lesion.
    area = sten["area_reduction"]
    assert 1 - (sten["min_diameter_mm"] / sten["local_diameter_mm"]) ** 2 == pytest.approx(area, abs=0.01)
    q = make_phantom(stenosis=area, **small)
    assert q.info["stenosis"]["nascet"] == pytest.approx(0.5, abs=0.005)
    assert np.allclose(q.branches[1].radii, ica.radii, atol=0.01)
    with pytest.raises(CarotidError, match="NASCET"):
        make_phantom(nascet=0.85, **small)


def _block_medians(image, keep, blocks=3):
    out = []
    for part in np.array_split(np.arange(image.shape[0]), blocks):
        for rows in np.array_split(np.arange(image.shape[1]), blocks):
            for cols in np.array_split(np.arange(image.shape[2]), blocks):
                box = np.ix_(part, rows, cols)
                if keep[box].sum() > 200:
                    out.append(np.median(image[box][keep[box]]))
    return np.array(out)


def test_mr_mode_is_not_hu_and_has_a_bias_field():
    flat = family_phantom(seed=7, modality="mr", plaque_size=1.5, bias=0.0, spacing=(0.6, 0.6, 0.8))
    biased = family_phantom(seed=7, modality="mr", plaque_size=1.5, spacing=(0.6, 0.6, 0.8))
    assert biased.info["bias_field"]["amplitude"] == 0.3 and flat.info["bias_field"] is None
    assert biased.info["levels"]["units"] == "MR arbitrary units" and "contrast_hu" not in biased.info
    for p in (flat, biased):
        img, labels, sdf = p.image.array, p.labels.array, p.sdf.array
        assert img.dtype == np.float32 and img.min() >= 0  # magnitude data: no air at -1000, no negative HU
        tissue = ndimage.binary_erosion(labels == LABELS["background"], iterations=3)
        muscle = np.median(img[tissue])
        assert 150 < muscle < 500
        assert 3.0 < np.median(img[sdf < -1.0]) / muscle < 12.0
        fat = ndimage.binary_erosion(labels == LABELS["fat"], iterations=2)
        assert np.median(img[fat]) > 1.3 * muscle
        centre = np.round(p.image.world_to_index(np.array(p.info["calcium_centre_mm"]))).astype(int)
        assert img[tuple(centre)] < 0.5 * muscle  # calcium is a signal void
        bone = labels == LABELS["bone"]
        cortex = bone & ~ndimage.binary_erosion(bone, iterations=2)
        assert np.percentile(img[cortex], 5) < 0.5 * muscle  # the cortical ring is dark too
    # The bias field: tissue is uniform without it; with it, it varies smoothly by +-30 % over the field of
    # view, which the muscle level, block by block, shows (the same draws otherwise).
    field = biased.info["bias_field"]
    assert field["min"] == pytest.approx(0.7, abs=1e-4) and field["max"] == pytest.approx(1.3, abs=1e-4)
    keep = ndimage.binary_erosion(flat.labels.array == LABELS["background"], iterations=3)
    level_flat = _block_medians(flat.image.array, keep)
    level_biased = _block_medians(biased.image.array, keep)
    assert level_flat.max() / level_flat.min() < 1.12
    assert (level_biased / level_flat).max() / (level_biased / level_flat).min() > 1.15
    assert np.abs(level_biased / level_flat - 1).max() > 0.12


def test_time_of_flight_mode_saturates_the_tissues_and_keeps_the_anatomy():
    """Time-of-flight MRA: muscle at 10-20 % of the inflowing blood, fat at 25-45 %, calcium and cortical bone
    void, a bias field; the anatomy and the other draws of a family case stay those of its CT or MR scan."""
    kwargs = sample_family(7, modality="tof")
    assert kwargs["modality"] == "tof" and 400 <= kwargs["arterial_hu"] <= 1000 and "calcium_hu" not in kwargs
    for key in ("stenosis", "vein_gap_mm", "venous_fraction", "plaque_size", "ica_shape", "bolus_fade"):
        assert kwargs[key] == sample_family(7)[key] == sample_family(7, modality="mr")[key], key
    kwargs.update(spacing=(0.6, 0.6, 0.8), noise=5.0, bias=0.0, plaque_size=1.5)
    p = family_phantom(**kwargs)
    assert p.info["modality"] == "tof" and p.info["levels"]["units"] == "MR arbitrary units"
    img, labels, sdf = p.image.array, p.labels.array, p.sdf.array
    arterial = p.info["levels"]["arterial_proximal"]
    muscle = np.median(img[ndimage.binary_erosion(labels == LABELS["background"], iterations=3)])
    fat = np.median(img[ndimage.binary_erosion(labels == LABELS["fat"], iterations=2)])
    assert 0.1 * arterial * 0.9 < muscle < 0.2 * arterial * 1.1
    assert 0.25 * arterial * 0.9 < fat < 0.45 * arterial * 1.1 and fat > 1.2 * muscle
    lumen = np.median(img[sdf < -1.0])
    assert muscle < fat < lumen <= arterial * 1.05
    centre = np.round(p.image.world_to_index(np.array(p.info["calcium_centre_mm"]))).astype(int)
    assert img[tuple(centre)] < 0.5 * muscle
    # never drawn, only forced; an MR draw of the same case is contrast-enhanced
    assert all(sample_family(s)["modality"] in ("ct", "mr") for s in range(60))
    with pytest.raises(CarotidError, match="modality"):
        sample_family(3, modality="pet")
    with pytest.raises(CarotidError, match="calcium"):
        make_phantom(modality="tof", calcium_hu=800, extent=(20, 20, 40))


@pytest.mark.parametrize("shape,seed", [("kink", 5), ("loop", 6), ("kink", 21), ("loop", 8)])
def test_kink_and_loop_stay_in_view_and_connected(shape, seed):
    p = family_phantom(ica_shape=shape, seed=seed, spacing=(0.6, 0.6, 0.6))
    extent = np.array(p.info["parameters"]["extent"])
    meta = p.info["ica_shape"]
    cca, ica, eca = p.branches
    s = ica.arclength
    assert meta["shape"] == shape
    assert meta["start_arclength_mm"] > p.info["stenosis"]["arclength_from_bifurcation_mm"] + 4
    # In the field of view.
    infov = (ica.points[:, 2] >= 0) & (ica.points[:, 2] <= extent[2])
    assert np.all(np.abs(ica.points[infov, :2]) + ica.radii[infov, None] <= extent[:2] / 2)
    # Not self-intersecting: parts of the axis more than 12 mm apart along it keep their walls apart.
    i, j = np.triu_indices(len(s), 1)
    far = s[j] - s[i] > 12.0
    gaps = np.linalg.norm(ica.points[i[far]] - ica.points[j[far]], axis=1) - ica.radii[i[far]] - ica.radii[j[far]]
    assert gaps.min() > 0.5
    # The shape is what it claims.
    part = (s >= meta["start_arclength_mm"]) & (s <= meta["end_arclength_mm"])
    tangent = np.gradient(ica.points, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    t0 = tangent[np.argmax(part)]
    turn = np.degrees(np.arccos(np.clip(tangent[part] @ t0, -1, 1)))
    if shape == "kink":
        assert 60 <= turn.max() <= 101 and abs(turn.max() - meta["angle_deg"]) < 2
    else:
        u1 = np.asarray(meta["bend_direction"])
        u2 = np.cross(t0, u1)
        azimuth = np.unwrap(np.arctan2(tangent[part] @ u2, tangent[part] @ u1))
        assert abs(abs(azimuth[-1] - azimuth[0]) - 2 * np.pi) < 0.2
    # Seeds inside the true lumen; the ICA seed on the distal axis beyond the kink or coil.
    for name, seed_mm in p.info["seeds_mm"].items():
        kji = np.round(p.sdf.world_to_index(np.array(seed_mm))).astype(int)
        assert p.sdf.array[tuple(kji)] < -1.0, name
    k_seed = int(np.argmin(np.linalg.norm(ica.points - p.info["seeds_mm"]["ICA"], axis=1)))
    assert s[k_seed] > meta["end_arclength_mm"] and p.info["seeds_mm"]["ICA"][2] < extent[2] - 2
    # The true lumen of the ICA is one connected piece from the bifurcation to the distal seed.
    xyz = _world(p.sdf)
    own = union_of_spheres_sdf(xyz, [ica]) <= union_of_spheres_sdf(xyz, [cca, eca])
    ica_lumen = (p.mask.array > 0) & own.reshape(p.mask.array.shape)
    pieces, _ = ndimage.label(ica_lumen, structure=np.ones((3, 3, 3)))
    path = (s > 3.0) & (s <= s[k_seed])
    kji = np.round(p.sdf.world_to_index(ica.points[path])).astype(int)
    along = pieces[tuple(kji.T)]
    assert np.all(along > 0) and len(np.unique(along)) == 1


def test_sample_family_covers_its_ranges():
    draws = [sample_family(seed) for seed in range(200)]
    assert sample_family(17) == draws[17] and json.loads(json.dumps(draws[17])) == draws[17]

    def values(key, rows=draws):
        return np.array([d[key] for d in rows if key in d], float)

    def covers(key, low, high, rows=draws):
        v = values(key, rows)
        width = high - low
        assert low - 1e-9 <= v.min() < low + 0.1 * width and high - 0.1 * width < v.max() <= high + 1e-9, key

    R = FAMILY_RANGES
    for key in ("stenosis", "blur_sigma_mm", "vein_gap_mm", "venous_fraction", "bolus_fade"):
        covers(key, *R[key])
    ct = [d for d in draws if d["modality"] == "ct"]
    mr = [d for d in draws if d["modality"] == "mr"]
    assert 0.12 < len(mr) / len(draws) < 0.28
    covers("arterial_hu", *R["arterial_hu"], rows=ct)
    covers("arterial_hu", *R["arterial_mr"], rows=mr)
    covers("noise", *R["noise_ct_hu"], rows=ct)
    covers("calcium_hu", *R["calcium_hu"], rows=ct)
    assert all(d["calcium_hu"] >= d["arterial_hu"] + 50 - 0.1 for d in ct if "calcium_hu" in d)
    assert all("calcium_hu" not in d and 0.15 <= d["bias"] <= 0.4 for d in mr)
    # MR noise: the same contrast-to-noise ratios as the CT draws (lumen over tissue of about 275).
    cnr_ct = [(d["arterial_hu"] - 40) / d["noise"] for d in ct]
    cnr_mr = [(d["arterial_hu"] - 275) / d["noise"] for d in mr]
    assert min(cnr_ct) / 2 < np.median(cnr_mr) < 2 * max(cnr_ct) and min(cnr_mr) > 3
    no_plaque = [d for d in draws if d["plaque_size"] == 0]
    assert 0.07 < len(no_plaque) / len(draws) < 0.25
    covers("plaque_size", *R["plaque_size"], rows=[d for d in draws if d["plaque_size"] > 0])
    covers("plaque_angle_deg", *R["plaque_angle_deg"])
    covers("plaque_offset_mm", *R["plaque_offset_mm"])
    spacing = np.array([d["spacing"] for d in draws])
    assert np.all(spacing[:, 0] == spacing[:, 1]) and np.all(spacing[:, 2] >= spacing[:, 0])
    assert 0.4 <= spacing.min() < 0.41 and 0.49 < spacing[:, 0].max() <= 0.5 and 0.95 < spacing[:, 2].max() <= 1.0
    assert np.any(spacing[:, 2] - spacing[:, 0] < 0.05)  # near-isotropic draws too
    shapes = [d["ica_shape"] for d in draws]
    for shape, share in R["ica_shape"].items():
        assert abs(shapes.count(shape) / len(draws) - share) < 0.08, shape
    # Forcing the modality keeps the anatomy and the other draws.
    forced = sample_family(3, modality="mr")
    assert forced["modality"] == "mr" and forced["ica_shape"] == draws[3]["ica_shape"]
    assert forced["vein_gap_mm"] == draws[3]["vein_gap_mm"] and forced["stenosis"] == draws[3]["stenosis"]
    assert all(sample_family(s, modality="ct")["modality"] == "ct" for s in range(20))


def test_family_phantoms_regenerate_from_their_json(tmp_path):
    kwargs = sample_family(19)
    kwargs["spacing"] = [0.8, 0.8, 0.8]
    p = make_phantom(**kwargs)
    out = write_phantom(p, tmp_path / "f")
    info = json.loads((out / "phantom.json").read_text())
    assert info["parameters"]["ica_shape"] == kwargs["ica_shape"] and info["model"] == "family"
    for key in ("min_gap_to_lumen_mm", "requested_gap_mm", "gap_to_cca_mm"):
        assert key in info["vein"]
    for key in ("arterial_proximal", "venous", "tissue", "venous_fraction", "bolus_fade"):
        assert key in info["levels"]
    again = make_phantom(**info["parameters"])
    assert np.array_equal(again.image.array, p.image.array) and np.array_equal(again.labels.array, p.labels.array)


def test_cli_phantom(tmp_path, capsys):
    out = tmp_path / "p"
    assert main(["phantom", str(out), "--family", "--seed", "3", "--spacing", "0.8", "0.8", "0.8",
                 "--vein-gap", "0.4", "--ica-shape", "kink", "--modality", "ct"]) == 0
    line = capsys.readouterr().out.strip()
    assert "area stenosis" in line and "NASCET" in line and "\n" not in line
    info = json.loads((out / "phantom.json").read_text())
    assert info["parameters"]["vein_gap_mm"] == 0.4 and info["ica_shape"]["shape"] == "kink"
    assert info["parameters"]["stenosis"] == sample_family(3)["stenosis"]
    assert abs(info["vein"]["min_gap_to_lumen_mm"] - 0.4) < 0.01
    assert main(["phantom", str(tmp_path / "n"), "--nascet", "0.5", "--extent", "24", "24", "50"]) == 0
    assert "NASCET 50%" in capsys.readouterr().out
    assert main(["phantom", str(tmp_path / "t"), "--family", "--seed", "3", "--modality", "tof",
                 "--spacing", "0.8", "0.8", "0.8"]) == 0
    assert capsys.readouterr().out.startswith(f"phantom written to {tmp_path / 't'} (TOF")
    assert json.loads((tmp_path / "t" / "phantom.json").read_text())["parameters"]["modality"] == "tof"
    for argv in (["--spacing", "0", "0.5", "0.5"], ["--vein-gap", "-1"], ["--venous-fraction", "1"],
                 ["--nascet", "0.99"], ["--stenosis", "0.97"], ["--modality", "mr", "--calcium-hu", "500"],
                 ["--noise-seed", "-1"]):
        assert main(["phantom", str(tmp_path / "bad"), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("carotid: error:") and "\n" not in err and "Traceback" not in err
        assert not (tmp_path / "bad").exists()
    assert main(["phantom", str(tmp_path / "bad"), "--nascet", "0.5", "--area-stenosis", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("carotid: error:") and "\n" not in err  # a usage error: one line, not the usage block


def test_written_files(tmp_path):
    p = phantom()
    out = write_phantom(p, tmp_path / "ph")
    names = sorted(f.name for f in out.iterdir())
    assert names == ["centerlines.json", "image.nii.gz", "labels.nii.gz", "phantom.json", "truth_mask.nii.gz",
                     "truth_sdf.nii.gz"]
    info = json.loads((out / "phantom.json").read_text())
    assert set(info["seeds_mm"]) == {"CCA", "ICA", "ECA"} and "nascet" in info["stenosis"]
    lines = json.loads((out / "centerlines.json").read_text())
    assert set(lines) == {"CCA", "ICA", "ECA"} and len(lines["ICA"]["radius_mm"]) == len(lines["ICA"]["points_mm"])
