"""Scoring against a true occupancy map on a grid: a simulated world's, a floor plan's, a ROS map's.

:class:`Truth` is the true map on the written maps' lattice; :func:`score_truth` scores
probabilities at its cell centres (AUC and occupied-class IoU, all cells and those the training
scans observed); :func:`score_against_truth` scores a fitted model against a simulated world.
Scoring against a plan's own pixels where the log looked is :mod:`gpomap.truth`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.maps import GRID_RESOLUTION
from gpomap.evaluation.scoring import auc_or_none
from gpomap.grid import DEFAULT_THRESHOLDS, GridSpec
from gpomap.metrics import fpr_at_tpr, iou, roc_auc

if TYPE_CHECKING:
    from gpomap.io.rosmap import RosMap


@dataclass(frozen=True)
class Truth:
    """A true occupancy map on a grid.

    Attributes
    ----------
    grid : GridSpec
    occupied : ndarray of bool, shape (ny, nx)
    known : ndarray of bool, shape (ny, nx)
        Cells to score (all of them by default).
    """

    grid: GridSpec
    occupied: NDArray[np.bool_]
    known: NDArray[np.bool_] | None = None

    @classmethod
    def from_world(cls, world: Any, resolution: float = GRID_RESOLUTION, wall_thickness: float | None = None) -> Truth:
        """A simulated world's true grid over its bounds (:meth:`gpomap.simulate.World.true_grid`), on
        the written maps' lattice (see :meth:`from_plan`)."""
        grid = GridSpec.from_extent(world.bounds, resolution, align=True)
        return cls(grid, world.true_grid(grid, wall_thickness))

    @classmethod
    def from_plan(
        cls,
        occupied_pixels: NDArray[np.bool_],
        lower_left: tuple[float, float],
        pixel_size: tuple[float, float],
        resolution: float = GRID_RESOLUTION,
        known_pixels: NDArray[np.bool_] | None = None,
    ) -> Truth:
        """A floor-plan bitmap resampled to `resolution`: a cell is occupied if any pixel in it is.

        The cells are those of every map written at `resolution` (corners on multiples of it, as
        ``gpomap map`` and the occupancy grids place theirs), not cells from the bitmap's corner:
        a map is scored cell for cell. Off that lattice every map cell straddles two true cells,
        and a wall one cell thick in the map is scored as two half-right cells, which costs a
        grid a good part of its IoU (docs/choices.md, "Measured for the code").

        Parameters
        ----------
        occupied_pixels : ndarray of bool, shape (h, w)
            Row 0 at the top (image order).
        lower_left : (x, y)
            Map-frame position of the bitmap's lower-left corner.
        pixel_size : (sx, sy)
            Pixel width and height, metres.
        resolution : float
        known_pixels : ndarray of bool, shape (h, w), optional
            The pixels the plan knows (default: every one); a cell is scored if any known pixel is
            in it, and occupied if any known occupied pixel is.
        """
        h, w = occupied_pixels.shape
        x0, y0 = lower_left
        grid = GridSpec.from_extent((x0, x0 + w * pixel_size[0], y0, y0 + h * pixel_size[1]), resolution, align=True)
        rows, cols = np.indices((h, w))
        centres = np.column_stack([x0 + (cols.ravel() + 0.5) * pixel_size[0], y0 + (h - rows.ravel() - 0.5) * pixel_size[1]])
        r, c, inside = grid.index_of(centres)
        scored = inside if known_pixels is None else inside & np.asarray(known_pixels, dtype=bool).ravel()
        occ = np.zeros(grid.shape, dtype=bool)
        hit = scored & occupied_pixels.ravel()
        occ[r[hit], c[hit]] = True
        known = np.zeros(grid.shape, dtype=bool)
        known[r[scored], c[scored]] = True
        return cls(grid, occ, known)

    @classmethod
    def from_rosmap(cls, rosmap: RosMap, resolution: float = GRID_RESOLUTION) -> Truth:
        """A ROS map_server map as the truth, resampled to `resolution` (:meth:`from_plan`).

        Its pixels are read as map_server reads them (:func:`gpomap.io.rosmap.read_rosmap`):
        occupied above the YAML's ``occupied_thresh``, free below ``free_thresh``, the rest unknown
        and not scored.
        """
        g = rosmap.grid
        # RosMap's rows start at the lowest y; from_plan takes image order.
        return cls.from_plan(
            rosmap.occupied[::-1], g.origin, (g.resolution, g.resolution), resolution, known_pixels=~rosmap.unknown[::-1]
        )

    def agreement(self, points: NDArray[np.float64], within: float = 0.1) -> float:
        """Share of `points` on the true map's walls: their cell within `within` of an occupied cell.

        A log and its true map in one frame put most hits on the walls; in different frames
        (another origin, a map frame against odometry) few.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
            Hits, metres. Points outside the grid count as off the walls.
        within : float
            Largest distance between the centres of a point's cell and an occupied cell, metres.

        Returns
        -------
        float
            In [0, 1]; 0 without points or without an occupied cell.
        """
        from scipy import ndimage

        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if len(pts) == 0 or not self.occupied.any():
            return 0.0
        # Distance from each cell's centre to the nearest occupied cell's centre, metres.
        distance = ndimage.distance_transform_edt(~self.occupied) * self.grid.resolution
        r, c, inside = self.grid.index_of(pts)
        near = distance[r[inside], c[inside]] <= within + 1e-9
        return float(near.sum() / len(pts))


