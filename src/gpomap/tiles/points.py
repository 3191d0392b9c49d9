"""The points a map holds per block, the cells grown from them, and a log's points held until the blocks are known.

A block's points come in observation order and only grow (an update appends); which free points
lie within the clearance of a hit is worked out for the new points only. Where a log's points
would not fit in memory they wait in a :class:`~gpomap.resources.SpillFile`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.lattice import column_bounds, rows
from gpomap.observations import Observations, free_near_hits
from gpomap.resources import SpillFile
from gpomap.unseen import cut_square


@dataclass
class _BlockCells:
    """The cells of one block (tile square), in tree order."""

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.tiles"

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    n_ambiguous: int
    member_points: NDArray[np.float64] | None
    member_offsets: NDArray[np.intp] | None


@dataclass(frozen=True)
class _SpilledPart:
    """Points of a block waiting in a :class:`~gpomap.resources.SpillFile` (a whole log's
    points filed under their blocks would be a gigabyte in memory)."""

    file: SpillFile
    points: tuple[int, int]
    occupied: tuple[int, int]
    shape: tuple[int, int]
    weight: tuple[int, int] | None = None

    @classmethod
    def put(
        cls, file: SpillFile, points: NDArray[np.float64], occupied: NDArray[np.bool_], weight: NDArray[np.int32] | None = None
    ) -> _SpilledPart:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        return cls(
            file,
            file.put(pts),
            file.put(np.ascontiguousarray(occupied, dtype=bool)),
            (int(pts.shape[0]), int(pts.shape[1])),
            None if weight is None else file.put(np.ascontiguousarray(weight, dtype=np.int32)),
        )

    def load(self) -> Part:
        weight = None if self.weight is None else self.file.get(self.weight, np.int32, (self.shape[0],))
        return (
            self.file.get(self.points, np.float64, self.shape),
            self.file.get(self.occupied, np.bool_, (self.shape[0],)),
            weight,
        )


#: Points of a block held in memory: the points (n, d), their labels (n,) and how many samples
#: each stands for (int32, (n,); None: one each, :attr:`gpomap.observations.Observations.weight`).
Part = tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.int32] | None]


def _part(p: Any) -> Part:
    """A block's part as :data:`Part`: read back from its spill file, or held."""
    if isinstance(p, _SpilledPart):
        return p.load()
    return p[0], p[1], p[2]


def part_rows(part: Part, keep: NDArray[np.bool_] | NDArray[np.intp]) -> Part:
    """The rows of `part` that `keep` (a mask of shape (n,) or indices) selects."""
    points, occupied, weight = part
    return rows(points, keep), occupied[keep], None if weight is None else weight[keep]


def _joined_weights(parts: list[Part]) -> NDArray[np.int32] | None:
    """The parts' weights joined, ones for a part without; None when no part has any."""
    if all(w is None for _, _, w in parts):
        return None
    return np.concatenate([np.ones(o.size, dtype=np.int32) if w is None else w for _, o, w in parts])


#: The scans a part of a block's points came from, in their order: each run's scan (its index in
#: the map's scans) and its number of points, two int64 arrays of shape (r,).
Runs = tuple[NDArray[np.int64], NDArray[np.int64]]


def scan_runs(scans: NDArray[np.integer[Any]]) -> Runs:
    """The runs (:data:`Runs`) of points whose scans are `scans`, shape (n,), non-decreasing."""
    if scans.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    first = np.flatnonzero(np.concatenate([[True], scans[1:] != scans[:-1]]))
    return scans[first].astype(np.int64), np.diff(np.append(first, scans.size)).astype(np.int64)


