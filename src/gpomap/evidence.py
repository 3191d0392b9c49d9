"""Ray evidence: how many scans saw each fine cell free and how many ended a beam in it.

The GP over cells is a smooth prior over the whole map; what it cannot keep is the count of beams
that crossed a particular 5 cm cell, which is what makes a plain occupancy grid sharp where the
robot has data. :class:`RayEvidence` keeps the beams and counts, on any grid, what each scan
said of each cell: a scan whose beams touch a cell adds one update there, shared between a hit and
a miss in proportion to its beams that ended in the cell and those that crossed it
(:data:`SHARED_UPDATES`). A cell a wall runs through at a grazing angle is crossed by most of the
beams that reach it and ended in by a few: a hit winning the whole update, as in OctoMap, made
such cells read occupied and walls thicker than they are. It also keeps the robot's own path:
space the robot drove through was free when it did.
:mod:`gpomap.fusion` combines these counts with the GP's probability.

Misses are told apart by where they fall on their beam. A beam that crossed a cell and ended its
return within :data:`NEAR_END` of it says little about that cell: the surface may lie in it, the
range noise and the beam's width put the end a cell or two either side. A beam that went on
well beyond the cell saw through it. The counts keep, beside all misses, the ``near`` share:
the part of a scan's update that came from beams crossing the cell and ending within
:data:`NEAR_END` of it; :mod:`gpomap.fusion` weighs it apart.

The rays of 3-D point clouds are counted the same way on a voxel lattice
(:class:`~gpomap.voxels.VoxelSpec`): every array here has the data's own dimension d.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_dilation

from gpomap import _compiled_counts, _compiled_raycast
from gpomap.config import MapConfig
from gpomap.lattice import (
    AnyGrid,
    bounds_extent,
    column_bounds,
    extent_bounds,
    flat_index,
    grid_dim,
    grid_size,
    make_grid,
    row_sums,
    rows,
)
from gpomap.observations import PlanarBeams, Rays, ScanData
from gpomap.raycast import Segments, traverse
from gpomap.robot_path import PATH_RADIUS, path_steps
from gpomap.scans import Scan

#: Beams :meth:`RayEvidence.from_scans` works out at once from planar scans: a pass over many scans
#: costs less than a pass a scan, and about 130 bytes a beam of temporaries are held meanwhile.
BEAMS_AT_ONCE: int = 1 << 18

#: A miss whose cell centre lies within this distance (metres) of its beam's returned end is a
#: near miss (see the module's docstring): about the range noise and footprint of a 2-D or 3-D
#: lidar's return at a few metres, a few cells of the count lattices. Chosen with
#: ``benchmarks/near_misses.py`` (docs/choices.md, "Near misses").
NEAR_END: float = 0.2

#: Whether a scan's update of a cell is shared between hit, miss and near miss in proportion to its
#: beams there (True), or is one whole hit if any of its beams ended in the cell, else one miss,
#: near if every crossing was near (False, OctoMap's rule; docs/choices.md, "Shared updates").
SHARED_UPDATES: bool = True

#: A scan's update of a cell is shared in whole parts of this many (:func:`scan_shares`): sums of
#: them stay exact in float32 up to 2**24 / SHARE_UNITS updates of a cell.
SHARE_UNITS: int = 256
#: The type ray counts are tallied in, a map's lattice held in: shares of one update per scan.
COUNT_DTYPE: type[np.floating[Any]] = np.float32

#: Whole counts per cell (the robot's path's passes, the silent updates) are 16-bit while fewer
#: scans than this are counted: a cell is passed at most once per step of the path and updated at
#: most once a scan, so none can overflow, and a building's lattice (tens of millions of cells)
#: takes half the memory of 32-bit counts. A log that grows past it (a long stream) widens them to
#: 32 bits. The silent updates of any count take this type too, so the compiled tally is compiled
#: for one set of types.
NARROW_COUNT_SCANS: int = 2**16 - 1


def path_dtype(n_scans: int) -> type[np.integer[Any]]:
    """The type of whole counts per cell for `n_scans` scans: uint16 below :data:`NARROW_COUNT_SCANS`, else int32."""
    return np.uint16 if n_scans < NARROW_COUNT_SCANS else np.int32


class RayCounts(NamedTuple):
    """Counts per cell of a grid, each ndarray of float64 (float32: a map's lattice; its silent
    updates uint16 or int32) of shape grid.shape.

    Each scan adds at most one update to a cell (:func:`scan_shares`), so hits and misses add up
    to the number of scans that touched it.

    Attributes
    ----------
    hits : ndarray
        The scans' shares of beams that ended in the cell.
    misses : ndarray
        The scans' shares of beams that crossed the cell without ending there (the near ones included).
    near : ndarray
        The part of `misses` from beams that ended their return within :data:`NEAR_END` of the cell.
    silent : ndarray
        The whole updates among `misses` of scans whose every beam in the cell returned nothing
        (no-return beams, free to the cap): where they are all a cell's updates, no beam that
        saw a surface reached it, and beams that return nothing cross walls as well as free space.
        Whole numbers: a map's lattice holds them in 16-bit integers while it can.
    """

    hits: NDArray[Any]
    misses: NDArray[Any]
    near: NDArray[Any]
    silent: NDArray[Any]


def scan_shares(
    through: NDArray[np.integer[Any]],
    ended: NDArray[np.integer[Any]],
    near: NDArray[np.integer[Any]],
    quiet: NDArray[np.integer[Any]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """One scan's update of cells from its beams there (:data:`SHARED_UPDATES`), each of the inputs' shape.

    A share is a whole number of :data:`SHARE_UNITS`-ths of the update, at least one where any beam
    gave it: sums of them are exact in float32, so counts add up the same whatever the order of
    the scans (a map updated later equals the map of all its scans at once).

    Parameters
    ----------
    through : ndarray of int
        The scan's beams that crossed or ended in each cell.
    ended : ndarray of int
        Those that returned and ended in it.
    near : ndarray of int
        Those that crossed it, did not end in it and ended their return within :data:`NEAR_END`.
    quiet : ndarray of int
        Those that crossed it and returned nothing.

    Returns
    -------
    hits, misses, near, silent : ndarray of float64
        Shares of one update (0 where no beam touched the cell); `silent` is the whole update
        where every beam there returned nothing (:attr:`RayCounts.silent`).
    """
    through = np.maximum(through, ended)
    touched = through > 0
    silent = (touched & (ended == 0) & (quiet == through)).astype(np.float64)
    if not SHARED_UPDATES:
        hit = ended > 0
        miss = touched & ~hit
        return hit.astype(np.float64), miss.astype(np.float64), (miss & (near == through)).astype(np.float64), silent
    total = np.where(touched, through, 1)
    hit_units = np.clip(
        np.floor(ended / total * SHARE_UNITS + 0.5), ended > 0, np.where(through > ended, SHARE_UNITS - 1, SHARE_UNITS)
    )
    miss_units = np.where(touched, SHARE_UNITS - hit_units, 0)
    near_units = np.clip(np.floor(near / total * SHARE_UNITS + 0.5), near > 0, miss_units)
    return hit_units / SHARE_UNITS, miss_units / SHARE_UNITS, near_units / SHARE_UNITS, silent


def next_to_hits(hits: NDArray[np.number[Any]]) -> NDArray[np.bool_]:
    """Cells a beam ended in, or next to one (their 3 x 3, or 3 x 3 x 3, block), of the same shape.

    Parameters
    ----------
    hits : ndarray, shape grid.shape
        Hits per cell (:attr:`RayCounts.hits`).

    Returns
    -------
    ndarray of bool, shape hits.shape
    """
    hit = np.asarray(hits) > 0
    return np.asarray(binary_dilation(hit, structure=np.ones((3,) * hit.ndim, dtype=bool)), dtype=bool)


# Traversal entries handled per batch of scans: bounds the temporary memory (~24 bytes each).
_ENTRIES_PER_BATCH: int = 1 << 22


def _beam_reach(
    origins: NDArray[np.float64],
    directions: NDArray[np.float64],
    lengths: NDArray[np.float64],
    ends: NDArray[np.float64],
    hit: NDArray[np.bool_],
    no_return_cap: float | None,
) -> NDArray[np.float64]:
    """Where each of b beams ends for the counts, shape (b, d): a no-return beam at most
    `no_return_cap` along (None: at its recorded range); a beam not shortened keeps its recorded
    endpoint exactly. `origins` of shape (d,) or (b, d); `directions` and `ends` (b, d)."""
    length = lengths if no_return_cap is None else np.where(hit, lengths, np.minimum(lengths, no_return_cap))
    return np.where((length == lengths)[:, None], ends, origins + length[:, None] * directions)


@dataclass(frozen=True)
class RayEvidence:
    """The beams of a set of scans, ready to be counted on any grid.

    Attributes
    ----------
    starts, ends : ndarray of shape (b, d)
        Sensor position and end point of each usable beam (no-return beams end at the cap).
    hit : ndarray of bool, shape (b,)
        Whether the beam returned (its end cell is a hit); False for no-return beams.
    scan : ndarray of int, shape (b,)
        Index of the scan each beam belongs to, non-decreasing.
    path : ndarray of shape (k, 2 d)
        The robot's own path between consecutive scans, as segments (x0, y0, x1, y1) (in 3-D
        (x0, y0, z0, x1, y1, z1)): :func:`gpomap.robot_path.path_steps`, which leaves out jumps in the log.
    """

    starts: NDArray[np.float64]
    ends: NDArray[np.float64]
    hit: NDArray[np.bool_]
    scan: NDArray[np.intp]
    path: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    #: Updates that :meth:`counts` saw some scans make, kept for :meth:`scan_counts_at` (``keep``):
    #: ``{(grid, scan): (cells, hits, misses, near, silent)}``, the cells sorted distinct flat indices.
    _kept: dict[tuple[AnyGrid, int], tuple[NDArray[Any], ...]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @classmethod
    def from_scans(cls, scans: ScanData, no_return_cap: float | None = MapConfig.no_return_cap) -> RayEvidence:
        """Collect the usable beams of planar scans or the rays of point clouds.

        Parameters
        ----------
        scans : sequence of Scan, or sequence of CloudScan
        no_return_cap : float or None
            No-return beams clear free space this far (None: to the recorded range); they never
            give a hit.
        """
        planar = [s for s in scans if isinstance(s, Scan)]
        if planar and len(planar) == len(scans):
            return cls(*cls._planar_beams(planar, no_return_cap), path_steps(scans))
        starts, ends, hit, scan = [], [], [], []
        for i, s in enumerate(scans):
            rays = Rays.of(s)
            n = rays.hit.size
            starts.append(np.broadcast_to(rays.origin, (n, rays.origin.size)))
            ends.append(_beam_reach(rays.origin, rays.directions, rays.lengths, rays.ends, rays.hit, no_return_cap))
            hit.append(rays.hit)
            scan.append(np.full(n, i, dtype=np.intp))
        if not starts:
            empty = np.zeros((0, 2))
            return cls(empty, empty.copy(), np.zeros(0, bool), np.zeros(0, np.intp))
        return cls(np.concatenate(starts), np.concatenate(ends), np.concatenate(hit), np.concatenate(scan), path_steps(scans))

    @staticmethod
    def _planar_beams(
        scans: list[Scan], no_return_cap: float | None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.intp]]:
        """:meth:`from_scans`' starts, ends, hit and scan of planar scans, as scan by scan, worked
        out a run of scans of about :data:`BEAMS_AT_ONCE` beams at a time
        (:class:`~gpomap.observations.PlanarBeams`): one pass for many scans, and a building's
        temporaries never all at once."""
        sizes = np.array([s.ranges.size for s in scans], dtype=np.int64)
        cuts = np.searchsorted(np.cumsum(sizes), np.arange(BEAMS_AT_ONCE, int(sizes.sum()), BEAMS_AT_ONCE), side="right")
        runs = [(a, b) for a, b in zip([0, *cuts.tolist()], [*cuts.tolist(), len(scans)], strict=True) if b > a]
        # Written into their places: the runs' arrays are never held beside the whole's.
        n = sum(int(np.count_nonzero(s.valid())) for s in scans)
        starts, ends = np.empty((n, 2)), np.empty((n, 2))
        hit, scan = np.empty(n, dtype=bool), np.empty(n, dtype=np.intp)
        at = 0
        for first, last in runs:
            beams = PlanarBeams.of(scans[first:last])
            stop = at + beams.hit.size
            ends[at:stop] = _beam_reach(beams.origins, beams.directions, beams.lengths, beams.ends, beams.hit, no_return_cap)
            starts[at:stop], hit[at:stop], scan[at:stop] = beams.origins, beams.hit, beams.scan + first
            at = stop
        return starts, ends, hit, scan

    @property
    def dim(self) -> int:
        """Number of spatial dimensions of the rays."""
        return int(self.starts.shape[1])

    def path_passes(self, grid: AnyGrid, out: NDArray[np.integer[Any]] | None = None) -> NDArray[np.integer[Any]]:
        """How many steps of the robot's path passed each cell of `grid`, shape grid.shape.

        A step passes the cells it crosses when shifted by any whole number of cells up to
        :data:`gpomap.robot_path.PATH_RADIUS` (the robot's body round the sensor's track), each cell once per step,
        so the passes add over the path's steps. With `out` (of the grid's shape) they are added
        into it, and it is returned.
        """
        d = self.dim
        starts, ends = self.path[:, :d].reshape(-1, d), self.path[:, d:].reshape(-1, d)
        size = grid_size(grid)
        passes = np.zeros(grid.shape, dtype=np.int32) if out is None else out
        if starts.shape[0] == 0:
            return passes
        reach = int(np.floor(PATH_RADIUS / grid.resolution + 1e-9))
        steps = np.arange(-reach, reach + 1)
        offsets = np.stack(np.meshgrid(*([steps] * d), indexing="ij"), axis=-1).reshape(-1, d)
        offsets = offsets[(offsets**2).sum(axis=1) <= reach * reach + 1e-9] * grid.resolution
        keys = []
        for shift in offsets:
            seg, *idx = traverse(grid, starts + shift, ends + shift)
            keys.append(seg.astype(np.int64) * size + np.ravel_multi_index(tuple(idx), grid.shape))
        # Counted over the cells passed only: a building's lattice has tens of millions.
        cells, n = np.unique(np.unique(np.concatenate(keys)) % size, return_counts=True)
        passes.reshape(-1)[cells] += n.astype(passes.dtype)
        return passes

    @property
    def n_scans(self) -> int:
        """Number of scans the beams came from."""
        return int(self.scan[-1]) + 1 if self.scan.size else 0

    def extent(self) -> tuple[float, ...]:
        """(xmin, xmax, ymin, ymax) of every beam's start and end ((..., zmin, zmax) in 3-D)."""
        pts = np.concatenate([self.starts, self.ends])
        return bounds_extent(*column_bounds(pts))

    def counts(
        self,
        grid: AnyGrid,
        scans: NDArray[np.intp] | None = None,
        keep: NDArray[np.intp] | None = None,
        out: RayCounts | None = None,
    ) -> RayCounts:
        """Hits, misses, near misses and silent updates per cell of `grid`, one update per cell per scan (:func:`scan_shares`).

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
            Of the rays' dimension.
        scans : ndarray of int, optional
            Count only these scans (default: all).
        keep : ndarray of int, optional
            Scans (among those counted) whose updates are remembered, so that
            :meth:`scan_counts_at` on this grid reads them instead of traversing the scan's beams
            again (a leave-one-scan-out calibration asks it of the scans it holds out, right after
            the whole counts); :meth:`forget` drops them.
        out : RayCounts, optional
            Arrays of float32 or float64 of `grid`'s shape, C-contiguous, the counts are added
            into, and returned: a lattice over a building is counted in place instead of beside a
            copy. The silent updates' array may be of uint16 or int32 too (whole updates).

        Returns
        -------
        RayCounts
        """
        widen = out is None
        if out is None:
            # Tallied as a map's lattice is (one compiled tally for both) and widened at the end:
            # the same numbers below 2**24 / SHARE_UNITS updates of a cell.
            size = grid_size(grid)
            hits, misses, near = (np.zeros(size, dtype=COUNT_DTYPE) for _ in range(3))
            counts = RayCounts(hits, misses, near, np.zeros(size, dtype=path_dtype(self.n_scans)))
        else:
            kinds = [(np.float32, np.float64)] * 3 + [(np.float32, np.float64, np.uint16, np.int32)]
            if any(
                a.dtype not in k or a.shape != grid.shape or not a.flags.c_contiguous for a, k in zip(out, kinds, strict=True)
            ):
                raise ValueError(
                    f"counts are added into C-contiguous float32 or float64 arrays of the grid's shape {grid.shape} "
                    "(the silent updates' into uint16 or int32 too)"
                )
            counts = RayCounts(*(a.reshape(-1) for a in out))
        # The compiled path's scratch: each cell's row in the scan's table, -1 between scans.
        slot = np.full(grid_size(grid), -1, dtype=np.int32) if _compiled_counts.ENABLED else None
        select = np.ones(self.scan.size, bool) if scans is None else np.isin(self.scan, scans)
        idx = np.flatnonzero(select)
        if idx.size == 0:
            return _shaped(counts, grid.shape, widen)
        # Batches of whole scans whose traversals stay under the entry budget.
        # In place: a building's beams are hundreds of megabytes a copy.
        span = rows(self.ends, idx)
        span /= grid.resolution
        np.floor(span, out=span)
        first = rows(self.starts, idx)
        first /= grid.resolution
        np.floor(first, out=first)
        span -= first
        del first
        cells_per_beam = row_sums(np.abs(span, out=span)) + 2
        del span
        cost = np.cumsum(cells_per_beam)
        scan_of = self.scan[idx]
        lo = 0
        while lo < idx.size:
            base = cost[lo - 1] if lo > 0 else 0.0
            hi = max(lo + 1, int(np.searchsorted(cost, base + _ENTRIES_PER_BATCH, side="right")))
            if hi < idx.size:
                # Round down to a scan boundary, keeping at least one whole scan.
                boundary = int(np.searchsorted(scan_of, scan_of[hi], side="left"))
                hi = boundary if boundary > lo else int(np.searchsorted(scan_of, scan_of[lo], side="right"))
            self._accumulate(grid, idx[lo:hi], counts, keep, slot)
            lo = hi
        return _shaped(counts, grid.shape, widen)

    def forget(self) -> None:
        """Drop the updates :meth:`counts` kept for :meth:`scan_counts_at` (their memory)."""
        self._kept.clear()

    def seen(self, grid: AnyGrid) -> NDArray[np.bool_]:
        """Whether any beam crossed or ended a hit in each cell of `grid`: ``hits + misses > 0``
        of :meth:`counts`, without sorting out which scan counted what. Shape grid.shape."""
        mark = np.zeros(grid_size(grid), dtype=bool)
        if self.scan.size == 0:
            return mark.reshape(grid.shape)
        end_cell, inside = flat_index(grid, self.ends)
        mark[end_cell[inside & self.hit]] = True
        for first, last in _batches(grid, self.starts, self.ends):
            if _compiled_raycast.ENABLED:
                _compiled_raycast.mark_crossed(
                    Segments.of(grid, self.starts[first:last], self.ends[first:last]), grid.shape, mark
                )
                continue
            _, *idx = traverse(grid, self.starts[first:last], self.ends[first:last])
            mark[np.ravel_multi_index(tuple(idx), grid.shape)] = True
        return mark.reshape(grid.shape)

    def scan_counts_at(
        self, grid: AnyGrid, scan: int, cells: NDArray[np.intp]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """What one scan alone counts at some cells: ``counts(grid, scans=[scan])`` read at `cells`.

        Without arrays of the grid's size: the cells asked for are looked up (a binary search
        each) among the sorted cells the scan touched, which :meth:`counts` kept when asked to
        (``keep``), or else come from traversing the scan's beams in batches. A leave-one-scan-out
        calibration asks this of each held-out scan at its own points, on a lattice of millions
        of cells.

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
        scan : int
            Index of the scan.
        cells : ndarray of int
            Flat (row-major) indices of cells of `grid`.

        Returns
        -------
        hits, misses, near, silent : ndarray of float64, shape cells.shape
            The scan's update of each cell (:func:`scan_shares`); 0 where it touched none.
        """
        cells = np.asarray(cells, dtype=np.intp)
        kept = self._kept.get((grid, int(scan)))
        touched, *shares = self._scan_updates(grid, int(scan)) if kept is None else kept
        if touched.size == 0:
            return np.zeros(cells.shape), np.zeros(cells.shape), np.zeros(cells.shape), np.zeros(cells.shape)
        at = np.minimum(np.searchsorted(touched, cells), touched.size - 1)
        found = touched[at] == cells
        hits, misses, near, silent = (np.where(found, share[at], 0.0) for share in shares)
        return hits, misses, near, silent

    def _scan_updates(
        self, grid: AnyGrid, scan: int
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The cells one scan touched (sorted distinct flat indices) and its hits, misses, near
        misses and silent updates there (:func:`scan_shares`)."""
        lo, hi = np.searchsorted(self.scan, [scan, scan + 1])
        parts = [
            self._tallies(grid, np.arange(lo + first, lo + last))
            for first, last in _batches(grid, self.starts[lo:hi], self.ends[lo:hi])
        ]
        if not parts:
            empty = np.zeros(0, dtype=np.int64)
            return empty, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
        # A cell's beams may fall in more than one batch: their tallies add before the shares.
        keys = np.concatenate([p[0] for p in parts]) % grid_size(grid)
        cells, row = np.unique(keys, return_inverse=True)
        through, ended, near, quiet = (
            np.bincount(row, weights=np.concatenate([p[k] for p in parts]), minlength=cells.size).astype(np.int64)
            for k in (1, 2, 3, 4)
        )
        return (cells.astype(np.int64), *scan_shares(through, ended, near, quiet))

    def _tallies(
        self, grid: AnyGrid, beams: NDArray[np.intp]
    ) -> tuple[NDArray[np.int64], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
        """Per distinct key ``scan * cells + cell`` that `beams` touched (sorted): how many of them
        crossed or ended in the cell, how many returned and ended there, how many crossed it
        near their returned end (:data:`NEAR_END`) without ending there, and how many crossed it
        and returned nothing."""
        ncell = grid_size(grid)
        scan = self.scan[beams].astype(np.int64)
        end_cell, inside = flat_index(grid, self.ends[beams])
        ended = inside & self.hit[beams]
        b, cell, near_entry = self._entries(grid, beams)
        own_end = ended[b] & (cell == end_cell[b])
        entry_keys = scan[b] * ncell + cell
        end_keys = scan[ended] * ncell + end_cell[ended]
        keys = _unique(np.concatenate([entry_keys, end_keys]))
        through = np.bincount(np.searchsorted(keys, entry_keys), minlength=keys.size)
        n_ended = np.bincount(np.searchsorted(keys, end_keys), minlength=keys.size)
        near = np.bincount(np.searchsorted(keys, entry_keys[near_entry & ~own_end]), minlength=keys.size)
        quiet = np.bincount(np.searchsorted(keys, entry_keys[~self.hit[beams][b]]), minlength=keys.size)
        return keys, through, n_ended, near, quiet

    def _entries(self, grid: AnyGrid, beams: NDArray[np.intp]) -> tuple[NDArray[np.intp], NDArray[np.int64], NDArray[np.bool_]]:
        """Every cell `beams` crossed (:func:`~gpomap.raycast.traverse`): the entry's beam (index
        into `beams`, non-decreasing), its cell's flat index, and whether the cell's centre lies
        within :data:`NEAR_END` of the beam's returned end."""
        b, *idx = traverse(grid, self.starts[beams], self.ends[beams])
        tail = _near_tail(grid)
        per_beam = np.bincount(b, minlength=len(beams))
        stop = np.cumsum(per_beam)  # one past each beam's last entry
        start = stop - per_beam
        back = np.arange(1, tail + 1)
        cand = (stop[:, None] - back[None, :])[self.hit[beams]]
        cand = cand[cand >= start[self.hit[beams]][:, None]]
        # Distance from each candidate cell's centre to its beam's end (idx is in array order, x last).
        origin = np.asarray(grid.origin, dtype=float)
        ends = self.ends[beams][b[cand]]
        d2 = np.zeros(cand.size)
        for k, i in enumerate(reversed(idx)):
            d2 += (origin[k] + (i[cand] + 0.5) * grid.resolution - ends[:, k]) ** 2
        near = np.zeros(b.size, dtype=bool)
        near[cand[d2 < NEAR_END**2]] = True
        return b, np.ravel_multi_index(tuple(idx), grid.shape).astype(np.int64, copy=False), near

    def _accumulate(
        self,
        grid: AnyGrid,
        beams: NDArray[np.intp],
        counts: RayCounts,
        keep: NDArray[np.intp] | None = None,
        slot: NDArray[np.int32] | None = None,
    ) -> None:
        """Add the updates of `beams` (whole scans) into `counts`; with `slot` (the compiled path's
        scratch, see :func:`gpomap._compiled_counts.count_beams`) in one compiled pass."""
        ncell = grid_size(grid)
        scan = self.scan[beams]
        mine = np.zeros(scan.size, dtype=bool) if keep is None else np.isin(scan, keep)
        if slot is not None:
            ends = rows(self.ends, beams)
            end_cell, inside = flat_index(grid, ends)
            # Each beam's cells tallied as they are walked, never listed; the kept scans' tallies
            # as well, which the numpy path below gives as their sorted keys.
            k_scan, k_cell, k_through, k_ended, k_near, k_quiet = _compiled_counts.count_beams(
                grid,
                rows(self.starts, beams),
                ends,
                self.hit[beams],
                scan,
                np.where(inside & self.hit[beams], end_cell, -1),
                NEAR_END,
                _near_tail(grid),
                tuple(counts),
                slot,
                SHARED_UPDATES,
                SHARE_UNITS,
                mine,
            )
            if not mine.any():
                return
            order = np.lexsort((k_cell, k_scan))
            keys = k_scan[order] * ncell + k_cell[order]
            through, ended, near, quiet = k_through[order], k_ended[order], k_near[order], k_quiet[order]
        else:
            keys, through, ended, near, quiet = self._tallies(grid, beams)
        shares = scan_shares(through, ended, near, quiet)
        if slot is None:
            cell = keys % ncell
            for total, share in zip(counts, shares, strict=True):
                np.add(total, np.bincount(cell, weights=share, minlength=ncell), out=total, casting="unsafe")
        if keep is not None:
            # Keys are scan * ncell + cell, sorted: each kept scan's cells are one slice (copied,
            # so the batch's arrays are not kept alive).
            for k in np.intersect1d(keep, scan):
                lo, hi = np.searchsorted(keys, [int(k) * ncell, (int(k) + 1) * ncell])
                self._kept[(grid, int(k))] = (keys[lo:hi] - int(k) * ncell, *(s[lo:hi].copy() for s in shares))


def _near_tail(grid: AnyGrid) -> int:
    """How many of a beam's last cells can lie within :data:`NEAR_END` of its end: a cell whose
    centre is within it meets the last NEAR_END + half a diagonal of the beam, and each cell there
    takes at least one of the d axes a step further."""
    d = grid_dim(grid)
    return d * (int(np.ceil(NEAR_END / grid.resolution + np.sqrt(d) / 2)) + 1)


def _shaped(counts: RayCounts, shape: tuple[int, ...], widen: bool) -> RayCounts:
    """`counts` (flat) in the grid's `shape`, as float64 when `widen`."""
    return RayCounts(*(a.reshape(shape).astype(np.float64) if widen else a.reshape(shape) for a in counts))


def _batches(grid: AnyGrid, starts: NDArray[np.float64], ends: NDArray[np.float64]) -> list[tuple[int, int]]:
    """Consecutive ranges [first, last) of beams whose traversals stay under the entry budget (at least one beam each)."""
    cost = np.cumsum(row_sums(np.abs(np.floor(ends / grid.resolution) - np.floor(starts / grid.resolution))) + 2)
    out, first = [], 0
    while first < cost.size:
        base = cost[first - 1] if first > 0 else 0.0
        last = max(first + 1, int(np.searchsorted(cost, base + _ENTRIES_PER_BATCH, side="right")))
        out.append((first, last))
        first = last
    return out


def _unique(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Sorted distinct values: one sort and a comparison, much cheaper than :func:`numpy.unique`
    on the tens of millions of keys a whole log gives (docs/choices.md, "Measured for the code")."""
    return _distinct(np.sort(keys))


def _distinct(s: NDArray[np.int64]) -> NDArray[np.int64]:
    """The distinct values of a sorted array."""
    if s.size == 0:
        return s
    return s[np.concatenate([[True], s[1:] != s[:-1]])]


def lattice_grid(extent: tuple[float, ...], resolution: float, margin: float = 0.0) -> AnyGrid:
    """The grid of cells ``[k r, (k + 1) r)`` covering `extent` (plus `margin`), r = `resolution`.

    Cells on this lattice are the same whatever the extent, so counts taken on grids of two
    extents agree cell by cell, but for a point exactly on a cell border: indices are taken from
    each grid's own origin, and two origins can round such a point to either side. A 4-value extent (xmin, xmax, ymin, ymax) gives a
    :class:`~gpomap.grid.GridSpec`, a 6-value one a :class:`~gpomap.voxels.VoxelSpec`.
    """
    lo, hi = extent_bounds(extent)
    origin = np.floor((lo - margin) / resolution) * resolution
    counts = np.floor((hi + margin - origin) / resolution).astype(int) + 1
    return make_grid(origin, resolution, counts)
