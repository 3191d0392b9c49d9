"""Ray evidence: how many scans saw each fine cell free and how many ended a beam in it.

The GP over cells is a smooth prior over the whole map; what it cannot keep is the count of beams
that crossed a particular 5 cm cell, which is what makes a plain occupancy grid sharp where the
robot has data. :class:`RayEvidence` keeps the beams and counts, on any grid, the scans that
ended a beam in each cell (hits) and the scans that crossed it without ending there (misses). As
in OctoMap, a scan updates a cell once, and a hit wins over a miss of the same scan. It also keeps
the robot's own path: space the robot drove through was free when it did.
:mod:`gpomap.fusion` combines these counts with the GP's probability.

Misses are told apart by where they fall on their beam. A beam that crossed a cell and ended its
return within :data:`NEAR_END` of it says little about that cell: the surface may lie in it, the
range noise and the beam's width put the end a cell or two either side. A beam that went on
well beyond the cell saw through it. The counts keep, beside all misses, the ``near`` ones: those
of scans whose every beam through the cell ended within :data:`NEAR_END` (a scan that saw
through the cell on any beam counts a plain miss); :mod:`gpomap.fusion` weighs them apart.

The rays of 3-D point clouds are counted the same way on a voxel lattice
(:class:`~gpomap.voxels.VoxelSpec`): every array here has the data's own dimension d.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_dilation

from gpomap import _compiled_counts
from gpomap.clouds import CloudScan
from gpomap.lattice import AnyGrid, bounds_extent, column_bounds, extent_bounds, flat_index, grid_size, make_grid
from gpomap.observations import Rays, ScanData, sensor_positions
from gpomap.raycast import traverse
from gpomap.scans import Scan

#: Longest step between consecutive scans' poses taken as the robot driving (metres); longer
#: steps are jumps in the log (a new session, a relocalisation), not a path. Logs thinned by
#: distance keep a scan every 0.5-1 m (Intel: median 0.67 m, 99 % under 1.06 m; MIT's infinite
#: corridor, the Freiburg campus and five other public logs: median 0.97-1.04 m, 99 % at most
#: 1.25 m). A scan lost, or held out, doubles a step there: at 1.5 m, those steps were jumps and
#: the robot's path had a gap at each (the corridor's every-10th split called 28 path cells
#: occupied, none at 2.5 m). A longer step is driving only where the robot drove straight along
#: it (:data:`STRAIGHT_STEP_STRAY`): Örebro loses one or two scans in a row (3 m steps).
MAX_PATH_STEP: float = 2.5

#: Longest step (metres) taken as driving where the robot drove straight along it: twice
#: :data:`MAX_PATH_STEP`. Longer gaps may hide a detour whatever the ends' headings (a block of 40
#: scans held out spans 10-40 m on the logs here).
MAX_STRAIGHT_STEP: float = 2 * MAX_PATH_STEP

#: Steps up to this long (metres) are the robot's path as they are. A longer one may not be
#: where the robot drove (a loop in a stretch held out, whose ends are 2.2 m apart across Intel's
#: wall, facing 85 degrees off the step): it is the path only where the robot drove straight
#: along it (:data:`STRAIGHT_STEP_ANGLE`) or neither end's scan has a hit within
#: :data:`PATH_RADIUS` of it. On the shared logs' every-10th splits, the steps over a held-out
#: scan keep 0.33 m or more from their ends' hits; on the corridor's, three straight ones pass
#: within 0.06 m of a hit (something the robot then drove through: a person, a door).
SURE_PATH_STEP: float = 1.5

#: A planar scan's step is straight driving when both ends' headings lie within this many degrees
#: of the step's direction, forward or backward (the corridor's straight steps over a held-out
#: scan: 2-10 degrees; turns in the logs' every-10th splits: up to 73).
STRAIGHT_STEP_ANGLE: float = 30.0

#: How far (metres) the robot may have strayed from a straight step. An arc that leaves and
#: reaches a step of length L at an angle a to it lies at most (L / 2) tan(a / 2) from it; this
#: is that distance for the longest step and the angle above (0.33 m), so a straight step longer
#: than :data:`MAX_PATH_STEP` holds its ends' headings closer to it (19 degrees at 4 m, 15 at 5 m).
STRAIGHT_STEP_STRAY: float = MAX_PATH_STEP / 2 * float(np.tan(np.radians(STRAIGHT_STEP_ANGLE) / 2))

#: The robot's body round its path (metres): the cells the path crosses, shifted by up to this
#: much, count its steps (:meth:`RayEvidence.path_passes`). Any robot that carries a planar lidar
#: is wider than 0.2 m, so these cells were inside it. Held-out hits this close to a log's training
#: path are 0-0.15 % of them on the shared logs (FR079's people beside the robot); the Stage
#: arena's robot passes closer to its walls (1 held-out hit within 0.1 m, 10 within 0.15 m).
PATH_RADIUS: float = 0.1

#: A miss whose cell centre lies within this distance (metres) of its beam's returned end is a
#: near miss (see the module's docstring): about the range noise and footprint of a 2-D or 3-D
#: lidar's return at a few metres, a few cells of the 5 cm (10 cm in 3-D) count lattices. On
#: every shared log and split, 0.1 and 0.2 m both cut the held-out log loss and tie; 0.3 m cuts
#: it less on 11 of 12 (``benchmarks/near_misses.py``, docs/choices.md).
NEAR_END: float = 0.2


def path_steps(scans: ScanData) -> NDArray[np.float64]:
    """The robot's path between consecutive scans, as segments (x0, y0, x1, y1), shape (k, 2 d).

    A step up to :data:`SURE_PATH_STEP` long is the path. A longer one is, when the robot drove
    straight along it (planar scans whose headings both lie within :data:`STRAIGHT_STEP_ANGLE` of
    it, and close enough that an arc between them strays at most :data:`STRAIGHT_STEP_STRAY`) and
    it is at most :data:`MAX_STRAIGHT_STEP` long, or, up to :data:`MAX_PATH_STEP`, when neither
    end's scan has a hit within :data:`PATH_RADIUS` of it (it could not have driven through what it
    saw); other steps are jumps.

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
        In log order.
    """
    scans = list(scans)
    if not scans:
        return np.zeros((0, 4))
    poses = sensor_positions(scans)
    d = poses.shape[1]
    steps = np.column_stack([poses[:-1], poses[1:]])
    lengths = np.sqrt(((steps[:, d:] - steps[:, :d]) ** 2).sum(axis=1))
    keep = lengths <= SURE_PATH_STEP
    for k in np.flatnonzero((lengths > SURE_PATH_STEP) & (lengths <= MAX_STRAIGHT_STEP)):
        if _drives_straight(scans[k], scans[k + 1]):
            keep[k] = True
            continue
        if lengths[k] > MAX_PATH_STEP:
            continue
        ends = [Rays.of(s) for s in (scans[k], scans[k + 1])]
        hits = np.concatenate([r.ends[r.hit] for r in ends]).reshape(-1, d)
        keep[k] = not (hits.size and _segment_distances(hits, steps[k, :d], steps[k, d:]).min() <= PATH_RADIUS)
    return steps[keep]


def _drives_straight(first: Scan | CloudScan, second: Scan | CloudScan) -> bool:
    """Whether two planar scans' headings both lie within :data:`STRAIGHT_STEP_ANGLE` of the step
    between them, forward or backward, and within the angle at which an arc between them strays
    :data:`STRAIGHT_STEP_STRAY` from it (point clouds carry no heading: False)."""
    if not (isinstance(first, Scan) and isinstance(second, Scan)):
        return False
    step = second.pose[:2] - first.pose[:2]
    direction = np.arctan2(step[1], step[0])
    # Off the step's line, forward or backward: the heading's difference folded into [0, pi/2].
    off = np.abs(np.angle(np.exp(2j * (np.array([first.pose[2], second.pose[2]]) - direction)))) / 2.0
    # The arc's stray (L / 2) tan(a / 2) solved for a.
    arc = 2.0 * np.arctan(2.0 * STRAIGHT_STEP_STRAY / max(float(np.hypot(*step)), 1e-12))
    return bool(np.all(off <= min(np.radians(STRAIGHT_STEP_ANGLE), arc)))


def _segment_distances(points: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance from each point (n, d) to the segment a-b, shape (n,)."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.sqrt(((points - (a + t[:, None] * ab)) ** 2).sum(axis=1))


class RayCounts(NamedTuple):
    """Counts per cell of a grid, each ndarray of int32 (or uint16: a map's lattice,
    :func:`gpomap.fusion.count_dtype`) of shape grid.shape.

    Attributes
    ----------
    hits : ndarray
        Scans that ended a beam in the cell.
    misses : ndarray
        Scans that crossed the cell without ending a beam there (the near ones included).
    near : ndarray
        Those misses whose every beam through the cell ended its return within :data:`NEAR_END`.
    """

    hits: NDArray[np.integer[Any]]
    misses: NDArray[np.integer[Any]]
    near: NDArray[np.integer[Any]]


def next_to_hits(hits: NDArray[np.integer]) -> NDArray[np.bool_]:
    """Cells a beam ended in, or next to one (their 3 x 3, or 3 x 3 x 3, block), of the same shape.

    Parameters
    ----------
    hits : ndarray of int, shape grid.shape
        Hits per cell (:attr:`RayCounts.hits`).

    Returns
    -------
    ndarray of bool, shape hits.shape
    """
    hit = np.asarray(hits) > 0
    return np.asarray(binary_dilation(hit, structure=np.ones((3,) * hit.ndim, dtype=bool)), dtype=bool)


# Traversal entries handled per batch of scans: bounds the temporary memory (~24 bytes each).
_ENTRIES_PER_BATCH: int = 1 << 22


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
        (x0, y0, z0, x1, y1, z1)): :func:`path_steps`, which leaves out jumps in the log.
    """

    starts: NDArray[np.float64]
    ends: NDArray[np.float64]
    hit: NDArray[np.bool_]
    scan: NDArray[np.intp]
    path: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    #: Cells that :meth:`counts` saw some scans count, kept for :meth:`scan_counts_at` (``keep``):
    #: ``{(grid, scan): (ended, crossed, crossed near the end only)}``, sorted distinct flat cell indices.
    _kept: dict[tuple[AnyGrid, int], tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @classmethod
    def from_scans(cls, scans: ScanData, no_return_cap: float | None = 10.0) -> RayEvidence:
        """Collect the usable beams of planar scans or the rays of point clouds.

        Parameters
        ----------
        scans : sequence of Scan, or sequence of CloudScan
        no_return_cap : float or None
            No-return beams clear free space this far (None: to the recorded range); they never
            give a hit.
        """
        starts, ends, hit, scan = [], [], [], []
        for i, s in enumerate(scans):
            rays = Rays.of(s)
            length = rays.lengths
            if no_return_cap is not None:
                length = np.where(rays.hit, length, np.minimum(length, no_return_cap))
            n = rays.hit.size
            starts.append(np.broadcast_to(rays.origin, (n, rays.origin.size)))
            # Uncapped rays keep their recorded endpoints exactly.
            ends.append(np.where((length == rays.lengths)[:, None], rays.ends, rays.origin + length[:, None] * rays.directions))
            hit.append(rays.hit)
            scan.append(np.full(n, i, dtype=np.intp))
        if not starts:
            empty = np.zeros((0, 2))
            return cls(empty, empty.copy(), np.zeros(0, bool), np.zeros(0, np.intp))
        return cls(np.concatenate(starts), np.concatenate(ends), np.concatenate(hit), np.concatenate(scan), path_steps(scans))

    @property
    def dim(self) -> int:
        """Number of spatial dimensions of the rays."""
        return int(self.starts.shape[1])

    def path_passes(self, grid: AnyGrid, out: NDArray[np.integer[Any]] | None = None) -> NDArray[np.integer[Any]]:
        """How many steps of the robot's path passed each cell of `grid`, shape grid.shape.

        A step passes the cells it crosses when shifted by any whole number of cells up to
        :data:`PATH_RADIUS` (the robot's body round the sensor's track), each cell once per step,
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
        """Hits, misses and near misses per cell of `grid`, one update per cell per scan, a hit winning.

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
            Of the rays' dimension.
        scans : ndarray of int, optional
            Count only these scans (default: all).
        keep : ndarray of int, optional
            Scans (among those counted) whose cells are remembered, so that
            :meth:`scan_counts_at` on this grid reads them instead of traversing the scan's beams
            again (a leave-one-scan-out calibration asks it of the scans it holds out, right after
            the whole counts); :meth:`forget` drops them.
        out : RayCounts, optional
            Arrays of int32 or uint16 (wide enough for the scans: each cell is counted at most
            once per scan) of `grid`'s shape, C-contiguous, the counts are added into, and
            returned: a lattice over a building is counted in place instead of beside a copy.

        Returns
        -------
        RayCounts
        """
        if out is None:
            counts = RayCounts(*(np.zeros(grid_size(grid), dtype=np.int32) for _ in range(3)))
        else:
            if any(a.dtype not in (np.int32, np.uint16) or a.shape != grid.shape or not a.flags.c_contiguous for a in out):
                raise ValueError(f"counts are added into C-contiguous int32 or uint16 arrays of the grid's shape {grid.shape}")
            counts = RayCounts(*(a.reshape(-1) for a in out))
        # The compiled path's scratch: the last scan that touched each cell (kept across batches),
        # as 3 scan + state: int32 while that fits (half a building's lattice of int64).
        wide = 3 * (int(self.scan[-1]) + 1 if self.scan.size else 0) + 3 >= 2**31
        mark = np.full(grid_size(grid), -1, dtype=np.int64 if wide else np.int32) if _compiled_counts.ENABLED else None
        select = np.ones(self.scan.size, bool) if scans is None else np.isin(self.scan, scans)
        idx = np.flatnonzero(select)
        if idx.size == 0:
            return RayCounts(*(a.reshape(grid.shape) for a in counts))
        # Batches of whole scans whose traversals stay under the entry budget.
        cells_per_beam = (
            np.abs(np.floor(self.ends[idx] / grid.resolution) - np.floor(self.starts[idx] / grid.resolution)).sum(axis=1) + 2
        )
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
            self._accumulate(grid, idx[lo:hi], counts, keep, mark)
            lo = hi
        return RayCounts(*(a.reshape(grid.shape) for a in counts))

    def forget(self) -> None:
        """Drop the cells :meth:`counts` kept for :meth:`scan_counts_at` (their memory)."""
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
            _, *idx = traverse(grid, self.starts[first:last], self.ends[first:last])
            mark[np.ravel_multi_index(tuple(idx), grid.shape)] = True
        return mark.reshape(grid.shape)

    def scan_counts_at(
        self, grid: AnyGrid, scan: int, cells: NDArray[np.intp]
    ) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32]]:
        """What one scan alone counts at some cells: ``counts(grid, scans=[scan])`` read at `cells`.

        Without arrays of the grid's size: the cells asked for are looked up (a binary search
        each) among the sorted cells the scan crossed and ended in, which :meth:`counts` kept
        when asked to (``keep``), or else come from traversing the scan's beams in batches. A
        leave-one-scan-out calibration asks this of each held-out scan at its own points, on a
        lattice of millions of cells.

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
        scan : int
            Index of the scan.
        cells : ndarray of int
            Flat (row-major) indices of cells of `grid`.

        Returns
        -------
        hits, misses, near : ndarray of int32, shape cells.shape
            1 where the scan ended a beam in the cell (a hit), or crossed it without ending a beam
            there (a miss; a near miss too if its every beam through the cell ended within
            :data:`NEAR_END`); else 0.
        """
        cells = np.asarray(cells, dtype=np.intp)
        kept = self._kept.get((grid, int(scan)))
        ended, crossed, near = self._scan_cells(grid, int(scan)) if kept is None else kept
        hit = _in_sorted(cells, ended)
        miss = _in_sorted(cells, crossed) & ~hit
        return hit.astype(np.int32), miss.astype(np.int32), (miss & _in_sorted(cells, near)).astype(np.int32)

    def _scan_cells(self, grid: AnyGrid, scan: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """The cells one scan ended a beam in (hits), crossed, and crossed only near a beam's end,
        each sorted distinct flat indices."""
        lo, hi = np.searchsorted(self.scan, [scan, scan + 1])
        if hi <= lo:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, empty
        end_cell, inside = flat_index(grid, self.ends[lo:hi])
        ended = _unique(end_cell[inside & self.hit[lo:hi]].astype(np.int64))
        crossed, near, far = [], [], []
        for first, last in _batches(grid, self.starts[lo:hi], self.ends[lo:hi]):
            c, n = self._crossed(grid, np.arange(lo + first, lo + last), np.zeros(last - first, dtype=np.int64), 1)
            crossed.append(c)
            near.append(n)
            far.append(c[~_sorted_in_sorted(c, n)])
        # A cell crossed near an end in one batch of beams may be seen through in another.
        near_all, far_all = _unique(np.concatenate(near)), _unique(np.concatenate(far))
        return ended, _unique(np.concatenate(crossed)), near_all[~_sorted_in_sorted(near_all, far_all)]

    def _crossed(
        self, grid: AnyGrid, beams: NDArray[np.intp], group: NDArray[np.int64], ncell: int
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Keys ``group * ncell + cell`` of the cells `beams` crossed, and of those crossed only
        near a returned end (within :data:`NEAR_END`), each sorted distinct.

        `group` (one per beam) is the beam's scan for whole counts, or 0 for one scan's cells.
        """
        b, cell, near = self._entries(grid, beams)
        return _crossed_keys(group[b] * ncell + cell, near)

    def _entries(self, grid: AnyGrid, beams: NDArray[np.intp]) -> tuple[NDArray[np.intp], NDArray[np.int64], NDArray[np.bool_]]:
        """Every cell `beams` crossed (:func:`~gpomap.raycast.traverse`): the entry's beam (index
        into `beams`, non-decreasing), its cell's flat index, and whether the cell's centre lies
        within :data:`NEAR_END` of the beam's returned end."""
        b, *idx = traverse(grid, self.starts[beams], self.ends[beams])
        d = len(idx)
        # Only a beam's last few cells can lie within NEAR_END of its end: a cell whose centre is
        # within it meets the last NEAR_END + half a diagonal of the beam, and each cell there
        # takes at least one of the d axes a step further.
        tail = d * (int(np.ceil(NEAR_END / grid.resolution + np.sqrt(d) / 2)) + 1)
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
        mark: Any = None,
    ) -> None:
        """Add the counts of `beams` (whole scans) into `counts`; with `mark` (the compiled path's
        scratch, see :func:`gpomap._compiled_counts.count_entries`) in one compiled pass."""
        ncell = grid_size(grid)
        scan = self.scan[beams]
        end_cell, inside = flat_index(grid, self.ends[beams])
        ended = inside & self.hit[beams]
        b, cell, near_entry = self._entries(grid, beams)
        if mark is not None:
            # uint16 counts too: the compiled pass adds one at a time, each within the type.
            arrays: Any = tuple(counts)
            _compiled_counts.count_entries(b, cell, near_entry, scan, np.where(ended, end_cell, -1), arrays, mark)
            mine = np.zeros(scan.size, dtype=bool) if keep is None else np.isin(scan, keep)
            if not mine.any():
                return
            # The kept scans' own cells, from their entries alone.
            sub = mine[b]
            b, cell, near_entry = b[sub], cell[sub], near_entry[sub]
            ended &= mine
        crossed, near = _crossed_keys(scan[b].astype(np.int64) * ncell + cell, near_entry)
        hit_keys = _unique(scan[ended].astype(np.int64) * ncell + end_cell[ended])
        if mark is None:
            # A scan that ended a beam in a cell counts a hit there, not also a miss.
            miss_keys = crossed[~_sorted_in_sorted(crossed, hit_keys)]
            near_keys = near[~_sorted_in_sorted(near, hit_keys)]
            for total, keys in zip(counts, (hit_keys, miss_keys, near_keys), strict=True):
                np.add(total, np.bincount(keys % ncell, minlength=ncell), out=total, casting="unsafe")
        if keep is not None:
            # Keys are scan * ncell + cell, sorted: each kept scan's cells are one slice (copied,
            # so the batch's arrays are not kept alive).
            for k in np.intersect1d(keep, scan):
                base = int(k) * ncell

                def own(keys: NDArray[np.int64], base: int = base) -> NDArray[np.int64]:
                    lo, hi = np.searchsorted(keys, [base, base + ncell])
                    return keys[lo:hi] - base

                self._kept[(grid, int(k))] = (own(hit_keys), own(crossed), own(near))


