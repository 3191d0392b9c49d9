"""Exact ray traversal of grid cells (Amanatides & Woo), for every beam at once, in any dimension.

Shared by the occupancy grids (:mod:`gpomap.baselines.ogm`) and the ray evidence of the GP map
(:mod:`gpomap.evidence`), on 2-D grids and 3-D voxel lattices alike.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.lattice import AnyGrid, grid_dim

__all__ = ["ENTRIES_PER_CHUNK", "traverse"]

# Traversal entries (grid-line crossings) handled per chunk: bounds temporary memory.
ENTRIES_PER_CHUNK: int = 1 << 22


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
    j = np.arange(seg.size, dtype=np.intp) - np.repeat(starts, counts)
    # Walk the lines in the direction of travel so t increases.
    down = (u1 < u0)[seg]
    k = np.where(down, first[seg] + (counts[seg] - 1 - j), first[seg] + j)
    t = (k - u0[seg]) / (u1[seg] - u0[seg])
    return seg, t


def traverse(grid: AnyGrid, starts: ArrayLike, ends: ArrayLike) -> tuple[NDArray[np.intp], ...]:
    """Every grid cell each segment passes through, in order from start to end.

    This is the Amanatides & Woo traversal done for all segments at once. Their algorithm steps
    to whichever grid line (plane in 3-D), x, y or z, comes next along the ray; the cells it
    visits are the intervals between the segment's grid-line crossings taken in increasing order.
    We list each segment's crossings per axis (each already in travel order), merge the lists
    exactly, one axis after another (no sort: a merge position is an index plus a count from
    ``searchsorted``), and take the cell holding the midpoint of each interval. Where a segment
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
    origin = np.asarray(grid.origin, dtype=float)
    p0 = (np.asarray(starts, dtype=float).reshape(-1, d) - origin) / grid.resolution
    p1 = (np.asarray(ends, dtype=float).reshape(-1, d) - origin) / grid.resolution
    b = len(p0)
    # Crossings per segment (an upper bound), to cut the work into chunks of bounded memory.
    cost = np.cumsum(np.abs(np.floor(p1) - np.floor(p0)).sum(axis=1) + 2)
    out: list[tuple[NDArray[np.intp], ...]] = []
    lo = 0
    while lo < b:
        base = cost[lo - 1] if lo > 0 else 0.0
        hi = max(lo + 1, int(np.searchsorted(cost, base + ENTRIES_PER_CHUNK, side="right")))
        seg, *idx = _traverse_chunk(p0[lo:hi], p1[lo:hi], grid.shape)
        out.append((seg + lo, *idx))
        lo = hi
    if not out:
        return tuple(np.zeros(0, dtype=np.intp) for _ in range(d + 1))
    return tuple(np.concatenate([part[j] for part in out]) for j in range(d + 1))


def _merge(
    seg_a: NDArray[np.intp], t_a: NDArray[np.float64], seg_b: NDArray[np.intp], t_b: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Two crossing lists, each sorted by (segment, t), merged into one (ties: `a` first)."""
    # Keys 4 seg + 2 t stay inside a segment's own range [4 seg, 4 seg + 2] whatever the
    # rounding, and both key arrays are sorted, so the positions below are an exact merge.
    ka, kb = 4.0 * seg_a + 2.0 * t_a, 4.0 * seg_b + 2.0 * t_b
    pos_a = np.arange(ka.size) + np.searchsorted(kb, ka, side="left")
    pos_b = np.arange(kb.size) + np.searchsorted(ka, kb, side="right")
    seg = np.empty(ka.size + kb.size, dtype=np.intp)
    t = np.empty(ka.size + kb.size)
    seg[pos_a], seg[pos_b] = seg_a, seg_b
    t[pos_a], t[pos_b] = t_a, t_b
    return seg, t


def _traverse_chunk(p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, ...]) -> tuple[NDArray[np.intp], ...]:
    b, d = p0.shape
    seg_c, t_c = _line_crossings(p0[:, 0], p1[:, 0])
    for k in range(1, d):
        seg_c, t_c = _merge(seg_c, t_c, *_line_crossings(p0[:, k], p1[:, k]))
    n_cross = np.bincount(seg_c, minlength=b)
    # Full per-segment sequences [0, crossings..., 1]: each segment gains two entries.
    first = np.cumsum(n_cross + 2) - (n_cross + 2)
    t = np.empty(seg_c.size + 2 * b)
    t[first] = 0.0
    t[first + n_cross + 1] = 1.0
    t[np.arange(seg_c.size) + 2 * seg_c + 1] = t_c
    seg = np.repeat(np.arange(b, dtype=np.intp), n_cross + 2)
    # Intervals between consecutive entries of the same segment.
    same = seg[1:] == seg[:-1]
    dt = t[1:] - t[:-1]
    length = np.sqrt(((p1 - p0) ** 2).sum(axis=1))[seg[:-1]]
    # Drop zero-length intervals (two lines crossed at once, at a grid corner), but keep the
    # single [0, 1] interval of a zero-length segment so it still visits its own cell.
    keep = same & ((dt * length > 1e-9) | (length == 0))
    s = seg[:-1][keep]
    tm = 0.5 * (t[:-1][keep] + t[1:][keep])
    mid = p0[s] + tm[:, None] * (p1[s] - p0[s])
    # Array order is coordinate order reversed (x last).
    idx = [np.floor(mid[:, k]).astype(np.intp) for k in reversed(range(d))]
    inside = np.ones(s.size, dtype=bool)
    for i, n in zip(idx, shape, strict=True):
        inside &= (i >= 0) & (i < n)
    return (s[inside], *(i[inside] for i in idx))
