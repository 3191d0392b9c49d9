"""Regular grids and the occupancy map sampled on them.

Conventions (the same as ROS map_server): `origin` is the map-frame position of the lower-left
corner of the lower-left cell; arrays are indexed ``[row, col]`` with row 0 at the *lowest* y
(unlike an image, whose row 0 is the top: writers flip). Cell ``(i, j)`` has its centre at
``origin + ((j + 0.5) * resolution, (i + 0.5) * resolution)``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gpomap.progress import progress

FREE: int = 0
OCCUPIED: int = 1
UNKNOWN: int = -1

#: The paper's thresholds: free below 0.33, occupied above 0.66, unknown between.
DEFAULT_THRESHOLDS: tuple[float, float] = (0.33, 0.66)
#: The ternary thresholds of a map whose probabilities are calibrated (one with ray evidence):
#: occupied where a cell is more likely occupied than not, free below map_server's free threshold
#: (a cell under 0.196 is free to a ROS navigation stack).
CALIBRATED_THRESHOLDS: tuple[float, float] = (0.196, 0.5)


@dataclass(frozen=True)
class GridSpec:
    """Geometry of a regular 2-D grid.

    Parameters
    ----------
    origin : tuple of float
        (x, y) of the lower-left corner of the lower-left cell, metres.
    resolution : float
        Cell side, metres.
    shape : tuple of int
        (rows, cols) = (ny, nx).
    """

    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"grid resolution must be a positive number, got {self.resolution}")
        ny, nx = (int(v) for v in self.shape)
        if ny <= 0 or nx <= 0:
            raise ValueError(f"grid shape must be positive, got {self.shape}")
        object.__setattr__(self, "shape", (ny, nx))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "resolution", float(self.resolution))

    @classmethod
    def from_extent(cls, extent: tuple[float, float, float, float], resolution: float, align: bool = False) -> GridSpec:
        """The grid of cells of side `resolution` covering `extent` = (xmin, xmax, ymin, ymax).

        The origin is `(xmin, ymin)`, or with `align` the multiple of `resolution` at or below
        each (then the cells are those of every aligned grid of that resolution, the ray
        counts' among them); the grid extends past `xmax` / `ymax` to a whole cell.
        """
        xmin, xmax, ymin, ymax = (float(v) for v in extent)
        if not (xmax > xmin and ymax > ymin):
            raise ValueError(f"extent must have xmin < xmax and ymin < ymax, got {extent}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"grid resolution must be a positive number, got {resolution}")
        if align:
            xmin = math.floor(xmin / resolution + 1e-9) * resolution
            ymin = math.floor(ymin / resolution + 1e-9) * resolution
        # Small tolerance so an extent that is a whole number of cells does not gain one.
        nx = max(1, math.ceil((xmax - xmin) / resolution - 1e-9))
        ny = max(1, math.ceil((ymax - ymin) / resolution - 1e-9))
        return cls((xmin, ymin), resolution, (ny, nx))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the grid's outer edges."""
        x0, y0 = self.origin
        ny, nx = self.shape
        return (x0, x0 + nx * self.resolution, y0, y0 + ny * self.resolution)

    def x_centres(self) -> NDArray[np.float64]:
        """Cell-centre x coordinates, ndarray of shape (nx,)."""
        return self.origin[0] + (np.arange(self.shape[1], dtype=np.float64) + 0.5) * self.resolution

    def y_centres(self) -> NDArray[np.float64]:
        """Cell-centre y coordinates, ndarray of shape (ny,)."""
        return self.origin[1] + (np.arange(self.shape[0], dtype=np.float64) + 0.5) * self.resolution

    def centres(self) -> NDArray[np.float64]:
        """All cell centres, row-major (row 0 = lowest y), ndarray of shape (ny * nx, 2)."""
        xx, yy = np.meshgrid(self.x_centres(), self.y_centres())
        return np.column_stack([xx.ravel(), yy.ravel()])

    def rows(self, start: int, stop: int) -> GridSpec:
        """The grid of rows `start` to `stop` (exclusive) of this one: the same cells, in a band."""
        if not 0 <= start < stop <= self.shape[0]:
            raise ValueError(f"rows {start}:{stop} are not a band of a grid of {self.shape[0]} rows")
        return GridSpec(
            (self.origin[0], self.origin[1] + start * self.resolution), self.resolution, (stop - start, self.shape[1])
        )

    def index_of(self, points: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """Row and column of the cell holding each point, and whether it is inside the grid.

        Parameters
        ----------
        points : ndarray of shape (n, 2)

        Returns
        -------
        rows, cols : ndarray of shape (n,)
        inside : ndarray of bool, shape (n,)
        """
        p = np.asarray(points, dtype=float)
        cols = np.floor((p[:, 0] - self.origin[0]) / self.resolution).astype(np.intp)
        rows = np.floor((p[:, 1] - self.origin[1]) / self.resolution).astype(np.intp)
        inside = (rows >= 0) & (rows < self.shape[0]) & (cols >= 0) & (cols < self.shape[1])
        return rows, cols, inside


def row_bands(grid: GridSpec, rows: int) -> Iterator[tuple[int, int, GridSpec]]:
    """`grid` in bands of `rows` rows, bottom up (the last one shorter), reporting each as it ends.

    Yields
    ------
    start, stop : int
        The band's rows of `grid` (stop exclusive).
    band : GridSpec
        Those rows (:meth:`GridSpec.rows`).
    """
    ny = grid.shape[0]
    with progress(-(-ny // rows), "building the map", unit="band") as bar:
        for start in range(0, ny, rows):
            stop = min(start + rows, ny)
            yield start, stop, grid.rows(start, stop)
            bar.update()


def ternary(
    probability: NDArray[np.float64],
    thresholds: tuple[float, float] = DEFAULT_THRESHOLDS,
    seen_through: NDArray[np.bool_] | None = None,
) -> NDArray[np.int8]:
    """Free / unknown / occupied labels from occupancy probabilities.

    Parameters
    ----------
    probability : ndarray of any shape
    thresholds : (free_below, occupied_above)
        Probability below the first is FREE (0), above the second OCCUPIED (1), between UNKNOWN (-1).
    seen_through : ndarray of bool, the shape of `probability`, optional
        Cells no beam ended in (beams or the robot crossed them, or nothing reached them): never
        OCCUPIED, UNKNOWN where their probability is above the occupied threshold.

    Returns
    -------
    ndarray of int8, the shape of `probability`
    """
    lo, hi = thresholds
    if not 0.0 <= lo <= hi <= 1.0:
        raise ValueError(f"thresholds must satisfy 0 <= free <= occupied <= 1, got {thresholds}")
    p = np.asarray(probability)
    out = np.full(p.shape, UNKNOWN, dtype=np.int8)
    out[p < lo] = FREE
    out[p > hi] = OCCUPIED
    if seen_through is not None:
        out[(out == OCCUPIED) & np.asarray(seen_through, dtype=bool)] = UNKNOWN
    return out


@dataclass
class OccupancyMap:
    """A continuous occupancy map sampled on a grid.

    Parameters
    ----------
    grid : GridSpec
    probability : ndarray of shape (ny, nx)
        Occupancy probability per cell, row 0 at the lowest y.
    variance : ndarray of shape (ny, nx), optional
        Latent predictive variance per cell (high where the map knows little).
    thresholds : (float, float)
        Free-below and occupied-above thresholds for the ternary map.
    path : ndarray of shape (k, 2), optional
        The robot's path (sensor positions), for figures.
    info : dict
        What made the map: method, hyperparameters, timings; written into outputs where they can hold it.
    seen_through : ndarray of bool, shape (ny, nx), optional
        Cells no beam ended in (crossed by beams or the robot's path, or reached by nothing),
        which the ternary map never calls occupied (see :func:`ternary`); None: no such cells known.
    """

    grid: GridSpec
    probability: NDArray[np.float64]
    variance: NDArray[np.float64] | None = None
    thresholds: tuple[float, float] = DEFAULT_THRESHOLDS
    path: NDArray[np.float64] | None = None
    info: dict = field(default_factory=dict)
    seen_through: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        self.probability = np.asarray(self.probability, dtype=float)
        if self.probability.shape != self.grid.shape:
            raise ValueError(f"probability has shape {self.probability.shape}, grid has {self.grid.shape}")
        if self.variance is not None:
            self.variance = np.asarray(self.variance, dtype=float)
            if self.variance.shape != self.grid.shape:
                raise ValueError(f"variance has shape {self.variance.shape}, grid has {self.grid.shape}")
        if self.seen_through is not None:
            self.seen_through = np.asarray(self.seen_through, dtype=bool)
            if self.seen_through.shape != self.grid.shape:
                raise ValueError(f"seen_through has shape {self.seen_through.shape}, grid has {self.grid.shape}")
        self.thresholds = (float(self.thresholds[0]), float(self.thresholds[1]))

    @property
    def ternary(self) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) per cell, ndarray of shape (ny, nx)."""
        return ternary(self.probability, self.thresholds, self.seen_through)


def coarse_grid(grid: GridSpec, factor: int) -> GridSpec:
    """A grid of cells `factor` times larger whose cell centres span `grid`'s, one cell beyond each edge.

    Values sampled at its centres can be interpolated to every centre of `grid` (see
    :func:`interpolate_to`) without extrapolating.
    """
    if factor <= 1:
        return grid
    step = grid.resolution * factor
    fine_x, fine_y = grid.x_centres(), grid.y_centres()
    nx = math.ceil((fine_x[-1] - fine_x[0]) / step) + 3
    ny = math.ceil((fine_y[-1] - fine_y[0]) / step) + 3
    return GridSpec((fine_x[0] - 1.5 * step, fine_y[0] - 1.5 * step), step, (ny, nx))


def interpolate_to(values: NDArray[np.float64], coarse: GridSpec, fine: GridSpec) -> NDArray[np.float64]:
    """Bilinear interpolation of per-cell `values` on `coarse` to the cell centres of `fine`.

    Parameters
    ----------
    values : ndarray of shape coarse.shape
    coarse, fine : GridSpec

    Returns
    -------
    ndarray of shape fine.shape
    """
    from scipy.interpolate import RegularGridInterpolator

    if coarse == fine:
        return np.asarray(values).reshape(fine.shape)
    interp = RegularGridInterpolator((coarse.y_centres(), coarse.x_centres()), np.asarray(values).reshape(coarse.shape))
    yy, xx = np.meshgrid(fine.y_centres(), fine.x_centres(), indexing="ij")
    return interp(np.column_stack([yy.ravel(), xx.ravel()])).reshape(fine.shape)
