"""Reading an occupancy grid: its file, its pixels' values, its known pixels as labelled points,
and the grid a converted map is written on.

A grid (a ROS map_server map, or an :class:`~gpomap.grid.OccupancyMap` such as one read from an
``.npz``) says how much of each pixel is occupied. Each known pixel's value is read as the
fraction of its area that is occupied (:func:`grid_fractions`), or by the grid's thresholds as
free / occupied / unknown (:func:`value_reading`); unknown pixels are not evidence.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError, InputFormatError
from gpomap.grid import FREE, OCCUPIED, GridSpec, OccupancyMap
from gpomap.io.npz import load_map
from gpomap.io.rosmap import RosMap, read_rosmap
from gpomap.observations import Observations

__all__ = [
    "GridSource",
    "VALUE_READINGS",
    "FRACTION_TOLERANCE",
    "GridObservations",
    "load_grid",
    "value_reading",
    "grid_fractions",
    "grid_to_observations",
    "output_grid",
]

GridSource = Union[RosMap, OccupancyMap, str, "os.PathLike[str]"]

# Tolerance for "the resolution divides the extent": relative to one output cell.
_DIVIDES_TOLERANCE = 1e-6


def load_grid(source: GridSource) -> RosMap | OccupancyMap:
    """Read a grid from a ROS map YAML or a gpomap ``.npz``; pass maps already read through.

    Parameters
    ----------
    source : RosMap, OccupancyMap, or path to a ``.yaml`` / ``.yml`` or ``.npz`` file

    Returns
    -------
    RosMap or OccupancyMap

    Raises
    ------
    InputFormatError
        Unknown suffix, or whatever the reader rejects (for example a rotated map origin).
    """
    if isinstance(source, (RosMap, OccupancyMap)):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        suffix = path.suffix.lower()
        if suffix in (".yaml", ".yml"):
            return read_rosmap(path)
        if suffix == ".npz":
            return load_map(path)
        raise InputFormatError(
            "cannot tell the grid format from the file name: expected a ROS map YAML (.yaml, .yml) or a gpomap map (.npz)",
            path=str(path),
        )
    raise TypeError(f"source must be a RosMap, an OccupancyMap or a path, got {type(source).__name__}")


#: How a grid's pixel values are read (:func:`grid_fractions`).
VALUE_READINGS = ("auto", "fraction", "ternary")
#: Values this close to 0 or 1 are wholly free or occupied (an 8-bit image's grey step is 1/255).
FRACTION_TOLERANCE = 0.005


def _labels(grid_map: RosMap | OccupancyMap) -> NDArray[np.int8]:
    """FREE / OCCUPIED / UNKNOWN per source pixel, ndarray of int8, shape (ny, nx)."""
    # RosMap.ternary keeps map_server's own reading (thresholds, modes, transparency);
    # OccupancyMap.ternary applies the map's thresholds, NaN probabilities being unknown.
    return np.asarray(grid_map.ternary, dtype=np.int8)


def value_reading(grid_map: RosMap | OccupancyMap, values: str = "auto") -> str:
    """How :func:`grid_fractions` reads `grid_map` with ``values``: ``"fraction"`` or ``"ternary"``.

    ``"auto"`` reads a ROS map in trinary mode (its values are codes) and a map with a latent
    variance (a GP's belief, such as gpomap's own ``.npz``) as ``"ternary"``; any other grid (a
    scale or raw ROS map, an OccupancyMap of plain values) as ``"fraction"``.
    """
    if values not in VALUE_READINGS:
        raise ValueError(f"values must be one of {VALUE_READINGS}, got {values!r}")
    if values != "auto":
        return values
    if isinstance(grid_map, RosMap):
        return "ternary" if grid_map.mode == "trinary" else "fraction"
    return "ternary" if grid_map.variance is not None else "fraction"


def grid_fractions(grid_map: RosMap | OccupancyMap, values: str = "auto") -> NDArray[np.float64]:
    """The occupied fraction of every source pixel, NaN where it is unknown, shape (ny, nx).

    Read as ``"fraction"``, a pixel's value is the fraction of its area that is occupied: a grid
    made by averaging a finer one (a 0.05 m pixel holding a 2 cm wall is 0.4) keeps its thin
    walls, where thresholding called them free. Values within :data:`FRACTION_TOLERANCE` of 0 or
    1 are wholly free or occupied; pixels the grid marks unknown (NaN in an
    :class:`~gpomap.grid.OccupancyMap`, transparent pixels of a scale-mode ROS map, raw values
    above 100) are unknown. Read as ``"ternary"``, pixels below the free threshold are free (0),
    above the occupied threshold occupied (1), between them unknown, as map_server reads a
    trinary map. ``"auto"``: see :func:`value_reading`.

    Parameters
    ----------
    grid_map : RosMap or OccupancyMap
    values : {"auto", "fraction", "ternary"}

    Returns
    -------
    ndarray of float64, shape (ny, nx)
    """
    if value_reading(grid_map, values) == "ternary":
        labels = _labels(grid_map)
        return np.where(labels == OCCUPIED, 1.0, np.where(labels == FREE, 0.0, np.nan))
    p = np.array(grid_map.probability, dtype=float)
    if isinstance(grid_map, RosMap):
        p[grid_map.unknown] = np.nan
    p[~np.isfinite(p)] = np.nan
    p = np.clip(p, 0.0, 1.0)
    p[p <= FRACTION_TOLERANCE] = 0.0
    p[p >= 1.0 - FRACTION_TOLERANCE] = 1.0
    return p


@dataclass(frozen=True)
class GridObservations(Observations):
    """Known pixel centres with the occupied fraction of each pixel.

    Attributes
    ----------
    fraction : ndarray of shape (n,)
        The occupied fraction of each pixel, in [0, 1] (:func:`grid_fractions`); ``occupied`` is
        ``fraction > 0`` (something in the pixel is occupied).
    values : str
        How the values were read (:func:`value_reading`): ``"fraction"`` or ``"ternary"``.
    """

    fraction: NDArray[np.float64] | None = None
    values: str = "fraction"


def grid_to_observations(grid_map: RosMap | OccupancyMap, values: str = "auto") -> GridObservations:
    """Known pixels of a grid as labelled points at their centres, with their occupied fractions.

    Parameters
    ----------
    grid_map : RosMap or OccupancyMap
        Row 0 at the lowest y. Free, occupied and partly occupied pixels are evidence; unknown pixels are not and give no point.
    values : {"auto", "fraction", "ternary"}
        How the pixels' values are read (:func:`grid_fractions`).

    Returns
    -------
    GridObservations
        ``points`` of shape (n_known, 2) in row-major pixel order, ``fraction`` and ``occupied``
        (fraction > 0) of shape (n_known,), ``scan_index`` all 0 (a grid has no scans).

    Raises
    ------
    EmptyDataError
        No known pixel, or no wholly free one, or none with anything occupied (a GP occupancy map
        needs free and occupied evidence).
    """
    fraction = grid_fractions(grid_map, values)
    known = np.isfinite(fraction)
    n_free = int((fraction == 0.0).sum())
    n_occ = int((fraction == 1.0).sum())
    n_partial = int(known.sum()) - n_free - n_occ
    n_unknown = int(fraction.size - known.sum())
    shape = f"{fraction.shape[0]} x {fraction.shape[1]}"
    if not known.any():
        raise EmptyDataError(f"the {shape} grid has no known pixels (all {n_unknown} unknown): nothing to convert")
    if n_free == 0 or n_occ + n_partial == 0:
        only = "free" if n_free else "occupied"
        raise EmptyDataError(
            f"the {shape} grid has only {only} known pixels ({n_free} free, {n_occ} occupied, {n_partial} partly "
            f"occupied, {n_unknown} unknown): a GP occupancy map needs both free and occupied pixels"
        )
    rows, cols = np.nonzero(known)
    g = grid_map.grid
    points = np.column_stack([g.x_centres()[cols], g.y_centres()[rows]])
    f = fraction[rows, cols]
    return GridObservations(
        points=points,
        occupied=f > 0.0,
        scan_index=np.zeros(points.shape[0], dtype=np.intp),
        fraction=f,
        values=value_reading(grid_map, values),
    )


def _cells_along(length: float, resolution: float) -> tuple[int, bool]:
    """Whole cells of side `resolution` covering `length`, and whether they fit it exactly."""
    ratio = length / resolution
    nearest = round(ratio)
    if nearest >= 1 and abs(ratio - nearest) <= _DIVIDES_TOLERANCE * max(1.0, ratio):
        return int(nearest), True
    return max(1, math.ceil(ratio)), False


def output_grid(
    source: GridSpec, resolution: float | None = None, extent: tuple[float, float, float, float] | None = None
) -> GridSpec:
    """The grid a converted map is written on.

    Parameters
    ----------
    source : GridSpec
        The source grid.
    resolution : float, optional
        Output cell side, metres; default the source's.
    extent : (xmin, xmax, ymin, ymax), optional
        Region to cover; default the source's extent.

    Returns
    -------
    GridSpec
        Origin = ``(xmin, ymin)`` of the extent (the source's origin by default). When `resolution`
        divides the extent's width / height (to a relative 1e-6 of a cell, which forgives float
        noise such as 19.2 / 0.01), the grid ends exactly on its right / top edge; otherwise it has
        one more cell there, ending less than one cell beyond the edge.
    """
    res = source.resolution if resolution is None else float(resolution)
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number, got {resolution}")
    xmin, xmax, ymin, ymax = source.extent if extent is None else (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"extent must have xmin < xmax and ymin < ymax, got {extent}")
    nx, _ = _cells_along(xmax - xmin, res)
    ny, _ = _cells_along(ymax - ymin, res)
    return GridSpec((xmin, ymin), res, (ny, nx))
