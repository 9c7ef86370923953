"""Segmentation on the inputs that broke it: a touching vein, a vein as bright as the artery beside it, MR
intensities (contrast-enhanced and time-of-flight), a stop point, a fading bolus, a string-sign stenosis, a
chamber, a chamber behind an open valve, a seed beside a calcified flap in coarse voxels.

Each test also runs the segmentation with its mechanism switched off and checks that the case then fails,
so that the case really needs the mechanism (a case any method passes would prove nothing).
"""

import functools

import numpy as np
import pytest
from scipy import ndimage

from carotid.centerline import compute_centerlines, extract
from carotid.centerline.axes import section_profile
from carotid.errors import CarotidError
from carotid.io import Volume
from carotid.phantom import LABELS, make_phantom, sample_family
from carotid.segment import SegmentParameters, calcium, segment
from carotid.segment.intensity import estimate_from_sample, local_level
from carotid.segment.metrics import dice


@functools.lru_cache(maxsize=None)
def family_phantom(**kwargs):
    return make_phantom(**kwargs)


def vein_case(venous_fraction, blur, seed):
    """A CTA whose jugular vein runs 0.5 mm from the artery."""
    return family_phantom(stenosis=0.6, noise=25.0, seed=seed, vein_gap_mm=0.5, venous_fraction=venous_fraction,
                          blur_sigma_mm=blur, plaque_size=0.0)


def scores(p, result):
    """Dice with the truth and the vein taken, as a fraction of the true lumen volume."""
    seg = result.mask.array > 0
    truth = p.mask.array > 0
    return dice(seg, truth), np.count_nonzero(seg & (p.labels.array == LABELS["vein"])) / np.count_nonzero(truth)


def cca_seed(p):
    return [p.info["seeds_mm"]["CCA"]]


def test_vein_half_a_millimetre_away_stays_out():
    """Vein at 80 % of the arterial enhancement, 0.5 mm away, 0.7 mm blur: the gap barely dips."""
    p = vein_case(0.8, 0.7, 5)
    assert p.info["vein"]["min_gap_to_lumen_mm"] == pytest.approx(0.5, abs=0.01)
    overlap, vein = scores(p, segment(p.image, seeds_xyz=cca_seed(p)))
    assert overlap >= 0.92 and vein < 0.01
    # The paper's GPF alone (no barrier, no under-enhanced neighbours, no companions) runs into the vein.
    _, vein_off = scores(p, segment(p.image, seeds_xyz=cca_seed(p),
                                    params=SegmentParameters(barrier=0, plateau=0, companion_depth=0)))
    assert vein_off > 0.5


def test_vein_as_bright_as_the_artery_beside_it_stays_out():
    """Vein at 85 %, 0.5 mm away: too bright to tell apart by intensity, and the blurred gap stays above every
    threshold; the captured region's basin beside the artery is a companion and is kept out."""
    p = vein_case(0.85, 0.6, 3)
    result = segment(p.image, seeds_xyz=cca_seed(p))
    overlap, vein = scores(p, result)
    assert overlap >= 0.92 and vein < 0.01
    assert sum(found["companions"] for found in result.report["chambers"]) == 1
    # Without the companions the front runs along the whole vein.
    _, vein_off = scores(p, segment(p.image, seeds_xyz=cca_seed(p), params=SegmentParameters(companion_depth=0)))
    assert vein_off > 0.5


def test_a_seedless_start_seeds_each_branch_and_keeps_a_touching_vein_out(monkeypatch):
    """The vein of ``test_vein_half_a_millimetre_away_stays_out`` without any seed: the forking start places
    one seed in the CCA and one near the end of each branch, and the seeded path's exclusions act."""
    p = vein_case(0.8, 0.7, 5)
    result = segment(p.image)
    overlap, vein = scores(p, result)
    assert overlap >= 0.92 and vein < 0.01
    seeds = np.round(p.image.world_to_index(np.asarray(result.report["seeds_mm"]))).astype(int)
    assert len(seeds) == 3 and np.all(p.mask.array[tuple(seeds.T)] > 0)
    # Started from the forking core alone, as before the seeds, the front runs along the vein.
    monkeypatch.setattr("carotid.segment.segmentation.fork_seeds", lambda region, spacing: None)
    _, vein_off = scores(p, segment(p.image))
    assert vein_off > 0.5


