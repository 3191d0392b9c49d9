"""Figures: the paper's three-panel map view, the input/cell-tree view, a scored map's ROC curves
and reliability diagrams, and a voxel map's slices and occupied voxels.

Everything draws on :class:`matplotlib.figure.Figure` objects rendered with the Agg canvas, never
through ``pyplot``: no window is opened, no global backend is switched and no figure is kept alive by
a figure manager, so the functions are safe on headless machines and in long-running processes.

The figures know no reader or writer of maps: :func:`figure_png` renders one to PNG bytes, and
:func:`save_figure` writes those as one file (:mod:`gpomap.atomic_files`); the output sets of
:mod:`gpomap.io` draw their figures here and write them with their other files.
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import PatchCollection
from matplotlib.colorbar import Colorbar
from matplotlib.colors import BoundaryNorm, ListedColormap, to_rgb
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from numpy.typing import ArrayLike, NDArray

from gpomap.atomic_files import atomic_write
from gpomap.grid import OCCUPIED, OccupancyMap, ternary
from gpomap.resources import figure_step
from gpomap.voxels import VoxelMap

__all__ = [
    "plot_map",
    "plot_inputs",
    "plot_evaluation",
    "plot_slices",
    "plot_3d",
    "ScoreCurve",
    "figure_png",
    "save_figure",
    "PROBABILITY_CMAP",
    "VARIANCE_CMAP",
]

#: Diverging blue (free) to red (occupied), white at p = 0.5, like the paper's probability maps.
PROBABILITY_CMAP = "RdBu_r"
#: Blue where the map is sure (low variance) to red where it knows little.
VARIANCE_CMAP = "RdYlBu_r"
# Ternary colours in label order UNKNOWN (-1), FREE (0), OCCUPIED (1).
_TERNARY_CMAP = ListedColormap(["#9e9e9e", "#ffffff", "#000000"], name="gpomap_ternary")
_TERNARY_NORM = BoundaryNorm([-1.5, -0.5, 0.5, 1.5], _TERNARY_CMAP.N)
_PATH_COLOUR = "#19b219"
_FREE_COLOUR = "#2ca02c"
_HIT_COLOUR = "#d62728"


def _shown(values: NDArray, step: int) -> NDArray:
    """Every `step`-th row and column of a map's array (shape (ny, nx)), for drawing."""
    return values[::step, ::step] if step > 1 else values


def _new_figure(width: float, height: float, constrained: bool = True) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)  # attaches itself as fig.canvas
    return fig


def _fixed_margins(fig: Figure, n: int, left: float, right: float, gap: float, bottom: float, top: float) -> None:
    """Place `fig`'s row of `n` panels by margins in inches, instead of a layout engine, which
    measures every label in extra passes (most of a figure's time)."""
    width, height = fig.get_size_inches()
    panel_width = (width - left - right - (n - 1) * gap) / n
    fig.subplots_adjust(
        left=left / width, right=1 - right / width, bottom=bottom / height, top=1 - top / height, wspace=gap / panel_width
    )


def _colorbar(fig: Figure, ax: Axes, mappable: ScalarMappable, label: str) -> Colorbar:
    """A colour bar in an inset beside `ax`, so that ``fig.axes`` holds only the panels."""
    cax = ax.inset_axes((1.03, 0.0, 0.045, 1.0))
    cbar = fig.colorbar(mappable, cax=cax)
    cbar.set_label(label)
    return cbar


def _draw_path(ax: Axes, path: NDArray[np.float64], legend: bool) -> None:
    ax.plot(path[:, 0], path[:, 1], "-", color=_PATH_COLOUR, lw=1.3, label="robot path" if legend else None)
    ax.plot(path[0, 0], path[0, 1], "o", color=_PATH_COLOUR, ms=5, mec="k", mew=0.6, label="start" if legend else None)


