"""The cell tree compiled with numba (:func:`gpomap.cells.build_cells`'s fast path).

The Python tree visits each node with a few numpy calls on its points (a count, a comparison, two
fancy-indexed copies), so on small maps its cost is per node more than per point. Here one
compiled pass walks the same tree depth first over the points' indices, coordinates and classes,
partitioned together in place and stably, so every node's points lie contiguous and keep their
order. The top of the tree, where every node is longer than ``max_cell`` and splits whatever its
points hold, is one stable sort of the points by the node they reach there instead of one
partition a level (over a block of millions of points the partitions were the walk's cost).
The cells, their order, their boxes and their members are the Python tree's exactly
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
    and `oc` together (through the scratch arrays, indexed from `a`); the index where the others
    begin. `first` may be a view of `oc`: it is read before `oc` is written."""
    n = first.size
    m = split = 0
    for want in (True, False):
        for k in range(n):
            if first[k] == want:
                s_order[m] = order[a + k]
                s_oc[m] = oc[a + k]
                for j in range(xs.shape[0]):
                    s_xs[j, m] = xs[j, a + k]
                m += 1
        if want:
            split = a + m
    for k in range(n):
        order[a + k] = s_order[k]
        oc[a + k] = s_oc[k]
    for j in range(xs.shape[0]):
        for k in range(n):
            xs[j, a + k] = s_xs[j, k]
    return split


#: Most nodes of the tree's forced top (:func:`_forced_top`): its boxes are a few numbers each.
FORCED_NODES = 1 << 16


