"""Image I/O: formats, geometry, DICOM series and clear errors."""

import tempfile
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from carotid.errors import CarotidError, CarotidWarning
from carotid.io import Volume, atomic_dir, atomic_path, read_image, write_image, write_json

DIRECTION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # rotated 90 degrees about z


def make_volume():
    rng = np.random.default_rng(0)
    array = rng.normal(100, 20, (7, 9, 11)).astype(np.float32)
    return Volume(array, spacing=(0.45, 0.5, 0.625), origin=(-10.0, 20.0, 5.0), direction=DIRECTION)


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd", ".mha", ".mhd"])
def test_roundtrip_keeps_values_and_geometry(tmp_path, suffix):
    vol = make_volume()
    path = write_image(vol, tmp_path / f"img{suffix}")
    back = read_image(path)
    assert back.array.dtype == np.float32 and back.array.shape == (7, 9, 11)
    np.testing.assert_allclose(back.array, vol.array, rtol=1e-6)
    np.testing.assert_allclose(back.spacing, vol.spacing)
    np.testing.assert_allclose(back.origin, vol.origin)
    np.testing.assert_allclose(back.direction, DIRECTION, atol=1e-6)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left


def test_world_index_transform_matches_simpleitk(tmp_path):
    vol = make_volume()
    image = sitk.ReadImage(str(write_image(vol, tmp_path / "img.nii.gz")))
    kji = np.array([[1.0, 2.0, 3.0], [6.0, 8.0, 10.0]])
    ours = vol.index_to_world(kji)
    theirs = [image.TransformContinuousIndexToPhysicalPoint(tuple(p[::-1])) for p in kji]
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    np.testing.assert_allclose(vol.world_to_index(ours), kji, atol=1e-9)
    assert vol.contains(ours).all()
    assert not vol.contains(np.array([[1e3, 0, 0]])).any()


def write_dicom_series(folder, vol, slices=None, thickness=None):
    """Write ``vol`` as a DICOM series, one file per slice index in ``slices`` (default: all, in order), with
    SliceThickness ``thickness`` (a string) if given."""
    array = np.round(vol.array).astype(np.int16)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    series = "1.2.826.0.1.3680043.2.1125.1"
    for number, k in enumerate(range(array.shape[0]) if slices is None else slices):
        sl = sitk.GetImageFromArray(array[k:k + 1])
        sl.SetSpacing(vol.spacing)
        origin = vol.index_to_world(np.array([k, 0, 0]))
        sl.SetOrigin(tuple(origin))
        sl.SetDirection(DIRECTION.ravel().tolist())
        for tag, value in [("0020|000e", series), ("0008|0060", "CT"), ("0020|0013", str(number + 1)),
                           ("0020|0032", "\\".join(f"{c:.4f}" for c in origin)),
                           ("0020|0037", "\\".join(f"{c:.6f}" for c in DIRECTION.T[:2].ravel())),
                           ("0008|0018", f"{series}.{number + 1}"), ("0028|0030", "0.5\\0.45")]:
            sl.SetMetaData(tag, value)
        if thickness is not None:
            sl.SetMetaData("0018|0050", thickness)
        writer.SetFileName(str(folder / f"slice{number:03d}.dcm"))
        writer.Execute(sl)
    return array


def test_dicom_series_folder(tmp_path):
    vol = make_volume()
    array = write_dicom_series(tmp_path, vol)
    back = read_image(tmp_path)
    assert back.array.shape == array.shape
    np.testing.assert_allclose(back.array, array)
    np.testing.assert_allclose(back.spacing, vol.spacing, atol=1e-4)
    np.testing.assert_allclose(back.origin, vol.origin, atol=1e-3)


@pytest.mark.parametrize("slices, what", [([0, 1, 2, 4, 5, 6, 7], "1 missing slice"),
                                          ([0, 1, 2, 3, 4, 6, 7, 9], "2 missing slice"),
                                          ([0, 1, 2, 2, 3, 4, 5], "uneven slice steps")])
def test_dicom_series_with_missing_or_repeated_slices_is_refused(tmp_path, slices, what):
    vol = make_volume()
    vol = Volume(np.repeat(vol.array[:1], 10, axis=0), vol.spacing, vol.origin, vol.direction)
    write_dicom_series(tmp_path, vol, slices)
    with pytest.raises(CarotidError, match=what):
        read_image(tmp_path)


def test_the_slice_thickness_a_scan_records_is_read(tmp_path):
    """DICOM SliceThickness (0018,0050), in a series and in one file, and the ``SliceThickness`` of the JSON
    sidecar dcm2niix writes beside a NIfTI file; formats that record none give None."""
    vol = make_volume()
    write_dicom_series(tmp_path, vol, thickness="1.25")
    assert read_image(tmp_path).slice_thickness == pytest.approx(1.25)
    single = sitk.GetImageFromArray(np.zeros((5, 6, 7), np.uint16))  # one multi-frame file
    single.SetMetaData("0018|0050", "2.0 ")
    sitk.WriteImage(single, str(tmp_path / "multi.dcm"))
    assert read_image(tmp_path / "multi.dcm").slice_thickness == pytest.approx(2.0)
    nifti = write_image(vol, tmp_path / "ct.nii.gz")
    assert read_image(nifti).slice_thickness is None
    (tmp_path / "ct.json").write_text('{"Modality": "CT", "SliceThickness": 1.5, "SpacingBetweenSlices": 0.625}')
    assert read_image(nifti).slice_thickness == pytest.approx(1.5)
    assert read_image(write_image(vol, tmp_path / "ct.nrrd")).slice_thickness is None
    # The thickness goes with the grid into every volume made from it.
    assert read_image(nifti).with_array(vol.array).slice_thickness == pytest.approx(1.5)


