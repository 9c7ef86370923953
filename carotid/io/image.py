"""Reading and writing 3D medical images through SimpleITK.

Arrays are indexed ``[k, j, i]`` (slice, row, column), as SimpleITK's
``GetArrayFromImage`` returns them; geometry follows ITK: ``spacing`` and
``origin`` are given ``(x, y, z)`` in mm and ``direction`` is the 3x3 matrix
whose columns are the index axes in the physical (LPS) frame.  A world point
is ``origin + direction @ (spacing * (i, j, k))``.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import tempfile
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from carotid.errors import CarotidError, CarotidWarning
from carotid.io.atomic import atomic_path

DETACHED_SUFFIXES = (".mhd", ".nhdr")


@dataclass(frozen=True)
class Volume:
    """A 3D image on a regular grid with its physical geometry.

    Attributes
    ----------
    array : ndarray, shape (nk, nj, ni)
        Voxel values; float32 for intensities, uint8 for masks.
    spacing : tuple of 3 float
        Voxel size along (i, j, k) in mm.
    origin : tuple of 3 float
        World position of voxel (0, 0, 0) in mm (LPS).
    direction : ndarray, shape (3, 3)
        Columns are the unit vectors of the i, j, k axes in the world frame.
    slice_thickness : float or None
        Reconstructed slice thickness along k in mm (DICOM SliceThickness), the width over which each slice
        integrates the scan; it exceeds the slice spacing when slices overlap.  None when the file does not
        record it.
    """

    array: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: np.ndarray = None  # type: ignore[assignment]
    slice_thickness: float | None = None

    def __post_init__(self):
        if self.direction is None:
            object.__setattr__(self, "direction", np.eye(3))
        object.__setattr__(self, "direction", np.asarray(self.direction, float).reshape(3, 3))
        object.__setattr__(self, "spacing", tuple(float(s) for s in self.spacing))
        object.__setattr__(self, "origin", tuple(float(o) for o in self.origin))

    @property
    def spacing_kji(self) -> np.ndarray:
        """Voxel size in mm in array order, shape (3,)."""
        return np.asarray(self.spacing[::-1])

    def with_array(self, array: np.ndarray) -> "Volume":
        """The same geometry carrying another array of the same shape."""
        if array.shape != self.array.shape:
            raise ValueError(f"shape {array.shape} differs from {self.array.shape}")
        return replace(self, array=array)

    def index_to_world(self, kji: np.ndarray) -> np.ndarray:
        """World points (mm, LPS) of continuous array indices.

        Parameters
        ----------
        kji : array_like, shape (..., 3)
            Indices in array order (k, j, i).

        Returns
        -------
        ndarray, shape (..., 3)
            Points (x, y, z) in mm.
        """
        ijk = np.asarray(kji, float)[..., ::-1]
        return np.asarray(self.origin) + (ijk * np.asarray(self.spacing)) @ self.direction.T

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """Continuous array indices (k, j, i) of world points (mm), shape (..., 3)."""
        rel = np.asarray(xyz, float) - np.asarray(self.origin)
        ijk = (rel @ np.linalg.inv(self.direction).T) / np.asarray(self.spacing)
        return ijk[..., ::-1]

    def grid(self) -> str:
        """The grid in words, for messages: shape (k, j, i), origin (mm) and spacing (mm)."""
        return (f"shape {self.array.shape}, origin {np.round(self.origin, 2).tolist()} mm, "
                f"spacing {np.round(self.spacing, 3).tolist()} mm")

    def same_grid(self, other: "Volume", tol_mm: float = 1e-3) -> bool:
        """Whether ``other`` has the same shape and voxel centres (to ``tol_mm`` over the whole grid)."""
        if other.array.shape != self.array.shape:
            return False
        corners = np.array(np.meshgrid(*[[0, n - 1] for n in self.array.shape], indexing="ij")).reshape(3, -1).T
        return bool(np.abs(self.index_to_world(corners) - other.index_to_world(corners)).max() <= tol_mm)

    def contains(self, xyz: np.ndarray, margin: float = 0.5) -> np.ndarray:
        """Whether world points (mm), shape (..., 3), lie within ``margin`` voxels of the box of the voxel
        centres (0.5, the default: inside the voxel grid; about 0: where the image holds data to interpolate)."""
        kji = self.world_to_index(xyz)
        return np.all((kji >= -margin) & (kji <= np.asarray(self.array.shape) - 1 + margin), axis=-1)


def to_sitk(volume: Volume) -> sitk.Image:
    """SimpleITK image of a volume's array with its spacing, origin and direction."""
    image = sitk.GetImageFromArray(volume.array)
    image.SetSpacing(volume.spacing)
    image.SetOrigin(volume.origin)
    image.SetDirection(volume.direction.ravel().tolist())
    return image