class _BlockPoints:
    """The observation points of one block in arrival order; updates append, reads join them once
    (points waiting in a spill file are read back at each read instead, and let go after).

    Where every part came with its scans' runs (:data:`Runs`), the block also gives its points
    without some scans' (:meth:`without`): those a map fitted on the other scans files here.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.tiles"

    # A block read back from a map file is filled from the map's scans when first read or added
    # to (gpomap.io.mapfile): what fills every such block of the map at once, and how many points
    # it will file here. Rendering or querying a map never reads its points.
    _restore: Callable[[], None] | None = None
    _restore_count: int | None = None

    def __init__(
        self,
        points: NDArray[np.float64] | _SpilledPart,
        occupied: NDArray[np.bool_] | None = None,
        runs: Runs | None = None,
        weight: NDArray[np.int32] | None = None,
    ) -> None:
        self._parts: list[Any] = [points if isinstance(points, _SpilledPart) else (points, occupied, weight)]
        # Each part's runs, or None once a part came without them (updates, labelled points given).
        self._runs: list[Runs] | None = None if runs is None else [runs]
        # Which of the first `_n_checked` points are free within the clearance of a hit among them.
        self._near = np.zeros(0, dtype=bool)
        self._n_checked = 0

    def append(
        self,
        points: NDArray[np.float64] | _SpilledPart,
        occupied: NDArray[np.bool_] | None = None,
        runs: Runs | None = None,
        weight: NDArray[np.int32] | None = None,
    ) -> None:
        self.made()
        # A block read back from a map file starts without parts; its runs come with them again.
        known = runs is not None and (self._runs is not None or not self._parts)
        self._parts.append(points if isinstance(points, _SpilledPart) else (points, occupied, weight))
        self._runs = [*(self._runs or []), runs] if known and runs is not None else None

    def without(self, scans: NDArray[np.integer[Any]]) -> Part | None:
        """The block's points, labels and weights (:data:`Part`) but those of `scans` (indices in
        the map's scans), in their order; None when a part came without its runs."""
        part = self.weighted_arrays()
        keep = self.kept_mask(scans)
        if keep is None:
            return None
        return part_rows(part, keep)

    def made(self) -> None:
        """Fill the block from its map's scans if it waits for them (a map read from its file)."""
        if self._restore is not None:
            self._restore()

    def knows_its_scans(self) -> bool:
        """Whether every part came with its scans' runs (:meth:`without` can leave scans out)."""
        self.made()
        return self._runs is not None

    def runs(self) -> Runs | None:
        """Every part's runs (:data:`Runs`) joined, in the points' order; None when a part came without them."""
        self.made()
        if self._runs is None:
            return None
        if not self._runs:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate([r[0] for r in self._runs]), np.concatenate([r[1] for r in self._runs])

    def kept_mask(self, scans: NDArray[np.integer[Any]]) -> NDArray[np.bool_] | None:
        """Which of the block's points are not of `scans`, shape (n,); None when a part came without its runs."""
        runs = self.runs()
        return None if runs is None else np.repeat(~np.isin(runs[0], scans), runs[1])

    def scans(self) -> NDArray[np.int32] | None:
        """Each point's scan (an index in the map's scans), shape (n,) in the points' order; None
        when a part came without its runs."""
        runs = self.runs()
        return None if runs is None else np.repeat(runs[0].astype(np.int32), runs[1])

    def spill(self, file: SpillFile) -> None:
        """Move the parts held in memory to `file`, in their places."""
        self.made()
        self._parts = [p if isinstance(p, _SpilledPart) else _SpilledPart.put(file, *_part(p)) for p in self._parts]

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The block's points, shape (n, d), and labels, shape (n,), in arrival order."""
        points, occupied, _ = self.weighted_arrays()
        return points, occupied

    def weighted_arrays(self) -> Part:
        """The block's points, their labels and weights (:data:`Part`), in arrival order."""
        self.made()
        if any(isinstance(p, _SpilledPart) for p in self._parts):
            if len(self._parts) == 1:
                return _part(self._parts[0])
            # Each part read back into its place and let go: the block's points held once, not twice.
            sizes = [p.shape[0] if isinstance(p, _SpilledPart) else p[1].size for p in self._parts]
            dim = next(p.shape[1] if isinstance(p, _SpilledPart) else p[0].shape[1] for p in self._parts)
            points, occupied = np.empty((sum(sizes), dim)), np.empty(sum(sizes), dtype=bool)
            weighted = any((p.weight if isinstance(p, _SpilledPart) else _part(p)[2]) is not None for p in self._parts)
            weight = np.ones(sum(sizes), dtype=np.int32) if weighted else None
            at = 0
            for p, size in zip(self._parts, sizes, strict=True):
                pts, occ, w = _part(p)
                points[at : at + size], occupied[at : at + size] = pts, occ
                if weight is not None and w is not None:
                    weight[at : at + size] = w
                at += size
                del pts, occ, w
            return points, occupied, weight
        parts = [_part(p) for p in self._parts]
        if len(parts) > 1:
            parts = [(np.concatenate([p for p, _, _ in parts]), np.concatenate([o for _, o, _ in parts]), _joined_weights(parts))]
            if self._runs is not None:
                self._runs = [(np.concatenate([r[0] for r in self._runs]), np.concatenate([r[1] for r in self._runs]))]
        self._parts = parts
        return parts[0]

    @property
    def n_cleared(self) -> int:
        """Free points found within the clearance of a hit at the last :meth:`free_near_hits`."""
        return int(self._near.sum())

    def free_near_hits(
        self, clearance: float, arrays: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None
    ) -> NDArray[np.bool_]:
        """:func:`~gpomap.observations.free_near_hits` of the block's points, worked out for the new ones only.

        Hits are only ever added, so a free point once near a hit stays so. Of the points seen
        at the last call, the free ones not yet near a hit are checked against the new hits; the
        new free points against every hit. The answer is the whole computation's, at the cost
        of the points appended since. `arrays`: the block's :meth:`arrays`, when read already.
        """
        points, occupied = self.arrays() if arrays is None else arrays
        n0 = self._n_checked
        if n0 == 0:
            near = free_near_hits(points, occupied, clearance)
        else:
            near = np.zeros(occupied.shape, dtype=bool)
            near[:n0] = self._near
            new_hits = rows(points[n0:], occupied[n0:])
            if new_hits.size:
                old_free = np.flatnonzero(~occupied[:n0] & ~self._near)
                near[old_free] = _near_any(rows(points, old_free), new_hits, clearance)
            new_free = n0 + np.flatnonzero(~occupied[n0:])
            near[new_free] = _near_any(rows(points, new_free), rows(points, occupied), clearance)
        self._near, self._n_checked = near, int(occupied.size)
        return near