@pytest.mark.parametrize("sidecar", ['{"SliceThickness": 0}', '{"SliceThickness": "thin"}', "{not json"])
def test_a_sidecar_without_a_usable_thickness_is_ignored_with_a_warning(tmp_path, sidecar):
    nifti = write_image(make_volume(), tmp_path / "ct.nii")
    (tmp_path / "ct.json").write_text(sidecar)
    with pytest.warns(CarotidWarning, match="slice thickness|sidecar"):
        assert read_image(nifti).slice_thickness is None


def test_a_sidecar_without_the_field_says_nothing(tmp_path, recwarn):
    nifti = write_image(make_volume(), tmp_path / "ct.nii")
    (tmp_path / "ct.json").write_text('["SliceThickness", 1.0]')
    assert read_image(nifti).slice_thickness is None
    assert not [w for w in recwarn if issubclass(w.category, CarotidWarning)]


def test_slice_steps_of_an_even_series_pass_and_a_gap_is_located():
    from carotid.io.image import check_slice_steps

    check_slice_steps(np.arange(20) * 0.625 + 3.0, "even")
    check_slice_steps(-np.arange(20) * 0.625, "descending")
    positions = np.delete(np.arange(20) * 0.625, 13)
    with pytest.raises(CarotidError, match="1.25 mm between slices 12 and 13 where the series steps 0.625 mm"):
        check_slice_steps(positions, "gap")


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
@pytest.mark.parametrize("kept", [0.5, 0.98])
def test_truncated_nifti_is_refused(tmp_path, suffix, kept):
    path = write_image(make_volume(), tmp_path / f"image{suffix}")
    data = path.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[:int(len(data) * kept)])
    with pytest.raises(CarotidError, match="truncated"):
        read_image(cut)
    read_image(path)  # the whole file reads