def _from_sitk(image: sitk.Image, source: str, dtype, slice_thickness: float | None = None) -> Volume:
    if image.GetDimension() != 3 or min(image.GetSize()) < 2:
        raise CarotidError(f"{source}: image of size {image.GetSize()} is not a 3D volume")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise CarotidError(f"{source}: image has {image.GetNumberOfComponentsPerPixel()} "
                           "components per voxel; a scalar (grey-level) image is required")
    array = sitk.GetArrayFromImage(image)
    if dtype is not None:
        array = array.astype(dtype, copy=False)
    return Volume(array, image.GetSpacing(), image.GetOrigin(), np.reshape(image.GetDirection(), (3, 3)),
                  slice_thickness)


SLICE_THICKNESS_TAG = "0018|0050"


def _thickness(value, source: str) -> float | None:
    """A recorded slice thickness as a positive number of mm; None (with a warning) when it is not one."""
    try:
        thickness = float(str(value).strip())
    except ValueError:
        thickness = math.nan
    if math.isfinite(thickness) and thickness > 0:
        return thickness
    warnings.warn(f"{source}: slice thickness {value!r} is not a positive number of mm; the slice spacing is "
                  "used instead", CarotidWarning, stacklevel=3)
    return None


def recorded_slice_thickness(path: Path, image: sitk.Image, reader: sitk.ImageSeriesReader | None) -> float | None:
    """The slice thickness (mm) a scan records: DICOM SliceThickness (0018,0050), or for NIfTI the
    ``SliceThickness`` of the BIDS sidecar ``<name>.json`` that dcm2niix writes beside it; None otherwise.

    A value that is not a positive number, or a sidecar that is not a JSON object, is ignored with a
    ``CarotidWarning``: the image itself is sound, and the slice spacing then stands in for the thickness.
    """
    if reader is not None:
        if reader.HasMetaDataKey(0, SLICE_THICKNESS_TAG):
            return _thickness(reader.GetMetaData(0, SLICE_THICKNESS_TAG), str(path))
        return None
    if image.HasMetaDataKey(SLICE_THICKNESS_TAG):
        return _thickness(image.GetMetaData(SLICE_THICKNESS_TAG), str(path))
    name = path.name.lower()
    if not name.endswith((".nii", ".nii.gz")):
        return None
    sidecar = path.with_name(path.name[: -len(".nii.gz") if name.endswith(".gz") else -len(".nii")] + ".json")
    if not sidecar.is_file():
        return None
    try:
        fields = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        warnings.warn(f"{sidecar}: sidecar is not readable JSON ({error}); its slice thickness is ignored",
                      CarotidWarning, stacklevel=2)
        return None
    if not isinstance(fields, dict) or "SliceThickness" not in fields:
        return None
    return _thickness(fields["SliceThickness"], str(sidecar))


# Relative deviation from the median slice step above which a DICOM series counts as uneven.
SLICE_STEP_TOLERANCE = 0.1


def _slice_positions(reader: sitk.ImageSeriesReader, n: int) -> np.ndarray | None:
    """Position of each slice of a read series along the slice normal, mm, shape (n,); None without the tags."""
    try:
        orient = np.array(reader.GetMetaData(0, "0020|0037").split("\\"), float).reshape(2, 3)
        corners = np.array([reader.GetMetaData(i, "0020|0032").split("\\") for i in range(n)], float)
    except (RuntimeError, ValueError):
        return None
    return corners @ np.cross(orient[0], orient[1])


def check_slice_steps(positions: np.ndarray, source: str) -> None:
    """Raise CarotidError when the slice positions (mm, in reading order) miss a slice or step unevenly.

    A step more than ``SLICE_STEP_TOLERANCE`` away from the median step is a missing slice (a gap of about
    a whole number of steps), a repeated slice (no step) or an uneven series; ITK would read any of them
    onto a regular grid, putting every later slice at the wrong place.
    """
    steps = np.abs(np.diff(positions))
    if len(steps) == 0:
        return
    median = float(np.median(steps))
    bad = np.flatnonzero(np.abs(steps - median) > SLICE_STEP_TOLERANCE * median)
    if median <= 0 or len(bad) == 0:
        return
    first = int(bad[0])
    missing = int(np.sum(np.maximum(np.round(steps[bad] / max(median, 1e-9)) - 1, 0)))
    kind = (f"{missing} missing slice(s)" if missing and np.all(steps[bad] > median) else "uneven slice steps")
    raise CarotidError(f"{source}: DICOM series with {kind}: {steps[first]:.3g} mm between slices {first} and "
                       f"{first + 1} where the series steps {median:.3g} mm ({len(bad)} such gap(s) in "
                       f"{len(positions)} slices)")


