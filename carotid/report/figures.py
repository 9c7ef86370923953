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


def segmentation_slices(image: Volume, mask: Volume, centre_kji=None, window=(-100.0, 600.0)) -> bytes:
    """Axial, coronal and sagittal slices through ``centre_kji`` with the lumen contour in red.

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
    """
    plt = _pyplot()
    inside = mask.array > 0
    if centre_kji is None:
        centre_kji = np.round(np.argwhere(inside).mean(axis=0)).astype(int) if inside.any() else \
            np.array(inside.shape) // 2
    k, j, i = (int(c) for c in centre_kji)
    sk, sj, si = image.spacing_kji
    views = [("axial", image.array[k], inside[k], sj / si), ("coronal", image.array[:, j], inside[:, j], sk / si),
             ("sagittal", image.array[:, :, i], inside[:, :, i], sk / sj)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    for ax, (name, picture, contour, aspect) in zip(axes, views):
        origin = "upper" if name == "axial" else "lower"
        ax.imshow(picture, cmap="gray", vmin=window[0], vmax=window[1], aspect=aspect, origin=origin)
        if contour.any():
            ax.contour(contour.astype(float), [0.5], colors="red", linewidths=1.0, origin=origin)
        ax.set_title(name)
        ax.axis("off")
    return _png(fig)


def _plotter():
    import pyvista as pv

    plotter = pv.Plotter(off_screen=True, window_size=WINDOW)
    plotter.set_background("white")
    return plotter


def _screenshot(plotter) -> bytes:
    from PIL import Image

    array = plotter.screenshot(return_img=True)
    plotter.close()
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def surface_view(surface, centerlines=None, scalars: str = "CellEntityIds", cmap: str = "tab10",
                 clim=None, title: str | None = None) -> bytes:
    """The surface coloured by a cell or point array, with the centerlines as tubes.

    Parameters
    ----------
    surface : pyvista.PolyData
        Lumen surface in mm.
    centerlines : pyvista.PolyData, optional
        Polylines with ``MaximumInscribedSphereRadius``.
    scalars : str
        Array to colour by (``CellEntityIds`` shows wall, inlet and outlets).
    cmap, clim, title
        Colour map, its limits and the scalar-bar title.
    """
    plotter = _plotter()
    opacity = 0.45 if centerlines is not None else 1.0
    plotter.add_mesh(surface, scalars=scalars, cmap=cmap, clim=clim, opacity=opacity, smooth_shading=True,
                     scalar_bar_args={"title": title or scalars, "color": "black"})
    if centerlines is not None and centerlines.n_points:
        plotter.add_mesh(centerlines.tube(radius=0.25), color="black")
    face_on(plotter, np.asarray(surface.points))
    return _screenshot(plotter)


def face_on(plotter, points: np.ndarray) -> None:
    """Look at ``points`` (n, 3) along their least principal axis, the longest one upright.

    A bifurcation lies roughly in a plane; seen along that plane's normal, both daughters show.
    """
    centre = points.mean(axis=0)
    _, _, axes = np.linalg.svd(points - centre, full_matrices=False)
    extent = np.ptp(points @ axes[0])
    plotter.camera_position = [tuple(centre + 2.0 * extent * axes[2]), tuple(centre), tuple(axes[0])]


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
