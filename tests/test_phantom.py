"""The synthetic CTA phantom: its truth is self-consistent and its distractors are where promised."""

import json

import numpy as np
import pytest
from scipy import ndimage

from carotid.errors import CarotidError
from carotid.phantom import LABELS, make_phantom, write_phantom
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


def test_bad_parameters_are_refused():
    with pytest.raises(CarotidError):
        make_phantom(stenosis=0.99)
    with pytest.raises(CarotidError):
        make_phantom(noise=-1)


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