def _batches(grid: AnyGrid, starts: NDArray[np.float64], ends: NDArray[np.float64]) -> list[tuple[int, int]]:
    """Consecutive ranges [first, last) of beams whose traversals stay under the entry budget (at least one beam each)."""
    cost = np.cumsum(np.abs(np.floor(ends / grid.resolution) - np.floor(starts / grid.resolution)).sum(axis=1) + 2)
    out, first = [], 0
    while first < cost.size:
        base = cost[first - 1] if first > 0 else 0.0
        last = max(first + 1, int(np.searchsorted(cost, base + _ENTRIES_PER_BATCH, side="right")))
        out.append((first, last))
        first = last
    return out


def _in_sorted(values: NDArray[np.integer], sorted_keys: NDArray[np.integer]) -> NDArray[np.bool_]:
    """Whether each of `values` is among `sorted_keys` (sorted ascending), shape values.shape.

    A binary search per value: ``np.isin`` sorts both arrays together, which costs far more when
    the values are many and the keys few, or the keys already sorted.
    """
    if sorted_keys.size == 0:
        return np.zeros(values.shape, dtype=bool)
    i = np.minimum(np.searchsorted(sorted_keys, values), sorted_keys.size - 1)
    return sorted_keys[i] == values


def _sorted_in_sorted(values: NDArray[np.int64], keys: NDArray[np.int64]) -> NDArray[np.bool_]:
    """:func:`_in_sorted` when `values` too are sorted and distinct: a binary search per key
    instead of per value (a whole log's millions of crossed cells against its hits)."""
    mask = np.zeros(values.shape, dtype=bool)
    pos = np.searchsorted(values, keys)
    ok = pos < values.size
    ok[ok] = values[pos[ok]] == keys[ok]
    mask[pos[ok]] = True
    return mask


