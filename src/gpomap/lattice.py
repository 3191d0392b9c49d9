"""What 2-D grids and 3-D voxel grids share, written once for both.

The 3-D :class:`~gpomap.voxels.VoxelSpec` follows the conventions of the 2-D
:class:`~gpomap.grid.GridSpec`, extended by one axis: `origin` is the lower corner in coordinate
order (x, y, z); arrays are indexed with x last, ``[iz, iy, ix]``, as a 2-D grid is ``[row, col]``
= ``[iy, ix]``; ``index_of`` returns one index per array axis and an inside mask. The functions
below take either kind (:data:`AnyGrid`), so the ray traversal, the ray evidence and its fusion
with the GP are written once for every dimension.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap import _compiled_bounds
from gpomap.grid import GridSpec
from gpomap.voxels import VoxelSpec

#: A 2-D grid or a 3-D voxel grid: both have `origin` (coordinate order), `resolution`, `shape`
#: (array order, x last) and `index_of`.
AnyGrid = GridSpec | VoxelSpec


def column_bounds(points: ArrayLike) -> tuple[NDArray[Any], NDArray[Any]]:
    """``points.min(axis=0)`` and ``points.max(axis=0)`` of an array of shape (n, d), each (d,).

    Column by column: numpy reduces an (n, 2) array along its first axis many times slower than
    it reduces each column in turn (docs/choices.md, "Measured for the code"), and a whole log's
    points are reduced so in several places; many planar or 3-D points take one compiled pass
    (:mod:`gpomap._compiled_bounds`). An empty array raises ValueError, as ``min`` does.
    """
    a = np.asarray(points)
    if _compiled_bounds.ENABLED:
        found = _compiled_bounds.bounds(a)
        if found is not None:
            return found
    lo = np.array([a[:, j].min() for j in range(a.shape[1])], dtype=a.dtype)
    hi = np.array([a[:, j].max() for j in range(a.shape[1])], dtype=a.dtype)
    return lo, hi


#: Indices of at least this many rows that run without a gap (a scan's beams among a log's) are
#: copied as a slice: five times quicker than ``np.take`` (docs/choices.md, "Measured for the code").
RUN_ROWS: int = 1024


def rows(a: NDArray[Any], which: ArrayLike) -> NDArray[Any]:
    """``a[which]`` of an array of points (n, d) by a mask of shape (n,) or indices of shape (k,): the same rows.

    Taken along the first axis by ``np.compress`` or ``np.take``: numpy's indexing of an array of
    a few columns by a mask or by indices is several times slower (docs/choices.md, "Measured for
    the code"), and a log's points are selected so in many places. A one-dimensional `a` is
    indexed as it is. A mask of the wrong length raises IndexError, as indexing does.
    """
    w = np.asarray(which)
    if a.ndim < 2:
        return a[w]
    if w.dtype == np.bool_:
        if w.shape != a.shape[:1]:
            raise IndexError(f"a mask of shape {w.shape} cannot select rows of an array of shape {a.shape}")
        return np.compress(w, a, axis=0)
    if _run_of_rows(w, a.shape[0]):
        return a[w[0] : w[-1] + 1].copy()
    return np.take(a, w, axis=0)


def _run_of_rows(w: NDArray[Any], n: int) -> bool:
    """Whether indices `w` name at least :data:`RUN_ROWS` rows of `n` one after another, without a gap."""
    if w.ndim != 1 or w.size < RUN_ROWS or w[0] < 0 or w[-1] >= n or w[-1] - w[0] + 1 != w.size:
        return False
    return bool(np.all(w[1:] > w[:-1]))  # increasing from the first to the last: every row between


def row_sums(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """``v.sum(axis=1)`` of an array of a few columns (n, d), shape (n,), column by column: the same
    sums in the same order (numpy adds a short row's entries one after another), several times
    quicker on millions of rows (docs/choices.md, "Measured for the code")."""
    out = v[:, 0].copy()
    for k in range(1, v.shape[1]):
        out += v[:, k]
    return out


def stable_order(keys: NDArray[np.integer[Any]]) -> NDArray[np.intp]:
    """``np.argsort(keys, kind="stable")`` of non-negative integers (-1 allowed), ndarray of shape (n,).

    Keys below 2^15 are sorted as int16, which numpy radix-sorts, an order of magnitude faster
    than int64 keys or a lexsort of the coordinates (docs/choices.md, "Measured for the code").
    """
    small = keys.size == 0 or int(keys.max()) < np.iinfo(np.int16).max
    return np.argsort(keys.astype(np.int16) if small else keys, kind="stable")


def in_box(points: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> NDArray[np.bool_]:
    """Which points (n, d) lie in the closed box `lower`..`upper` along its k <= d axes, ndarray of bool (n,).

    Column by column, for the reason :func:`column_bounds` gives (``np.all(..., axis=1)`` on
    (n, 2) comparisons is as slow). A box of fewer axes than the
    points (k < d) bounds their first k coordinates: a square bounds 3-D points as a column.
    NaN coordinates are outside.
    """
    a = np.asarray(points)
    lo, hi = np.ravel(lower), np.ravel(upper)
    out = np.ones(a.shape[0], dtype=bool)
    for j in range(lo.size):
        column = a[:, j]
        out &= column >= lo[j]
        out &= column <= hi[j]
    return out


def box_shape(lower: ArrayLike, upper: ArrayLike, scale: float, pad: int = 0) -> tuple[int, ...]:
    """Boxes per axis of a lattice of boxes of side ``1 / scale`` from `lower` that holds `upper`,
    with `pad` empty boxes more on either side (the order of `lower`'s axes, x first)."""
    span = np.floor((np.asarray(upper, dtype=float) - np.asarray(lower, dtype=float)) * scale)
    return tuple(int(v) + 1 + 2 * pad for v in span)


def box_index(
    points: NDArray[np.float64], lower: ArrayLike, scale: float, shape: tuple[int, ...], pad: int = 0
) -> NDArray[np.int64]:
    """Flat index, row-major over `shape` (:func:`box_shape`), of the box holding each point (n, d), shape (n,).

    Column by column (the offsets from `lower` are >= 0, so the integer cast floors them),
    without (n, d) temporaries; indices past the last box are clipped to it.
    """
    lo = np.asarray(lower, dtype=float)
    flat = np.zeros(points.shape[0], dtype=np.int64)
    for j, size in enumerate(shape):
        flat *= size
        flat += np.minimum(((points[:, j] - lo[j]) * scale).astype(np.int64) + pad, size - 1 - pad)
    return flat


def extent_bounds(extent: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lower and upper corners, each ndarray of shape (d,), of ``(xmin, xmax, ymin, ymax, ...)``."""
    e = np.asarray(extent, dtype=float).reshape(-1, 2)
    return e[:, 0], e[:, 1]


def bounds_extent(lower: ArrayLike, upper: ArrayLike) -> tuple[float, ...]:
    """``(xmin, xmax, ymin, ymax, ...)`` from lower and upper corners of shape (d,)."""
    return tuple(float(v) for pair in zip(np.ravel(lower), np.ravel(upper), strict=True) for v in pair)


#: Cells of margin round the data's bounding box in a map's default extent: a hit on the box's edge
#: lies in the cell past it, and the wall there is drawn whole.
EXTENT_MARGIN_CELLS: int = 2


def data_extent(lower: ArrayLike, upper: ArrayLike, resolution: float) -> tuple[float, ...]:
    """A map's default extent at `resolution`: the data's box, corners `lower` and `upper` of
    shape (d,), grown by :data:`EXTENT_MARGIN_CELLS` cells on every side, as ``(xmin, xmax, ...)``."""
    pad = EXTENT_MARGIN_CELLS * float(resolution)
    return bounds_extent(np.asarray(lower, dtype=float) - pad, np.asarray(upper, dtype=float) + pad)


def grid_dim(grid: AnyGrid) -> int:
    """Number of dimensions of `grid`."""
    return len(grid.shape)


def grid_size(grid: AnyGrid) -> int:
    """Number of cells of `grid`."""
    return math.prod(grid.shape)


def make_grid(origin: ArrayLike, resolution: float, counts: ArrayLike) -> AnyGrid:
    """A grid from its lower corner and cells per coordinate (x first): a GridSpec in 2-D, a VoxelSpec in 3-D."""
    o = tuple(float(v) for v in np.ravel(origin))
    shape = tuple(int(v) for v in np.ravel(counts))[::-1]
    if len(o) == 2:
        return GridSpec((o[0], o[1]), resolution, (shape[0], shape[1]))
    if len(o) == 3:
        return VoxelSpec((o[0], o[1], o[2]), resolution, (shape[0], shape[1], shape[2]))
    raise ValueError(f"grids are 2-D or 3-D, got a {len(o)}-D origin")


def grid_from_extent(extent: tuple[float, ...], resolution: float) -> AnyGrid:
    """The grid of side-`resolution` cells covering `extent` from its lower corner on (a GridSpec for
    4 values (xmin, xmax, ymin, ymax), a VoxelSpec for 6)."""
    if len(extent) == 4:
        return GridSpec.from_extent((extent[0], extent[1], extent[2], extent[3]), resolution)
    lo, hi = extent_bounds(extent)
    return VoxelSpec.from_extent(lo, hi, resolution, align=False)


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

    Both are regular lattices, so the interpolation is separable: linear along x (every source
    row to the target's x centres), then along y, then z; each pass takes two neighbours and two
    weights per output value (a point-by-point interpolator finds 2^d corners and their weights
    for every target cell, an order of magnitude slower). The
    result equals the point-by-point multilinear interpolation up to round-off.

    Parameters
    ----------
    values : array_like of shape source.shape
    source, target : GridSpec or VoxelSpec, of one dimension

    Returns
    -------
    ndarray of shape target.shape

    Raises
    ------
    ValueError
        A target centre lies outside the span of the source's centres (no extrapolation).
    """
    v = np.asarray(values, dtype=float).reshape(source.shape)
    if source == target:
        return v
    d = grid_dim(source)
    for k in range(d):
        lo, hi, w = _axis_weights(_axis_centres(source, k), _axis_centres(target, k))
        axis = d - 1 - k  # array order is coordinate order reversed (x last)
        shape = [1] * d
        shape[axis] = w.size
        w = w.reshape(shape)
        a, b = np.take(v, lo, axis=axis), np.take(v, hi, axis=axis)
        v = a + w * (b - a)
    return v


def lattice_corners(points: ArrayLike, step: float) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.float64]]:
    """The corners of the cells of a lattice `step` apart, on the origin, that hold `points`, and
    each point's multilinear weights on its cell's corners.

    Parameters
    ----------
    points : array_like of shape (m, d)
    step : float
        The lattice's spacing; its nodes lie at integer multiples of it.

    Returns
    -------
    nodes : ndarray of shape (k, d)
        Every corner of a cell holding a point, once.
    corner : ndarray of shape (m, 2^d)
        Each point's cell's corners, as rows of `nodes`.
    weight : ndarray of shape (m, 2^d)
        Their weights: ``(weight * values[corner]).sum(axis=1)`` interpolates values at `nodes`.
    """
    pts = np.asarray(points, dtype=float)
    m, d = pts.shape
    scaled = pts / step
    base = np.floor(scaled)
    frac = scaled - base
    offsets = np.array(list(itertools.product((0, 1), repeat=d)), dtype=np.int64)  # (2^d, d)
    keys = base.astype(np.int64)[:, None, :] + offsets[None]
    weight = np.prod(np.where(offsets[None] == 1, frac[:, None, :], 1.0 - frac[:, None, :]), axis=2)
    if m == 0:
        return np.zeros((0, d)), np.zeros((0, offsets.shape[0]), dtype=np.intp), weight
    # One integer a node (row-major over the keys' box), uniqued as numbers: in the rows' order,
    # several times faster than unique rows.
    flat = keys.reshape(-1, d)
    low = flat.min(axis=0)
    span = tuple(int(v) for v in flat.max(axis=0) - low + 1)
    codes, inverse = np.unique(np.ravel_multi_index(tuple((flat - low).T), span), return_inverse=True)
    unique = np.column_stack(np.unravel_index(codes, span)) + low
    return unique * step, inverse.reshape(m, offsets.shape[0]).astype(np.intp), weight


def interpolation_block(source: AnyGrid, target: AnyGrid) -> tuple[slice, ...]:
    """The block of `source` cells whose values :func:`interpolate` onto `target` depends on.

    Every value it reads lies in the block, or is read with a weight of exactly 0 (the upper
    neighbour of a target centre on a source centre, where ``a + 0 * (b - a)`` is `a` for any
    finite `b`): values outside the block, if finite, do not change the result by a bit. A
    :func:`coarse` lattice, one cell beyond the target at each edge, has one or two cells per
    axis and side outside it.

    Parameters
    ----------
    source, target : GridSpec or VoxelSpec, of one dimension

    Returns
    -------
    tuple of slice
        One per array axis (x last).
    """
    d = grid_dim(source)
    if source == target:
        return tuple(slice(0, n) for n in source.shape)
    block = []
    for axis in range(d):
        k = d - 1 - axis  # array order is coordinate order reversed (x last)
        lo, hi, w = _axis_weights(_axis_centres(source, k), _axis_centres(target, k))
        if lo.size == 0:
            block.append(slice(0, 0))
            continue
        top = int(lo.max())
        if (w > 0).any():
            top = max(top, int(hi[w > 0].max()))
        block.append(slice(int(lo.min()), top + 1))
    return tuple(block)


def _axis_weights(
    source: NDArray[np.float64], target: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """For each target coordinate, the source interval holding it (lower and upper index) and the
    weight of its upper end.

    `source` is evenly spaced and increasing; a single source value is both ends, weight 0 (the
    target must then be that value).
    """
    n = source.size
    if n == 1:
        if not np.allclose(target, source[0]):
            raise ValueError("target centres lie outside the source lattice's centres")
        zero = np.zeros(target.size, dtype=np.intp)
        return zero, zero, np.zeros(target.size)
    step = (source[-1] - source[0]) / (n - 1)
    u = (target - source[0]) / step
    tol = 1e-9 * max(1.0, float(n))
    if u.size and (u.min() < -tol or u.max() > n - 1 + tol):
        raise ValueError("target centres lie outside the source lattice's centres (no extrapolation)")
    lo = np.clip(np.floor(u), 0, n - 2).astype(np.intp)
    return lo, lo + 1, np.clip(u - lo, 0.0, 1.0)


def grid_extent(grid: AnyGrid) -> tuple[float, ...]:
    """(xmin, xmax, ymin, ymax[, zmin, zmax]) of the grid's outer edges."""
    counts = grid.shape[::-1]
    return tuple(v for o, n in zip(grid.origin, counts, strict=True) for v in (o, o + n * grid.resolution))


def cell_offset(grid: AnyGrid, base: AnyGrid) -> tuple[int, ...]:
    """Array index on `base` of `grid`'s first cell (both on one cell lattice), one per array axis."""
    d = grid_dim(grid)
    return tuple(round((grid.origin[k] - base.origin[k]) / base.resolution) for k in reversed(range(d)))


def overlap(
    offset: tuple[int, ...], shape: tuple[int, ...], base_shape: tuple[int, ...]
) -> tuple[tuple[slice, ...], tuple[slice, ...]] | None:
    """Where a block of `shape` placed at `offset` on an array of `base_shape` overlaps it.

    Returns
    -------
    (in_block, in_base) : tuples of slices, one per axis, or None when they do not overlap
    """
    block, base = [], []
    for o, n, m in zip(offset, shape, base_shape, strict=True):
        lo, hi = max(o, 0), min(o + n, m)
        if lo >= hi:
            return None
        block.append(slice(lo - o, hi - o))
        base.append(slice(lo, hi))
    return tuple(block), tuple(base)
