"""Pictures of a case for the HTML report, rendered off-screen to PNG bytes.

Slices use matplotlib (Agg); 3-D views use pyvista's off-screen plotter,
which needs no display (VTK's EGL window with Mesa; ``xvfb-run`` is the
fallback where EGL is missing).  Every function returns PNG bytes.
"""

from __future__ import annotations

import io
import os

import numpy as np

from carotid.io import Volume

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
WINDOW = (900, 700)  # pixels of a 3-D view


def _png(fig) -> bytes:
    """A matplotlib figure as PNG bytes (the figure is closed)."""
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def slice_panels(image: Volume, mask: Volume, centre_kji=None, window=(-100.0, 600.0)):
    """Draw axial, coronal and sagittal slices through ``centre_kji`` with the lumen contour in red.

    Each slice is shown with ``imshow``, which puts array element (row r, column c) at data point
    (x = c, y = r); the contour is traced on the same array with no ``origin`` of its own, so its
    vertices are in that same (column, row) frame whatever way up the image is displayed.  Axial
    slices have row 0 (anterior in LPS) at the top and column 0 (the patient's right) on the left,
    the radiological convention; coronal and sagittal slices have the highest ``k`` (superior) at the top.

    Parameters
    ----------
    image : Volume
        CT in HU.
    mask : Volume
        Lumen mask on the same grid (nonzero inside).
    centre_kji : sequence of 3 int, optional
        Slice indices; the centroid of the mask by default.
    window : (float, float)
        Display window in HU.

    Returns
    -------
    (matplotlib.figure.Figure, list of dict)
        The figure and one dict per panel: ``name``, ``picture`` (the 2-D slice, HU), ``axes``,
        ``contour`` (the ``QuadContourSet``, or None when the slice misses the lumen).
    """
    plt = _pyplot()
    inside = mask.array > 0
    if centre_kji is None:
        centre_kji = np.round(np.argwhere(inside).mean(axis=0)).astype(int) if inside.any() else \
            np.array(inside.shape) // 2
    k, j, i = (int(c) for c in centre_kji)
    sk, sj, si = image.spacing_kji
    views = [("axial", image.array[k], inside[k], sj / si, "upper"),
             ("coronal", image.array[:, j], inside[:, j], sk / si, "lower"),
             ("sagittal", image.array[:, :, i], inside[:, :, i], sk / sj, "lower")]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    panels = []
    for ax, (name, picture, region, aspect, origin) in zip(axes, views):
        ax.imshow(picture, cmap="gray", vmin=window[0], vmax=window[1], aspect=aspect, origin=origin)
        contour = ax.contour(region.astype(float), [0.5], colors="red", linewidths=1.0) if region.any() else None
        ax.set_title(name)
        ax.axis("off")
        panels.append({"name": name, "picture": picture, "axes": ax, "contour": contour})
    return fig, panels


def segmentation_slices(image: Volume, mask: Volume, centre_kji=None, window=(-100.0, 600.0)) -> bytes:
    """The slices of :func:`slice_panels` as PNG bytes."""
    return _png(slice_panels(image, mask, centre_kji, window)[0])


def _plotter(window=WINDOW):
    import pyvista as pv

    plotter = pv.Plotter(off_screen=True, window_size=window)
    plotter.set_background("white")
    return plotter


def _screenshot(plotter) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(_snapshot(plotter)).save(buffer, format="PNG")
    return buffer.getvalue()


def _snapshot(plotter) -> np.ndarray:
    """The plotter's picture as an RGB array (the plotter is closed)."""
    array = plotter.screenshot(return_img=True)
    plotter.close()
    return array


# Names of the six LPS half-axes, as the side a viewer stands on.
_SIDES = {(0, 1): "left", (0, -1): "right", (1, 1): "posterior", (1, -1): "anterior", (2, 1): "superior",
          (2, -1): "inferior"}


def face_on(plotter, points: np.ndarray, side: float = 1.0) -> np.ndarray:
    """Look at ``points`` (n, 3) along their least principal axis, the longest one upright.

    A bifurcation lies roughly in a plane; seen along that plane's normal, both daughters show.  The
    longest axis points to the superior side (+z in LPS) so the head is up; ``side`` +1 puts the
    camera on the anterior-or-left side of the plane, -1 on the opposite side.

    Returns
    -------
    ndarray, shape (3,)
        Unit vector from the points' centre towards the camera.
    """
    centre = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - centre, full_matrices=False)
    up = axes[0] * (1.0 if axes[0][2] >= 0 else -1.0)
    normal = axes[2] * (1.0 if axes[2] @ np.array([1.0, -1.0, 0.0]) >= 0 else -1.0) * np.sign(side)
    extent = np.ptp(points @ axes[0])
    plotter.camera_position = [tuple(centre + 2.0 * extent * normal), tuple(centre), tuple(up)]
    plotter.reset_camera()
    return normal


