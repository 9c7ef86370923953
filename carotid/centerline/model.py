"""The centerline model shared by the centerline, surface and mesh stages.

Every coordinate is in mm in the image's physical (LPS) frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Branch:
    """One vessel axis between two graph nodes.

    Attributes
    ----------
    name : str
        ``"CCA"``, ``"ICA"``, ``"ECA"``, or ``"branch<k>"`` for any further branch.
    points : ndarray, shape (n, 3)
        Smoothed axis points in mm. The CCA runs from its inlet end to the bifurcation;
        every other branch runs from the bifurcation outward to its outlet end.
    radii : ndarray, shape (n,)
        Radius of the maximal inscribed sphere at each point, mm.
    areas : ndarray, shape (n,), optional
        Area of the lumen section normal to the axis at each point, mm^2 (``axes.section_areas``); NaN where
        the image border cuts the section.
    median_radii, narrow_radii : ndarray, shape (n,), optional
        Median radius and half the narrowest diameter of the section normal to the axis at each point, mm
        (``axes.section_profile``): the stenosis grading's robust measures of a rough wall; NaN where the
        image border cuts the section.
    """

    name: str
    points: np.ndarray
    radii: np.ndarray
    areas: np.ndarray | None = None
    median_radii: np.ndarray | None = None
    narrow_radii: np.ndarray | None = None

    @property
    def length_mm(self) -> float:
        """Arc length of the axis, mm."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())

    def end_tangent(self, end: int) -> np.ndarray:
        """Unit tangent pointing out of the vessel at ``end`` (0: first point, -1: last point), shape (3,).

        Taken over the last ~2 radii of axis so that voxel-scale wiggles do not tilt it.
        """
        pts = self.points if end == -1 else self.points[::-1]
        span = max(2.0 * float(self.radii[-1 if end == -1 else 0]), 1e-6)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts[::-1], axis=0), axis=1))])
        k = int(np.searchsorted(arc, span))
        k = min(max(k, 1), len(pts) - 1)
        t = pts[-1] - pts[-1 - k]
        return t / np.linalg.norm(t)


@dataclass
class Centerlines:
    """The branch graph of one bifurcation.

    Attributes
    ----------
    branches : list of Branch
        The CCA first, then the ICA and ECA (when found), then any further branches.
    bifurcation : ndarray, shape (3,)
        The bifurcation point in mm.
    info : dict
        Features (stenosis, lengths, tortuosity) as written to ``geometry.json``.
    """

    branches: list[Branch]
    bifurcation: np.ndarray
    info: dict = field(default_factory=dict)

    def branch(self, name: str) -> Branch:
        """The branch called ``name``; KeyError if there is none."""
        for b in self.branches:
            if b.name == name:
                return b
        raise KeyError(name)

    def ends(self) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
        """The open ends of the vessel tree: the CCA inlet first, then each outlet.

        Returns
        -------
        list of (branch name, point (3,) mm, outward unit tangent (3,), radius mm)
        """
        out = []
        for b in self.branches:
            end = 0 if b.name == "CCA" else -1
            out.append((b.name, b.points[end].copy(), b.end_tangent(end), float(b.radii[end])))
        return out


def nearest_axis_points(points: np.ndarray, branches) -> tuple[np.ndarray, np.ndarray]:
    """The centerline point nearest to each point: its branch and its index along that branch.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Query points (wall nodes, triangle centroids), mm.
    branches : list of Branch
        Centerline branches.

    Returns
    -------
    branch : ndarray of int, shape (n,)
        Index of the branch in ``branches``.
    index : ndarray of int, shape (n,)
        Index of the nearest point in that branch's ``points``.
    """
    from scipy.spatial import cKDTree

    axis = np.concatenate([b.points for b in branches])
    sizes = np.array([len(b.points) for b in branches])
    owner = np.repeat(np.arange(len(branches)), sizes)
    local = np.arange(len(axis)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    nearest = cKDTree(axis).query(points)[1]
    return owner[nearest], local[nearest]


def branch_regions(points: np.ndarray, branches) -> np.ndarray:
    """Index of the branch whose axis passes nearest to each point.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Wall points, mm.
    branches : list of Branch
        Centerline branches.

    Returns
    -------
    ndarray of int, shape (n,)
    """
    return nearest_axis_points(points, branches)[0]
