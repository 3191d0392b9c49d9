"""Ray traversal of grid cells compiled with numba (:func:`gpomap.raycast.traverse`'s fast path).

The numpy path lists every segment's grid-line crossings per axis, merges them by one stable sort
of the key ``4 seg + 2 t`` and takes the cell holding the midpoint of each interval between
consecutive entries. Here one compiled pass per segment does the same arithmetic in the same
order: the crossings of each axis as the numpy path computes them, merged by the same key (ties
to the earlier list: the start, the axes in order, the end, as the stable sort leaves them), the
same zero-length test and the same midpoint cells, without the numpy path's temporaries (about
120 bytes an entry). The cells are the numpy path's exactly (``tests/test_raycast.py`` compares
the two on random and grid-aligned segments).

``ENABLED``: :func:`gpomap.raycast.traverse` takes this path (read at each call;
:func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

__all__ = [
    "AVAILABLE",
    "ENABLED",
    "mark_crossed",
    "most_crossings",
    "traverse_chunk",
    "walk_scratch",
    "walk_segment",
]

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.raycast.traverse` takes the compiled path.
ENABLED: bool = compiled_by_default()


@jit(cache=True, nogil=True)
def crossings(u0: float, u1: float) -> int:  # pragma: no cover - compiled
    """How many integer lines the segment u0 -> u1 (cell units, one axis) crosses strictly inside."""
    n = np.int64(math.ceil(max(u0, u1)) - (math.floor(min(u0, u1)) + 1.0))
    return int(n) if n > 0 else 0


@jit(cache=True, nogil=True)
def walk_segment(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    s: int,
    place: int,
    length: float,
    shape: NDArray[np.int64],
    t_cross: NDArray[np.float64],
    key_cross: NDArray[np.float64],
    work: NDArray[np.int64],
    out: NDArray[np.intp],
    at: int,
) -> int:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """The cells segment `s` of `p0` -> `p1` crosses inside the grid, written as columns of `out`
    (d, n) from `at` (array order, x last); how many. `place` is its index within its chunk
    (:class:`gpomap.raycast.Segments`); `t_cross`, `key_cross` hold at least its crossings;
    `work` is scratch of shape (4, d). Callers pass int64 (``np.int64(0)``, never a bare 0):
    numba compiles this, and its caller again, for every argument type, a literal among them."""
    d = p0.shape[1]
    if d == 2:
        return _walk_plane(p0, p1, s, place, length, shape, out, at)
    if d == 3:
        return _walk_space(p0, p1, s, place, length, shape, out, at)
    count, run, pos, cell = work[0], work[1], work[2], work[3]
    # Each axis's crossings in travel order, as the numpy path computes them: the lines are
    # whole numbers, exact whichever way they are summed.
    m = 0
    for k in range(d):
        u0, u1 = p0[s, k], p1[s, k]
        first = math.floor(min(u0, u1)) + 1.0
        count[k] = max(np.int64(math.ceil(max(u0, u1)) - first), 0)
        run[k] = m
        pos[k] = 0
        down = u1 < u0
        for j in range(count[k]):
            t_cross[m] = _next_crossing(first, count[k], j, down, u0, u1)
            m += 1
    # Merged by the key 4 place + 2 t, ties to the earlier list, as the numpy path's stable sort
    # leaves them: the start (t = 0, the smallest key) first, the end (t = 1: a crossing's t never
    # rounds above it) last, the axes' crossings between, ties to the lower axis.
    base = 4.0 * np.float64(place)
    for j in range(m):
        key_cross[j] = base + 2.0 * t_cross[j]
    n = 0
    prev = 0.0
    for step in range(m + 1):
        if step < m:
            best = -1
            best_key = 0.0
            for k in range(d):
                if pos[k] < count[k]:
                    key = key_cross[run[k] + pos[k]]
                    if best < 0 or key < best_key:
                        best, best_key = k, key
            t = t_cross[run[best] + pos[best]]
            pos[best] += 1
        else:
            t = 1.0
        # The interval from the previous entry, unless of zero length (two lines crossed at
        # once); a zero-length segment keeps its one interval. Its cell holds its midpoint.
        if (t - prev) * length > 1e-9 or length == 0:
            tm = 0.5 * (prev + t)
            inside = True
            for a in range(d):
                k = d - 1 - a  # array order is coordinate order reversed (x last)
                i = np.intp(math.floor(p0[s, k] + tm * (p1[s, k] - p0[s, k])))
                if i < 0 or i >= shape[a]:
                    inside = False
                cell[a] = i
            if inside:
                for a in range(d):
                    out[a, at + n] = cell[a]
                n += 1
        prev = t
    return n


@jit(cache=True, nogil=True)
def _lines_within(u0: float, u1: float, cells: int) -> tuple[float, int]:  # pragma: no cover - compiled
    """The whole-number lines an axis's coordinate crosses going from u0 to u1 (the lowest, and how
    many), of those within the grid's 0..`cells` only.

    A line outside bounds no interval inside the grid: the intervals it would cut apart lie
    outside on that axis either way, so leaving it out changes no cell the walk writes, and a
    long beam across a small grid crosses only the lines within it."""
    first = math.floor(min(u0, u1)) + 1.0
    last = min(first + np.float64(max(int(math.ceil(max(u0, u1)) - first), 0)) - 1.0, np.float64(cells))
    first = max(first, 0.0)
    return first, max(int(last - first) + 1, 0)


@jit(cache=True, nogil=True)
def _next_crossing(first: float, count: int, j: int, down: bool, u0: float, u1: float) -> float:  # pragma: no cover - compiled
    """The `j`-th of an axis's `count` crossings in travel order (lines from `first`), as the t along u0 -> u1."""
    line = (first + np.float64(count) - 1.0) - np.float64(j) if down else first + np.float64(j)
    return (line - u0) / (u1 - u0)