def plot_map(occupancy_map: OccupancyMap, path: str | os.PathLike[str] | None = None, title: str | None = None) -> Figure:
    """The paper's three panels side by side: probability, latent variance, ternary map.

    Parameters
    ----------
    occupancy_map : OccupancyMap
        Probability and (optional) variance of shape (ny, nx) on its grid; ``path`` of shape (k, 2)
        is drawn on every panel when set.
    path : str or path-like, optional
        When given, the figure is also written there as a PNG (atomically).
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        ``fig.axes`` holds exactly the three panels (probability, variance, ternary); their colour
        bars are inset axes of the panels. Axes are in metres with equal aspect.
    """
    m = occupancy_map
    grid = m.grid
    ny, nx = grid.shape
    extent = grid.extent
    # Panel size follows the map's aspect ratio, within limits that keep labels readable.
    aspect = min(max(ny / nx, 0.4), 2.5)
    panel = 4.0
    fig = _new_figure(3 * (panel + 1.1), panel * aspect + (0.9 if title else 0.6), constrained=False)
    # The y labels left, a colour bar and its labels right of each panel.
    _fixed_margins(fig, 3, left=0.75, right=1.05, gap=1.25, bottom=0.5, top=0.3 + (0.35 if title else 0.0))
    axes = fig.subplots(1, 3, sharex=True, sharey=True)

    imshow = {"extent": extent, "origin": "lower", "interpolation": "nearest", "aspect": "equal"}
    step = figure_step((ny, nx))
    probability = _shown(m.probability, step)
    im = axes[0].imshow(probability, cmap=PROBABILITY_CMAP, vmin=0.0, vmax=1.0, **imshow)
    _colorbar(fig, axes[0], im, "occupancy probability")
    axes[0].set_title("probability")

    if m.variance is not None:
        var = m.variance
        finite = np.isfinite(var)
        top = float(np.max(var, where=finite, initial=-np.inf))  # of every cell, not the ones drawn
        vmax = top if top > 0 else 1.0
        im = axes[1].imshow(_shown(var, step), cmap=VARIANCE_CMAP, vmin=0.0, vmax=vmax, **imshow)
        _colorbar(fig, axes[1], im, "latent variance")
    else:
        # Keep the panel (and the three-panel layout) but say why it is empty.
        axes[1].imshow(np.full((len(range(0, ny, step)), len(range(0, nx, step))), np.nan), **imshow)
        axes[1].text(0.5, 0.5, "no variance", transform=axes[1].transAxes, ha="center", va="center", color="0.4")
    axes[1].set_title("latent variance")

    # The drawn cells' classes only (the whole map's would be sliced the same).
    seen = None if m.seen_through is None else _shown(m.seen_through, step)
    im = axes[2].imshow(ternary(probability, m.thresholds, seen), cmap=_TERNARY_CMAP, norm=_TERNARY_NORM, **imshow)
    cbar = _colorbar(fig, axes[2], im, "")
    cbar.set_ticks([-1, 0, 1], labels=["unknown", "free", "occupied"])
    axes[2].set_title(f"ternary (free < {m.thresholds[0]:.3g}, occupied > {m.thresholds[1]:.3g})")

    for i, ax in enumerate(axes):
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_xlabel("x [m]")
        if m.path is not None and len(m.path):
            _draw_path(ax, np.asarray(m.path, dtype=float), legend=i == 0)
    axes[0].set_ylabel("y [m]")
    if m.path is not None and len(m.path):
        axes[0].legend(loc="upper right", fontsize="small", framealpha=0.8)
    if title:
        fig.suptitle(title)
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_inputs(
    observations_points: ArrayLike,
    occupied_mask: ArrayLike,
    boxes: ArrayLike | None = None,
    box_labels: ArrayLike | None = None,
    path: str | os.PathLike[str] | None = None,
) -> Figure:
    """Training inputs: free points green, hits red, and optionally the cells (boxes) of the tree.

    Parameters
    ----------
    observations_points : array_like of shape (n, 2)
        Observation positions, metres.
    occupied_mask : array_like of bool, shape (n,)
        True for hits (occupied), False for free samples.
    boxes : array_like of shape (m, 2, 2), optional
        Rectangles ``[[xmin, ymin], [xmax, ymax]]``, such as the area supports of the paper's
        Fig. 3 / Fig. 5.
    box_labels : array_like of shape (m,), optional
        +1 (occupied: red) or -1 (free: green) per box; other values or no labels draw grey boxes.
    path : str or path-like, optional
        When given, the figure is also written there as a PNG (atomically).

    Returns
    -------
    matplotlib.figure.Figure
        One axes, metres, equal aspect.
    """
    pts = np.asarray(observations_points, dtype=float).reshape(-1, 2)
    occ = np.asarray(occupied_mask, dtype=bool).reshape(-1)
    if occ.shape[0] != pts.shape[0]:
        raise ValueError(f"{pts.shape[0]} points but {occ.shape[0]} occupied flags")
    fig = _new_figure(6.4, 5.6)
    ax = fig.subplots()

    # Marker area shrinks with the point count so that dense scans stay readable.
    size = float(np.clip(3000.0 / max(len(pts), 1), 0.3, 16.0))
    if boxes is not None:
        b = np.asarray(boxes, dtype=float).reshape(-1, 2, 2)
        labels = np.zeros(len(b)) if box_labels is None else np.asarray(box_labels).reshape(-1)
        if labels.shape[0] != b.shape[0]:
            raise ValueError(f"{b.shape[0]} boxes but {labels.shape[0]} box labels")
        colours = np.where(labels > 0, _HIT_COLOUR, np.where(labels < 0, _FREE_COLOUR, "0.45"))
        rects = [Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1]) for lo, hi in b]
        faces = [(*to_rgb(c), 0.12) for c in colours]
        ax.add_collection(PatchCollection(rects, facecolors=faces, edgecolors=list(colours), linewidths=1.2, zorder=1))
        if len(b):
            ax.update_datalim(b.reshape(-1, 2))
        # Legend proxies: a PatchCollection has no per-class legend entries of its own.
        for sign, colour, name in ((1, _HIT_COLOUR, "occupied cells"), (-1, _FREE_COLOUR, "free cells")):
            count = int(np.count_nonzero(labels > 0 if sign > 0 else labels < 0))
            if count:
                ax.add_patch(Rectangle((np.nan, np.nan), 0, 0, fc=(*to_rgb(colour), 0.12), ec=colour, label=f"{name} ({count})"))
    ax.scatter(
        pts[~occ, 0], pts[~occ, 1], s=size, c=_FREE_COLOUR, lw=0, label=f"free ({int((~occ).sum())})", zorder=2, rasterized=True
    )
    ax.scatter(
        pts[occ, 0], pts[occ, 1], s=size * 1.5, c=_HIT_COLOUR, lw=0, label=f"hits ({int(occ.sum())})", zorder=3, rasterized=True
    )
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper right", fontsize="small", markerscale=max(1.0, 4.0 / np.sqrt(size)), framealpha=0.85)
    if path is not None:
        save_figure(fig, path)
    return fig


