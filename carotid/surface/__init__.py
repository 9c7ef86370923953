"""The clipped, smoothed, remeshed lumen surface (issue #3, paper section 3 steps 2-4)."""

from carotid.surface.clip import cap_info, clip_surface
from carotid.surface.external import label_caps, levelset_from_surface, load_external_surface
from carotid.surface.extract import extract_surface
from carotid.surface.pipeline import build_surface, build_surface_keeping_caps, write_surface
from carotid.surface.quality import surface_quality
from carotid.surface.remesh import radius_size_field, remesh
from carotid.surface.smooth import laplacian_smooth, taubin_smooth

__all__ = ["extract_surface", "clip_surface", "cap_info", "taubin_smooth", "laplacian_smooth", "remesh",
           "radius_size_field", "surface_quality", "load_external_surface", "levelset_from_surface",
           "label_caps", "build_surface", "build_surface_keeping_caps", "write_surface"]
