"""Ray counts from traversal entries compiled with numba (:mod:`gpomap.evidence`'s fast path).

:meth:`gpomap.evidence.RayEvidence.counts` turns the cells every beam crossed into one update
per cell per scan (:func:`gpomap.evidence.scan_shares`). The numpy path sorts keys
``scan * cells + cell`` of every traversal entry; here one compiled pass over the entries, scan by
scan, tallies each touched cell in a small table (a slot per cell, reset after the scan), in time
linear in the entries. The counts are the numpy path's (``tests/test_fusion.py`` compares the two).

``ENABLED``: the counts take this path (:func:`gpomap.compiled.compiled_by_default` at import;
tests switch it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`gpomap.evidence.RayEvidence.counts` takes the compiled path (read at each call).
ENABLED: bool = compiled_by_default()


@jit(cache=True, nogil=True)
def _count_entries(
    entry_beam: NDArray[np.intp],
    entry_cell: NDArray[np.int64],
    entry_near: NDArray[np.bool_],
    beam_scan: NDArray[np.intp],
    beam_end: NDArray[np.int64],
    hits: Any,
    misses: Any,
    near: Any,
    slot: NDArray[np.int32],
    shared: bool,
    units: int,
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    n_beams = beam_scan.size
    n_entries = entry_beam.size
    e = 0
    first = 0
    while first < n_beams:
        s = beam_scan[first]
        last = first
        while last < n_beams and beam_scan[last] == s:
            last += 1
        stop = e
        while stop < n_entries and entry_beam[stop] < last:
            stop += 1
        # The scan's table: a row per cell its beams touched.
        size = (stop - e) + (last - first)
        cells = np.empty(size, dtype=np.int64)
        through = np.zeros(size, dtype=np.int64)
        ended = np.zeros(size, dtype=np.int64)
        close = np.zeros(size, dtype=np.int64)
        rows = 0
        for b in range(first, last):
            c = beam_end[b]
            if c >= 0:
                k = slot[c]
                if k < 0:
                    k = rows
                    slot[c] = k
                    cells[k] = c
                    rows += 1
                ended[k] += 1
        while e < stop:
            c = entry_cell[e]
            k = slot[c]
            if k < 0:
                k = rows
                slot[c] = k
                cells[k] = c
                rows += 1
            through[k] += 1
            if entry_near[e] and c != beam_end[entry_beam[e]]:
                close[k] += 1
            e += 1
        for k in range(rows):
            c = cells[k]
            slot[c] = -1
            t = max(through[k], ended[k])
            if shared:
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
        first = last


def count_entries(
    entry_beam: NDArray[np.intp],
    entry_cell: NDArray[np.int64],
    entry_near: NDArray[np.bool_],
    beam_scan: NDArray[np.intp],
    beam_end: NDArray[np.int64],
    counts: tuple[NDArray[np.floating[Any]], NDArray[np.floating[Any]], NDArray[np.floating[Any]]],
    slot: NDArray[np.int32],
    shared: bool = True,
    units: int = 256,
) -> None:
    """Add a batch of beams' hits, misses and near misses into `counts` (flat arrays), in place.

    Parameters
    ----------
    entry_beam : ndarray of int, shape (m,)
        Beam of each traversal entry, non-decreasing.
    entry_cell : ndarray of int64, shape (m,)
        Flat index of each entry's cell.
    entry_near : ndarray of bool, shape (m,)
        Whether the entry's cell is within :data:`gpomap.evidence.NEAR_END` of its beam's returned end.
    beam_scan : ndarray of int, shape (b,)
        Scan of each beam, non-decreasing; a scan's beams all in this batch.
    beam_end : ndarray of int64, shape (b,)
        Flat index of each returned beam's end cell, -1 for beams that did not return or end outside.
    counts : (hits, misses, near), each ndarray of float32 or float64 of the grid's size
    slot : ndarray of int32 of the grid's size
        Scratch, -1 everywhere (and so again after each call).
    shared : bool
        :data:`gpomap.evidence.SHARED_UPDATES`.
    units : int
        :data:`gpomap.evidence.SHARE_UNITS`.
    """
    _count_entries(
        np.ascontiguousarray(entry_beam, dtype=np.intp),
        np.ascontiguousarray(entry_cell, dtype=np.int64),
        np.ascontiguousarray(entry_near, dtype=np.bool_),
        np.ascontiguousarray(beam_scan, dtype=np.intp),
        np.ascontiguousarray(beam_end, dtype=np.int64),
        *counts,
        slot,
        bool(shared),
        int(units),
    )
