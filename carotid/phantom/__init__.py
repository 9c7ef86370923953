"""Synthetic carotid CT angiograms with ground truth, generated in-process (nothing is downloaded)."""

from carotid.phantom.ct import LABELS, Phantom, make_phantom, write_phantom

__all__ = ["LABELS", "Phantom", "make_phantom", "write_phantom"]