def side_name(direction: np.ndarray) -> str:
    """The LPS side a view direction (3,) mostly points to: ``"left"``, ``"anterior"``, ..."""
    axis = int(np.argmax(np.abs(direction)))
    return _SIDES[(axis, int(np.sign(direction[axis])))]


def two_views(add, points: np.ndarray, window=(420, 760)) -> list[tuple[str, np.ndarray]]:
    """Render a scene face-on from both sides of its plane.

    Parameters
    ----------
    add : callable
        ``add(plotter)`` puts the meshes in a fresh off-screen plotter.
    points : ndarray, shape (n, 3)
        Points that define the view (:func:`face_on`), mm.
    window : (int, int)
        Pixels of each view (portrait: the vessels run upright).

    Returns
    -------
    list of (str, ndarray)
        ``("seen from the left", RGB array)`` and the opposite view.
    """
    views = []
    for side in (1.0, -1.0):
        plotter = _plotter(window)
        add(plotter)
        direction = face_on(plotter, points, side)
        views.append((f"seen from the {side_name(direction)}", _snapshot(plotter)))
    return _crop(views)


def _crop(views: list[tuple[str, np.ndarray]], margin: int = 6) -> list[tuple[str, np.ndarray]]:
    """Views cut to the smallest common box holding every non-white pixel of any of them."""
    content = np.any(np.stack([picture for _, picture in views])[..., :3] < 250, axis=(0, 3))
    if not content.any():
        return views
    rows, cols = np.flatnonzero(content.any(axis=1)), np.flatnonzero(content.any(axis=0))
    r0, r1 = max(rows[0] - margin, 0), rows[-1] + margin + 1
    c0, c1 = max(cols[0] - margin, 0), cols[-1] + margin + 1
    return [(title, picture[r0:r1, c0:c1]) for title, picture in views]


def _views_figure(views, width: float = 4.6):
    """A matplotlib figure of RGB views side by side with their titles, and room below for a legend."""
    plt = _pyplot()
    height = width * views[0][1].shape[0] / (len(views) * views[0][1].shape[1]) + 0.9
    fig, axes = plt.subplots(1, len(views), figsize=(width, height), gridspec_kw={"wspace": 0.02})
    for ax, (title, picture) in zip(np.atleast_1d(axes), views):
        ax.imshow(picture)
        ax.set_title(title, fontsize=11)
        ax.axis("off")
    return fig, np.atleast_1d(axes)


def wall_map(wall, scalars: str, label: str, clim: tuple[float, float], cmap: str = "viridis") -> bytes:
    """A wall index on the surface from both sides, with a horizontal colour bar under the views.

    Values outside ``clim`` take the end colours; the bar shows a pointed end on each side where
    some values were clipped, and its label (below the ticks) carries the name and unit.

    Parameters
    ----------
    wall : pyvista.PolyData
        Wall surface with the point array ``scalars``, mm.
    scalars : str
        Point array to show.
    label : str
        Colour-bar label with its unit, e.g. ``"TAWSS (Pa)"``.
    clim : (float, float)
        Colour range.
    cmap : str
        A perceptually uniform matplotlib colour map.
    """
    import matplotlib as mpl

    values = np.asarray(wall[scalars])
    views = two_views(lambda p: p.add_mesh(wall, scalars=scalars, cmap=cmap, clim=clim, show_scalar_bar=False,
                                           smooth_shading=True), np.asarray(wall.points))
    fig, axes = _views_figure(views)
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
        (bool(np.nanmin(values) < clim[0]), bool(np.nanmax(values) > clim[1]))]
    bar = fig.colorbar(mpl.cm.ScalarMappable(mpl.colors.Normalize(*clim), cmap=cmap), ax=list(axes),
                       orientation="horizontal", fraction=0.05, pad=0.03, aspect=30, extend=extend)
    bar.set_label(label, fontsize=12)
    bar.ax.tick_params(labelsize=10)
    return _png(fig)


def labelled_surface(surface, labels: np.ndarray, legend: list[tuple[str, str]], marker=None,
                     centerlines=None) -> bytes:
    """The surface coloured by category from both sides, with a legend of the category names.

    Parameters
    ----------
    surface : pyvista.PolyData
        Lumen surface, mm.
    labels : ndarray of int, shape (n_cells,)
        Category of each cell, an index into ``legend``.
    legend : list of (str, str)
        Name and matplotlib colour of each category.
    marker : (ndarray (3,), str), optional
        A point (mm) drawn as a red sphere, with its legend text (the stenosis).
    centerlines : pyvista.PolyData, optional
        Polylines drawn as thin black tubes.
    """
    import matplotlib.colors as mcolors
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    import pyvista as pv

    colours = np.array([mcolors.to_rgb(colour) for _, colour in legend])
    painted = surface.copy()
    painted.cell_data["colour"] = (colours[labels] * 255).astype(np.uint8)
    radius = 0.02 * float(np.ptp(np.asarray(surface.points), axis=0).max())  # marker, mm

    def add(plotter):
        plotter.add_mesh(painted, scalars="colour", rgb=True, opacity=0.5 if marker is not None else 1.0,
                         smooth_shading=True)
        if centerlines is not None and centerlines.n_points:
            plotter.add_mesh(centerlines.tube(radius=0.2), color="black")
        if marker is not None:
            plotter.add_mesh(pv.Sphere(radius=radius, center=marker[0]), color="red")

    fig, axes = _views_figure(two_views(add, np.asarray(surface.points)))
    handles = [Patch(facecolor=colour, edgecolor="0.3", label=name) for name, colour in legend]
    if marker is not None:
        handles.append(Line2D([], [], marker="o", color="red", linestyle="", label=marker[1]))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), fontsize=8, frameon=False)
    return _png(fig)


