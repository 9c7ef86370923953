"""Axis polylines in mm: arc length, resampling, smoothing along the arc, and the inscribed-sphere radius.

The radius of the maximal inscribed sphere at a point is its distance to the
lumen wall, the zero level set of ``phi``.  Interpolating ``-phi`` itself
would be the obvious estimate, but on the axis the distance function has a
cone-shaped peak that trilinear interpolation flattens: on 0.45 x 0.45 x
0.625 mm voxels it reads about 0.2 mm low.  The wall, extracted by marching
cubes (scikit-image, Lewiner) where ``phi`` is smooth, gives the distance to
within a few hundredths of a mm; a k-d tree (scipy) answers the queries.

The inscribed radius is the narrowest half-width of a section, so it is as
low as the deepest dent in the wall; the section area (``section_areas``,
VMTK's ``CenterlineSectionArea``) averages dents out and is what an area
stenosis or a flow rate per area needs.

Sections (``section_radii``, ``section_areas``) find the wall by sampling
``phi`` with cubic B-spline interpolation (``SectionSampler``).  Trilinear
interpolation is exact only where ``phi`` is linear: it errs by about
``h^2 / 8`` times ``phi``'s second derivative (``h`` the voxel size), which
is largest across a sharply curved wall and at a crease of ``phi`` (a plaque
cut out of the lumen).  At a short, tight stenosis that moves the wall out:
the phantom's own distance function of a throat 2.9 mm across (0.42 x 0.42
x 0.8 mm voxels, a calcification cut out of the lumen) reads 0.23 mm too
wide trilinearly and 0.11 mm with the cubic spline (0.10 and 0.04 mm on
0.25 mm voxels), and analytic stenoses on 0.45 mm voxels grade within 0.2
NASCET points (0.9 trilinearly).

Smoothing is a Gaussian in arc length applied to the uniformly resampled
axis, with the axis continued beyond each end by point reflection
(``2 p_end - p``) so that the end points stay where they are and a straight
end stays straight (a plain Gaussian would pull the ends inwards).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from carotid.io import Volume


def arclength(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length (n,) in mm of a polyline (n, 3), starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def resample(points: np.ndarray, step: float) -> np.ndarray:
    """The polyline (n, 3) resampled at (nearly) uniform arc-length intervals of about ``step`` mm, ends kept."""
    s = arclength(points)
    if s[-1] <= 0:
        return points[[0, -1]].copy()
    t = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / step)), 1) + 1)
    return np.stack([np.interp(t, s, points[:, d]) for d in range(3)], axis=1)


def smooth_axis(points: np.ndarray, sigma_mm: float, step: float) -> np.ndarray:
    """Resample a polyline every ~``step`` mm and smooth it with a Gaussian of ``sigma_mm`` in arc length.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Axis in mm.
    sigma_mm : float
        Standard deviation of the Gaussian along the arc, mm; 0 only resamples.
    step : float
        Sampling interval, mm.

    Returns
    -------
    ndarray, shape (m, 3)
        The smoothed axis; its first and last points are those of ``points``.
    """
    p = resample(points, step)
    if sigma_mm <= 0 or len(p) < 3:
        return p
    width = min(int(np.ceil(4.0 * sigma_mm / step)), len(p) - 1)
    ext = np.concatenate([2 * p[0] - p[width:0:-1], p, 2 * p[-1] - p[-2:-width - 2:-1]])
    out = ndimage.gaussian_filter1d(ext, sigma_mm / step, axis=0, mode="nearest")[width:width + len(p)]
    out[0], out[-1] = p[0], p[-1]
    return out


def sample(volume: Volume, points: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a volume at world points (n, 3) mm; points outside take the nearest voxel."""
    kji = volume.world_to_index(np.asarray(points, float).reshape(-1, 3))
    return ndimage.map_coordinates(volume.array, kji.T, order=1, mode="nearest").astype(float)