@jit(cache=True, nogil=True)
def _walk_plane(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    s: int,
    place: int,
    length: float,
    shape: NDArray[np.int64],
    out: NDArray[np.intp],
    at: int,
) -> int:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """:func:`walk_segment` of a planar segment: the same arithmetic in the same order, each
    axis's next crossing held in scalars and computed when the last is taken, instead of listed
    and merged through arrays (which kept the generic walk's state out of registers)."""
    x0, y0, x1, y1 = p0[s, 0], p0[s, 1], p1[s, 0], p1[s, 1]
    fx, nx = _lines_within(x0, x1, shape[1])
    fy, ny = _lines_within(y0, y1, shape[0])
    down_x, down_y = x1 < x0, y1 < y0
    base = 4.0 * np.float64(place)
    jx = jy = 0
    tx = kx = ty = ky = 0.0
    if nx > 0:
        tx = _next_crossing(fx, nx, 0, down_x, x0, x1)
        kx = base + 2.0 * tx
    if ny > 0:
        ty = _next_crossing(fy, ny, 0, down_y, y0, y1)
        ky = base + 2.0 * ty
    n = 0
    prev = 0.0
    m = nx + ny
    for step in range(m + 1):
        if step < m:
            # The smaller key first, ties to x (the lower axis), as the generic merge takes them.
            if jx < nx and (jy >= ny or not ky < kx):
                t = tx
                jx += 1
                if jx < nx:
                    tx = _next_crossing(fx, nx, jx, down_x, x0, x1)
                    kx = base + 2.0 * tx
            else:
                t = ty
                jy += 1
                if jy < ny:
                    ty = _next_crossing(fy, ny, jy, down_y, y0, y1)
                    ky = base + 2.0 * ty
        else:
            t = 1.0
        if (t - prev) * length > 1e-9 or length == 0:
            tm = 0.5 * (prev + t)
            iy = np.intp(math.floor(y0 + tm * (y1 - y0)))
            ix = np.intp(math.floor(x0 + tm * (x1 - x0)))
            if iy >= 0 and iy < shape[0] and ix >= 0 and ix < shape[1]:
                out[0, at + n] = iy
                out[1, at + n] = ix
                n += 1
        prev = t
    return n