def test_stop_point_keeps_a_vein_out():
    """The same vein with the companions switched off, where the front runs along it
    (``test_vein_as_bright_as_the_artery_beside_it_stays_out``): the user marks it with a stop point."""
    p = vein_case(0.85, 0.6, 3)
    off = SegmentParameters(companion_depth=0)
    stop = p.vein.points[len(p.vein.points) // 3]
    result = segment(p.image, seeds_xyz=cca_seed(p), stops_xyz=[stop], params=off)
    overlap, vein = scores(p, result)
    assert overlap >= 0.92 and vein < 0.01
    assert result.report["stops_mm"] == [stop.tolist()]
    with pytest.raises(CarotidError, match="stop point"):
        segment(p.image, seeds_xyz=cca_seed(p), stops_xyz=[[0.0, 0.0, 900.0]], params=off)


def test_mr_angiogram_with_defaults():
    """CE-MRA: unitless intensities, bias field, dark calcium; defaults and one seed per branch."""
    p = family_phantom(stenosis=0.6, noise=30.0, seed=3, modality="mr", bias=0.3)
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]
    result = segment(p.image, seeds_xyz=seeds)
    overlap, vein = scores(p, result)
    assert overlap >= 0.92 and vein < 0.01
    intensity = result.report["intensity"]
    lumen_truth = np.median(p.image.array[p.sdf.array < -1.0])
    assert intensity["window_source"] == "estimated"
    assert intensity["lumen"] == pytest.approx(lumen_truth, rel=0.15)
    assert intensity["window"][0] < intensity["background"] < intensity["lumen"] < intensity["window"][1]
    # The HU window the segmentation used to have fails: the front vanishes or takes the wrong structures.
    try:
        wrong = segment(p.image, seeds_xyz=seeds, params=SegmentParameters(window=[-100.0, 550.0]))
    except CarotidError as exc:
        assert "vanished" in str(exc)
    else:
        assert scores(p, wrong)[0] < 0.5


def test_time_of_flight_angiogram_with_defaults():
    """TOF-MRA: saturated muscle at a tenth of the inflowing blood, fat at a third of it lying against the artery,
    a bias field; defaults and one seed per branch take the lumen and neither the fat nor the vein."""
    p = family_phantom(stenosis=0.6, noise=35.0, seed=3, modality="tof", bias=0.3)
    truth, labels = p.mask.array > 0, p.labels.array
    near = ndimage.distance_transform_edt(~truth, sampling=p.image.spacing_kji) < 2.0
    assert np.count_nonzero(near & (labels == LABELS["fat"])) > 0.3 * np.count_nonzero(truth), \
        "premise: fat lies against the artery"
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]
    result = segment(p.image, seeds_xyz=seeds)
    overlap, vein = scores(p, result)
    seg = result.mask.array > 0
    assert overlap >= 0.95 and vein < 0.01
    assert np.count_nonzero(seg & (labels == LABELS["fat"])) < 0.02 * np.count_nonzero(truth)
    intensity = result.report["intensity"]
    assert intensity["window"][0] < intensity["background"] < p.info["levels"]["fat"] < intensity["lumen"]
    # The HU window the segmentation used to have folds the blood above 550 back down: the front vanishes.
    with pytest.raises(CarotidError, match="vanished"):
        segment(p.image, seeds_xyz=seeds, params=SegmentParameters(window=[-100.0, 550.0]))


