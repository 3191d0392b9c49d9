"""Ray counts from traversal entries compiled with numba (:mod:`gpomap.evidence`'s fast path).

:meth:`gpomap.evidence.RayEvidence.counts` turns the cells every beam crossed into one update
per cell per scan (:func:`gpomap.evidence.scan_shares`). The numpy path sorts keys
``scan * cells + cell`` of every traversal entry; here one compiled pass walks the beams, scan by
scan, and tallies each touched cell in a small table (a slot per cell, reset after the scan), in
time linear in the cells walked. The counts are the numpy path's (``tests/test_fusion.py`` compares the two).

``ENABLED``: the counts take this path (:func:`gpomap.compiled.compiled_by_default` at import;
tests switch it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap._compiled_raycast import walk_scratch, walk_segment
from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit
from gpomap.lattice import AnyGrid
from gpomap.raycast import Segments

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`gpomap.evidence.RayEvidence.counts` takes the compiled path (read at each call).
ENABLED: bool = compiled_by_default()


@jit(cache=True, nogil=True)
def _add_scan(
    cells: NDArray[np.int64],
    through: NDArray[np.int64],
    ended: NDArray[np.int64],
    close: NDArray[np.int64],
    quiet: NDArray[np.int64],
    rows: int,
    hits: Any,
    misses: Any,
    near: Any,
    silent: Any,
    slot: NDArray[np.int32],
    shared: bool,
    units: int,
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """One scan's update of each cell of its table (the first `rows` rows) added into the counts,
    and the cells' slots reset."""
    for k in range(rows):
        c = cells[k]
        slot[c] = -1
        t = max(through[k], ended[k])
        if quiet[k] == t and ended[k] == 0:
            silent[c] += 1
        if shared and ended[k] == 0 and close[k] == 0:
            # Most rows: a plain miss, the whole update (adding the zero shares changes nothing).
            misses[c] += 1.0
        elif shared:
            # Whole units, as gpomap.evidence.scan_shares rounds them.
            h = np.floor(ended[k] / t * units + 0.5)
            h = max(h, 1.0) if ended[k] > 0 else h
            h = min(h, units - 1.0) if t > ended[k] else h
            n = np.floor(close[k] / t * units + 0.5)
            n = max(n, 1.0) if close[k] > 0 else n
            n = min(n, units - h)
            hits[c] += h / units
            misses[c] += (units - h) / units
            near[c] += n / units
        elif ended[k] > 0:
            hits[c] += 1
        else:
            misses[c] += 1
            if close[k] == t:
                near[c] += 1


@jit(cache=True, nogil=True)
def _count_beams(
    p0: NDArray[np.float64],
    p1: NDArray[np.float64],
    length: NDArray[np.float64],
    place: NDArray[np.intp],
    kept: NDArray[np.intp],
    beam_scan: NDArray[np.intp],
    beam_end: NDArray[np.int64],
    beam_hit: NDArray[np.bool_],
    beam_kept: NDArray[np.bool_],
    ends: NDArray[np.float64],
    origin: NDArray[np.float64],
    resolution: float,
    shape: NDArray[np.int64],
    near2: float,
    tail: int,
    hits: Any,
    misses: Any,
    near: Any,
    silent: Any,
    slot: NDArray[np.int32],
    shared: bool,
    units: int,
) -> tuple[
    NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], int
]:  # pragma: no cover
    # (compiled; the numpy path is the tests' reference)
    n_beams = beam_scan.size
    d = p0.shape[1]
    # The kept scans' tables, one after another: scan, cell, through, ended, close, quiet.
    kept_size = 0
    for b in range(n_beams):
        if beam_kept[b]:
            kept_size = 1 << 12
            break
    kept_rows = np.empty((6, kept_size), dtype=np.int64)
    n_kept = 0
    t_cross, key_cross, work, walked, strides = walk_scratch(p0, p1, shape)
    size = 1 << 12
    cells = np.empty(size, dtype=np.int64)
    through = np.empty(size, dtype=np.int64)
    ended = np.empty(size, dtype=np.int64)
    close = np.empty(size, dtype=np.int64)
    quiet = np.empty(size, dtype=np.int64)
    # Counters start as int64, not literal 0s: numba would compile each callee once more for a literal.
    j = np.int64(0)  # the next kept segment
    first = 0
    while first < n_beams:
        s = beam_scan[first]
        last = first
        while last < n_beams and beam_scan[last] == s:
            last += 1
        # The scan's table: a row per cell its beams touched.
        rows = np.int64(0)
        for b in range(first, last):
            if rows + 1 > size:
                size *= 2
                cells, through, ended, close, quiet = _grown(cells, through, ended, close, quiet, rows, size)
            c = beam_end[b]
            if c >= 0:
                k = slot[c]
                if k < 0:
                    k = rows
                    slot[c] = k
                    cells[k] = c
                    through[k] = 0
                    ended[k] = 0
                    close[k] = 0
                    quiet[k] = 0
                    rows += 1
                ended[k] += 1
        while j < kept.size and kept[j] < last:
            b = kept[j]
            n = walk_segment(p0, p1, j, place[j], length[j], shape, t_cross, key_cross, work, walked, np.int64(0))
            j += 1
            if rows + n > size:
                while rows + n > size:
                    size *= 2
                cells, through, ended, close, quiet = _grown(cells, through, ended, close, quiet, rows, size)
            for e in range(n):
                c = np.int64(0)
                for a in range(d):
                    c += walked[a, e] * strides[a]
                k = slot[c]
                if k < 0:
                    k = rows
                    slot[c] = k
                    cells[k] = c
                    through[k] = 0
                    ended[k] = 0
                    close[k] = 0
                    quiet[k] = 0
                    rows += 1
                through[k] += 1
                if not beam_hit[b]:
                    quiet[k] += 1
                # Only a returned beam's last `tail` cells can lie within the near distance of
                # its end (the centre's squared distance summed x first, as the numpy path does).
                if beam_hit[b] and e >= n - tail and c != beam_end[b]:
                    d2 = 0.0
                    for q in range(d):
                        v = origin[q] + (np.float64(walked[d - 1 - q, e]) + 0.5) * resolution - ends[b, q]
                        d2 += v * v
                    if d2 < near2:
                        close[k] += 1
        if beam_kept[first]:
            if n_kept + rows > kept_size:
                while n_kept + rows > kept_size:
                    kept_size *= 2
                more = np.empty((6, kept_size), dtype=np.int64)
                for q in range(6):
                    for k in range(n_kept):
                        more[q, k] = kept_rows[q, k]
                kept_rows = more
            for k in range(rows):
                kept_rows[0, n_kept] = s
                kept_rows[1, n_kept] = cells[k]
                kept_rows[2, n_kept] = through[k]
                kept_rows[3, n_kept] = ended[k]
                kept_rows[4, n_kept] = close[k]
                kept_rows[5, n_kept] = quiet[k]
                n_kept += 1
        _add_scan(cells, through, ended, close, quiet, rows, hits, misses, near, silent, slot, shared, units)
        first = last
    return kept_rows[0], kept_rows[1], kept_rows[2], kept_rows[3], kept_rows[4], kept_rows[5], n_kept