class _KeptBlock(_BlockPoints):
    """A block's points without some scans' (:meth:`_BlockPoints.without`), read from the block at
    each read: the block of a map fitted on the other scans, which holds no points of its own."""

    def __init__(self, block: _BlockPoints, dropped: NDArray[np.integer[Any]], clearance: float | None = None) -> None:
        self._block, self._dropped, self._clearance = block, dropped, clearance
        self._parts, self._runs = [], None
        self._near = np.zeros(0, dtype=bool)
        self._n_checked = 0

    def weighted_arrays(self) -> Part:
        kept = self._block.without(self._dropped)
        if kept is None:
            raise ValueError("the block's points came without their scans")
        return kept

    def free_near_hits(
        self, clearance: float, arrays: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None
    ) -> NDArray[np.bool_]:
        """:meth:`_BlockPoints.free_near_hits` of the points kept. Where the block has checked all
        its points at the same clearance, only the free points it found near a hit are asked
        again, about the kept hits: with fewer hits, no other free point can be near one."""
        block = self._block
        whole = block._near
        if self._clearance != clearance or block._n_checked != whole.size or self._n_checked:
            return super().free_near_hits(clearance, arrays)
        points, occupied = self.arrays() if arrays is None else arrays
        kept = block.kept_mask(self._dropped)
        if kept is None or kept.size != whole.size or int(kept.sum()) != occupied.size:
            return super().free_near_hits(clearance, arrays)
        near = whole[kept]
        ask = np.flatnonzero(near)
        if ask.size:
            near[ask] = _near_any(rows(points, ask), rows(points, occupied), clearance)
        self._near, self._n_checked = near, int(occupied.size)
        return near

    def append(self, points: Any, occupied: Any = None, runs: Runs | None = None, weight: Any = None) -> None:
        raise TypeError("a block of another map's points takes no points of its own")

    def last_scan(self) -> int:
        """The last scan kept with a point here (an index in the other map's scans), -1 for none."""
        runs = self._block.runs()
        ids = runs[0] if runs is not None else np.zeros(0, dtype=np.int64)
        ids = ids[~np.isin(ids, self._dropped)]
        return int(ids.max()) if ids.size else -1


@dataclass(frozen=True)
class KeptPoints:
    """A fitted map's points but those of some of its scans, by block: what the same map fitted
    on the other scans files, in the same order, without making them again from the scans.

    Attributes
    ----------
    blocks : dict
        The fitted map's blocks (:class:`_BlockPoints`) by key, each with its scans' runs.
    dropped : ndarray of int, shape (h,)
        The scans left out, as indices in the fitted map's scans.
    kept : ndarray of int, shape (k,)
        The scans kept, in the same numbering, in order: the other map's scans.
    dim : int
        Of the points.
    clearance : float, optional
        The fitted map's clearance: where the other map's is the same, its blocks take which
        free points are near a hit from the fitted map's (:meth:`_KeptBlock.free_near_hits`).
    """

    blocks: dict[int, _BlockPoints]
    dropped: NDArray[np.intp]
    kept: NDArray[np.intp]
    dim: int
    clearance: float | None = None