@jit(cache=True, nogil=True)
def _forced_top(
    lo0: NDArray[np.float64], hi0: NDArray[np.float64], max_cell: float, limit: int
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - compiled
    """The top of the tree where every node splits whatever its points (its longest side above
    `max_cell`), with the tree's own arithmetic: each split node's axis and midpoint, its
    children (a frontier node ``f`` as ``-1 - f``), and the frontier's boxes (lower then upper)
    in the order the tree walks them. At most about `limit` frontier nodes: below them the walk
    goes on as usual."""
    d = lo0.size
    # Split nodes: axis, left child, right child; their midpoints apart.
    split = np.empty((64, 3), dtype=np.intp)
    mids = np.empty(64)
    n_split = 0
    # The frontier in walk order, each a box and the (split node, side) that points at it.
    front = np.empty((1, 2 * d))
    parent = np.empty((1, 2), dtype=np.intp)
    for j in range(d):
        front[0, j], front[0, d + j] = lo0[j], hi0[j]
    parent[0, 0], parent[0, 1] = -1, 0
    grew = True
    while grew and front.shape[0] <= limit:
        grew = False
        n_front = front.shape[0]
        new_front = np.empty((2 * n_front, 2 * d))
        new_parent = np.empty((2 * n_front, 2), dtype=np.intp)
        m = 0
        for f in range(n_front):
            axis = 0
            longest = front[f, d] - front[f, 0]
            for j in range(1, d):
                side = front[f, d + j] - front[f, j]
                if side > longest:  # the first longest
                    longest, axis = side, j
            if longest <= max_cell:
                for j in range(2 * d):
                    new_front[m, j] = front[f, j]
                new_parent[m, 0], new_parent[m, 1] = parent[f, 0], parent[f, 1]
                m += 1
                continue
            grew = True
            split = _grow_rows(split, n_split + 1)
            mids = _grow_flat(mids, n_split + 1)
            if parent[f, 0] >= 0:
                split[parent[f, 0], 1 + parent[f, 1]] = n_split
            mid = 0.5 * (front[f, axis] + front[f, d + axis])
            split[n_split, 0] = axis
            mids[n_split] = mid
            for side_ in range(2):
                for j in range(2 * d):
                    new_front[m, j] = front[f, j]
                if side_ == 0:
                    new_front[m, d + axis] = mid
                else:
                    new_front[m, axis] = mid
                new_parent[m, 0], new_parent[m, 1] = n_split, side_
                m += 1
            n_split += 1
        front = new_front[:m].copy()
        parent = new_parent[:m].copy()
    for f in range(front.shape[0]):
        if parent[f, 0] >= 0:
            split[parent[f, 0], 1 + parent[f, 1]] = -1 - f
    return split[:n_split].copy(), mids[:n_split].copy(), front


@jit(cache=True, nogil=True)
def _frontier_of(
    pts: NDArray[np.float64], k: int, split: NDArray[np.intp], mids: NDArray[np.float64]
) -> int:  # pragma: no cover - compiled
    """The frontier node of :func:`_forced_top` point `k` falls in: left where it lies below the midpoint."""
    if split.shape[0] == 0:
        return 0
    node = 0
    while node >= 0:
        # Without a branch (the comparison's truth as an index): half of these would be mispredicted.
        node = split[node, 2 - np.intp(pts[k, split[node, 0]] < mids[node])]
    return -1 - node


@jit(cache=True, nogil=True)
def _tree(
    pts: NDArray[np.float64],
    occ: NDArray[np.bool_],
    min_cell: float,
    max_cell: float,
    tight: bool,
    split_nodes: NDArray[np.intp],
    mids: NDArray[np.float64],
    front: NDArray[np.float64],
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], NDArray[np.int8]]:  # pragma: no cover - compiled
    # (the Python tree is the tests' reference)
    n, d = pts.shape
    # The nodes whose longest side is above max_cell split whatever their points hold (neither
    # pure and small enough nor below min_cell): the stable partitions down to their frontier
    # (split_nodes, mids, front: :func:`_forced_top`'s) are one stable sort by frontier node,
    # made in one pass instead of one a level.
    n_front = front.shape[0]
    starts = np.zeros(n_front + 1, dtype=np.intp)
    where = np.empty(n, dtype=np.int32)
    for k in range(n):
        where[k] = _frontier_of(pts, k, split_nodes, mids)
        starts[where[k] + 1] += 1
    widest = 0
    for f in range(n_front):
        widest = max(widest, starts[f + 1])
        starts[f + 1] += starts[f]
    # The points' indices, coordinates (column by column) and classes, partitioned together so
    # that every node's points lie contiguous and are read in order.
    order = np.empty(n, dtype=np.intp)
    xs = np.empty((d, n))
    oc = np.empty(n, dtype=np.bool_)
    at = starts[:-1].copy()
    for k in range(n):
        f = where[k]
        i = at[f]
        at[f] += 1
        order[i] = k
        oc[i] = occ[k]
        for j in range(d):
            xs[j, i] = pts[k, j]
    where = np.empty(0, dtype=np.int32)  # let go before the scratch below
    # Scratch for the partitions below the frontier, each within one frontier node's points.
    s_order = np.empty(widest, dtype=np.intp)
    s_xs = np.empty((d, widest))
    s_oc = np.empty(widest, dtype=np.bool_)
    # Per cell: its members' range, its box and node box (lower then upper, 4 d numbers), and
    # flags (bit 0 occupied, bit 1 ambiguous).
    ranges = np.empty((64, 2), dtype=np.intp)
    boxes = np.empty((64, 4 * d))
    flags = np.empty(64, dtype=np.int8)
    n_cells = 0
    # The stack of nodes: their range and box (2 d numbers); the frontier pushed last first, so
    # that it is walked in the tree's order.
    stack_range = np.empty((max(64, n_front), 2), dtype=np.intp)
    stack_box = np.empty((max(64, n_front), 2 * d))
    for f in range(n_front):
        t = n_front - 1 - f
        stack_range[t, 0], stack_range[t, 1] = starts[f], starts[f + 1]
        for j in range(2 * d):
            stack_box[t, j] = front[f, j]
    top = n_front
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
    lo0, hi0 = np.asarray(root_lower, dtype=np.float64), np.asarray(root_upper, dtype=np.float64)
    # Called from here, not from _tree: a compiled caller compiles its callees' code again with its own.
    split_nodes, mids, front = _forced_top(lo0, hi0, float(max_cell), FORCED_NODES)
    order, ranges, boxes, flags = _tree(
        pts,
        np.ascontiguousarray(occupied, dtype=np.bool_),
        float(min_cell),
        float(max_cell),
        bool(tight),
        split_nodes,
        mids,
        front,
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
