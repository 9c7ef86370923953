"""Reading and writing 3D medical images through SimpleITK.

Arrays are indexed ``[k, j, i]`` (slice, row, column), as SimpleITK's
``GetArrayFromImage`` returns them; geometry follows ITK: ``spacing`` and
``origin`` are given ``(x, y, z)`` in mm and ``direction`` is the 3x3 matrix
whose columns are the index axes in the physical (LPS) frame.  A world point
is ``origin + direction @ (spacing * (i, j, k))``.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from carotid.errors import CarotidError
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
    """

    array: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: np.ndarray = None  # type: ignore[assignment]

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

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """Whether world points (mm), shape (..., 3), lie inside the voxel grid."""
        kji = self.world_to_index(xyz)
        upper = np.asarray(self.array.shape) - 0.5
        return np.all((kji >= -0.5) & (kji <= upper), axis=-1)


def to_sitk(volume: Volume) -> sitk.Image:
    """SimpleITK image of a volume's array with its spacing, origin and direction."""
    image = sitk.GetImageFromArray(volume.array)
    image.SetSpacing(volume.spacing)
    image.SetOrigin(volume.origin)
    image.SetDirection(volume.direction.ravel().tolist())
    return image


def _from_sitk(image: sitk.Image, source: str, dtype) -> Volume:
    if image.GetDimension() != 3 or min(image.GetSize()) < 2:
        raise CarotidError(f"{source}: image of size {image.GetSize()} is not a 3D volume")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise CarotidError(f"{source}: image has {image.GetNumberOfComponentsPerPixel()} "
                           "components per voxel; a scalar (grey-level) image is required")
    array = sitk.GetArrayFromImage(image)
    if dtype is not None:
        array = array.astype(dtype, copy=False)
    return Volume(array, image.GetSpacing(), image.GetOrigin(), np.reshape(image.GetDirection(), (3, 3)))


def _read_dicom_series(folder: Path) -> sitk.Image:
    reader = sitk.ImageSeriesReader()
    series = reader.GetGDCMSeriesIDs(str(folder))
    if not series:
        raise CarotidError(f"{folder}: folder holds no DICOM series")
    files = max((reader.GetGDCMSeriesFileNames(str(folder), s) for s in series), key=len)
    reader.SetFileNames(files)
    return reader.Execute()


def _nifti_nan_count(path: Path) -> int:
    """NaN voxels stored in a floating-point NIfTI-1 file (ITK's reader silently turns them into 0).

    Integer files, and files that are not NIfTI-1, give 0.
    """
    import gzip
    import struct

    opener = gzip.open if path.name.lower().endswith(".gz") else open
    with opener(path, "rb") as f:
        header = f.read(348)
        if len(header) < 348:
            return 0
        endian = "<" if struct.unpack("<i", header[:4])[0] == 348 else ">"
        if struct.unpack(endian + "i", header[:4])[0] != 348:
            return 0
        dtype = {16: "f4", 64: "f8"}.get(struct.unpack(endian + "h", header[70:72])[0])
        if dtype is None:
            return 0
        offset = int(struct.unpack(endian + "f", header[108:112])[0])
        f.read(max(offset - 348, 0))
        count = 0
        while chunk := f.read(1 << 24):
            usable = len(chunk) - len(chunk) % np.dtype(dtype).itemsize
            count += int(np.count_nonzero(np.isnan(np.frombuffer(chunk[:usable], endian + dtype))))
        return count


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

    Raises
    ------
    CarotidError
        If the path is missing, is not an image, is not a scalar 3D volume, or
        (NIfTI) holds NaN voxels.  Other formats keep NaN in the array, which
        the stages refuse.
    """
    path = Path(path)
    if not path.exists():
        raise CarotidError(f"{path}: no such file or folder")
    try:
        image = _read_dicom_series(path) if path.is_dir() else sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else ""
        raise CarotidError(f"{path}: cannot be read as an image (DICOM, NIfTI, NRRD or MHA): {first}") from None
    if path.is_file() and path.name.lower().endswith((".nii", ".nii.gz")):
        nans = _nifti_nan_count(path)
        if nans:
            raise CarotidError(f"{path}: image has {nans} NaN voxels")
    return _from_sitk(image, str(path), dtype)


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
