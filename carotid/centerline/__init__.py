"""Centerlines, branch graph and stenosis grading (issue #3)."""

from carotid.centerline.model import Branch, Centerlines

__all__ = ["Branch", "Centerlines"]
