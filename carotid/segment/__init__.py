"""Segmentation of the arterial lumen by the GPF deformable model (paper section 2)."""

from carotid.segment.potential import gpf_potential, gpf_potential_vector
from carotid.segment.segmentation import SegmentParameters, Segmentation, segment, write_segmentation

__all__ = ["SegmentParameters", "Segmentation", "segment", "write_segmentation", "gpf_potential",
           "gpf_potential_vector"]
