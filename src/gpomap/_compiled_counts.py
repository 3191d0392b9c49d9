"""Ray counts from traversal entries compiled with numba (:mod:`gpomap.evidence`'s fast path).

:meth:`gpomap.evidence.RayEvidence.counts` turns the cells every beam crossed into one update
per cell per scan (a hit winning, a miss near only if each of the scan's crossings of the cell
was near its beam's end) by sorting keys ``scan * cells + cell`` of every traversal entry: on a
whole Intel log 0.9 of its 2.0 CPU seconds were that sort. Here one compiled pass over the
entries, scan by scan, does the same with a mark per cell (the last scan that touched it and how),
in time linear in the entries. The counts are the numpy path's exactly
(``tests/test_fusion.py`` compares the two).

``ENABLED``: the counts take this path (:func:`gpomap.compiled.compiled_by_default` at import;
tests switch it).
"""

from __future__ import annotations

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
    hits: NDArray[np.int32],
    misses: NDArray[np.int32],
    near: NDArray[np.int32],
    mark: NDArray[np.int64],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    # mark[c] = 3 s + state for the last scan s that touched cell c: 0 a hit, 1 a near miss so
    # far, 2 a miss that saw through it. A scan's hits are marked before its crossings.
    n_beams = beam_scan.size
    n_entries = entry_beam.size
    e = 0
    first = 0
    while first < n_beams:
        s = beam_scan[first]
        last = first
        while last < n_beams and beam_scan[last] == s:
            last += 1
        base = 3 * np.int64(s)
        for b in range(first, last):
            c = beam_end[b]
            if c >= 0 and mark[c] != base:
                mark[c] = base
                hits[c] += 1
        while e < n_entries and entry_beam[e] < last:
            c = entry_cell[e]
            m = mark[c]
            if m == base + 1:
                if not entry_near[e]:
                    mark[c] = base + 2
                    near[c] -= 1
            elif m != base and m != base + 2:
                misses[c] += 1
                if entry_near[e]:
                    mark[c] = base + 1
                    near[c] += 1
                else:
                    mark[c] = base + 2
            e += 1
        first = last


def count_entries(
    entry_beam: NDArray[np.intp],
    entry_cell: NDArray[np.int64],
    entry_near: NDArray[np.bool_],
    beam_scan: NDArray[np.intp],
    beam_end: NDArray[np.int64],
    counts: tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32]],
    mark: NDArray[np.int64],
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
    counts : (hits, misses, near), each ndarray of int32 of the grid's size
    mark : ndarray of int64 of the grid's size
        Scratch, -1 everywhere before a call's first batch and kept between the batches of one count.
    """
    _count_entries(
        np.ascontiguousarray(entry_beam, dtype=np.intp),
        np.ascontiguousarray(entry_cell, dtype=np.int64),
        np.ascontiguousarray(entry_near, dtype=np.bool_),
        np.ascontiguousarray(beam_scan, dtype=np.intp),
        np.ascontiguousarray(beam_end, dtype=np.int64),
        *counts,
        mark,
    )
