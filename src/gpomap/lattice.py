"""Regular grids in any number of dimensions: the 3-D voxel lattice, and what 2-D and 3-D grids share.

A :class:`Lattice` follows the conventions of the 2-D :class:`~gpomap.grid.GridSpec`, extended by
one axis: `origin` is the lower corner in coordinate order (x, y, z); arrays are indexed with x
last, ``[iz, iy, ix]``, as a 2-D grid is ``[row, col]`` = ``[iy, ix]``; cell ``(iz, iy, ix)`` has
its centre at ``origin + ((ix + 0.5) r, (iy + 0.5) r, (iz + 0.5) r)``. The functions below take
either kind (:data:`AnyGrid`), so the ray traversal, the ray evidence and its fusion with the GP
are written once for every dimension.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.grid import GridSpec


@dataclass(frozen=True)
class Lattice:
    """Geometry of a regular grid of cubes in d dimensions.

    Parameters
    ----------
    origin : tuple of float
        Lower corner of the lowest cell in coordinate order, (x, y, z), metres.
    resolution : float
        Cell side, metres.
    shape : tuple of int
        Cells per axis in array order, x last: (nz, ny, nx).
    """

    origin: tuple[float, ...]
    resolution: float
    shape: tuple[int, ...]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"lattice resolution must be a positive number, got {self.resolution}")
        shape = tuple(int(v) for v in self.shape)
        origin = tuple(float(v) for v in self.origin)
        if len(shape) != len(origin) or any(n <= 0 for n in shape):
            raise ValueError(f"lattice needs one positive size per origin coordinate, got shape {self.shape}, origin {self.origin}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "resolution", float(self.resolution))

    @classmethod
    def from_extent(cls, extent: tuple[float, ...], resolution: float) -> Lattice:
        """The lattice of cells of side `resolution` covering `extent` = (xmin, xmax, ymin, ymax, ...).

        The origin is the extent's lower corner; the lattice extends past each upper bound to a
        whole cell.
        """
        lo, hi = extent_bounds(extent)
        if not np.all(hi > lo):
            raise ValueError(f"extent must have each minimum below its maximum, got {extent}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"lattice resolution must be a positive number, got {resolution}")
        # Small tolerance so an extent that is a whole number of cells does not gain one.
        n = [max(1, math.ceil((h - l) / resolution - 1e-9)) for l, h in zip(lo, hi, strict=True)]
        return cls(tuple(lo), resolution, tuple(reversed(n)))

    @property
    def dim(self) -> int:
        """Number of dimensions."""
        return len(self.shape)

    @property
    def size(self) -> int:
        """Number of cells."""
        return math.prod(self.shape)

    @property
    def extent(self) -> tuple[float, ...]:
        """(xmin, xmax, ymin, ymax, ...) of the lattice's outer edges."""
        counts = tuple(reversed(self.shape))
        return tuple(v for o, n in zip(self.origin, counts, strict=True) for v in (o, o + n * self.resolution))

    def axis_centres(self, k: int) -> NDArray[np.float64]:
        """Cell-centre coordinates along coordinate `k` (0 = x), ndarray of shape (n_k,)."""
        n = self.shape[self.dim - 1 - k]
        return self.origin[k] + (np.arange(n, dtype=np.float64) + 0.5) * self.resolution

    def centres(self) -> NDArray[np.float64]:
        """All cell centres in array (row-major, x fastest) order, ndarray of shape (size, d)."""
        return grid_centres(self)

    def index_of(self, points: ArrayLike) -> tuple[NDArray[np.intp], ...]:
        """Array index of the cell holding each point, and whether it is inside.

        Parameters
        ----------
        points : array_like of shape (n, d)

        Returns
        -------
        (iz, iy, ix, inside) : ndarrays of shape (n,)
            One index per array axis (x last), then a bool mask of points inside the lattice.
        """
        p = np.asarray(points, dtype=float).reshape(-1, self.dim)
        idx = [np.floor((p[:, k] - self.origin[k]) / self.resolution).astype(np.intp) for k in range(self.dim)][::-1]
        inside = np.ones(p.shape[0], dtype=bool)
        for i, n in zip(idx, self.shape, strict=True):
            inside &= (i >= 0) & (i < n)
        return (*idx, inside)


#: A 2-D grid or a lattice of any dimension: both have `origin` (coordinate order), `resolution`,
#: `shape` (array order, x last) and `index_of`.
AnyGrid = GridSpec | Lattice