@dataclass(frozen=True)
class ScoreCurve:
    """One scored prediction as :func:`plot_evaluation` draws it.

    Attributes
    ----------
    label : str
    scores : mapping
        :func:`gpomap.evaluation.score`'s dict: ``reliability`` and ``ece``; ``roc`` and ``auc``
        for the ROC panel.
    colour : str, optional
        A matplotlib colour (default: the next of the colour cycle).
    linestyle : str
    """

    label: str
    scores: Mapping[str, Any]
    colour: str | None = None
    linestyle: str = "-"


def plot_evaluation(
    panels: Sequence[tuple[str, Sequence[ScoreCurve]]], path: str | os.PathLike[str] | None = None, title: str | None = None
) -> Figure:
    """ROC curves and reliability diagrams: a column per split, a curve per prediction.

    Parameters
    ----------
    panels : sequence of (str, sequence of ScoreCurve)
        Each column's title (a split) and its curves.
    path : str or path-like, optional
        When given, the figure is also written there as a PNG (atomically).
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Two rows of panels, ROC curves above reliability diagrams; the reliability row alone when
        a curve has no ``roc``. ``fig.axes`` holds them row by row.
    """
    with_roc = all("roc" in c.scores for _, curves in panels for c in curves)
    rows = 2 if with_roc else 1
    fig = _new_figure(5.2 * len(panels), 4.6 * rows + (0.4 if title else 0.0))
    axes = np.asarray(fig.subplots(rows, len(panels), squeeze=False))
    for col, (name, curves) in enumerate(panels):
        if with_roc:
            ax = axes[0, col]
            ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="chance")
            for c in curves:
                roc = c.scores["roc"]
                ax.plot(roc["fpr"], roc["tpr"], c.linestyle, color=c.colour, label=f"{c.label} (AUC {c.scores['auc']:.3f})")
            ax.set(xlabel="false positive rate", ylabel="true positive rate", xlim=(0, 1), ylim=(0, 1), title=name)
            ax.legend(loc="lower right", fontsize=7)
        ax = axes[rows - 1, col]
        ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="calibrated")
        for c in curves:
            rel = c.scores["reliability"]
            # Empty bins have no point.
            x = [m for m, n in zip(rel["mean_prob"], rel["counts"], strict=True) if n]
            y = [f for f, n in zip(rel["frac_pos"], rel["counts"], strict=True) if n]
            ax.plot(x, y, c.linestyle, marker="o", ms=3, color=c.colour, label=f"{c.label} (ECE {c.scores['ece']:.3f})")
        ax.set(xlabel="predicted occupancy probability", ylabel="fraction occupied", xlim=(0, 1), ylim=(0, 1))
        if not with_roc:
            ax.set_title(name)
        ax.legend(loc="upper left", fontsize=7)
    if title:
        fig.suptitle(title)
    if path is not None:
        save_figure(fig, path)
    return fig