def test_fat_against_the_artery_in_a_time_of_flight_angiogram_stays_out():
    """TOF-MRA of family case 29: fat lobules at 25-45 % of the inflowing blood touch the distal ICA and ECA, and
    a bias field of +-37 % lifts them towards half of the lumen's level.  The half-level barrier, whose local
    maximum reaches 3 mm, holds a band about 2 mm thick beyond the blurred wall; reaching 1.5 mm, the band is
    about half a millimetre thick, the noise opens it, and the front fills the lobules."""
    kwargs = sample_family(29, modality="tof")
    p = family_phantom(**{k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()})
    truth, fat = p.mask.array > 0, p.labels.array == LABELS["fat"]
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]

    def fat_taken(result):
        return np.count_nonzero((result.mask.array > 0) & fat) / np.count_nonzero(truth)

    result = segment(p.image, seeds_xyz=seeds)
    assert scores(p, result)[0] >= 0.95 and fat_taken(result) < 0.02
    assert fat_taken(segment(p.image, seeds_xyz=seeds, params=SegmentParameters(barrier_reach_mm=1.5))) > 0.1


def test_lumen_level_is_followed_along_a_fading_bolus():
    """The arterial level falls by 30 % from the CCA to the distal ICA; the followed level tracks it."""
    p = family_phantom(stenosis=0.5, noise=15.0, seed=2, bolus_fade=0.3, plaque_size=0.0)
    core = p.sdf.array < -1.0
    level = local_level(p.image.array, core, p.image.spacing_kji, 10.0, float(np.median(p.image.array[core])))
    k = np.indices(core.shape)[0]
    low, high = core & (k < 20), core & (k > k[core].max() - 10)
    for part in (low, high):
        assert np.median(level[part]) == pytest.approx(np.median(p.image.array[part]), rel=0.1)
    levels = p.info["levels"]
    drop = (levels["arterial_distal"] - levels["tissue"]) / (levels["arterial_proximal"] - levels["tissue"])
    assert drop < 0.75
    assert np.median(level[high]) < 0.9 * np.median(level[low])


def test_a_kinked_ica_under_an_mr_bias_field_stays_one_piece(monkeypatch):
    """Family case 71 (MR angiogram, kinked ICA, a 39 % bias field): the kink, which runs across the slices
    between the CCA and ICA seeds, is a basin of the captured region's contrast of its own, and the axis
    read across it makes its surface with the vessel face across.  A companion may not join seeds
    (``barrier.linking_seeds``): taken for one, the kink was cut out and the ICA's seed left in a piece of its
    own (Dice 0.88)."""
    from carotid.segment import barrier

    p = make_phantom(**sample_family(71))
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]
    result = segment(p.image, seeds_xyz=seeds)
    assert ndimage.label(result.mask.array > 0)[1] == 1
    assert dice(result.mask.array > 0, p.mask.array > 0) >= 0.92
    # Mutation: a companion may join seeds.
    monkeypatch.setattr(barrier, "linking_seeds", lambda *args: set())
    cut = segment(p.image, seeds_xyz=seeds)
    assert ndimage.label(cut.mask.array > 0)[1] > 1
    assert dice(cut.mask.array > 0, p.mask.array > 0) < 0.9


def test_intensity_model_from_a_seed_and_its_refusals():
    p = family_phantom(stenosis=0.5, noise=15.0, seed=2, bolus_fade=0.3, plaque_size=0.0)
    image, spacing = p.image.array, p.image.spacing_kji
    sample = p.sdf.array < -1.5
    sample[20:] = False
    model = estimate_from_sample(image, sample, spacing, "seeds")
    assert model.lumen == pytest.approx(p.info["levels"]["arterial_proximal"], rel=0.05)
    assert abs(model.background - p.info["levels"]["tissue"]) < 60.0
    tissue = (p.labels.array == LABELS["background"]) & (p.sdf.array > 8.0)
    with pytest.raises(CarotidError, match="not brighter"):
        estimate_from_sample(image, tissue & (np.indices(image.shape)[0] == 10), spacing, "seeds")