def _read_dicom_series(folder: Path) -> tuple[sitk.Image, sitk.ImageSeriesReader]:
    reader = sitk.ImageSeriesReader()
    series = reader.GetGDCMSeriesIDs(str(folder))
    if not series:
        raise CarotidError(f"{folder}: folder holds no DICOM series")
    files = max((reader.GetGDCMSeriesFileNames(str(folder), s) for s in series), key=len)
    reader.SetFileNames(files)
    reader.MetaDataDictionaryArrayUpdateOn()
    image = reader.Execute()
    positions = _slice_positions(reader, len(files))
    if positions is not None:
        check_slice_steps(positions, str(folder))
    return image, reader


@contextmanager
def itk_messages():
    """Collect what ITK and its IO libraries print on the process's stderr while the block runs.

    ITK reports through its own output window and MetaIO/GDCM through ``std::cerr``, both straight to file
    descriptor 2, past Python.  The descriptor is pointed at a temporary file for the block; the yielded
    list receives, when the block ends, one entry per message with ITK's source-file lines and object
    addresses removed.
    """
    messages: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield messages
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            text = sink.read().decode(errors="replace")
            for block in re.split(r"\n\s*\n", text):
                lines = [re.sub(r"^\w+ \(0x[0-9a-f]+\): ", "", line.strip()) for line in block.splitlines()
                         if line.strip() and not re.match(r"^(WARNING|ERROR): In .*, line \d+$", line.strip())]
                if lines:
                    messages.append(" ".join(lines))


def _metaimage_matrix(path: Path) -> np.ndarray | None:
    """The 3 x 3 direction matrix a MetaImage header (``.mhd``, or the text ahead of an ``.mha``'s data) states,
    before ITK reads it: ``TransformMatrix``, ``Rotation`` or ``Orientation``; None when it states none or not
    nine numbers."""
    with open(path, "rb") as handle:
        header = handle.read(65536).decode("latin-1")
    for line in header.splitlines():
        key, _, value = line.partition("=")
        key = key.strip()
        if key == "ElementDataFile":
            break
        if key in ("TransformMatrix", "Rotation", "Orientation"):
            try:
                numbers = [float(v) for v in value.split()]
            except ValueError:
                return None
            return np.array(numbers).reshape(3, 3).T if len(numbers) == 9 else None
    return None


def _nifti_scan(path: Path) -> tuple[float, int, tuple]:
    """The fraction of voxel data missing from a NIfTI-1 file, its non-finite voxels and its voxel sizes.

    ITK's reader fills the voxels of a truncated file with 0, turns NaN and infinities into numbers, and
    reads a voxel size (``pixdim``) of 0 or NaN as 1 mm, all silently, so the file is read once more as a
    stream: the data must cover ``prod(dim) * bitpix / 8`` bytes after ``vox_offset`` (a truncated ``.gz``
    stream counts as missing data), and a floating-point file is scanned for NaN and infinities.  Files that
    are not NIfTI-1 give ``(0, 0, ())``.

    Returns
    -------
    missing : float
        Fraction of the voxel data the file lacks (0 when complete; for a cut ``.gz``, over by at most one 64 KiB
        read).
    bad : int
        NaN or infinite voxels (0 for integer files).
    pixdim : tuple of float
        The header's voxel size along each of the image's axes, mm, as written.
    """
    import gzip
    import struct
    import zlib

    opener = gzip.open if path.name.lower().endswith(".gz") else open
    with opener(path, "rb") as f:
        header = f.read(348)
        if len(header) < 348:
            return 0, 0, ()
        endian = "<" if struct.unpack("<i", header[:4])[0] == 348 else ">"
        if struct.unpack(endian + "i", header[:4])[0] != 348:
            return 0, 0, ()
        dims = struct.unpack(endian + "8h", header[40:56])
        pixdim = struct.unpack(endian + "8f", header[76:108])[1:1 + max(min(dims[0], 3), 0)]
        bitpix = struct.unpack(endian + "h", header[72:74])[0]
        expected = math.prod(max(d, 1) for d in dims[1:1 + max(min(dims[0], 7), 0)]) * bitpix // 8
        dtype = {16: "f4", 64: "f8"}.get(struct.unpack(endian + "h", header[70:72])[0])
        offset = int(struct.unpack(endian + "f", header[108:112])[0])
        received, nans, tail = 0, 0, b""
        try:
            f.read(max(offset - 348, 0))
            while chunk := f.read(1 << 16):  # small reads: a cut .gz stream loses at most one of them
                received += len(chunk)
                if dtype is not None:
                    chunk = tail + chunk
                    usable = len(chunk) - len(chunk) % np.dtype(dtype).itemsize
                    nans += int(np.count_nonzero(~np.isfinite(np.frombuffer(chunk[:usable], endian + dtype))))
                    tail = chunk[usable:]
        except (EOFError, zlib.error, gzip.BadGzipFile):
            pass  # a cut compressed stream: what was decoded counts
        return max(expected - received, 0) / max(expected, 1), nans, pixdim


