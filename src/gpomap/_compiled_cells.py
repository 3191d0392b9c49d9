"""The cell tree compiled with numba (:func:`gpomap.cells.build_cells`'s fast path).

The Python tree visits each node with a few numpy calls on its points (a count, a comparison, two
fancy-indexed copies), so on small maps its cost is per node more than per point. Here one
compiled pass walks the same tree depth first over the points' indices, coordinates and classes,
partitioned together in place and stably, so every node's points lie contiguous and keep their
order. Over a block of millions of points both walks cost about the same, the work being per
point there (timings: docs/choices.md, "Measured for the code"). The cells, their order, their boxes and their members are the Python tree's exactly
(``tests/test_cells.py`` compares the two): the same comparisons and the same IEEE arithmetic on
the same numbers.

``ENABLED``: :func:`gpomap.cells.build_cells` takes this path (read at each call;
:func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = ["AVAILABLE", "ENABLED", "cell_tree"]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.cells.build_cells` takes the compiled path.
ENABLED: bool = compiled_by_default()


# Every copy below is an explicit loop, not a slice assignment (``out[:k] = a``): numba compiles a
# slice assignment with its shape-mismatch error, whose message formatting (strings) took 6 of the
# 11.6 CPU seconds this module's first compilation cost; loops bring it to 4.


@jit(cache=True, nogil=True)
def _grow_rows(a: NDArray, n: int) -> NDArray:  # pragma: no cover - compiled
    """The 2-D `a` with room for at least `n` rows (its first rows kept)."""
    if a.shape[0] >= n:
        return a
    out = np.empty((max(n, 2 * a.shape[0]), a.shape[1]), dtype=a.dtype)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            out[i, j] = a[i, j]
    return out


@jit(cache=True, nogil=True)
def _grow_flat(a: NDArray, n: int) -> NDArray:  # pragma: no cover - compiled
    """The 1-D `a` with room for at least `n` entries (its first ones kept)."""
    if a.shape[0] >= n:
        return a
    out = np.empty(max(n, 2 * a.shape[0]), dtype=a.dtype)
    for i in range(a.shape[0]):
        out[i] = a[i]
    return out


@jit(cache=True, nogil=True)
def _partition(
    first: NDArray[np.bool_],
    a: int,
    order: NDArray[np.intp],
    xs: NDArray[np.float64],
    oc: NDArray[np.bool_],
    s_order: NDArray[np.intp],
    s_xs: NDArray[np.float64],
    s_oc: NDArray[np.bool_],
) -> int:  # pragma: no cover - compiled
    """Stably move the points ``a + k`` where ``first[k]`` ahead of the others, in `order`, `xs`
    and `oc` together (through the scratch arrays); the index where the others begin. `first`
    may be a view of `oc`: it is read before `oc` is written."""
    b = a + first.size
    m = split = a
    for want in (True, False):
        for k in range(a, b):
            if first[k - a] == want:
                s_order[m] = order[k]
                s_oc[m] = oc[k]
                for j in range(xs.shape[0]):
                    s_xs[j, m] = xs[j, k]
                m += 1
        if want:
            split = m
    for k in range(a, b):
        order[k] = s_order[k]
        oc[k] = s_oc[k]
    for j in range(xs.shape[0]):
        for k in range(a, b):
            xs[j, k] = s_xs[j, k]
    return split


@jit(cache=True, nogil=True)
def _tree(
    pts: NDArray[np.float64],
    occ: NDArray[np.bool_],
    lo0: NDArray[np.float64],
    hi0: NDArray[np.float64],
    min_cell: float,
    max_cell: float,
    tight: bool,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], NDArray[np.int8]]:  # pragma: no cover - compiled
    # (the Python tree is the tests' reference)
    n, d = pts.shape
    # The points' indices, coordinates (column by column) and classes, partitioned together so
    # that every node's points lie contiguous and are read in order.
    order = np.empty(n, dtype=np.intp)
    xs = np.empty((d, n))
    oc = np.empty(n, dtype=np.bool_)
    for k in range(n):
        order[k] = k
        oc[k] = occ[k]
        for j in range(d):
            xs[j, k] = pts[k, j]
    s_order = np.empty(n, dtype=np.intp)
    s_xs = np.empty((d, n))
    s_oc = np.empty(n, dtype=np.bool_)
    # Per cell: its members' range, its box and node box (lower then upper, 4 d numbers), and
    # flags (bit 0 occupied, bit 1 ambiguous).
    ranges = np.empty((64, 2), dtype=np.intp)
    boxes = np.empty((64, 4 * d))
    flags = np.empty(64, dtype=np.int8)
    n_cells = 0
    # The stack of nodes: their range and box (2 d numbers).
    stack_range = np.empty((64, 2), dtype=np.intp)
    stack_box = np.empty((64, 2 * d))
    stack_range[0, 0], stack_range[0, 1] = 0, n
    for j in range(d):
        stack_box[0, j], stack_box[0, d + j] = lo0[j], hi0[j]
    top = 1
    lo = np.empty(d)
    hi = np.empty(d)
    while top > 0:
        top -= 1
        a, b = stack_range[top, 0], stack_range[top, 1]
        for j in range(d):
            lo[j], hi[j] = stack_box[top, j], stack_box[top, d + j]
        if b == a:
            continue  # empty cells carry no evidence
        n_occ = 0
        for k in range(a, b):
            if oc[k]:
                n_occ += 1
        pure = n_occ == 0 or n_occ == b - a
        axis = 0
        longest = hi[0] - lo[0]
        for j in range(1, d):
            side = hi[j] - lo[j]
            if side > longest:  # the first longest
                longest, axis = side, j
        if (pure and longest <= max_cell) or longest < min_cell:
            if pure:
                parts = ((a, b, n_occ > 0), (b, b, False))
            else:
                # Occupied first: the occupied cell, then the free one.
                split = _partition(oc[a:b], a, order, xs, oc, s_order, s_xs, s_oc)
                parts = ((a, split, True), (split, b, False))
            for part in parts:
                s, e, label = part
                if e == s:
                    continue
                ranges = _grow_rows(ranges, n_cells + 1)
                boxes = _grow_rows(boxes, n_cells + 1)
                flags = _grow_flat(flags, n_cells + 1)
                ranges[n_cells, 0], ranges[n_cells, 1] = s, e
                bounding = tight or not pure
                for j in range(d):
                    if bounding:
                        cmin, cmax = xs[j, s], xs[j, s]
                        for k in range(s + 1, e):
                            v = xs[j, k]
                            cmin = min(cmin, v)
                            cmax = max(cmax, v)
                        boxes[n_cells, j], boxes[n_cells, d + j] = cmin, cmax
                    else:
                        boxes[n_cells, j], boxes[n_cells, d + j] = lo[j], hi[j]
                    boxes[n_cells, 2 * d + j], boxes[n_cells, 3 * d + j] = lo[j], hi[j]
                flags[n_cells] = (1 if label else 0) + (0 if pure else 2)
                n_cells += 1
            continue
        mid = 0.5 * (lo[axis] + hi[axis])
        # The points left of the midpoint first.
        split = _partition(xs[axis, a:b] < mid, a, order, xs, oc, s_order, s_xs, s_oc)
        # The right half is pushed first, so the left one is walked first (the Python tree's order).
        stack_range = _grow_rows(stack_range, top + 2)
        stack_box = _grow_rows(stack_box, top + 2)
        stack_range[top, 0], stack_range[top, 1] = split, b
        stack_range[top + 1, 0], stack_range[top + 1, 1] = a, split
        for j in range(d):
            stack_box[top, j], stack_box[top, d + j] = lo[j], hi[j]
            stack_box[top + 1, j], stack_box[top + 1, d + j] = lo[j], hi[j]
        stack_box[top, axis] = mid
        stack_box[top + 1, d + axis] = mid
        top += 2
    return order, ranges[:n_cells], boxes[:n_cells], flags[:n_cells]


def cell_tree(
    points: NDArray[np.float64],
    occupied: NDArray[np.bool_],
    root_lower: NDArray[np.float64],
    root_upper: NDArray[np.float64],
    min_cell: float,
    max_cell: float,
    tight: bool,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
    """The cells of :func:`gpomap.cells.build_cells`'s tree, in its order.

    Parameters
    ----------
    points : ndarray of shape (m, d)
    occupied : ndarray of bool, shape (m,)
    root_lower, root_upper : ndarray of shape (d,)
        The root box.
    min_cell, max_cell : float
    tight : bool
        Cells take the bounding box of their points (``box="tight"``); ambiguous halves always do.

    Returns
    -------
    member_order : ndarray of int, shape (m,)
        Indices into the points, grouped by cell, in each cell's order.
    member_offsets : ndarray of int, shape (n + 1,)
    box : ndarray of shape (n, 2 d)
        Each cell's box, lower then upper corner.
    node : ndarray of shape (n, 2 d)
        The tree node each cell came from.
    occupied, ambiguous : ndarray of bool, shape (n,)
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    d = pts.shape[1]
    order, ranges, boxes, flags = _tree(
        pts,
        np.ascontiguousarray(occupied, dtype=np.bool_),
        np.asarray(root_lower, dtype=np.float64),
        np.asarray(root_upper, dtype=np.float64),
        float(min_cell),
        float(max_cell),
        bool(tight),
    )
    # Every point is in one cell, and the cells' ranges of `order` follow one another in the
    # order they were emitted (left halves first): `order` is the members, cell by cell.
    offsets = np.concatenate([ranges[:, 0], ranges[-1:, 1]]).astype(np.intp)
    return (
        order.astype(np.intp, copy=False),
        offsets,
        boxes[:, : 2 * d],
        boxes[:, 2 * d :],
        (flags & 1).astype(bool),
        (flags & 2).astype(bool),
    )