class SectionSampler:
    """Cubic B-spline interpolation of a level set near a set of axis points (scipy's spline filter).

    The spline coefficients are computed once, on the box around the points widened by ``reach_mm`` and
    four voxels (the filter's influence decays by 0.27 per voxel, so the box's edge does not reach the
    wall); points outside the box take the nearest coefficient.

    Parameters
    ----------
    levelset : Volume
        Negative inside the lumen.
    points : ndarray, shape (n, 3)
        World points (mm) around which it will be sampled.
    reach_mm : float
        Distance (mm) from ``points`` out to which it will be sampled.
    """

    def __init__(self, levelset: Volume, points: np.ndarray, reach_mm: float):
        kji = levelset.world_to_index(np.asarray(points, float).reshape(-1, 3))
        pad = reach_mm / np.asarray(levelset.spacing_kji, float) + 4.0
        shape = np.asarray(levelset.array.shape)
        lo = np.clip(np.floor(kji.min(axis=0) - pad).astype(int), 0, shape - 1)
        hi = np.clip(np.ceil(kji.max(axis=0) + pad).astype(int) + 1, lo + 1, shape)
        self.levelset, self.corner = levelset, lo
        self.coefficients = ndimage.spline_filter(
            np.asarray(levelset.array[tuple(slice(a, b) for a, b in zip(lo, hi))], np.float32), order=3,
            output=np.float32, mode="nearest")

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """The level set at world points (n, 3) mm, shape (n,)."""
        kji = self.levelset.world_to_index(np.asarray(points, float).reshape(-1, 3)) - self.corner
        return ndimage.map_coordinates(self.coefficients, kji.T, order=3, mode="nearest",
                                       prefilter=False).astype(float)


class WallDistance:
    """Distance (mm) from points to the lumen wall, the zero level set of a level set volume.

    Parameters
    ----------
    levelset : Volume
        Negative inside; only its zero level set and its sign are used.
    region : ndarray of bool, optional
        Voxels whose bounding box (plus a margin of two voxels) is searched for the wall; default all.
    """

    def __init__(self, levelset: Volume, region: np.ndarray | None = None):
        phi = np.asarray(levelset.array, np.float32)
        box = (slice(None),) * 3
        if region is not None and region.any():
            found = ndimage.find_objects(region.astype(np.uint8))[0]
            box = tuple(slice(max(s.start - 2, 0), min(s.stop + 2, n)) for s, n in zip(found, phi.shape))
        crop = phi[box]
        if crop.min() >= 0 or crop.max() <= 0:
            raise ValueError("the level set has no zero crossing")
        verts, _, _, _ = marching_cubes(crop, 0.0, method="lewiner")
        corner = np.array([s.start or 0 for s in box], float)
        self.levelset = levelset
        self.tree = cKDTree(levelset.index_to_world(verts + corner))

    def radius(self, points: np.ndarray) -> np.ndarray:
        """Radius (n,) in mm of the maximal inscribed sphere centred at points (n, 3) mm; 0 outside the lumen."""
        points = np.asarray(points, float).reshape(-1, 3)
        d, _ = self.tree.query(points)
        return np.where(sample(self.levelset, points) < 0, d, 0.0)

    __call__ = radius


