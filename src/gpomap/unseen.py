"""Held-out points where no kept beam went, and the squares of the map they are drawn from.

The squash's variance scale (:mod:`gpomap.extrapolation`) is fitted where the question is the
same as a user's: the log's scans are cut into stretches (:func:`gpomap.heldout.holdout_stretches`),
and a GP of the kept stretches is asked about the held-out stretches' points (the evaluation
protocol's, at their natural frequencies) that lie where no kept beam went. This module makes
those points and the kept scans' points the held-in GP is fitted on, one square region of the map
at a time:

- :func:`_unseen_points`: the held-out scans' points in a square where no kept beam went, decided
  on a lattice of :data:`UNSEEN_RESOLUTION` as the evaluation's reference grid decides it; kept as
  a bit a point (:class:`_UnseenPoints`) and made again only where drawn.
- :func:`region_observations` and :func:`_kept_region`: the kept scans' labelled points in a
  square, with the map's clearance, cut from the map's points (or made again a part at a time)
  without observing the kept scans again; :func:`_observes_both`: whether the kept scans saw both
  classes there.
- :func:`new_ground_centre`: where held-out stretches saw most new ground, the square tried when
  the first regions hold too few unseen points.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from gpomap.config import PROFILES
from gpomap.evidence import RayEvidence, lattice_grid
from gpomap.heldout import FOLD_STARTS, CalibrationPoints, holdout_stretches
from gpomap.lattice import bounds_extent, column_bounds, flat_index, in_box, rows
from gpomap.observations import Observations, ScanPoints, beams_reach, data_dim, free_near_hits
from gpomap.resources import POINT_MEMORY

#: A held-out hit farther than this from every kept hit saw new ground (metres): where the first
#: regions hold too few unseen points, the square where held-out stretches saw most of it is
#: tried (:func:`new_ground_centre`).
NEW_HIT_DISTANCE: float = 1.0
#: Cell side of the lattice on which "no kept beam went" is decided, as the evaluation's
#: reference grid decides it, metres (planar maps; voxel maps use 0.1 m).
UNSEEN_RESOLUTION: dict[int, float] = {d: p.unseen_resolution for d, p in PROFILES.items()}


def _in_square(
    points: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64], grow: float = 0.0
) -> NDArray[np.bool_]:
    """Which points (m, d) lie in the square lo..hi (x, y) grown by `grow` on every side (negative: shrunk)."""
    return in_box(points, np.asarray(lo)[:2] - grow, np.asarray(hi)[:2] + grow)


class PointSource(Protocol):
    """A map's labelled points as this module asks them: their bounds, all of them a part at a
    time, and those in a box. Every point once, each with its scan (``scan_index``)."""

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]

    def parts(self) -> Iterator[Observations]:
        """Every point, a part at a time."""
        ...

    def square_parts(
        self, box_lo: NDArray[np.float64], box_hi: NDArray[np.float64], among: NDArray[np.intp] | None
    ) -> Iterator[Observations]:
        """The points in the box `box_lo`..`box_hi` (x, y), of every scan or of those `among`
        (sorted indices), a part at a time; within a part, in the log's order."""
        ...


class _HeldPoints:
    """Labelled points held in memory (:class:`PointSource`)."""

    def __init__(self, obs: Observations) -> None:
        self.obs = obs
        self.lower, self.upper = column_bounds(obs.points)

    def parts(self) -> Iterator[Observations]:
        yield self.obs

    def square_parts(
        self, box_lo: NDArray[np.float64], box_hi: NDArray[np.float64], among: NDArray[np.intp] | None
    ) -> Iterator[Observations]:
        yield cut_square(self.obs, box_lo, box_hi, among)


def cut_square(
    obs: Observations, box_lo: NDArray[np.float64], box_hi: NDArray[np.float64], among: NDArray[np.intp] | None
) -> Observations:
    """The points of `obs` in the box `box_lo`..`box_hi` (x, y), of every scan or of those `among`
    (:meth:`PointSource.square_parts` of points held), in their order."""
    inside = in_box(obs.points, box_lo, box_hi)
    if among is not None:
        inside &= _from_kept(obs.scan_index, among)
    return obs.selected(inside)