#: The tint over a slice's voxels no ray went to (the GP's guess there), RGBA.
UNOBSERVED_TINT = (0.35, 0.55, 0.85, 0.45)


def plot_slices(voxel_map: VoxelMap, heights: Sequence[float] | None = None, title: str | None = None) -> Figure:
    """Horizontal slices of the probability at `heights` (metres; default 4 evenly spread), as a
    figure; where the map knows which voxels rays went to, the others are tinted
    (:data:`UNOBSERVED_TINT`): their probability is the GP's guess, which reaches behind the
    surfaces and far into space no ray saw."""
    spec = voxel_map.spec
    zs = list(heights) if heights is not None else list(np.linspace(spec.lower[2], spec.upper[2], 6)[1:-1])
    width, height = 4.2 * len(zs) + 0.6, 4.4 + (0.35 if title else 0.0)
    fig = _new_figure(width, height, constrained=False)
    right, bottom, top = 1.2, 0.55, 0.35 + (0.35 if title else 0.0)  # the colour bar in the right margin
    _fixed_margins(fig, len(zs), left=0.7, right=right, gap=0.8, bottom=bottom, top=top)
    axes = fig.subplots(1, len(zs), squeeze=False)
    lo, hi = spec.lower, spec.upper
    image = None
    for ax, z in zip(axes[0], zs):
        k = spec.slice_index(z)
        extent = (lo[0], hi[0], lo[1], hi[1])
        image = ax.imshow(voxel_map.probability[k], origin="lower", extent=extent, cmap="gray_r", vmin=0, vmax=1)
        if voxel_map.observed is not None:
            tint = np.zeros((*voxel_map.observed[k].shape, 4))
            tint[~voxel_map.observed[k]] = UNOBSERVED_TINT
            ax.imshow(tint, origin="lower", extent=extent)
        ax.set_title(f"z = {spec.axis_centres('z')[k]:.2f} m")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    if image is not None:
        span = (height - bottom - top) / height
        cax = fig.add_axes(((width - right + 0.2) / width, bottom / height + 0.1 * span, 0.15 / width, 0.8 * span))
        fig.colorbar(image, cax=cax, label="occupancy probability")
    if voxel_map.observed is not None:
        axes[0][0].legend(
            handles=[Rectangle((0, 0), 1, 1, color=UNOBSERVED_TINT, label="no ray went there")],
            loc="upper right",
            fontsize="small",
            framealpha=0.85,
        )
    if title:
        fig.suptitle(title)
    return fig


def plot_3d(voxel_map: VoxelMap, title: str | None = None, max_points: int = 60000) -> Figure:
    """The occupied voxels (ternary OCCUPIED) as points coloured by height, in a 3-D view."""
    occ = voxel_map.ternary.reshape(-1) == OCCUPIED
    pts = voxel_map.spec.centres()[occ]
    if len(pts) > max_points:  # a figure cannot show more; an even thinning keeps the shapes
        pts = pts[:: int(np.ceil(len(pts) / max_points))]
    fig = _new_figure(8, 6.5, constrained=False)
    # Fixed places (no layout engine, as _fixed_margins): the view, and the colour bar at its right.
    ax = fig.add_subplot(projection="3d")
    ax.set_position((0.0, 0.02, 0.8, 0.9))
    sc = ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=pts[:, 2], s=1.5, cmap="viridis", depthshade=False)
    lo, hi = voxel_map.spec.lower, voxel_map.spec.upper
    ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-6)))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    fig.colorbar(sc, cax=fig.add_axes((0.87, 0.2, 0.025, 0.6)), label="height (m)")
    ax.set_title(title or f"occupied voxels ({len(pts):,} shown)")
    return fig


def figure_png(fig: Figure, dpi: int = 150) -> bytes:
    """`fig` rendered as a PNG (with the Agg canvas, attached if it has another).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    dpi : int

    Returns
    -------
    bytes
        The PNG file's content.
    """
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int = 150) -> Path:
    """Write `fig` as a PNG, atomically (the old file stays if rendering fails).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : str or path-like
    dpi : int

    Returns
    -------
    Path
        `path`.
    """
    # Rendered to memory first: a failing render then never even creates the temporary file.
    png = figure_png(fig, dpi)
    target = Path(path)
    with atomic_write(target, "wb") as f:
        f.write(png)
    return target