def mesh_cut_view(mesh, normal=(1.0, 0.0, 0.0), origin=None, zoom: float = 1.0) -> bytes:
    """Tetrahedra cut by a plane (cells on one side kept whole, edges drawn), showing the wall layers.

    Parameters
    ----------
    mesh : pyvista.UnstructuredGrid
        Volume mesh in mm.
    normal : (3,) float
        Normal of the cutting plane.
    origin : (3,) float, optional
        A point of the plane; the mesh centre by default.
    zoom : float
        Camera zoom; > 1 for a close-up of the wall.
    """
    import pyvista as pv

    tets = mesh.extract_cells_by_type(pv.CellType.TETRA)
    cut = tets.clip(normal=normal, origin=origin or tets.center, crinkle=True)
    plotter = _plotter()
    scalars = "Region" if "Region" in cut.cell_data else None
    plotter.add_mesh(cut, scalars=scalars, show_edges=True, cmap="Pastel1", edge_color="black", line_width=0.3,
                     show_scalar_bar=False)
    face_on(plotter, np.asarray(cut.points))
    plotter.camera.zoom(zoom)
    return _screenshot(plotter)


def time_series(series: dict[str, tuple[np.ndarray, np.ndarray]], xlabel: str, ylabel: str,
                title: str = "") -> bytes:
    """Line plot of named (x, y) series."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for name, (x, y) in series.items():
        ax.plot(x, y, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if len(series) > 1:
        ax.legend()
    return _png(fig)


def histogram(values: dict[str, np.ndarray], xlabel: str, bins=40, title: str = "") -> bytes:
    """Overlaid histograms of named samples."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.4))
    for name, v in values.items():
        ax.hist(np.asarray(v).ravel(), bins=bins, alpha=0.6, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    ax.set_title(title)
    if len(values) > 1:
        ax.legend()
    return _png(fig)


def diameter_profile(s: np.ndarray, narrow: np.ndarray, median: np.ndarray, stenosis: dict | None,
                     xlabel: str) -> bytes:
    """Lumen diameter along a vessel axis, with the stenosis and its reference diameters marked.

    Parameters
    ----------
    s : ndarray, shape (n,)
        Arc length, mm (0 at the bifurcation).
    narrow, median : ndarray, shape (n,)
        The two diameters the stenosis is graded on (``carotid.centerline.features.grading_profiles``): twice
        half the narrowest diameter of each section (the residual lumen) and twice its median radius (the
        vessel), mm.
    stenosis : dict, optional
        ``geometry.json``'s stenosis: ``arclength_from_bifurcation_mm``, ``min_diameter_mm``,
        ``distal_diameter_mm`` (NASCET reference), ``local_diameter_mm`` (ECST reference).
    xlabel : str
        Label of the arc-length axis.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.4, 3.3))
    ax.plot(s, narrow, color="C0", label="narrowest width (graded lumen)")
    ax.plot(s, median, color="C0", alpha=0.45, linestyle="--", label="median diameter (graded vessel)")
    ax.axvline(0.0, color="0.5", linewidth=0.8)
    ax.annotate("bifurcation", (0.0, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -12),
                textcoords="offset points", fontsize=8, color="0.4")
    if stenosis is not None:
        at = stenosis["arclength_from_bifurcation_mm"]
        ax.plot([at], [stenosis["min_diameter_mm"]], "o", color="red",
                label=f"minimal diameter {stenosis['min_diameter_mm']:.2f} mm")
        ax.axhline(stenosis["distal_diameter_mm"], color="C2", linestyle=":",
                   label=f"NASCET reference (distal) {stenosis['distal_diameter_mm']:.2f} mm")
        ax.plot([at], [stenosis["local_diameter_mm"]], "s", color="C1", markerfacecolor="none",
                label=f"ECST reference (local) {stenosis['local_diameter_mm']:.2f} mm")
        ax.vlines(at, stenosis["min_diameter_mm"], stenosis["local_diameter_mm"], color="red", linewidth=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("diameter (mm)")
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="lower left")
    return _png(fig)
