"""Exact ray traversal of grid cells (Amanatides & Woo), for every beam at once, in any dimension.

Shared by the occupancy grids (:mod:`gpomap.baselines.ogm`) and the ray evidence of the GP map
(:mod:`gpomap.evidence`), on 2-D grids and 3-D voxel lattices alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap import _compiled_raycast
from gpomap.lattice import AnyGrid, grid_dim, row_sums

__all__ = ["ENTRIES_PER_CHUNK", "Segments", "traverse"]

# Traversal entries (grid-line crossings) handled per chunk: bounds temporary memory (about 120
# bytes an entry), and small chunks stay in cache (timings by chunk size: docs/choices.md,
# "Measured for the code").
ENTRIES_PER_CHUNK: int = 1 << 17


def _line_crossings(u0: NDArray[np.float64], u1: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Where segments u0 -> u1 (1-D, in cell units) cross integer lines, in travel order.

    Returns
    -------
    seg : ndarray of int, shape (c,)
        Segment of each crossing, non-decreasing.
    t : ndarray of shape (c,)
        Crossing parameter in (0, 1), increasing within each segment.
    """
    lo, hi = np.minimum(u0, u1), np.maximum(u0, u1)
    first = np.floor(lo) + 1  # first integer strictly above lo
    counts = np.maximum(np.ceil(hi) - first, 0).astype(np.intp)  # integers strictly inside
    seg = np.repeat(np.arange(u0.size, dtype=np.intp), counts)
    starts = np.cumsum(counts) - counts
    # Walk the lines in the direction of travel so t increases: the j-th crossing of a segment is
    # line first + j going up, first + counts - 1 - j going down. The lines are integers, exact in
    # floating point whatever the order of the sums, so per-segment offsets repeated (sequential
    # copies) give them without gathering per crossing.
    down = u1 < u0
    sign = np.where(down, -1.0, 1.0)
    offset = np.where(down, first + counts - 1, first) - sign * starts
    k = np.repeat(offset, counts) + np.repeat(sign, counts) * np.arange(seg.size, dtype=np.float64)
    t = (k - np.repeat(u0, counts)) / np.repeat(u1 - u0, counts)
    return seg, t


@dataclass(frozen=True)
class Segments:
    """Segments in a grid's cell units, cut into the chunks :func:`traverse` walks them in.

    Both traversals (numpy and compiled) merge a segment's crossings by a key holding its index
    within its chunk, so the chunks decide the rounding they share; whatever walks segments the
    way :func:`traverse` does takes them from here.

    Attributes
    ----------
    p0, p1 : ndarray of shape (k, d)
        Start and end of each segment that comes near the grid, in cell units (the grid's origin
        at 0, coordinates x first).
    kept : ndarray of int, shape (k,)
        Index of each among the segments given.
    chunks : list of (int, int)
        Consecutive ranges [lo, hi) of the kept segments, each at most about
        :data:`ENTRIES_PER_CHUNK` entries (at least one segment).
    """

    p0: NDArray[np.float64]
    p1: NDArray[np.float64]
    kept: NDArray[np.intp]
    chunks: list[tuple[int, int]]

    @classmethod
    def of(cls, grid: AnyGrid, starts: ArrayLike, ends: ArrayLike) -> Segments:
        """The segments `starts` -> `ends` (shape (b, d), map frame) on `grid`."""
        d = grid_dim(grid)
        origin = np.asarray(grid.origin, dtype=float)
        # C order whatever the inputs' (a transposed array's F order would compile the walks again).
        p0 = np.ascontiguousarray((np.asarray(starts, dtype=float).reshape(-1, d) - origin) / grid.resolution)
        p1 = np.ascontiguousarray((np.asarray(ends, dtype=float).reshape(-1, d) - origin) / grid.resolution)
        # Segments that never come near the grid visit none of its cells: left out before the
        # walk (a region's grid among a whole log's beams).
        near = _near_box(p0, p1, grid.shape)
        if near.all():
            kept = np.arange(len(p0), dtype=np.intp)
        else:
            kept = np.flatnonzero(near)
            p0, p1 = p0[kept], p1[kept]
        # Crossings per segment (an upper bound), to cut the work into chunks of bounded memory.
        cost = np.cumsum(row_sums(np.abs(np.floor(p1) - np.floor(p0))) + 2)
        chunks = []
        lo = 0
        while lo < len(p0):
            base = cost[lo - 1] if lo > 0 else 0.0
            hi = max(lo + 1, int(np.searchsorted(cost, base + ENTRIES_PER_CHUNK, side="right")))
            chunks.append((lo, hi))
            lo = hi
        return cls(p0, p1, kept, chunks)

    def lengths(self) -> NDArray[np.float64]:
        """Each kept segment's length in cell units, computed chunk by chunk as the numpy walk does, shape (k,)."""
        return np.concatenate(
            [np.sqrt(row_sums((self.p1[lo:hi] - self.p0[lo:hi]) ** 2)) for lo, hi in self.chunks] or [np.zeros(0)]
        )

    def places(self) -> NDArray[np.intp]:
        """Each kept segment's index within its chunk, shape (k,)."""
        place = np.arange(len(self.p0), dtype=np.intp)
        for lo, hi in self.chunks:
            place[lo:hi] -= lo
        return place


