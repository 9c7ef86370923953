"""Centerlines, branch graph and stenosis grading (issue #3, paper section 3 step 1)."""

from carotid.centerline.extract import compute_centerlines
from carotid.centerline.features import branch_features, geometry_features, stenosis
from carotid.centerline.io import read_centerlines, write_centerlines
from carotid.centerline.model import Branch, Centerlines

__all__ = ["Branch", "Centerlines", "compute_centerlines", "branch_features", "geometry_features", "stenosis",
           "read_centerlines", "write_centerlines"]