def extent_bounds(extent: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lower and upper corners, each ndarray of shape (d,), of ``(xmin, xmax, ymin, ymax, ...)``."""
    e = np.asarray(extent, dtype=float).reshape(-1, 2)
    return e[:, 0], e[:, 1]


def bounds_extent(lower: ArrayLike, upper: ArrayLike) -> tuple[float, ...]:
    """``(xmin, xmax, ymin, ymax, ...)`` from lower and upper corners of shape (d,)."""
    return tuple(float(v) for pair in zip(np.ravel(lower), np.ravel(upper), strict=True) for v in pair)


def grid_dim(grid: AnyGrid) -> int:
    """Number of dimensions of `grid`."""
    return len(grid.shape)


def grid_size(grid: AnyGrid) -> int:
    """Number of cells of `grid`."""
    return math.prod(grid.shape)


def make_grid(origin: ArrayLike, resolution: float, counts: ArrayLike) -> AnyGrid:
    """A grid from its lower corner and cells per coordinate (x first): a GridSpec in 2-D, else a Lattice."""
    o = tuple(float(v) for v in np.ravel(origin))
    shape = tuple(int(v) for v in np.ravel(counts))[::-1]
    if len(o) == 2:
        return GridSpec((o[0], o[1]), resolution, (shape[0], shape[1]))
    return Lattice(o, resolution, shape)


def grid_from_extent(extent: tuple[float, ...], resolution: float) -> AnyGrid:
    """The grid of side-`resolution` cells covering `extent` (a GridSpec for 4 values, else a Lattice)."""
    if len(extent) == 4:
        return GridSpec.from_extent((extent[0], extent[1], extent[2], extent[3]), resolution)
    return Lattice.from_extent(extent, resolution)


def flat_index(grid: AnyGrid, points: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Row-major flat index of the cell holding each point (0 where outside), and the inside mask."""
    *idx, inside = grid.index_of(np.asarray(points, dtype=float))
    safe = tuple(np.where(inside, i, 0) for i in idx)
    return np.ravel_multi_index(safe, grid.shape).astype(np.intp), inside.astype(bool)


def grid_centres(grid: AnyGrid) -> NDArray[np.float64]:
    """Cell centres of `grid` in row-major order (x fastest), ndarray of shape (size, d)."""
    d = grid_dim(grid)
    axes = [_axis_centres(grid, k) for k in range(d)][::-1]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.column_stack([m.ravel() for m in mesh[::-1]])


def _axis_centres(grid: AnyGrid, k: int) -> NDArray[np.float64]:
    n = grid.shape[grid_dim(grid) - 1 - k]
    return grid.origin[k] + (np.arange(n, dtype=np.float64) + 0.5) * grid.resolution


def coarse(grid: AnyGrid, factor: int) -> AnyGrid:
    """A grid of cells `factor` times larger whose centres span `grid`'s, one cell beyond each edge.

    Values sampled at its centres can be interpolated to every centre of `grid`
    (:func:`interpolate`) without extrapolating. In 2-D this is :func:`gpomap.grid.coarse_grid`.
    """
    if factor <= 1:
        return grid
    step = grid.resolution * factor
    d = grid_dim(grid)
    first = np.array([_axis_centres(grid, k)[0] for k in range(d)])
    last = np.array([_axis_centres(grid, k)[-1] for k in range(d)])
    counts = [math.ceil((b - a) / step) + 3 for a, b in zip(first, last, strict=True)]
    return make_grid(first - 1.5 * step, step, counts)


def interpolate(values: ArrayLike, source: AnyGrid, target: AnyGrid) -> NDArray[np.float64]:
    """Multilinear interpolation of per-cell `values` on `source` to the cell centres of `target`.

    Parameters
    ----------
    values : array_like of shape source.shape
    source, target : GridSpec or Lattice, of one dimension

    Returns
    -------
    ndarray of shape target.shape
    """
    from scipy.interpolate import RegularGridInterpolator

    if source == target:
        return np.asarray(values, dtype=float).reshape(target.shape)
    d = grid_dim(source)
    # Array order (x last) on both sides, so the result needs no transposing.
    interp = RegularGridInterpolator(
        tuple(_axis_centres(source, k) for k in reversed(range(d))), np.asarray(values, dtype=float).reshape(source.shape)
    )
    mesh = np.meshgrid(*(_axis_centres(target, k) for k in reversed(range(d))), indexing="ij")
    return interp(np.column_stack([m.ravel() for m in mesh])).reshape(target.shape)