@jit(cache=True, nogil=True)
def _walk_space(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    s: int,
    place: int,
    length: float,
    shape: NDArray[np.int64],
    out: NDArray[np.intp],
    at: int,
) -> int:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """:func:`walk_segment` of a segment in space: :func:`_walk_plane`'s scalars for three axes
    (the same arithmetic in the same order as the generic walk)."""
    x0, y0, z0, x1, y1, z1 = p0[s, 0], p0[s, 1], p0[s, 2], p1[s, 0], p1[s, 1], p1[s, 2]
    fx, nx = _lines_within(x0, x1, shape[2])
    fy, ny = _lines_within(y0, y1, shape[1])
    fz, nz = _lines_within(z0, z1, shape[0])
    down_x, down_y, down_z = x1 < x0, y1 < y0, z1 < z0
    base = 4.0 * np.float64(place)
    jx = jy = jz = 0
    tx = kx = ty = ky = tz = kz = 0.0
    if nx > 0:
        tx = _next_crossing(fx, nx, 0, down_x, x0, x1)
        kx = base + 2.0 * tx
    if ny > 0:
        ty = _next_crossing(fy, ny, 0, down_y, y0, y1)
        ky = base + 2.0 * ty
    if nz > 0:
        tz = _next_crossing(fz, nz, 0, down_z, z0, z1)
        kz = base + 2.0 * tz
    n = 0
    prev = 0.0
    m = nx + ny + nz
    for step in range(m + 1):
        if step < m:
            # The smallest key first, ties to the lower axis, as the generic merge takes them.
            if jx < nx and (jy >= ny or not ky < kx) and (jz >= nz or not kz < kx):
                t = tx
                jx += 1
                if jx < nx:
                    tx = _next_crossing(fx, nx, jx, down_x, x0, x1)
                    kx = base + 2.0 * tx
            elif jy < ny and (jz >= nz or not kz < ky):
                t = ty
                jy += 1
                if jy < ny:
                    ty = _next_crossing(fy, ny, jy, down_y, y0, y1)
                    ky = base + 2.0 * ty
            else:
                t = tz
                jz += 1
                if jz < nz:
                    tz = _next_crossing(fz, nz, jz, down_z, z0, z1)
                    kz = base + 2.0 * tz
        else:
            t = 1.0
        if (t - prev) * length > 1e-9 or length == 0:
            tm = 0.5 * (prev + t)
            iz = np.intp(math.floor(z0 + tm * (z1 - z0)))
            iy = np.intp(math.floor(y0 + tm * (y1 - y0)))
            ix = np.intp(math.floor(x0 + tm * (x1 - x0)))
            if iz >= 0 and iz < shape[0] and iy >= 0 and iy < shape[1] and ix >= 0 and ix < shape[2]:
                out[0, at + n] = iz
                out[1, at + n] = iy
                out[2, at + n] = ix
                n += 1
        prev = t
    return n


@jit(cache=True, nogil=True)
def most_crossings(p0: NDArray[np.float64], p1: NDArray[np.float64]) -> tuple[int, int]:  # pragma: no cover - compiled
    """The crossings of all segments (plus one each: an upper bound of their cells) and of the longest."""
    total = 0
    longest = 0
    for s in range(p0.shape[0]):
        m = 0
        for k in range(p0.shape[1]):
            m += crossings(p0[s, k], p1[s, k])
        total += m + 1
        longest = max(longest, m)
    return total, longest