def flap_scan(noise_seed):
    """A coarse CT (1.5 mm voxels) of an aorta-like tube (radius 12 mm, true lumen 450 HU) split by a 1.5 mm
    dissection flap (100 HU, calcified over 8 mm at 2500 HU) from a false lumen (250 HU), blurred by 0.8 mm;
    and its true lumen.  Built three times finer and averaged over each voxel."""
    shape, fine, h = (24, 40, 40), 3, 0.5
    k, j, i = np.indices(tuple(n * fine for n in shape), dtype=np.float32)
    y, x = (j + 0.5) * h - 30.0, (i + 0.5) * h - 30.0
    inside = np.hypot(x, y) < 12.0
    image = np.where(x < -25.0, -100.0, 40.0).astype(np.float32)
    image[inside] = np.where(x[inside] < 2.0, 450.0, 250.0)
    flap = inside & (np.abs(x - 2.0) < 0.75)
    image[flap] = np.where(np.abs(y[flap]) < 4.0, 2500.0, 100.0)
    image = ndimage.gaussian_filter(image, 0.8 / h)

    def coarse(a):
        return a.reshape(shape[0], fine, shape[1], fine, shape[2], fine).mean(axis=(1, 3, 5))

    image = coarse(image) + np.random.default_rng(noise_seed).normal(0.0, 20.0, shape)
    return Volume(image.astype(np.float32), (1.5, 1.5, 1.5), (0.0, 0.0, 0.0)), coarse(inside & (x < 1.25)) > 0.5


def test_a_seed_beside_a_calcified_flap_in_coarse_voxels(monkeypatch):
    """A 1.5 mm seed sphere in 1.5 mm voxels holds one voxel: the lumen level of one voxel, with no spread,
    misplaces the background (the CTA's seed beside its flap read Dice 0.78 or 0.84 as it moved 0.06 mm).
    The sample is drawn from a ball of at least two voxels' radius (``sample_radius``)."""
    from carotid.segment import segmentation

    image, truth = flap_scan(0)
    seeds = [image.index_to_world(np.array([[12.0, 20.0, i]])) for i in (16, 17, 18)]  # 3-6 mm from the flap
    for seed in seeds:
        assert dice(segment(image, seeds_xyz=seed).mask.array > 0, truth) > 0.9
    monkeypatch.setattr(segmentation, "sample_radius", lambda radius_mm, spacing_kji: radius_mm)
    worst = 1.0
    for seed in seeds:
        try:
            worst = min(worst, dice(segment(image, seeds_xyz=seed).mask.array > 0, truth))
        except CarotidError:
            worst = 0.0
    assert worst < 0.85


def test_the_lumen_sample_leaves_calcium_out():
    """Otsu's upper class of lumen, tissue and calcium is calcium; in CT the voxels above ``CT_NOT_LUMEN_HU``
    go first, unless they are the sample's majority (a lumen enhanced above it)."""
    from carotid.segment.intensity import CT_NOT_LUMEN_HU, lumen_ceiling
    from carotid.segment.segmentation import lumen_sample

    rng = np.random.default_rng(0)
    image = np.full((4, 10, 10), -100.0, np.float32)  # fat: a CT image
    region = np.zeros(image.shape, bool)
    region[1:3, 2:8, 2:8] = True
    values = np.concatenate([rng.normal(450.0, 20.0, 50), rng.uniform(1000.0, 1700.0, 12), np.full(10, 40.0)])
    image[region] = values.astype(np.float32)
    assert lumen_ceiling(image) == CT_NOT_LUMEN_HU and lumen_ceiling(image + 200.0) == np.inf  # CT, magnitude MR
    lumen = region & (np.abs(image - 450.0) < 100.0)
    assert np.array_equal(lumen_sample(image, region), lumen)
    image[region & (image > 800.0)] = 40.0
    image[lumen] += 500.0  # a lumen at 950 HU beside tissue: above the ceiling, and most of the sample
    assert np.array_equal(lumen_sample(image, region), lumen)