def _unique(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Sorted distinct values: one sort and a comparison (numpy's hash-based unique measured
    several times slower on the tens of millions of keys a whole log gives)."""
    return _distinct(np.sort(keys))


def _distinct(s: NDArray[np.int64]) -> NDArray[np.int64]:
    """The distinct values of a sorted array."""
    if s.size == 0:
        return s
    return s[np.concatenate([[True], s[1:] != s[:-1]])]


def _crossed_keys(keys: NDArray[np.int64], near: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The distinct `keys`, and those whose every entry is `near`, each sorted.

    A key's near entries are counted against all its entries (the few near keys sorted apart:
    tagging every key with its flag made the one large sort slower).
    """
    ordered = np.sort(keys)
    near_keys, near_entries = _unique_counts(keys[near])
    entries = np.searchsorted(ordered, near_keys, side="right") - np.searchsorted(ordered, near_keys, side="left")
    return _distinct(ordered), near_keys[near_entries == entries]


def _unique_counts(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.intp]]:
    """:func:`_unique` and how many times each value occurs."""
    s = np.sort(keys)
    if s.size == 0:
        return s, np.zeros(0, dtype=np.intp)
    first = np.flatnonzero(np.concatenate([[True], s[1:] != s[:-1]]))
    return s[first], np.diff(np.append(first, s.size))


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