@jit(cache=True, nogil=True)
def walk_scratch(
    p0: NDArray[np.float64], p1: NDArray[np.float64], shape: NDArray[np.int64]
) -> tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.intp], NDArray[np.int64]
]:  # pragma: no cover - compiled
    """What :func:`walk_segment` needs to walk any of the segments `p0` -> `p1` into one column
    block: ``t_cross`` and ``key_cross`` for the longest's crossings, ``work`` (4, d), ``walked``
    (d, longest + 1) for its cells, and the strides of a grid of `shape`'s flat index."""
    d = p0.shape[1]
    _, longest = most_crossings(p0, p1)
    strides = np.ones(d, dtype=np.int64)
    for a in range(d - 2, -1, -1):
        strides[a] = strides[a + 1] * shape[a + 1]
    return (
        np.empty(longest, dtype=np.float64),
        np.empty(longest, dtype=np.float64),
        np.empty((4, d), dtype=np.int64),
        np.empty((d, longest + 1), dtype=np.intp),
        strides,
    )


@jit(cache=True, nogil=True)
def _traverse(
    p0: NDArray[np.float64], p1: NDArray[np.float64], length: NDArray[np.float64], shape: NDArray[np.int64]
) -> tuple[NDArray[np.intp], NDArray[np.intp], int]:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    b, d = p0.shape
    capacity, longest = most_crossings(p0, p1)
    seg_out = np.empty(capacity, dtype=np.intp)
    idx_out = np.empty((d, capacity), dtype=np.intp)
    t_cross = np.empty(longest, dtype=np.float64)
    key_cross = np.empty(longest, dtype=np.float64)
    work = np.empty((4, d), dtype=np.int64)
    n_out = np.int64(0)  # int64, as walk_segment is called everywhere
    for s in range(b):
        n = walk_segment(p0, p1, s, s, length[s], shape, t_cross, key_cross, work, idx_out, n_out)
        for j in range(n_out, n_out + n):
            seg_out[j] = s
        n_out += n
    return seg_out, idx_out, int(n_out)


def traverse_chunk(p0: NDArray[np.float64], p1: NDArray[np.float64], shape: tuple[int, ...]) -> tuple[NDArray[np.intp], ...]:
    """:func:`gpomap.raycast._traverse_chunk` compiled: the cells segments p0 -> p1 (cell units) cross.

    Parameters
    ----------
    p0, p1 : ndarray of shape (b, d)
        Segment ends in cell units (the grid's origin at 0), coordinates x first.
    shape : tuple of int
        The grid's shape, array order (x last).

    Returns
    -------
    seg : ndarray of int, shape (m,)
        Segment of each visited cell, non-decreasing.
    index : d ndarrays of int, shape (m,)
        The cells' array indices (x last), inside the grid, in order along each segment.
    """
    p0 = np.ascontiguousarray(p0, dtype=np.float64)
    p1 = np.ascontiguousarray(p1, dtype=np.float64)
    # The lengths as the numpy path computes them (its sum's order is numpy's own).
    length = np.sqrt(((p1 - p0) ** 2).sum(axis=1))
    seg, idx, n = _traverse(p0, p1, length, np.array(shape, dtype=np.int64))
    return (seg[:n], *(idx[a, :n] for a in range(p0.shape[1])))