def read_image(path: str | os.PathLike, dtype=np.float32) -> Volume:
    """Read a 3D image: a DICOM series folder, NIfTI, NRRD, MHA/MHD or one DICOM file.

    Parameters
    ----------
    path : path-like
        File, or folder holding one or more DICOM series (the largest is read).
    dtype : numpy dtype or None
        Type of the returned array (float32 for intensities); None keeps the file's.

    Returns
    -------
    Volume
        With the slice thickness the scan records (``recorded_slice_thickness``), if any.

    Raises
    ------
    CarotidError
        If the path is missing, is not an image, is not a scalar 3D volume, is a
        DICOM series with missing, repeated or unevenly stepped slices, or (NIfTI)
        is truncated, holds NaN or infinite voxels or gives a voxel size of 0 or NaN.
        Other formats keep NaN in the array, which the stages refuse.  ITK's own messages are part of the error.

    Warns
    -----
    CarotidWarning
        What ITK printed while reading an image it could read.
    """
    path = Path(path)
    if not path.exists():
        raise CarotidError(f"{path}: no such file or folder")
    if path.is_file() and path.name.lower().endswith((".mhd", ".mha")):
        matrix = _metaimage_matrix(path)
        if matrix is not None and not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-3):
            raise CarotidError(f"{path}: the header's TransformMatrix {np.round(matrix, 3).ravel().tolist()} is not a "
                               "rotation (it shears or scales the grid); ITK would force it orthogonal and every "
                               "output would lie in another frame: correct the header")
    failure = None
    with itk_messages() as messages:
        try:
            image, reader = _read_dicom_series(path) if path.is_dir() else (sitk.ReadImage(str(path)), None)
        except RuntimeError as exc:
            failure = str(exc).strip().splitlines()[-1] if str(exc).strip() else ""
    if failure is not None:
        said = "; ".join([*messages, failure] if messages else [failure])
        raise CarotidError(f"{path}: cannot be read as an image (DICOM, NIfTI, NRRD or MHA): {said}")
    for message in messages:
        warnings.warn(f"{path}: {message}", CarotidWarning, stacklevel=2)
    if path.is_file() and path.name.lower().endswith((".nii", ".nii.gz")):
        missing, bad, pixdim = _nifti_scan(path)
        if missing:
            raise CarotidError(f"{path}: the file is truncated: {100 * missing:.0f}% of its voxel data is missing "
                               "(an interrupted copy or download?)")
        if bad:
            raise CarotidError(f"{path}: image has {bad} NaN or infinite voxels")
        if not all(math.isfinite(h) and h != 0 for h in pixdim):
            raise CarotidError(f"{path}: the header gives voxel sizes {', '.join(f'{h:g}' for h in pixdim)} mm "
                               "(pixdim): a size of 0 or NaN would be read as 1 mm; correct the header")
    return _from_sitk(image, str(path), dtype, recorded_slice_thickness(path, image, reader))


def write_image(volume: Volume, path: str | os.PathLike, compress: bool = True) -> Path:
    """Write a volume atomically (temporary file in the same folder, then rename).

    The format follows the suffix (``.nii.gz``, ``.nrrd``, ``.mha``...).
    """
    path = Path(path)
    if path.suffix.lower() in DETACHED_SUFFIXES:
        # The header names its data file, so both are written under their final names in a
        # temporary folder and moved into place, the header last.
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{path.name}.", dir=path.parent) as folder:
            tmp = Path(folder)
            sitk.WriteImage(to_sitk(volume), str(tmp / path.name), compress)
            for part in sorted(tmp.iterdir(), key=lambda p: p.name == path.name):
                os.replace(part, path.parent / part.name)
        return path
    with atomic_path(path) as tmp:
        sitk.WriteImage(to_sitk(volume), str(tmp), compress)
    return path