def test_a_bright_outlier_is_not_the_lumen(monkeypatch):
    """The 31 voxels of a seed's ball inside the thoracic CTA's true lumen (``bench_aorta``'s sweep): Otsu's
    upper class is the +6 SD voxel and one more, and the lumen level read from them was 614 HU against 479."""
    from carotid.segment import segmentation

    values = np.array([394, 411, 418, 438, 443, 444, 446, 446, 450, 463, 465, 466, 466, 470, 472, 476, 479, 482,
                       483, 487, 487, 492, 493, 501, 508, 519, 520, 526, 529, 535, 693], np.float32)
    image = np.full((3, 8, 8), 40.0, np.float32)
    region = np.zeros(image.shape, bool)
    region.flat[np.arange(values.size) + 64] = True
    image[region] = values
    sample = segmentation.lumen_sample(image, region)
    assert np.count_nonzero(sample) >= 10 and abs(np.median(image[sample]) - 479.0) < 30.0
    monkeypatch.setattr(segmentation, "MIN_LUMEN_SHARE", 0.0)
    assert np.count_nonzero(segmentation.lumen_sample(image, region)) < 5


def graded(p, levelset):
    """NASCET and minimal diameter (mm) of the ICA stenosis graded on ``levelset``."""
    cl = compute_centerlines(p.image.with_array(np.asarray(levelset, np.float32)))
    s = cl.info["stenosis"]
    assert s["branch"] == "ICA"
    return s["nascet"], s["min_diameter_mm"]


def test_calcified_stenosis_keeps_its_throat(monkeypatch):
    """NASCET 50 % with a 700 HU plaque at the throat, 0.5 mm blur: calcium blooming must not widen the throat."""
    p = family_phantom(nascet=0.5, noise=15.0, seed=4, calcium_hu=700.0, arterial_hu=300.0, plaque_size=1.3,
                       blur_sigma_mm=0.5, plaque_offset_mm=0.0)
    true_min = p.info["stenosis"]["min_diameter_mm"]
    true_nascet, _ = graded(p, p.sdf.array)
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]

    def errors(params=SegmentParameters()):
        nascet, d_min = graded(p, segment(p.image, seeds_xyz=seeds, params=params).levelset.array)
        return 100.0 * (nascet - true_nascet), d_min - true_min

    nascet_error, d_error = errors()
    assert abs(nascet_error) <= 5.0 and abs(d_error) <= 0.25
    # Mutations: no calcium model (the blooming fills the throat), and the calcium's edge to the voxel only.
    assert errors(SegmentParameters(calcium_edge=False))[1] > 1.0
    monkeypatch.setattr(calcium, "edge_fraction", lambda image, extent, *args, **kwargs: extent.astype(np.float32))
    assert errors()[1] > 0.25


def test_calcified_throat_of_family_case_17_is_graded_within_five_points():
    """Family case 17 (area stenosis 65 %, 0.66 mm blur, 26 HU noise, a 1140 HU plaque at the throat): the
    converged front grades 6.3 points too mild; the blur-model refinement brings it to -3.7."""
    p = make_phantom(**sample_family(17))
    true_nascet, _ = graded(p, p.sdf.array)
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]

    def error(params=SegmentParameters()):
        return 100.0 * (graded(p, segment(p.image, seeds_xyz=seeds, params=params).levelset.array)[0]
                        - true_nascet)

    assert abs(error()) <= 5.0
    # Mutation: no refinement.
    assert error(SegmentParameters(deblur=False)) < -5.0


def test_mild_calcified_stenosis_of_family_case_23_is_graded_on_chords(monkeypatch):
    """Family case 23 (area stenosis 36 %, a 1466 HU nodule at the throat, 0.56 mm blur, 25 HU noise), the
    true lumen and the segmented one graded alike: on chords through the axis NASCET is within 5 points of
    the true lumen's (+3.3); on the distance from the axis to the nearest wall (mutation), the segmented
    axis's offset at the throat reads as stenosis, +6.2."""
    p = make_phantom(**sample_family(23))
    seeds = [p.info["seeds_mm"][name] for name in ("CCA", "ICA", "ECA")]
    levelset = segment(p.image, seeds_xyz=seeds).levelset.array

    def error():
        return 100.0 * (graded(p, levelset)[0] - graded(p, p.sdf.array)[0])

    assert abs(error()) <= 5.0
    monkeypatch.setattr(extract, "section_profile", functools.partial(section_profile, through_axis=False))
    assert error() > 5.0