@jit(cache=True, nogil=True)
def _grown(
    cells: NDArray[np.int64],
    through: NDArray[np.int64],
    ended: NDArray[np.int64],
    close: NDArray[np.int64],
    quiet: NDArray[np.int64],
    rows: int,
    size: int,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:  # pragma: no cover
    """The table's arrays of `size` rows, the first `rows` kept (compiled)."""
    out = (
        np.empty(size, np.int64),
        np.empty(size, np.int64),
        np.empty(size, np.int64),
        np.empty(size, np.int64),
        np.empty(size, np.int64),
    )
    for k in range(rows):
        out[0][k] = cells[k]
        out[1][k] = through[k]
        out[2][k] = ended[k]
        out[3][k] = close[k]
        out[4][k] = quiet[k]
    return out


def count_beams(
    grid: AnyGrid,
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    hit: NDArray[np.bool_],
    beam_scan: NDArray[np.intp],
    beam_end: NDArray[np.int64],
    near_end: float,
    tail: int,
    counts: tuple[NDArray[Any], ...],
    slot: NDArray[np.int32],
    shared: bool = True,
    units: int = 256,
    kept: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.int64], ...]:
    """Add a batch of beams' hits, misses, near misses and silent updates into `counts` (flat
    arrays), in place: each beam's cells found (:func:`gpomap.raycast.traverse`'s, by
    :func:`gpomap._compiled_raycast.walk_segment`) and tallied as they are found, never listed;
    and return the tallies of the scans whose beams are `kept`.

    Parameters
    ----------
    grid : GridSpec or VoxelSpec
    starts, ends : ndarray of shape (b, d)
        The beams, map frame.
    hit : ndarray of bool, shape (b,)
        Whether each beam returned.
    beam_scan : ndarray of int, shape (b,)
        Scan of each beam, non-decreasing; a scan's beams all in this batch.
    beam_end : ndarray of int64, shape (b,)
        Flat index of each returned beam's end cell, -1 for beams that did not return or end outside.
    near_end : float
        :data:`gpomap.evidence.NEAR_END`: a cell whose centre is closer to a returned beam's end
        (and not its end's cell) is a near miss.
    tail : int
        How many of a returned beam's last cells can be that close (the numpy path's bound).
    counts : (hits, misses, near, silent), each ndarray of the grid's size
        (:class:`gpomap.evidence.RayCounts`): float32 or float64; `silent` may be 16- or 32-bit
        integers too, its updates being whole.
    slot : ndarray of int32 of the grid's size
        Scratch, -1 everywhere (and so again after the call).
    shared : bool
        :data:`gpomap.evidence.SHARED_UPDATES`.
    units : int
        :data:`gpomap.evidence.SHARE_UNITS`.
    kept : ndarray of bool, shape (b,), optional
        Beams whose scans' tallies are returned (all of a scan's beams alike).

    Returns
    -------
    scan, cell, through, ended, near, quiet : ndarray of int64, shape (r,)
        Per cell a kept scan touched (grouped by scan, in the order of the beams, the cells of a
        scan in no order): how many of its beams crossed or ended in the cell, how many returned
        and ended there, how many crossed it near their returned end without ending there, and
        how many of them returned nothing (:meth:`gpomap.evidence.RayEvidence._tallies`' counts).
    """
    walk = Segments.of(grid, starts, ends)
    keep = np.zeros(len(beam_scan), dtype=np.bool_) if kept is None else np.ascontiguousarray(kept, dtype=np.bool_)
    *rows, n = _count_beams(
        walk.p0,
        walk.p1,
        walk.lengths(),
        walk.places(),
        walk.kept,
        np.ascontiguousarray(beam_scan, dtype=np.intp),
        np.ascontiguousarray(beam_end, dtype=np.int64),
        np.ascontiguousarray(hit, dtype=np.bool_),
        keep,
        np.ascontiguousarray(ends, dtype=np.float64),
        np.asarray(grid.origin, dtype=np.float64),
        float(grid.resolution),
        np.array(grid.shape, dtype=np.int64),
        float(near_end) ** 2,
        int(tail),
        *counts,
        slot,
        bool(shared),
        int(units),
    )
    return tuple(r[:n].copy() for r in rows)