class _MadePoints:
    """A log's points made again from its scans where asked (:class:`PointSource` over
    :class:`~gpomap.observations.ScanPoints`): only the scans that reach a box are made."""

    def __init__(self, points: ScanPoints) -> None:
        self.points = points
        self.lower, self.upper = points.lower, points.upper

    def parts(self) -> Iterator[Observations]:
        return self.points.parts()

    def square_parts(
        self, box_lo: NDArray[np.float64], box_hi: NDArray[np.float64], among: NDArray[np.intp] | None
    ) -> Iterator[Observations]:
        source = self.points
        meets = np.all((source.scan_lower[:, :2] <= box_hi) & (source.scan_upper[:, :2] >= box_lo), axis=1)
        scans = np.flatnonzero(meets) if among is None else among[meets[among]]
        if scans.size == 0:
            return
        for part in source.parts(scans.tolist()):
            inside = in_box(part.points, box_lo, box_hi)
            yield part.selected(inside)


def _source(observations: Observations | ScanPoints | PointSource) -> PointSource:
    if isinstance(observations, ScanPoints):
        return _MadePoints(observations)
    return _HeldPoints(observations) if isinstance(observations, Observations) else observations


def region_observations(
    obs: Observations, kept: NDArray[np.intp], lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float
) -> Observations:
    """The kept scans' labelled points in a square, from the map's points before the clearance.

    Equal to observing the kept scans alone (with the clearance) and keeping the points in the
    square: a free point there is cleared only by a kept hit within `clearance`, which lies in
    the square grown by `clearance`; so only that much of the map is looked at.

    Parameters
    ----------
    obs : Observations
        The map's points from all its scans, no clearance applied; ``scan_index`` numbers the scans.
    kept : ndarray of int
        Indices of the kept scans.
    lo, hi : ndarray of shape (2,)
        Corners of the square (x, y); in 3-D a column.
    clearance : float
        The map's free clearance, metres.

    Returns
    -------
    Observations
    """
    grown = _from_kept(obs.scan_index, kept) & _in_square(obs.points, lo, hi, clearance)
    return _cleared(obs.selected(grown), lo, hi, clearance)


def _cleared(grown: Observations, lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float) -> Observations:
    """Of points in the square `lo`..`hi` grown by `clearance`, those in the square that the
    clearance keeps (:func:`region_observations`)."""
    keep = ~free_near_hits(grown.points, grown.occupied, clearance) & _in_square(grown.points, lo, hi)
    return grown.selected(keep)


def _square_parts(
    source: PointSource | ScanPoints,
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    grow: float = 0.0,
    among: NDArray[np.intp] | None = None,
) -> Iterator[Observations]:
    """The points in the square `lo`..`hi` grown by `grow`, of every scan or of those `among`
    (sorted indices), a part at a time: what ``source.square`` cuts, never all held at once."""
    box_lo, box_hi = np.asarray(lo, dtype=float)[:2] - grow, np.asarray(hi, dtype=float)[:2] + grow
    return _source(source).square_parts(box_lo, box_hi, among)


def _kept_region(
    source: PointSource | ScanPoints, kept: NDArray[np.intp], lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float
) -> Observations:
    """:func:`region_observations` of the map's points, made again from the kept scans alone
    (or cut from the points held or filed): the other scans' points in the region are never made.

    A held-in GP files the points under the same blocks, each block's in the order they come,
    so the parts may come block by block: each block's points are still in the log's order."""
    cut = list(_square_parts(source, lo, hi, clearance, among=kept))
    grown = Observations.joined(cut, source.lower.size)
    del cut
    return _cleared(grown, lo, hi, clearance)


def new_ground_centre(
    observations: Observations | ScanPoints | PointSource, n_scans: int, side: float
) -> NDArray[np.float64] | None:
    """Where the first pattern's held-out stretches saw most that its kept stretches did not.

    The centre (x, y) of the square of side `side` (on a lattice from the origin) that holds the
    most new hits, held-out hits farther than :data:`NEW_HIT_DISTANCE` from every kept hit, among
    the squares where the kept scans have a hit and a free point (elsewhere a held-in GP would
    only give its prior). None when there is no such square.

    Parameters
    ----------
    observations : Observations, ScanPoints or PointSource
        The map's labelled points (or what makes them again, a part at a time, or gives them
        as filed); ``scan_index`` numbers the scans.
    n_scans : int
        Scans in the log.
    side : float
        Side of the squares, metres.

    Returns
    -------
    ndarray of shape (2,) or None
    """
    source = _source(observations)
    kept = holdout_stretches(n_scans, FOLD_STARTS[0])[0]
    squares = _SquareLattice(np.vstack([source.lower[:2], source.upper[:2]]), side)
    # The hits, and the squares of the kept free points, a part of the log at a time.
    kept_parts, held_parts = [], []
    free_kept = np.zeros(squares.size, dtype=bool)
    for part in source.parts():
        from_kept = _from_kept(part.scan_index, kept)
        xy, occupied = part.points[:, :2], part.occupied
        kept_parts.append(xy[occupied & from_kept])
        held_parts.append(xy[occupied & ~from_kept])
        free_kept |= squares.holding(xy, ~occupied & from_kept)
    hits_kept, hits_held = np.concatenate(kept_parts), np.concatenate(held_parts)
    if hits_kept.size == 0 or hits_held.size == 0:
        return None
    # Kept hits to the decimetre: a whole log repeats each wall thousands of times.
    distance, _ = cKDTree(np.unique(np.round(hits_kept, 1), axis=0)).query(hits_held, distance_upper_bound=NEW_HIT_DISTANCE)
    counts = np.bincount(squares.index(hits_held[np.isinf(distance)]), minlength=squares.size)
    # Only squares where the kept scans observed both classes (a few hundred squares per log).
    counts[~(squares.holding(hits_kept) & free_kept)] = 0
    if not counts.any():
        return None
    return squares.centre(int(np.argmax(counts)))


