"""Ray counts of a few cells of a lattice, counted window by window without the lattice's arrays.

A map asked at a few points (the later visit's map of the other stretches, asked at a held-out
stretch's points) needs the counts of the cells holding them, not of every cell of a building's
lattice (tens of millions, each array of them hundreds of megabytes). :func:`count_cells` counts
the beams and the robot's path on square windows of the lattice that hold asked cells, one window
at a time, each grown by a cell so a cell at its edge knows whether a beam ended next to it
(:func:`gpomap.evidence.next_to_hits`), and keeps only the asked cells' values.

The windows are cells of the same lattice (:func:`gpomap.evidence.lattice_grid`), so each cell
gets the counts the whole lattice gives it, but for a beam that ends on or runs along a cell
border, which grids of different origins may round to either side.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evidence import RayEvidence, next_to_hits
from gpomap.lattice import AnyGrid, grid_dim, make_grid, rows

#: Side of the counting windows, in cells: a window's counts and scratch take about 40 bytes a
#: cell (42 MB), and beams longer than a window are walked once for each window they reach.
WINDOW_CELLS: int = 1024


@dataclass(frozen=True)
class CellCounts:
    """The counts of some cells of a lattice.

    Attributes
    ----------
    lattice : GridSpec or VoxelSpec
        The lattice the cells belong to.
    cells : ndarray of int, shape (n,)
        Their flat (row-major) indices, sorted and distinct.
    hits, misses, near, silent : ndarray of float, shape (n,)
        Their counts (:class:`gpomap.evidence.RayCounts`).
    path : ndarray of int, shape (n,)
        The robot's path's passes (:meth:`gpomap.evidence.RayEvidence.path_passes`).
    at_surface : ndarray of bool, shape (n,)
        Whether a beam ended in the cell or a neighbour (:func:`gpomap.evidence.next_to_hits`).
    """

    lattice: AnyGrid
    cells: NDArray[np.intp]
    hits: NDArray[np.floating[Any]]
    misses: NDArray[np.floating[Any]]
    near: NDArray[np.floating[Any]]
    silent: NDArray[np.number[Any]]
    path: NDArray[np.int64]
    at_surface: NDArray[np.bool_]

    def at(self, cells: NDArray[np.intp], inside: NDArray[np.bool_]) -> tuple[NDArray[Any], ...]:
        """Hits, misses, near misses, silent updates, path passes and whether at a surface, of each of `cells`
        (flat indices, shape (m,)) where `inside` (shape (m,)), 0 or False elsewhere.

        Raises
        ------
        ValueError
            If a cell inside was not counted.
        """
        wanted = np.asarray(cells, dtype=np.intp)[inside]
        row = np.minimum(np.searchsorted(self.cells, wanted), max(self.cells.size - 1, 0))
        if wanted.size and (self.cells.size == 0 or not np.array_equal(self.cells[row], wanted)):
            raise ValueError("the ray counts were taken only at the cells of the points this map was made for")
        values = (self.hits, self.misses, self.near, self.silent, self.path, self.at_surface)
        out = tuple(np.zeros(inside.shape, dtype=v.dtype) for v in values)
        for whole, counted in zip(out, values, strict=True):
            whole[inside] = counted[row]
        return out


def count_cells(
    evidence: RayEvidence,
    lattice: AnyGrid,
    cells: NDArray[np.intp],
    dtype: type[np.floating[Any]] = np.float64,
    window: int = WINDOW_CELLS,
) -> CellCounts:
    """The counts of `cells` of `lattice`, window by window (see the module's docstring).

    Parameters
    ----------
    evidence : RayEvidence
        The beams and path to count.
    lattice : GridSpec or VoxelSpec
        A lattice of :func:`gpomap.evidence.lattice_grid` (its origin a whole number of cells).
    cells : ndarray of int
        Flat (row-major) indices of cells of `lattice`, any order, repeats allowed.
    dtype : type
        Of the counts returned (those of the lattice they stand for: its arithmetic is theirs).
    window : int
        Side of the windows, in cells.

    Returns
    -------
    CellCounts
    """
    cells = np.unique(np.asarray(cells, dtype=np.intp))
    n = cells.size
    hits, misses, near, silent = (np.zeros(n, dtype=dtype) for _ in range(4))
    path, at_surface = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=bool)
    if n == 0:
        return CellCounts(lattice, cells, hits, misses, near, silent, path, at_surface)
    shape = np.array(lattice.shape)
    index = np.stack(np.unravel_index(cells, lattice.shape), axis=1)  # array order, x last
    tiles = index // window
    tile_keys = np.ravel_multi_index(tiles.T, tuple(-(-shape // window)))
    corner = np.round(np.asarray(lattice.origin, dtype=float) / lattice.resolution)  # x first
    reach = _reach(evidence, lattice, corner)
    for key in np.unique(tile_keys):
        rows = np.flatnonzero(tile_keys == key)
        lo = np.maximum(tiles[rows[0]] * window - 1, 0)
        hi = np.minimum((tiles[rows[0]] + 1) * window + 1, shape)
        # The window's corner as lattice_grid places one: a whole number of cells times the side.
        grid = make_grid((corner + lo[::-1]) * lattice.resolution, lattice.resolution, (hi - lo)[::-1])
        near_window = np.all((reach[0] <= hi[::-1]) & (reach[1] >= lo[::-1]), axis=1)
        counts = _beams(evidence, near_window).counts(grid)
        local = np.ravel_multi_index(tuple((index[rows] - lo).T), grid.shape)
        hits[rows], misses[rows], near[rows], silent[rows] = (a.reshape(-1)[local] for a in counts)
        at_surface[rows] = next_to_hits(counts.hits).reshape(-1)[local]
        path[rows] = evidence.path_passes(grid).reshape(-1)[local]
    return CellCounts(lattice, cells, hits, misses, near, silent, path, at_surface)


#: Largest count a cell may hold for counts to be taken out of it exactly: shares are whole
#: 256ths (:data:`gpomap.evidence.SHARE_UNITS`), exact in float32 below 2^24 of them.
EXACT_BELOW: float = float(2**16)
# Cells are keyed by their place on the lattice of every lattice (whole multiples of the side).
_KEY_OFFSET, _KEY_SPAN = 1 << 30, 1 << 31


def _keys(lattice: AnyGrid, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.int64]:
    """Keys of the cells (rows, cols) of a planar `lattice`, the same for a cell on any lattice."""
    corner = np.round(np.asarray(lattice.origin, dtype=float) / lattice.resolution).astype(np.int64)
    return (cols.astype(np.int64) + corner[0] + _KEY_OFFSET) * _KEY_SPAN + (rows.astype(np.int64) + corner[1] + _KEY_OFFSET)


@dataclass(frozen=True)
class CountsNear:
    """A planar lattice's counts at the cells round some points, known by their place on any
    lattice of the same side: a map of some of its scans takes its counts there from these,
    less the other scans' (:func:`count_cells_without`).

    Attributes
    ----------
    lattice : GridSpec
        The lattice the counts were taken on.
    keys : ndarray of int64, shape (n,)
        The cells, sorted and distinct (:func:`_keys`).
    hits, misses, near, silent : ndarray of float, shape (n,)
        Their counts (:class:`gpomap.evidence.RayCounts`).
    """

    lattice: AnyGrid
    keys: NDArray[np.int64]
    hits: NDArray[np.floating[Any]]
    misses: NDArray[np.floating[Any]]
    near: NDArray[np.floating[Any]]
    silent: NDArray[np.number[Any]]

    #: Cells either side of a point's own: a lattice of another origin may round a point on a
    #: border into the next cell, whose neighbours are then asked too.
    REACH = 2

    @classmethod
    def of(
        cls,
        lattice: AnyGrid,
        counts: tuple[NDArray[Any], ...],
        points: NDArray[np.float64],
    ) -> CountsNear:
        """The counts (hits, misses, near misses, silent updates, each of shape lattice.shape) of the cells within
        :attr:`REACH` cells of each of `points` (shape (m, 2)) on the planar `lattice`."""
        *index, inside = lattice.index_of(np.asarray(points, dtype=float))
        rows, cols = index  # a planar lattice
        around, ok = _around(rows[inside], cols[inside], cls.REACH, lattice.shape)
        flat = np.unique(around[ok])
        r, c = np.unravel_index(flat, lattice.shape)
        keys = _keys(lattice, r, c)
        order = np.argsort(keys)
        hits, misses, near, silent = (np.asarray(a).reshape(-1)[flat][order] for a in counts)
        return cls(lattice, keys[order], hits, misses, near, silent)

    def at(self, keys: NDArray[np.int64]) -> tuple[NDArray[np.number[Any]], ...] | None:
        """Hits, misses, near misses and silent updates at the cells `keys`, or None when one is not held or
        holds too many to take counts out of exactly (:data:`EXACT_BELOW`)."""
        row = np.minimum(np.searchsorted(self.keys, keys), max(self.keys.size - 1, 0))
        if keys.size and (self.keys.size == 0 or not np.array_equal(self.keys[row], keys)):
            return None
        values = tuple(a[row] for a in (self.hits, self.misses, self.near, self.silent))
        if any(v.size and float(v.max()) >= EXACT_BELOW for v in values):
            return None
        return values


def _around(
    rows: NDArray[np.intp], cols: NDArray[np.intp], reach: int, shape: tuple[int, ...]
) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """The flat indices of the cells within `reach` cells (a square) of each cell (rows, cols)
    of a planar lattice of `shape`, shape (n, (2 reach + 1)^2), and which of them lie inside it
    (those outside hold 0)."""
    steps = np.arange(-reach, reach + 1)
    r = (rows[:, None] + np.repeat(steps, steps.size)[None, :]).astype(np.intp)
    c = (cols[:, None] + np.tile(steps, steps.size)[None, :]).astype(np.intp)
    inside = (r >= 0) & (r < shape[0]) & (c >= 0) & (c < shape[1])
    clipped = (np.clip(r, 0, shape[0] - 1), np.clip(c, 0, shape[1] - 1))
    return np.where(inside, np.ravel_multi_index(clipped, shape), 0), inside


def count_cells_without(
    whole: CountsNear,
    left_out: RayEvidence,
    kept: RayEvidence,
    lattice: AnyGrid,
    cells: NDArray[np.intp],
    dtype: type[np.floating[Any]] = np.float64,
) -> CellCounts | None:
    """:func:`count_cells` of the kept scans' beams, as the counts of every scan (`whole`) less
    those of the scans left out, counted on `whole`'s lattice: counts on one lattice add over
    scans, and in whole shares below :data:`EXACT_BELOW` the difference is exact, so only the
    beams left out are walked. The cells are `whole`'s lattice's, and so is the rounding of a
    beam that ends on or runs along a cell border (:func:`count_cells`).

    Parameters
    ----------
    whole : CountsNear
        The counts of every scan round the asked points.
    left_out : RayEvidence
        The beams of the scans left out.
    kept : RayEvidence
        The kept scans' beams and path (the path is counted as it is: the kept scans' path
        steps over the stretches left out).
    lattice, cells, dtype
        As :func:`count_cells`'; `lattice` is planar, on `whole`'s side.

    Returns
    -------
    CellCounts or None
        None when `whole` lacks a cell it needs or a count too large to take from exactly.
    """
    cells = np.unique(np.asarray(cells, dtype=np.intp))
    own = whole.lattice
    if grid_dim(lattice) != 2 or grid_dim(own) != 2 or lattice.resolution != own.resolution:
        return None
    rows, cols = np.unravel_index(cells, lattice.shape)
    # Each cell and the cells next to it on this lattice (next_to_hits' 3 x 3).
    around, inside = _around(rows, cols, 1, lattice.shape)
    wanted = np.unique(around[inside])
    wr, wc = np.unravel_index(wanted, lattice.shape)
    keys = _keys(lattice, wr, wc)
    order = np.argsort(keys)
    found = whole.at(keys[order])
    if found is None:
        return None
    totals = [np.empty_like(v) for v in found]
    for total, v in zip(totals, found, strict=True):
        total[order] = v
    # The same cells on whole's lattice, where the scans left out are counted.
    shift = np.round((np.asarray(lattice.origin, dtype=float) - np.asarray(own.origin, dtype=float)) / own.resolution).astype(
        np.intp
    )
    there = np.ravel_multi_index((wr + shift[1], wc + shift[0]), own.shape)
    out = count_cells(left_out, own, there, dtype=whole.hits.dtype.type)
    at = np.searchsorted(out.cells, there)
    left = (out.hits, out.misses, out.near, out.silent)
    hits, misses, near, silent = (np.asarray(t - o[at], dtype=dtype) for t, o in zip(totals, left, strict=True))
    if any(v.size and float(v.min()) < 0.0 for v in (hits, misses, near, silent)):
        return None  # not counted on one lattice after all
    at_cell = np.searchsorted(wanted, around)
    at_surface = np.any(inside & (hits[np.minimum(at_cell, wanted.size - 1)] > 0), axis=1)
    place = np.searchsorted(wanted, cells)
    path = count_cells(_beams(kept, np.zeros(kept.hit.size, dtype=bool)), lattice, cells, dtype).path
    return CellCounts(lattice, cells, hits[place], misses[place], near[place], silent[place], path, at_surface)


def _reach(
    evidence: RayEvidence, lattice: AnyGrid, corner: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each beam's box in the lattice's cells (x first), grown by a cell: shapes (b, d) each,
    whole numbers held as floats (two arrays the beams' size, made in place, not eight)."""
    d = grid_dim(lattice)
    start = np.divide(evidence.starts.reshape(-1, d), lattice.resolution)
    np.floor(start, out=start)
    start -= corner
    end = np.divide(evidence.ends.reshape(-1, d), lattice.resolution)
    np.floor(end, out=end)
    end -= corner
    swap = start > end
    start[swap], end[swap] = end[swap], start[swap]
    start -= 1
    end += 1
    return start, end


def _beams(evidence: RayEvidence, keep: NDArray[np.bool_]) -> RayEvidence:
    """The beams of `evidence` at `keep`, with all of its path."""
    return RayEvidence(
        rows(evidence.starts, keep), rows(evidence.ends, keep), evidence.hit[keep], evidence.scan[keep], evidence.path
    )
