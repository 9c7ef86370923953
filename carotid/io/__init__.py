"""Image input and output in the image's physical frame (mm, LPS), and atomic writes."""

from carotid.io.atomic import atomic_dir, atomic_path, read_json, read_record, write_json
from carotid.io.image import Volume, read_image, to_sitk, write_image

__all__ = ["Volume", "read_image", "to_sitk", "write_image", "atomic_dir", "atomic_path", "read_json", "read_record", "write_json"]