class _SquareLattice:
    """Squares of side `side` on a lattice from the origin, over the extent of some points (n, 2),
    numbered x-major (so the first of equal counts is the one of least x, then least y).

    Squares are marked in a boolean array, not found by sorting: ``np.unique`` over a whole log's
    tens of millions of points takes tens of seconds (docs/choices.md, "Measured for the code")."""

    #: Points handled at a time when marking squares (bounds the temporaries to ~100 MB).
    CHUNK = 1 << 22

    def __init__(self, points: NDArray[np.float64], side: float) -> None:
        lo, hi = column_bounds(points)
        self.side = float(side)
        self.origin = np.floor(lo / self.side).astype(np.int64)
        self.shape = np.floor(hi / self.side).astype(np.int64) - self.origin + 1
        self.size = int(np.prod(self.shape))

    def index(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Flat index of the square holding each point (m, 2), points within the extent."""
        ij = np.floor(points / self.side).astype(np.int64) - self.origin
        return ij[:, 0] * self.shape[1] + ij[:, 1]

    def holding(self, points: NDArray[np.float64], mask: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
        """Whether each square holds any of `points` (those `mask` selects), shape (size,)."""
        marked = np.zeros(self.size, dtype=bool)
        for start in range(0, len(points), self.CHUNK):
            part = points[start : start + self.CHUNK]
            if mask is not None:
                part = rows(part, mask[start : start + self.CHUNK])
            marked[self.index(part)] = True
        return marked

    def centre(self, k: int) -> NDArray[np.float64]:
        """Centre (x, y) of square `k`."""
        ix, iy = divmod(k, int(self.shape[1]))
        return (self.origin + np.array([ix, iy]) + 0.5) * self.side


def _from_kept(scan_index: NDArray[np.integer], kept: NDArray[np.intp]) -> NDArray[np.bool_]:
    """Which points (by their scan's index) come from the `kept` scans, shape scan_index.shape.

    A table of the scans, not np.isin, which sorts a copy of every point's scan index; kept
    scans with no point (past the last index) mark nothing.
    """
    is_kept = np.zeros(int(scan_index.max(initial=-1)) + 1, dtype=bool)
    is_kept[kept[kept < is_kept.size]] = True
    return is_kept[scan_index]


def _observes_both(
    source: PointSource | ScanPoints, n_scans: int, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> Callable[[NDArray[np.intp]], bool]:
    """Whether given kept scans have a hit and a free point in the square `lo`..`hi`, before the
    clearance (which could, in principle, clear every free point): which scans have either there,
    found a part at a time."""
    hit, free = np.zeros(n_scans, dtype=bool), np.zeros(n_scans, dtype=bool)
    for part in _square_parts(source, lo, hi):
        hit[part.scan_index[part.occupied]] = True
        free[part.scan_index[~part.occupied]] = True

    def observes(kept: NDArray[np.intp]) -> bool:
        return bool(hit[kept].any() and free[kept].any())

    return observes


class _UnseenPoints:
    """Held-out scans' calibration points where no kept beam went (:func:`_unseen_points`), in
    order: which of each run of a scan's points they are, a bit each, and those drawn made again
    from their rays (:meth:`take`), so a depth frame's millions are never held at once.

    Attributes
    ----------
    size : int
        How many.
    n_occupied : int
        How many are hits.
    """

    def __init__(self, dim: int, no_return_cap: float | None) -> None:
        self.dim = dim
        self.no_return_cap = no_return_cap
        self.size = self.n_occupied = 0
        # Per run: its scan, its first and last + 1 point in the scan, the bits of those unseen,
        # and how many are.
        self._runs: list[tuple[Any, int, int, NDArray[np.uint8], int]] = []

    def add(self, scan: Any, start: int, stop: int, unseen: NDArray[np.bool_], n_occupied: int) -> None:
        """Mark which of the scan's points `start` .. `stop` - 1 are unseen (`unseen`, shape
        (stop - start,)), `n_occupied` of them hits."""
        n = int(np.count_nonzero(unseen))
        if n:
            self._runs.append((scan, start, stop, np.packbits(unseen), n))
            self.size += n
            self.n_occupied += int(n_occupied)

    def take(self, index: NDArray[np.integer]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The unseen points at sorted places `index` (k,) among them all: points (k, d), classes (k,)."""
        index = np.asarray(index, dtype=np.intp)
        points, occupied = [np.zeros((0, self.dim))], [np.zeros(0, dtype=bool)]
        first = 0
        held: CalibrationPoints | None = None
        held_scan = None
        for scan, start, stop, bits, n in self._runs:
            lo, hi = np.searchsorted(index, [first, first + n])
            if lo < hi:
                if scan is not held_scan:
                    held, held_scan = CalibrationPoints(scan, no_return_cap=self.no_return_cap), scan
                assert held is not None
                places = np.flatnonzero(np.unpackbits(bits, count=stop - start))[index[lo:hi] - first] + start
                p, o = held.take(places)
                points.append(p)
                occupied.append(o)
            first += n
        return np.concatenate(points), np.concatenate(occupied)


def _unseen_points(
    kept_scans: Sequence[Any],
    held_scans: Sequence[Any],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin: float,
    no_return_cap: float | None,
    memory: int = POINT_MEMORY,
) -> _UnseenPoints:
    """The held-out scans' protocol points in the square `lo`..`hi` (x, y) shrunk by `margin`, where
    no kept beam went.

    Scans whose beams cannot reach the square are passed over (a whole log's scans mostly look
    elsewhere, and would be most of the stage's time). The points are made a run of rays at a
    time (:class:`~gpomap.heldout.CalibrationPoints`), twice: once for the box of those in the
    square, on which "no kept beam went" is decided, then to decide it; those of the first pass
    are kept for the second while they take at most `memory` bytes. What is unseen is kept as a
    bit a point: the points themselves are made again only where drawn.
    """
    unseen = _UnseenPoints(data_dim(held_scans), no_return_cap)
    runs: list[tuple[Any, int, int, NDArray[np.uint8], tuple[NDArray[np.float64], NDArray[np.bool_]] | None]] = []
    bounds: list[NDArray[np.float64]] = []
    kept_bytes = 0
    for scan in held_scans:
        if not beams_reach(scan, lo, hi, no_return_cap):
            continue
        held = CalibrationPoints(scan, no_return_cap=no_return_cap)
        for start, stop in held.spans():
            p, o = held.between(start, stop)
            inside = _in_square(p, lo, hi, -margin)
            if not inside.any():
                continue
            p, o = rows(p, inside), o[inside]
            bounds += column_bounds(p)
            kept_bytes += p.nbytes + o.nbytes
            runs.append((scan, start, stop, np.packbits(inside), (p, o) if kept_bytes <= memory else None))
    if not runs:
        return unseen
    # Where no kept beam went: no hit and no miss on the evaluation's reference lattice.
    box_lo, box_hi = np.min(bounds[0::2], axis=0), np.max(bounds[1::2], axis=0)
    rays = RayEvidence.from_scans([s for s in kept_scans if beams_reach(s, box_lo, box_hi, no_return_cap)], no_return_cap)
    grid = lattice_grid(bounds_extent(box_lo, box_hi), UNSEEN_RESOLUTION[box_lo.size])
    seen_cells = rays.seen(grid).reshape(-1)
    again: CalibrationPoints | None = None
    again_scan = None
    for scan, start, stop, bits, part in runs:
        inside = np.unpackbits(bits, count=stop - start).view(bool)
        if part is None:
            if scan is not again_scan:
                again, again_scan = CalibrationPoints(scan, no_return_cap=no_return_cap), scan
            assert again is not None
            p, o = again.between(start, stop)
            part = rows(p, inside), o[inside]
        cell, ok = flat_index(grid, part[0])
        new = ~(ok & seen_cells[cell])
        marks = np.zeros(stop - start, dtype=bool)
        marks[inside] = new
        unseen.add(scan, start, stop, marks, int(np.count_nonzero(part[1] & new)))
    return unseen