def section_areas(levelset: Volume, points: np.ndarray, radii: np.ndarray, step: float = 0.1,
                  reach: float = 1.5, margin: float = 0.5) -> np.ndarray:
    """Area (mm^2) of the lumen section through each axis point, in the plane normal to the axis.

    The level set is sampled (``SectionSampler``) on a square grid of ``step`` mm in the plane (coarser, 1/40
    of the disc radius, for wide vessels) within a disc of ``reach * radius + margin`` around the point, and
    only the part of the section connected to the point counts (a neighbouring branch cut by the same plane
    does not).

    Parameters
    ----------
    levelset : Volume
        Negative inside the lumen.
    points : ndarray, shape (n, 3)
        Axis points, mm, in order along the axis.
    radii : ndarray, shape (n,)
        Inscribed radius at each point, mm (sets the disc).
    step, reach, margin : float
        Grid step (mm), disc radius as a multiple of the radius, and added to it (mm).

    Returns
    -------
    ndarray, shape (n,)
    """
    points = np.asarray(points, float).reshape(-1, 3)
    radii = np.asarray(radii, float)
    if len(points) < 2:
        return np.pi * radii ** 2
    u, v = normal_frames(points)
    disc = reach * radii + margin
    step = max(step, float(disc.max()) / 40.0)
    g = np.arange(-disc.max(), disc.max() + 0.5 * step, step)
    a, b = np.meshgrid(g, g, indexing="ij")
    m = len(g)
    inside = np.empty((len(points), m, m), bool)
    phi_at = SectionSampler(levelset, points, float(disc.max()) * np.sqrt(2.0))
    for lo in range(0, len(points), 64):  # blocks of points bound the memory of the sample grid
        sl = slice(lo, lo + 64)
        grid = (points[sl, None, None] + a[None, ..., None] * u[sl, None, None]
                + b[None, ..., None] * v[sl, None, None])
        inside[sl] = phi_at(grid.reshape(-1, 3)).reshape(-1, m, m) < 0
    inside &= np.hypot(a, b)[None] <= disc[:, None, None]
    planar = np.zeros((3, 3, 3), bool)
    planar[1] = ndimage.generate_binary_structure(2, 1)
    labels, _ = ndimage.label(inside, planar)
    centre = labels[:, m // 2, m // 2]
    own = (labels == centre[:, None, None]) & (centre[:, None, None] > 0)
    return np.count_nonzero(own, axis=(1, 2)) * step ** 2


SECTION_RAYS = 36
"""Rays per section of :func:`section_radii` (every 10 degrees)."""
NARROW_ARC_DEG = 90.0
"""Arc over which :func:`section_profile` takes the running median before the narrowest width."""


def section_radii(levelset: Volume, points: np.ndarray, radii: np.ndarray, n_rays: int = SECTION_RAYS,
                  reach: float = 1.5, margin: float = 1.0) -> np.ndarray:
    """Distance (mm) from each axis point to the lumen wall along rays in the plane normal to the axis.

    Each ray samples the level set (cubic B-spline, ``SectionSampler``) every quarter of the smallest voxel
    size and the wall is the first zero crossing along it, placed by linear interpolation between the two
    samples that bracket it.  A ray that stays inside out to ``reach * radius + margin`` (into a branch that
    leaves through the section) reads that length.  A ray whose wall point lies beyond the image (outside
    the box of its voxel centres) reads NaN: where the image border cuts a vessel, the level set sampled
    past the border repeats the border's values and the ray runs on through lumen that was never imaged
    (a 2.6 mm ICA cut obliquely read a median radius of 3.6 mm in such a section).

    Parameters
    ----------
    levelset : Volume
        Negative inside the lumen.
    points : ndarray, shape (n, 3)
        Axis points, mm, in order along the axis.
    radii : ndarray, shape (n,)
        Inscribed radius at each point, mm (sets the ray length).
    n_rays : int
        Rays per section, evenly spaced in angle from the first normal direction.
    reach, margin : float
        Ray length as a multiple of the point's radius, plus ``margin`` mm.

    Returns
    -------
    ndarray, shape (n, n_rays)
        Wall distance along each ray, mm; NaN where the wall point lies beyond the image.
    """
    points = np.asarray(points, float).reshape(-1, 3)
    radii = np.asarray(radii, float)
    if len(points) < 2:
        return np.repeat(radii[:, None], n_rays, axis=1)
    u, v = normal_frames(points)
    angle = np.linspace(0.0, 2.0 * np.pi, n_rays, endpoint=False)
    ray = np.cos(angle)[None, :, None] * u[:, None] + np.sin(angle)[None, :, None] * v[:, None]  # (n, m, 3)
    step = 0.25 * float(min(levelset.spacing))
    length = reach * radii + margin
    along = np.arange(0.0, float(length.max()) + step, step)
    out = np.empty((len(points), n_rays))
    phi_at = SectionSampler(levelset, points, float(along[-1]))
    for lo in range(0, len(points), 32):  # blocks of points bound the memory of the samples
        sl = slice(lo, lo + 32)
        xyz = points[sl, None, None] + along[None, None, :, None] * ray[sl, :, None]
        phi = phi_at(xyz.reshape(-1, 3)).reshape(xyz.shape[:3])
        outside = (phi >= 0) | (along[None, None, :] > length[sl, None, None])
        k = np.where(outside.any(axis=2), np.argmax(outside, axis=2), len(along) - 1).clip(1)
        a = np.take_along_axis(phi, (k - 1)[..., None], axis=2)[..., 0]
        b = np.take_along_axis(phi, k[..., None], axis=2)[..., 0]
        crossing = (b >= 0) & (a < 0)
        fraction = np.where(crossing, -a / np.where(crossing, b - a, 1.0), 1.0)
        out[sl] = np.minimum(along[k - 1] + fraction * step, length[sl, None])
    out[~levelset.contains(points[:, None] + out[..., None] * ray, margin=1e-6)] = np.nan
    return out


def section_profile(rays: np.ndarray, arc_deg: float = NARROW_ARC_DEG,
                    through_axis: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The median radius and half the narrowest width of each section, robust to the roughness of the wall.

    A segmented wall is never smooth: noise and the grid leave bumps and dents of 0.1-0.3 mm over an arc of
    a millimetre or two, and the maximal inscribed sphere, which touches the deepest dent, reads that much
    too low (0.2 mm in radius on a 2.5 mm distal ICA of the phantom family).  Over the ray distances
    ``r(theta)`` of :func:`section_radii`:

    * the median radius, the median of ``r(theta)``, is the radius of a round vessel, whatever its bumps and
      dents and whatever branch leaves through the section;
    * the narrow radius is half the narrowest diameter: the smallest value of the running median, over
      ``arc_deg`` (circular), of the chord through the axis point, ``(r(theta) + r(theta + pi)) / 2``.  A
      dent narrower than half that arc is ignored; an elliptic lumen reads its minor semi-axis.  The chord
      does not depend, to first order, on where the axis point lies in the section: an axis ``e`` mm off
      the centre of a round lumen of radius ``R`` reads ``R - O(e^2 / R)``, where the half-width from the
      axis point to the nearest wall (``through_axis=False``) reads ``R - e``.  Axes of a stenosis's
      throat lie 0.1-0.3 mm off its centre (their smoothing, the throat's eccentric plaque): the distance
      to the nearest wall would take that much off the graded minimal diameter.

    A section with a ray that was not measured (NaN: its wall lies beyond the image) is not measured
    either: both its radii are NaN.

    Parameters
    ----------
    rays : ndarray, shape (n, m)
        Wall distances along ``m`` rays evenly spaced in angle, mm; ``m`` even for the chords.
    arc_deg : float
        Arc of the running median, degrees.
    through_axis : bool
        Half the chord through the axis point (default); False: the distance from the axis point.

    Returns
    -------
    median, narrow : ndarray, shape (n,)
        mm; NaN for the sections not measured.
    """
    rays = np.asarray(rays, float)
    cut = ~np.all(np.isfinite(rays), axis=1)
    rays = np.where(cut[:, None], 0.0, rays)
    m = rays.shape[1]
    if through_axis and m % 2:
        raise ValueError(f"chords through the axis need an even number of rays (got {m})")
    reach = 0.5 * (rays + np.roll(rays, m // 2, axis=1)) if through_axis else rays  # half-chords or rays
    span = max(int(round(arc_deg / 360.0 * m)) | 1, 1)
    running = ndimage.median_filter(reach, size=(1, span), mode="wrap")
    median, narrow = np.median(rays, axis=1), running.min(axis=1)
    median[cut] = narrow[cut] = np.nan
    return median, narrow


def tangents(points: np.ndarray) -> np.ndarray:
    """Unit tangents (n, 3) of a polyline by central differences (one-sided at the ends)."""
    t = np.gradient(points, axis=0)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def normal_frames(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (n, 3) each spanning, with the other, the plane normal to a polyline (n, 3) at each
    point: ``u`` orthogonal to the tangent and to the x axis (the y axis where the tangent is near x), and
    ``v = t x u``."""
    t = tangents(points)
    helper = np.where(np.abs(t[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(t, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(t, u)


def recentre(wall: WallDistance, points: np.ndarray, max_shift: float, tol: float = 0.01) -> np.ndarray:
    """Move each axis point within its normal plane to the centre of the maximal inscribed sphere.

    A thinned axis lies up to about a voxel off the medial axis, and the inscribed radius drops by
    as much as the offset; this hill-climbs the wall distance in the plane orthogonal to the local tangent with
    halving steps (a move is kept only where it deepens the point), every point at once.

    Parameters
    ----------
    wall : WallDistance
    points : ndarray, shape (n, 3)
        Smoothed axis in mm; its end points (junctions shared with other branches, or open ends) stay.
    max_shift : float
        Largest displacement of a point, mm (the first step is half of it).
    tol : float
        Smallest step, mm.

    Returns
    -------
    ndarray, shape (n, 3)
    """
    if len(points) < 3:
        return points.copy()
    t = tangents(points)
    p = points.copy()
    depth = wall(p)
    h = 0.25 * float(min(wall.levelset.spacing))
    eye = np.eye(3)
    step = 0.5 * max_shift
    while step >= tol:
        for _ in range(2):
            grad = np.stack([wall(p + h * e) - wall(p - h * e) for e in eye], axis=1)
            grad -= np.sum(grad * t, axis=1, keepdims=True) * t
            norm = np.linalg.norm(grad, axis=1, keepdims=True)
            cand = p + step * grad / np.maximum(norm, 1e-12)
            cand_depth = wall(cand)
            ok = (cand_depth > depth) & (np.linalg.norm(cand - points, axis=1) <= max_shift) & (norm[:, 0] > 0)
            ok[[0, -1]] = False
            p[ok], depth[ok] = cand[ok], cand_depth[ok]
        step *= 0.5
    return p


def trim_open_end(points: np.ndarray, radii: np.ndarray, at_start: bool, keep: float = 0.75) -> np.ndarray:
    """Cut the tail of an axis where thinning bent it towards the rim of a closed, flat end.

    At a capped vessel end the skeleton stops about one radius short of the cap and its last stretch
    veers into a corner of the cap, where the inscribed radius falls.  Within the last 1.5 radii of arc
    (the radius ``R`` being the median over the 1.5 to 4 radii before the end), the axis is cut where the
    radius first drops below ``keep * R``.  An end at the image border, where the vessel is cut open, keeps
    its radius and is not touched.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    radii : ndarray, shape (n,)
    at_start : bool
        Whether the open end is the first point (the CCA inlet) rather than the last.
    keep : float

    Returns
    -------
    ndarray, shape (m, 3), m <= n
    """
    p, r = (points[::-1], radii[::-1]) if at_start else (points, radii)
    back = arclength(p[::-1])[::-1]  # arc length to the end
    ref = float(np.median(r[back <= 5.0]))  # first guess, over the last 5 mm
    body = (back >= 1.5 * ref) & (back <= 4.0 * ref)
    if body.sum() >= 3:
        ref = float(np.median(r[body]))
    low = np.flatnonzero((back < 1.5 * ref) & (r < keep * ref))
    if len(low) == 0 or low[0] < 2:
        return points
    p = p[:low[0]]
    return p[::-1] if at_start else p


def straighten_border_end(volume: Volume, points: np.ndarray, radius: float, at_start: bool) -> np.ndarray:
    """Continue the axis straight to the image border where a vessel leaves the image.

    Thinning extends a vessel cut by the border perpendicular to that border (see
    ``skeleton.skeletonize_lumen``), so where the vessel leaves the image obliquely the last radius or so
    of axis bends.  If the end point lies within a voxel of the border, the axis beyond 1.5 ``radius``
    from the end is replaced by its tangent line (fitted over 1.5 to 4 radii from the end) continued to
    the border.  Other ends are returned unchanged.

    Parameters
    ----------
    volume : Volume
        The image grid.
    points : ndarray, shape (n, 3)
        Axis in mm.
    radius : float
        Vessel radius near the end, mm.
    at_start : bool
        Whether the end is the first point (else the last).

    Returns
    -------
    ndarray, shape (m, 3)
    """
    p = points[::-1] if at_start else points
    shape = np.asarray(volume.array.shape)
    end_kji = volume.world_to_index(p[-1])
    if np.all((end_kji > 1.0) & (end_kji < shape - 2.0)):
        return points
    back = arclength(p[::-1])[::-1]
    fit = p[(back >= 1.5 * radius) & (back <= 4.0 * radius)]
    if len(fit) < 3:
        return points
    centre = fit.mean(axis=0)
    direction = np.linalg.svd(fit - centre)[2][0]
    direction = direction if direction @ (p[-1] - fit[0]) > 0 else -direction
    keep = p[back >= 1.5 * radius]
    start = centre + ((keep[-1] - centre) @ direction) * direction
    # Ray-box exit in index space, where the box is [0, n - 1] on each axis.
    k0 = volume.world_to_index(start)
    dk = volume.world_to_index(start + direction) - k0
    with np.errstate(divide="ignore", invalid="ignore"):
        exits = np.where(dk > 0, (shape - 1 - k0) / dk, np.where(dk < 0, -k0 / dk, np.inf))
    t = float(np.clip(exits.min(), 0.0, 4.0 * radius))
    tail = start + np.linspace(0.0, t, max(int(np.ceil(t / 0.1)), 1) + 1)[1:, None] * direction
    out = np.concatenate([keep[:-1], start[None], tail])
    return out[::-1] if at_start else out
