"""Synthetic carotid angiograms (CT or MR) with ground truth, generated in-process (nothing is downloaded)."""

from carotid.phantom.ct import FAMILY_KEYWORDS, LABELS, Phantom, make_phantom, write_phantom
from carotid.phantom.family import FAMILY_RANGES, sample_family

__all__ = ["FAMILY_KEYWORDS", "FAMILY_RANGES", "LABELS", "Phantom", "make_phantom", "sample_family", "write_phantom"]