def string_sign_case(throat_mm, gap_mm=0.0):
    """A straight tube of radius 2.5 mm along z narrowed over 10 mm to ``throat_mm`` (a string sign; 3 mm
    raised-cosine tapers), interrupted over ``gap_mm`` at its middle (an occlusion); 0.4 mm voxels, 0.6 mm
    Gaussian blur, lumen 400 HU on 40 HU, 10 HU noise; seeds 2 mm inside each end."""
    h = 0.4
    z = (np.arange(125) * h - 25.0)[:, None, None]
    y = (np.arange(40) * h - 8.0 + 0.037)[None, :, None]
    x = (np.arange(40) * h - 8.0 + 0.071)[None, None, :]
    taper = np.clip((np.abs(z) - 5.0) / 3.0, 0, 1)
    sdf = np.hypot(x, y) - (throat_mm + (2.5 - throat_mm) * 0.5 * (1 - np.cos(np.pi * taper)))
    sdf = np.maximum(sdf, gap_mm / 2 - np.abs(z)) if gap_mm else sdf
    occupancy = np.clip(0.5 - sdf / h, 0, 1).astype(np.float32)
    image = 40.0 + 360.0 * ndimage.gaussian_filter(occupancy, 0.6 / h)
    image += 10.0 * np.random.default_rng(0).standard_normal(image.shape)
    volume = Volume(image.astype(np.float32), spacing=(h, h, h))
    return volume, volume.index_to_world(np.array([[5.0, 19.7, 19.7], [119.0, 19.7, 19.7]]))


@pytest.mark.parametrize("throat_mm", [0.6, 0.75])
def test_string_sign_is_joined_and_keeps_its_diameter(throat_mm):
    """A throat of 1.2-1.5 mm over 10 mm, about as thin as the blur: the front pinches there and the two seeds
    end in separate pieces, which no centerline joins (mutation: joining off).  Joined along the minimal path
    as a tube of the radius its axis intensity gives, and refined, the narrowest diameter is within 0.25 mm."""
    volume, seeds = string_sign_case(throat_mm)
    result = segment(volume, seeds_xyz=seeds)
    assert [join["accepted"] for join in result.report["seed_joins"]] == [True]
    assert ndimage.label(result.mask.array)[1] == 1
    d_min = compute_centerlines(result.levelset, result.mask).info["stenosis"]["min_diameter_mm"]
    assert abs(d_min - 2 * throat_mm) <= 0.25
    off = segment(volume, seeds_xyz=seeds, params=SegmentParameters(join_contrast=0))
    assert ndimage.label(off.mask.array)[1] == 2
    with pytest.raises(CarotidError, match="fragmented"):
        compute_centerlines(off.levelset, off.mask)


def test_an_occlusion_is_not_joined():
    """The same string interrupted over 3 mm: no lumen-like path crosses the gap, so the seeds' pieces stay
    apart and the centerlines refuse them."""
    volume, seeds = string_sign_case(0.75, gap_mm=3.0)
    result = segment(volume, seeds_xyz=seeds)
    assert [join["accepted"] for join in result.report["seed_joins"]] == [False]
    assert result.report["seed_joins"][0]["min_contrast"] < 0.25
    with pytest.raises(CarotidError, match="fragmented"):
        compute_centerlines(result.levelset, result.mask)


def chamber_case():
    """A 3 mm tube opening without any gap into a 12 mm sphere as bright as it (a heart chamber behind an
    open valve), 0.6 mm blur, 0.75 mm voxels; returns the image, the tube and the sphere (voxel masks)."""
    h, shape = 0.75, (100, 40, 40)
    k, j, i = (axis * h for axis in np.indices(shape, dtype=np.float32))
    centre = 0.5 * (shape[1] - 1) * h
    tube = np.where(k <= 60.0, np.hypot(j - centre, i - centre) - 3.0, np.inf)
    sphere = np.sqrt((k - 60.0) ** 2 + (j - centre) ** 2 + (i - centre) ** 2) - 12.0
    occupancy = np.clip(0.5 - np.minimum(tube, sphere) / h, 0.0, 1.0)
    rng = np.random.default_rng(4)
    image = 40.0 + 360.0 * ndimage.gaussian_filter(occupancy, 0.6 / h) + rng.normal(0.0, 15.0, shape)
    return Volume(image.astype(np.float32), spacing=(h, h, h)), (tube < -0.5) & (k < 45.0), sphere < -1.5