class FiledPoints:
    """A fitted map's points as filed under its blocks, each with its scan: a
    :class:`gpomap.unseen.PointSource`, so its variance scale cuts its held-in squares from the
    blocks instead of making the scans' points again.

    Parameters
    ----------
    blocks : dict
        The map's blocks (:class:`_BlockPoints`) by key, each with its scans' runs.
    meeting : callable
        ``meeting(lo, hi)``: the keys of the blocks that may hold points of the box `lo`..`hi` (x, y).
    lower, upper : ndarray of shape (d,)
        Bounds of every point.
    """

    def __init__(
        self,
        blocks: dict[int, _BlockPoints],
        meeting: Callable[[NDArray[np.float64], NDArray[np.float64]], list[int]],
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
    ) -> None:
        if any(b._runs is None for b in blocks.values()):
            raise ValueError("every block's points must come with their scans")
        self._blocks, self._meeting = blocks, meeting
        self.lower, self.upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)

    @staticmethod
    def _observations(block: _BlockPoints) -> Observations:
        points, occupied, weight = block.weighted_arrays()
        scans = block.scans()
        assert scans is not None  # checked when made
        return Observations(points, occupied, scans, weight=weight)

    def parts(self) -> Iterator[Observations]:
        """Every block's points, block by block."""
        for block in self._blocks.values():
            yield self._observations(block)

    def square_parts(
        self, box_lo: NDArray[np.float64], box_hi: NDArray[np.float64], among: NDArray[np.intp] | None
    ) -> Iterator[Observations]:
        """The points in the box (x, y), of every scan or those `among`, block by block."""
        for key in self._meeting(box_lo, box_hi):
            block = self._blocks.get(key)
            if block is not None:
                yield cut_square(self._observations(block), box_lo, box_hi, among)


class _HeldParts:
    """A log's labelled points, a part at a time, held until the grid of blocks is known.

    In memory while they come within `budget` bytes; past it every part waits in a temporary
    file instead, and the blocks they are filed under keep theirs in another
    (:attr:`blocks_file`), so that a building's points are never all in memory. Once the grid is
    known the parts are taken (:meth:`take`) as they come, and never wait in the first file.
    """

    def __init__(self, budget: int, with_scans: bool = True) -> None:
        self.budget = int(budget)
        # Whether the parts' scans are held too (points made from scans, in scan order).
        self.with_scans = with_scans
        self._parts: list[Any] = []
        self._bytes = 0
        self._file: SpillFile | None = None
        self.blocks_file: SpillFile | None = None
        self.dim = 2
        # Bounds of every point so far, x and y (the grid of blocks is known from them).
        self.lower = np.full(2, np.inf)
        self.upper = np.full(2, -np.inf)

    def count(self, part: Observations) -> bool:
        """Count `part` in (its bounds and bytes) without holding it; whether its bytes took the
        points past the budget (the files made now, the parts held so far moved to the first)."""
        if part.occupied.size == 0:
            return False
        self.dim = int(part.points.shape[1])
        lo, hi = column_bounds(part.points[:, :2])
        self.lower, self.upper = np.minimum(self.lower, lo), np.maximum(self.upper, hi)
        self._bytes += int(part.points.nbytes + part.occupied.nbytes + (0 if part.weight is None else part.weight.nbytes))
        if self._file is not None or self._bytes <= self.budget:
            return False
        self._file, self.blocks_file = SpillFile(), SpillFile()
        self._parts = [(_SpilledPart.put(self._file, *_part(p)), runs) for p, runs in self._parts]
        return True

    def hold(self, part: Observations) -> None:
        """Hold `part` (counted already) until it is taken: in the first file past the budget.
        Its scans are held as runs (:func:`scan_runs`)."""
        if part.occupied.size == 0:
            return
        runs = scan_runs(np.asarray(part.scan_index)) if self.with_scans else None
        held = (part.points, part.occupied, part.weight)
        self._parts.append((_SpilledPart.put(self._file, *held) if self._file is not None else held, runs))

    def take(self) -> Iterator[Observations]:
        """The parts held, in order, each read back (if it waited in the file) as it is asked and
        let go."""
        parts, self._parts = self._parts, []
        while parts:
            p, runs = parts.pop(0)
            points, occupied, weight = _part(p)
            del p
            scans = np.zeros(0, dtype=np.int32) if runs is None else np.repeat(runs[0], runs[1]).astype(np.int32)
            yield Observations(points, occupied, scans, weight=weight)

    def close(self) -> None:
        self._parts = []
        if self._file is not None:
            self._file.close()


def _near_any(free: NDArray[np.float64], hits: NDArray[np.float64], clearance: float) -> NDArray[np.bool_]:
    """Which of the free points, shape (m, d), lie within `clearance` of one of the hits, shape (h, d)."""
    if free.shape[0] == 0 or hits.shape[0] == 0:
        return np.zeros(free.shape[0], dtype=bool)
    both = np.concatenate([free, hits])
    occupied = np.concatenate([np.zeros(free.shape[0], bool), np.ones(hits.shape[0], bool)])
    return free_near_hits(both, occupied, clearance)[: free.shape[0]]