@jit(cache=True, nogil=True)
def _mark_cells(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    length: NDArray[np.float64],
    place: NDArray[np.intp],
    shape: NDArray[np.int64],
    mark: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    t_cross, key_cross, work, walked, strides = walk_scratch(p0, p1, shape)
    for s in range(p0.shape[0]):
        n = walk_segment(p0, p1, s, place[s], length[s], shape, t_cross, key_cross, work, walked, np.int64(0))
        for e in range(n):
            c = np.int64(0)
            for a in range(walked.shape[0]):
                c += walked[a, e] * strides[a]
            mark[c] = True


def mark_crossed(walk: Any, shape: tuple[int, ...], mark: NDArray[np.bool_]) -> None:
    """Set `mark` (flat, of the grid's size) at every cell the segments of `walk` (a
    :class:`gpomap.raycast.Segments` on a grid of `shape`) cross: the cells of
    :func:`gpomap.raycast.traverse`, never listed."""
    _mark_cells(walk.p0, walk.p1, walk.lengths(), walk.places(), np.array(shape, dtype=np.int64), mark)


@jit(cache=True, nogil=True)
def _samples(
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    counts: NDArray[np.intp],
    step: float,
    points: NDArray[np.float64],
    ray: NDArray[np.intp],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    d = origins.shape[1]
    m = 0
    for r in range(counts.size):
        for k in range(1, counts[r] + 1):
            dist = np.float64(k) * step
            for a in range(d):
                points[m, a] = origins[r, a] + dist * directions[r, a]
            ray[m] = r
            m += 1


def free_samples(
    origins: NDArray[np.float64], directions: NDArray[np.float64], counts: NDArray[np.intp], step: float
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Points at ``step, 2 step, ..., counts[r] step`` along each ray r, written where they go:
    :func:`gpomap.observations.ray_free_points`'s points and rays (the same products and sums),
    without its gathered copies of the origins and directions per point.

    Parameters
    ----------
    origins, directions : ndarray of shape (b, d)
    counts : ndarray of int, shape (b,)
    step : float

    Returns
    -------
    points : ndarray of shape (counts.sum(), d)
    ray : ndarray of int, shape (counts.sum(),)
    """
    # Writeable as well as C order: a read-only array (a broadcast) would compile _samples again.
    origins = np.require(np.broadcast_to(origins, directions.shape), np.float64, ["C", "W"])
    counts = np.ascontiguousarray(counts, dtype=np.intp)
    total = int(counts.sum())
    points = np.empty((total, directions.shape[1]), dtype=np.float64)
    ray = np.empty(total, dtype=np.intp)
    _samples(origins, np.ascontiguousarray(directions, dtype=np.float64), counts, float(step), points, ray)
    return points, ray


@jit(cache=True, nogil=True)
def _voxel_index(
    points: NDArray[np.float64],
    lower: NDArray[np.float64],
    resolution: float,
    size: NDArray[np.int64],
    k: NDArray[np.intp],
    j: NDArray[np.intp],
    i: NDArray[np.intp],
    inside: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    cell = np.empty(3, dtype=np.intp)
    for q in range(points.shape[0]):
        ok = True
        for a in range(3):
            f = np.floor((points[q, a] - lower[a]) / resolution)
            if not np.isfinite(f):
                ok = False
                f = 0.0
            elif not (f >= 0 and f < size[a]):
                ok = False
            cell[a] = np.intp(min(max(f, 0.0), np.float64(size[a] - 1)))
        i[q], j[q], k[q] = cell[0], cell[1], cell[2]
        inside[q] = ok


def voxel_index(
    points: NDArray[np.float64], lower: NDArray[np.float64], resolution: float, shape: tuple[int, int, int]
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
    """:meth:`gpomap.voxels.VoxelSpec.index_of` compiled: the voxel ``k, j, i`` of each point
    (n, 3) (clipped to the grid) and whether it is inside, the same floors of the same quotients,
    without the numpy path's (n, 3) temporaries."""
    n = points.shape[0]
    k, j, i = (np.empty(n, dtype=np.intp) for _ in range(3))
    inside = np.empty(n, dtype=np.bool_)
    nz, ny, nx = shape
    _voxel_index(
        np.ascontiguousarray(points, dtype=np.float64),
        np.asarray(lower, dtype=np.float64),
        float(resolution),
        np.array([nx, ny, nz], dtype=np.int64),
        k,
        j,
        i,
        inside,
    )
    return k, j, i, inside


#: Offset of a cube's index on each axis in a packed key (21 bits an axis): a scan's cubes lie
#: within this many of its first ray's origin.
_CUBE_OFFSET = 1 << 20


@jit(cache=True, nogil=True)
def _merged_samples(
    origins: NDArray[np.float64], directions: NDArray[np.float64], counts: NDArray[np.intp], step: float, cube: float
) -> tuple[NDArray[np.float64], NDArray[np.int32], int]:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    d = origins.shape[1]
    size = 1 << 12
    points = np.empty((size, d), dtype=np.float64)
    weight = np.empty(size, dtype=np.int32)
    # Open addressing over packed cube keys: each cube's row in `points`, -1 for an empty slot.
    bits = 14
    keys = np.full(1 << bits, -1, dtype=np.int64)
    slots = np.empty(1 << bits, dtype=np.int64)
    n = 0
    sample = np.empty(d, dtype=np.float64)
    # The cube and row of the last ray's k-th sample: a frame's neighbouring pixels are
    # neighbouring rays, whose samples at one distance mostly share a cube, found here without
    # the table.
    longest = 0
    for r in range(counts.size):
        longest = max(longest, counts[r])
    last_key = np.full(longest + 1, -1, dtype=np.int64)
    last_slot = np.empty(longest + 1, dtype=np.int64)
    for r in range(counts.size):
        for k in range(1, counts[r] + 1):
            dist = np.float64(k) * step
            key = np.int64(0)
            for a in range(d):
                # The sample as _samples writes it, then its cube's index.
                sample[a] = origins[r, a] + dist * directions[r, a]
                q = np.int64(math.floor((sample[a] - origins[0, a]) / cube)) + _CUBE_OFFSET
                key = (key << 21) | q
            if last_key[k] == key:
                weight[last_slot[k]] += 1
                continue
            # Fibonacci hashing: the key times 2^64 / golden ratio, its top bits (neighbouring
            # cubes' keys differ in their low bits, which a plain mask would keep together).
            h = (key * np.int64(-7046029254386353131)) >> (64 - bits) & ((1 << bits) - 1)
            while keys[h] != -1 and keys[h] != key:
                h = (h + 1) & ((1 << bits) - 1)
            if keys[h] == key:
                weight[slots[h]] += 1
                last_key[k], last_slot[k] = key, slots[h]
                continue
            if n == size:
                size *= 2
                more_points = np.empty((size, d), dtype=np.float64)
                more_points[:n] = points[:n]
                more_weight = np.empty(size, dtype=np.int32)
                more_weight[:n] = weight[:n]
                points, weight = more_points, more_weight
            keys[h] = key
            slots[h] = n
            last_key[k], last_slot[k] = key, n
            points[n] = sample
            weight[n] = 1
            n += 1
            if 2 * n > (1 << bits):
                # Half full: every key placed again in a table twice the size.
                old_keys, old_slots = keys, slots
                bits += 1
                keys = np.full(1 << bits, -1, dtype=np.int64)
                slots = np.empty(1 << bits, dtype=np.int64)
                for s in range(old_keys.size):
                    if old_keys[s] != -1:
                        g = (old_keys[s] * np.int64(-7046029254386353131)) >> (64 - bits) & ((1 << bits) - 1)
                        while keys[g] != -1:
                            g = (g + 1) & ((1 << bits) - 1)
                        keys[g] = old_keys[s]
                        slots[g] = old_slots[s]
    return points, weight, n


def merged_free_samples(
    origins: NDArray[np.float64], directions: NDArray[np.float64], counts: NDArray[np.intp], step: float, cube: float
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """:func:`free_samples` merged by cube: the first sample in each cube of side `cube` (a
    lattice through the first ray's origin), in the samples' order, with how many samples fell
    in that cube (:func:`gpomap.observations.merge_by_cube`'s, never listing the samples).

    Parameters
    ----------
    origins, directions : ndarray of shape (b, d)
    counts : ndarray of int, shape (b,)
    step, cube : float
        The samples' spacing along a ray and the cubes' side; every sample within
        ``2**20 - 1`` cubes of the first origin (the caller checks).

    Returns
    -------
    points : ndarray of shape (u, d)
    weight : ndarray of int32, shape (u,)
    """
    origins = np.require(np.broadcast_to(origins, directions.shape), np.float64, ["C", "W"])
    points, weight, n = _merged_samples(
        origins,
        np.ascontiguousarray(directions, dtype=np.float64),
        np.ascontiguousarray(counts, dtype=np.intp),
        float(step),
        float(cube),
    )
    return points[:n].copy(), weight[:n].copy()