def traverse(grid: AnyGrid, starts: ArrayLike, ends: ArrayLike) -> tuple[NDArray[np.intp], ...]:
    """Every grid cell each segment passes through, in order from start to end.

    This is the Amanatides & Woo traversal done for all segments at once. Their algorithm steps
    to whichever grid line (plane in 3-D), x, y or z, comes next along the ray; the cells it
    visits are the intervals between the segment's grid-line crossings taken in increasing order.
    We list each segment's crossings per axis (each already in travel order), merge the lists
    exactly (one stable sort of their concatenation, which finds the sorted runs and merges them
    in linear time), and take the cell holding the midpoint of each interval. Where a segment
    passes exactly through a grid corner (or edge) the interval between the crossings has zero
    length and is dropped, so the diagonal neighbour is visited and the side neighbours are not.

    Parameters
    ----------
    grid : GridSpec or VoxelSpec
    starts, ends : array_like of shape (b, d)
        Segment end points in the map frame, d the grid's dimension.

    Returns
    -------
    beam : ndarray of int, shape (m,)
        Segment index of each visited cell (non-decreasing).
    index : d ndarrays of int, shape (m,)
        The visited cells' array indices, x last (rows, cols in 2-D; iz, iy, ix in 3-D), in
        order along each segment. Cells outside the grid are left out; the cells of one segment
        are distinct.
    """
    d = grid_dim(grid)
    walk = Segments.of(grid, starts, ends)
    out: list[tuple[NDArray[np.intp], ...]] = []
    chunk = _compiled_raycast.traverse_chunk if _compiled_raycast.ENABLED else _traverse_chunk
    for lo, hi in walk.chunks:
        seg, *idx = chunk(walk.p0[lo:hi], walk.p1[lo:hi], grid.shape)
        out.append((walk.kept[seg + lo], *idx))
    if not out:
        return tuple(np.zeros(0, dtype=np.intp) for _ in range(d + 1))
    return tuple(np.concatenate([part[j] for part in out]) for j in range(d + 1))


def _near_box(p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, ...]) -> NDArray[np.bool_]:
    """Whether each segment p0 -> p1 (cell units) meets the grid's box grown by a cell on every side.

    The slab test (Liang & Barsky): the parameter interval where the segment lies within each
    axis's bounds, intersected over the axes and with [0, 1]. The margin of a cell keeps every
    segment that could visit a grid cell whatever the rounding. Shape (b,).
    """
    t_in, t_out = np.zeros(p0.shape[0]), np.ones(p0.shape[0])
    for k, n in zip(range(p0.shape[1]), reversed(shape), strict=True):
        a, z, d = -1.0, float(n) + 1.0, p1[:, k] - p0[:, k]
        flat = d == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (a - p0[:, k]) / d, (z - p0[:, k]) / d
        inside = (p0[:, k] >= a) & (p0[:, k] <= z)
        t_in = np.maximum(t_in, np.where(flat, np.where(inside, 0.0, np.inf), np.minimum(t1, t2)))
        t_out = np.minimum(t_out, np.where(flat, np.where(inside, 1.0, -np.inf), np.maximum(t1, t2)))
    return t_in <= t_out


def _traverse_chunk(p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, ...]) -> tuple[NDArray[np.intp], ...]:
    b, d = p0.shape
    # Every segment's entries [0, crossings..., 1] in travel order: the start, each axis's
    # crossings and the end, each list sorted by the key 4 seg + 2 t (a segment's keys stay in
    # its own range [4 seg, 4 seg + 2] whatever the rounding), merged by one stable sort of their
    # concatenation (timsort finds the sorted runs and merges them in linear time; ties keep the
    # lists' order: the start first, then the axes in order, the end last).
    beams = np.arange(b, dtype=np.intp)
    segs, ts = [beams], [np.zeros(b)]
    for k in range(d):
        seg_k, t_k = _line_crossings(p0[:, k], p1[:, k])
        segs.append(seg_k)
        ts.append(t_k)
    segs.append(beams)
    ts.append(np.ones(b))
    seg, t = np.concatenate(segs), np.concatenate(ts)
    order = np.argsort(4.0 * seg + 2.0 * t, kind="stable")
    seg, t = seg[order], t[order]
    # Intervals between consecutive entries of the same segment. Drop zero-length intervals (two
    # lines crossed at once, at a grid corner), but keep the single [0, 1] interval of a
    # zero-length segment so it still visits its own cell.
    length = np.sqrt(((p1 - p0) ** 2).sum(axis=1))[seg[:-1]]
    keep = (seg[1:] == seg[:-1]) & (((t[1:] - t[:-1]) * length > 1e-9) | (length == 0))
    s = seg[:-1][keep]
    tm = 0.5 * (t[:-1][keep] + t[1:][keep])
    # The cell holding each interval's midpoint, one coordinate at a time (contiguous columns).
    # Array order is coordinate order reversed (x last).
    start, step = np.ascontiguousarray(p0.T), np.ascontiguousarray((p1 - p0).T)
    idx = []
    inside = np.ones(s.size, dtype=bool)
    for k, n in zip(reversed(range(d)), shape, strict=True):
        i = np.floor(start[k][s] + tm * step[k][s]).astype(np.intp)
        inside &= i.view(np.uintp) < n  # negative indices wrap to huge ones
        idx.append(i)
    return (s[inside], *(i[inside] for i in idx))