def test_front_stays_out_of_a_chamber():
    """A front from the tube must not fill the sphere; without the chamber test it does."""
    volume, tube, sphere = chamber_case()
    seed = [[14.6, 14.6, 10.0]]  # x, y, z mm: on the tube's axis, 38 mm from the sphere
    result = segment(volume, seeds_xyz=seed)
    seg = result.mask.array > 0
    assert np.count_nonzero(seg & tube) / np.count_nonzero(tube) > 0.95
    assert np.count_nonzero(seg & sphere) / np.count_nonzero(sphere) < 0.05
    found = result.report["chambers"]
    assert len(found) == 1 and found[0]["cores"] == 1
    assert found[0]["vessel_radius_mm"] == pytest.approx(3.0, abs=0.5)
    assert np.allclose(found[0]["centres_mm"], [[14.6, 14.6, 60.0]], atol=2.0)  # the sphere's centre, x y z
    off = segment(volume, seeds_xyz=seed, params=SegmentParameters(chamber_ratio=0)).mask.array > 0
    assert np.count_nonzero(off & sphere) / np.count_nonzero(sphere) > 0.9


def valve_case():
    """A 4 mm tube narrowing to 2.8 mm (a valve's annulus), then a 4.5 mm outflow tract opening into a 13 mm
    sphere, all as bright as each other except a 1.5 mm slab at the tract's end 20 % dimmer (blood less
    opacified), 0.6 mm blur, 0.75 mm voxels.  Returns the image, the tube before the annulus and the tract."""
    h, shape = 0.75, (110, 48, 48)
    k, j, i = (axis * h for axis in np.indices(shape, dtype=np.float32))
    centre = 0.5 * (shape[1] - 1) * h
    rho = np.hypot(j - centre, i - centre)
    radius = np.where(k < 42.0, 4.0 - 1.2 * np.exp(-((k - 40.0) / 1.2) ** 2), 4.5)
    vessel = np.where(k <= 50.0, rho - radius, np.inf)
    sphere = np.sqrt((k - 59.0) ** 2 + rho ** 2) - 13.0
    occupancy = np.clip(0.5 - np.minimum(vessel, sphere) / h, 0.0, 1.0)
    level = np.where((k > 46.0) & (k < 47.5), 0.8, 1.0)
    rng = np.random.default_rng(4)
    image = 40.0 + 360.0 * ndimage.gaussian_filter(occupancy * level, 0.6 / h) + rng.normal(0.0, 15.0, shape)
    tube = (rho < 3.0) & (k > 5.0) & (k < 37.0)
    tract = (rho < 3.5) & (k > 42.5) & (k < 45.5)
    return Volume(image.astype(np.float32), spacing=(h, h, h)), tube, tract


def test_a_chamber_is_cut_at_its_valve_annulus(monkeypatch):
    """The outflow tract between the annulus and the chamber goes with the chamber, although the darkest
    surface lies at the tract's far end; cut there (``chamber_neck`` switched off), the tract stays."""
    from carotid.segment import segmentation

    volume, tube, tract = valve_case()
    seed = [[17.6, 17.6, 12.0]]  # x, y, z mm: on the tube's axis, 28 mm before the annulus

    def kept():
        seg = segment(volume, seeds_xyz=seed).mask.array > 0
        return (np.count_nonzero(seg & tube) / np.count_nonzero(tube),
                np.count_nonzero(seg & tract) / np.count_nonzero(tract))

    tube_kept, tract_kept = kept()
    assert tube_kept > 0.95 and tract_kept < 0.05
    monkeypatch.setattr(segmentation, "chamber_neck", lambda region, chamber, *args: chamber)
    tube_kept, tract_kept = kept()
    assert tube_kept > 0.95 and tract_kept > 0.9