def score_truth(
    truth: Truth,
    prob: NDArray[np.float64],
    observed: NDArray[np.bool_] | None = None,
    threshold: float = DEFAULT_THRESHOLDS[1],
    occupied: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """Score probabilities at the truth grid's cell centres against it.

    Parameters
    ----------
    truth : Truth
    prob : ndarray of shape (ny * nx,)
        Predicted occupancy at ``truth.grid.centres()``.
    observed : ndarray of bool, shape (ny * nx,), optional
        Cells the training data observed: also scored alone.
    threshold : float
        Occupied above this (the map's ternary threshold): the IoU's predicted class.
    occupied : ndarray of bool, shape (ny * nx,), optional
        The IoU's predicted class itself, the map's ternary map (:func:`occupied_at`,
        :func:`lookup_occupied`), in place of `prob` above `threshold`.

    Returns
    -------
    dict
        ``auc``, ``iou``, ``observed_auc``, ``observed_iou`` (None without `observed`),
        ``n_cells``, ``n_occupied_cells``.
    """
    known = np.ones(truth.occupied.size, bool) if truth.known is None else truth.known.ravel()
    y = truth.occupied.ravel()
    called = prob > threshold if occupied is None else np.asarray(occupied, dtype=bool)
    out: dict[str, Any] = {
        "auc": auc_or_none(y[known], prob[known]),
        "iou": iou(called[known], y[known]),
        "n_cells": int(known.sum()),
        "n_occupied_cells": int(y[known].sum()),
        "observed_auc": None,
        "observed_iou": None,
    }
    if observed is not None:
        sel = known & observed
        out["observed_auc"] = auc_or_none(y[sel], prob[sel])
        out["observed_iou"] = iou(called[sel], y[sel])
        out["n_observed_cells"] = int(sel.sum())
    return out


def score_against_truth(model: Any, world: Any, grid: GridSpec | float, wall_thickness: float | None = None) -> dict[str, Any]:
    """Score a fitted map against a simulated world's true occupancy on a grid.

    Parameters
    ----------
    model : fitted estimator
        Anything with ``predict_proba(points)``.
    world : gpomap.simulate.World
    grid : GridSpec or float
        The grid to score on; a float is a resolution over the world's bounds.
    wall_thickness : float, optional
        Width of the wall bands counted occupied (default the grid resolution, see
        :meth:`gpomap.simulate.World.true_grid`).

    Returns
    -------
    dict
        ``auc``, ``fpr_at_tpr95``, ``n_cells``, ``n_occupied_cells``, ``resolution``.
    """
    if not isinstance(grid, GridSpec):
        grid = GridSpec.from_extent(world.bounds, float(grid))
    truth = world.true_grid(grid, wall_thickness).ravel()
    prob = np.asarray(model.predict_proba(grid.centres()), dtype=float)
    return {
        "auc": roc_auc(truth, prob),
        "fpr_at_tpr95": fpr_at_tpr(truth, prob, 0.95),
        "n_cells": int(truth.size),
        "n_occupied_cells": int(truth.sum()),
        "resolution": grid.resolution,
    }
