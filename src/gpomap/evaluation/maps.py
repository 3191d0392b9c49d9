"""The maps an evaluation scores: a method's model, its written grid, and reading both at points.

:func:`make_model` builds the estimator a method of the registry names
(:mod:`gpomap.evaluation.methods`); :func:`written_grid` is the map
``gpomap map`` writes for a fitted model (an occupancy grid's is its own grid);
:func:`lookup` and :func:`lookup_occupied` read a written map's cell at each point;
:func:`occupied_at` is a fitted model's own ternary call at points.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.methods import method_named
from gpomap.grid import DEFAULT_THRESHOLDS, OCCUPIED, OccupancyMap
from gpomap.protocol import Mapper, OwnGrid, TernaryPredictor

#: The written map's resolution (m) unless told otherwise.
GRID_RESOLUTION = 0.05


def make_model(
    method: str, kernel: str | None = None, seed: int = 0, resolution: float = 0.1, n_workers: int | None = None, **options: Any
) -> Mapper:
    """The estimator `method` names (:data:`gpomap.evaluation.methods.REGISTRY`), with `options`
    passed to its constructor.

    Parameters
    ----------
    method : str
        A name of :data:`gpomap.evaluation.methods.METHODS` ("ogm" is "ogm-logodds").
    kernel : {"se", "matern32"}, optional
        Point kernel of the GP methods (default: each method's own default). Ignored by the grids.
    seed : int
        Ignored by the grids.
    resolution : float
        Cell side of the grids (the GP methods predict anywhere).
    n_workers : int, optional
        "msk": workers for its tiles (default: the CPU count, as ``gpomap map``).

    Raises
    ------
    ValueError
        An unknown method.
    """
    return method_named(method).build(kernel, seed, resolution, n_workers, **options)


def n_inputs(model: Any) -> int:
    """GP inputs of a fitted model (cells, beams or points); for a grid, the cells it observed."""
    if hasattr(model, "n_inputs_"):
        return int(model.n_inputs_)
    # Occupancy grid: the cells it observed are its "inputs".
    return int((model.observed_ > 0).sum())


def written_grid(model: Mapper, resolution: float = GRID_RESOLUTION) -> OccupancyMap:
    """The map ``gpomap map`` writes for a fitted model, at `resolution` over the data's extent.

    MSK-GPOM and the GP baselines: ``grid(resolution)``; an occupancy grid
    (:class:`~gpomap.protocol.OwnGrid`): its own grid (it has no finer map to give).
    """
    if isinstance(model, OwnGrid):
        return model.grid_map()
    return model.grid(resolution)


def lookup(occupancy_map: OccupancyMap, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Probability of the written map's cell holding each point (0.5 outside the map), shape (n,)."""
    rows, cols, inside = occupancy_map.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.full(len(rows), 0.5)
    out[inside] = occupancy_map.probability[rows[inside], cols[inside]]
    return out


def lookup_occupied(occupancy_map: OccupancyMap, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether the written map's ternary map calls the cell holding each point occupied (False
    outside the map), shape (n,)."""
    rows, cols, inside = occupancy_map.grid.index_of(np.asarray(points, dtype=float).reshape(-1, 2))
    out = np.zeros(len(rows), dtype=bool)
    out[inside] = occupancy_map.ternary[rows[inside], cols[inside]] == OCCUPIED
    return out


def occupied_at(model: Mapper, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether a fitted model's ternary map calls each point occupied, shape (n,): its own
    ``predict_ternary`` where it has one (:class:`~gpomap.protocol.TernaryPredictor`: MSK-GPOM's
    fitted threshold, cells beams saw through never occupied), else its probability above the
    paper's occupied threshold (the grids)."""
    if isinstance(model, TernaryPredictor):
        return np.asarray(model.predict_ternary(points)) == OCCUPIED
    return np.asarray(model.predict_proba(points), dtype=float) > DEFAULT_THRESHOLDS[1]