def test_a_cut_compressed_file_says_how_much_is_missing(tmp_path):
    """Random voxels do not compress, so half of a .gz holds about half of the voxel data: the message says
    so, not that all of it is missing (the reading stops at the cut, losing at most one 64 KiB read)."""
    array = np.random.default_rng(1).normal(100, 20, (64, 64, 64)).astype(np.float32)  # 1 MiB
    data = write_image(Volume(array), tmp_path / "image.nii.gz").read_bytes()
    (cut := tmp_path / "cut.nii.gz").write_bytes(data[:len(data) // 2])
    with pytest.raises(CarotidError, match="truncated") as error:
        read_image(cut)
    missing = float(str(error.value).split("truncated: ")[1].split("%")[0])
    assert 45 <= missing <= 57


def test_itk_messages_go_into_the_error_not_on_stderr(tmp_path, capfd):
    path = write_image(make_volume(), tmp_path / "image.mha", compress=False)
    data = path.read_bytes()
    cut = tmp_path / "cut.mha"
    cut.write_bytes(data[:len(data) * 2 // 3])
    with pytest.raises(CarotidError, match="data not read completely") as error:
        read_image(cut)
    assert "\n" not in str(error.value) and "line " not in str(error.value)
    assert capfd.readouterr().err == ""


def test_same_grid_compares_every_voxel_centre():
    vol = make_volume()
    assert vol.same_grid(vol.with_array(np.zeros_like(vol.array)))
    shifted = Volume(vol.array, vol.spacing, np.asarray(vol.origin) + [0.0, 0.5, 0.0], vol.direction)
    finer = Volume(vol.array, np.asarray(vol.spacing) * 1.01, vol.origin, vol.direction)
    turned = Volume(vol.array, vol.spacing, vol.origin, vol.direction[:, [1, 0, 2]])
    assert not vol.same_grid(shifted) and not vol.same_grid(finer) and not vol.same_grid(turned)


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(CarotidError, match="no such file"):
        read_image(tmp_path / "missing.nii.gz")
    text = tmp_path / "notes.nii.gz"
    text.write_text("not an image")
    with pytest.raises(CarotidError, match="cannot be read as an image"):
        read_image(text)
    flat = tmp_path / "flat.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((5, 6), np.float32)), str(flat))
    with pytest.raises(CarotidError, match="not a 3D volume"):
        read_image(flat)
    rgb = tmp_path / "rgb.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 5, 6, 3), np.uint8), isVector=True), str(rgb))
    with pytest.raises(CarotidError, match="components"):
        read_image(rgb)
    with pytest.raises(CarotidError, match="no DICOM series"):
        read_image(tmp_path)


def test_failed_write_leaves_previous_file(tmp_path):
    path = write_json({"a": 1}, tmp_path / "x.json")
    with pytest.raises(TypeError):
        write_json({"a": object()}, path)
    assert path.read_text().strip().startswith("{") and '"a": 1' in path.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]


def test_the_next_write_removes_a_killed_writes_temporary_and_nothing_else(tmp_path):
    user_files = [".git", ".DS_Store", ".notes.txt", "seg"]
    for name in user_files[:3]:
        (tmp_path / name).write_text("mine")
    with atomic_dir(tmp_path / "seg") as tmp:
        (tmp / "mask.nii.gz").write_bytes(b"old")
    # Entered and never left (kept referenced, so not closed either), as when the process is killed mid-write.
    writers = [atomic_path(tmp_path / "levelset.nii.gz"), atomic_dir(tmp_path / "seg"),
               atomic_path(tmp_path / "other.nii.gz")]
    file_tmp, folder_tmp, other_tmp = (writer.__enter__() for writer in writers)
    (folder_tmp / "mask.nii.gz").write_bytes(b"half")
    parked = Path(tempfile.mkdtemp(prefix=".seg.old.", dir=tmp_path))  # killed between atomic_dir's two renames
    with atomic_path(tmp_path / "levelset.nii.gz") as tmp:
        tmp.write_bytes(b"levelset")
    with atomic_dir(tmp_path / "seg") as tmp:
        (tmp / "mask.nii.gz").write_bytes(b"new")
    assert not any(p.exists() for p in (file_tmp, folder_tmp, parked)) and other_tmp.exists()  # another path's stays
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(user_files + ["levelset.nii.gz", other_tmp.name])
    assert (tmp_path / "seg" / "mask.nii.gz").read_bytes() == b"new"


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_voxels_in_nifti_are_reported(tmp_path, value):
    # ITK's NIfTI reader turns NaN and infinities into numbers, so the file itself is checked.
    array = np.zeros((4, 5, 6), np.float32)
    array[1, 2, 3] = value
    image = sitk.GetImageFromArray(array)
    for name in ("bad.nii", "bad.nii.gz"):
        sitk.WriteImage(image, str(tmp_path / name))
        with pytest.raises(CarotidError, match="1 NaN or infinite voxels"):
            read_image(tmp_path / name)
    kept = read_image(write_image(Volume(array), tmp_path / "bad.mha"))
    assert np.count_nonzero(~np.isfinite(kept.array)) == 1


@pytest.mark.parametrize("size", [0.0, np.nan])
def test_a_nifti_voxel_size_of_zero_or_nan_is_refused(tmp_path, size):
    """ITK reads a pixdim of 0 or NaN as 1 mm: the header is checked."""
    import gzip

    path = tmp_path / "image.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.arange(120, dtype=np.float32).reshape(4, 5, 6)), str(path))
    raw = bytearray(gzip.open(path).read())
    raw[80:84] = np.float32(size).tobytes()  # pixdim[1], the first axis
    path.write_bytes(gzip.compress(bytes(raw)))
    with pytest.raises(CarotidError, match=r"voxel sizes .* mm \(pixdim\)"):
        read_image(path)


@pytest.mark.parametrize("matrix, refused", [("1 0 0 0.5 1 0 0 0 1", True), ("2 0 0 0 1 0 0 0 1", True),
                                             ("0 1 0 1 0 0 0 0 -1", False)])
def test_a_metaimage_whose_matrix_is_not_a_rotation_is_refused(tmp_path, matrix, refused):
    """ITK forces a sheared or scaled TransformMatrix orthogonal with only a warning, and the outputs then lie
    in a frame rotated from the image's (13 degrees for a shear of 0.5): refused.  A permutation with a flip
    is a rotation and is read."""
    np.full((4, 5, 6), 100, np.int16).tofile(tmp_path / "image.raw")
    (tmp_path / "image.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        f"TransformMatrix = {matrix}\nOffset = 0 0 0\nElementSpacing = 0.5 0.5 0.8\nDimSize = 6 5 4\n"
        "ElementType = MET_SHORT\nElementDataFile = image.raw\n")
    if refused:
        with pytest.raises(CarotidError, match="TransformMatrix .* is not a rotation"):
            read_image(tmp_path / "image.mhd")
    else:
        assert read_image(tmp_path / "image.mhd").array.shape == (4, 5, 6)


def test_numba_caches_in_the_temporary_folder_when_the_install_is_read_only(monkeypatch, tmp_path):
    """A read-only install (a container without a home): numba's kernels are cached under the temporary
    folder instead of stopping the import; a NUMBA_CACHE_DIR the user set is kept, and a writable install
    keeps numba's own choice."""
    from carotid import numba_cache_dir

    monkeypatch.setattr("os.access", lambda path, mode: False)
    folder = numba_cache_dir(tmp_path, {})
    assert folder is not None and Path(folder).parent == Path(tempfile.gettempdir())
    assert numba_cache_dir(tmp_path, {"NUMBA_CACHE_DIR": "/somewhere"}) is None
    monkeypatch.setattr("os.access", lambda path, mode: True)
    assert numba_cache_dir(tmp_path, {}) is None
