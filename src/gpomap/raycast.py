"""Exact ray traversal of grid cells (Amanatides & Woo), for every beam at once.

Shared by the occupancy grids (:mod:`gpomap.baselines.ogm`) and the ray evidence of the GP map
(:mod:`gpomap.evidence`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.grid import GridSpec

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


def traverse(grid: GridSpec, starts: ArrayLike, ends: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Every grid cell each segment passes through, in order from start to end.

    This is the Amanatides & Woo traversal done for all segments at once. Their algorithm steps
    to whichever grid line, x or y, comes next along the ray; the cells it visits are the
    intervals between the segment's grid-line crossings taken in increasing order. We list each
    segment's x and y crossings (each already in travel order), merge the two lists exactly
    (no sort: a merge position is an index plus a count from ``searchsorted``), and take the
    cell holding the midpoint of each interval. Where a segment passes exactly through a grid
    corner the interval between the two crossings has zero length and is dropped, so the
    diagonal neighbour is visited and the side neighbours are not.

    Parameters
    ----------
    grid : GridSpec
    starts, ends : array_like of shape (b, 2)
        Segment end points in the map frame.

    Returns
    -------
    beam : ndarray of int, shape (m,)
        Segment index of each visited cell (non-decreasing).
    rows, cols : ndarray of int, shape (m,)
        The visited cells, in order along each segment. Cells outside the grid are left out;
        the cells of one segment are distinct.
    """
    p0 = (np.asarray(starts, dtype=float).reshape(-1, 2) - grid.origin) / grid.resolution
    p1 = (np.asarray(ends, dtype=float).reshape(-1, 2) - grid.origin) / grid.resolution
    b = len(p0)
    # Crossings per segment (an upper bound), to cut the work into chunks of bounded memory.
    cost = np.cumsum(np.abs(np.floor(p1) - np.floor(p0)).sum(axis=1) + 2)
    out_b, out_r, out_c = [], [], []
    lo = 0
    while lo < b:
        base = cost[lo - 1] if lo > 0 else 0.0
        hi = max(lo + 1, int(np.searchsorted(cost, base + ENTRIES_PER_CHUNK, side="right")))
        bb, rr, cc = _traverse_chunk(p0[lo:hi], p1[lo:hi], grid.shape)
        out_b.append(bb + lo)
        out_r.append(rr)
        out_c.append(cc)
        lo = hi
    if not out_b:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty.copy(), empty.copy()
    return np.concatenate(out_b), np.concatenate(out_r), np.concatenate(out_c)


def _traverse_chunk(
    p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, int]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    b = len(p0)
    sx, tx = _line_crossings(p0[:, 0], p1[:, 0])
    sy, ty = _line_crossings(p0[:, 1], p1[:, 1])
    # Merge the x and y crossings by (segment, t). Keys 4 seg + 2 t stay inside a segment's own
    # range [4 seg, 4 seg + 2] whatever the rounding, and both key arrays are sorted, so the
    # positions below are an exact merge (ties: x first).
    kx, ky = 4.0 * sx + 2.0 * tx, 4.0 * sy + 2.0 * ty
    nx_, ny_ = kx.size, ky.size
    pos_x = np.arange(nx_) + np.searchsorted(ky, kx, side="left")
    pos_y = np.arange(ny_) + np.searchsorted(kx, ky, side="right")
    n_cross = np.bincount(sx, minlength=b) + np.bincount(sy, minlength=b)
    # Full per-segment sequences [0, crossings..., 1]: each segment gains two entries.
    first = np.cumsum(n_cross + 2) - (n_cross + 2)
    t = np.empty(nx_ + ny_ + 2 * b)
    t[first] = 0.0
    t[first + n_cross + 1] = 1.0
    t[pos_x + 2 * sx + 1] = tx
    t[pos_y + 2 * sy + 1] = ty
    seg = np.repeat(np.arange(b, dtype=np.intp), n_cross + 2)
    # Intervals between consecutive entries of the same segment.
    same = seg[1:] == seg[:-1]
    dt = t[1:] - t[:-1]
    length = np.hypot(*(p1 - p0).T)[seg[:-1]]
    # Drop zero-length intervals (x and y lines crossed at once, at a grid corner), but keep the
    # single [0, 1] interval of a zero-length segment so it still visits its own cell.
    keep = same & ((dt * length > 1e-9) | (length == 0))
    s = seg[:-1][keep]
    tm = 0.5 * (t[:-1][keep] + t[1:][keep])
    mid = p0[s] + tm[:, None] * (p1[s] - p0[s])
    cols = np.floor(mid[:, 0]).astype(np.intp)
    rows = np.floor(mid[:, 1]).astype(np.intp)
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    return s[inside], rows[inside], cols[inside]
