"""Held-out data for the calibrations: which scans are held out, and the points their beams observed.

Every fitted calibration (the ray-count weights in :mod:`gpomap.fusion`, the variance scale in
:mod:`gpomap.extrapolation`, the later-visit recalibration in :mod:`gpomap.revisit`) scores a map
on scans it did not see, at the points those scans' beams observed, as the evaluation protocol
does: hits, and free points along each beam up to a lidar's range noise short of the hit, at
their natural frequencies.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.config import MapConfig
from gpomap.errors import EmptyDataError
from gpomap.observations import Rays, data_dim, natural_subsample, observations_from_scans, ray_free_points
from gpomap.scans import Scan

__all__ = [
    "CALIBRATION_HIT_MARGIN",
    "FOLD_STARTS",
    "HOLDOUT_EVERY",
    "N_STRETCHES",
    "RUN_POINTS",
    "CalibrationPoints",
    "DrawnPoints",
    "calibration_points",
    "draw_calibration_points",
    "calibration_scans",
    "holdout_stretches",
]

#: Calibration points: free points along a returned beam stop this short of its end (m), about a
#: lidar's range noise. Closer in, a point is free as the world is: a wall cell is mostly free
#: space, and a map calibrated only on hits there makes every wall too thick (docs/choices.md).
CALIBRATION_HIT_MARGIN: float = 0.02

#: The log is cut into this many contiguous stretches (or one per scan, when shorter) ...
N_STRETCHES: int = 10
#: ... and every this-many-th stretch is held out (3 of 10, starting at the second) ...
HOLDOUT_EVERY: int = 3
#: ... starting at these stretches in turn, while a calibration finds too few points.
FOLD_STARTS: tuple[int, ...] = (1, 2, 0)


def calibration_scans(n: int, n_scans: int) -> NDArray[np.intp]:
    """Indices of the scans a calibration holds out in turn: `n_scans` evenly spaced among `n` (all when fewer)."""
    return np.unique(np.linspace(0, n - 1, min(n_scans, n)).round().astype(np.intp))


def holdout_stretches(n_scans: int, first: int = FOLD_STARTS[0]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices of the kept and the held-out scans: every third of ten contiguous stretches held out.

    Parameters
    ----------
    n_scans : int
    first : int
        The first stretch held out (0-based); then every :data:`HOLDOUT_EVERY`-th.

    Returns
    -------
    kept, held_out : ndarray of int
        Sorted; together they are ``0 .. n_scans - 1``. Fewer than 3 scans: nothing held out.
    """
    idx = np.arange(n_scans)
    if n_scans < HOLDOUT_EVERY:
        return idx, idx[:0]
    stretches = np.array_split(idx, min(N_STRETCHES, n_scans))
    held = np.zeros(n_scans, bool)
    for s in stretches[first::HOLDOUT_EVERY]:
        held[s] = True
    return idx[~held], idx[held]


def calibration_points(
    scan: Scan | CloudScan, step: float = 0.1, no_return_cap: float | None = MapConfig.no_return_cap
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A scan's hits and its free points every `step` along each beam up to :data:`CALIBRATION_HIT_MARGIN` short of the hit.

    Parameters
    ----------
    scan : Scan or CloudScan
    step : float
        Spacing of the free points, metres.
    no_return_cap : float or None
        No-return beams give free points this far (never beyond the max range; None: to it).

    Returns
    -------
    points : ndarray of shape (n, d)
    occupied : ndarray of bool, shape (n,)
    """
    try:
        # Points as the world holds them: no clearance round hits, free up to the hit itself.
        obs = observations_from_scans([scan], step, CALIBRATION_HIT_MARGIN, no_return_cap, free_clearance=0.0)
    except EmptyDataError:
        return np.zeros((0, data_dim([scan]))), np.zeros(0, bool)
    return obs.points, obs.occupied


#: Most points :meth:`CalibrationPoints.spans` puts in a run (whole rays, so a run of one long ray
#: may hold more): about 24 MB of 3-D points, where one depth frame's are hundreds of megabytes.
RUN_POINTS: int = 1 << 20


class CalibrationPoints:
    """One scan's calibration points (:func:`calibration_points`) without making them all at once.

    Their number and classes are known from the rays alone; they are made a run of consecutive
    points at a time (:meth:`between`, runs from :meth:`spans`) or only at given places
    (:meth:`take`): the same numbers in the same order as :func:`calibration_points` gives, every
    free point ray by ray, then the hits. A depth frame at every pixel gives about 10 million
    (40 a ray), of which a calibration uses a few thousand.

    Parameters
    ----------
    scan : Scan or CloudScan
    step, no_return_cap : float
        As :func:`calibration_points`'.

    Attributes
    ----------
    size : int
        Points of the scan.
    n_free : int
        Free points among them (the first `n_free`); the rest are hits.
    """

    def __init__(self, scan: Scan | CloudScan, step: float = 0.1, no_return_cap: float | None = MapConfig.no_return_cap) -> None:
        rays = Rays.of(scan)
        lengths = rays.free_lengths(CALIBRATION_HIT_MARGIN, no_return_cap)
        use = lengths > 0
        self.dim = data_dim([scan])
        self.step = float(step)
        self._origin = rays.origin
        self._directions = rays.directions[use]
        self._lengths = lengths[use]
        # ray_free_points' count of samples on each ray (its rounding slack included).
        counts = np.floor(np.maximum(self._lengths, 0.0) / self.step + 1e-9).astype(np.intp)
        # first[r]: the place of ray r's first free point; first[-1] the number of free points.
        self._first = np.concatenate([np.zeros(1, np.intp), np.cumsum(counts)])
        self._hits = rays.ends[rays.hit]
        self.n_free = int(self._first[-1])
        self.size = self.n_free + len(self._hits)

    @property
    def n_occupied(self) -> int:
        """Hits of the scan."""
        return self.size - self.n_free

    @property
    def n_rays(self) -> int:
        """Rays that hold free points: what this holds is a few numbers each."""
        return int(self._directions.shape[0])

    def _free(self, first_ray: int, stop_ray: int) -> NDArray[np.float64]:
        """The free points of rays `first_ray` .. `stop_ray` - 1, shape (m, d)."""
        directions = self._directions[first_ray:stop_ray]
        origins = np.broadcast_to(self._origin, directions.shape)
        return ray_free_points(origins, directions, self._lengths[first_ray:stop_ray], self.step)[0]

    def spans(self, max_points: int | None = None) -> list[tuple[int, int]]:
        """Consecutive runs (start, stop) covering the points, each of whole rays holding at most
        `max_points` (default :data:`RUN_POINTS`) or of one ray, the hits in runs of `max_points`."""
        max_points = RUN_POINTS if max_points is None else int(max_points)
        out = []
        first, n_rays = self._first, self._directions.shape[0]
        r = 0
        while r < n_rays:
            end = max(r + 1, int(np.searchsorted(first, first[r] + max_points, side="right")) - 1)
            end = min(end, n_rays)
            if first[end] > first[r]:
                out.append((int(first[r]), int(first[end])))
            r = end
        out += [(s, min(s + max_points, self.size)) for s in range(self.n_free, self.size, max_points)]
        return out

    def between(self, start: int, stop: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Points `start` .. `stop` - 1 (shape (m, d)) and their classes (m,)."""
        parts = []
        if start < min(stop, self.n_free):
            r0 = int(np.searchsorted(self._first, start, side="right")) - 1
            r1 = int(np.searchsorted(self._first, min(stop, self.n_free), side="left"))
            offset = start - int(self._first[r0])
            parts.append(self._free(r0, r1)[offset : offset + min(stop, self.n_free) - start])
        n_free = sum(len(p) for p in parts)
        if stop > self.n_free:
            parts.append(self._hits[max(start, self.n_free) - self.n_free : stop - self.n_free])
        points = np.concatenate(parts, axis=0) if parts else np.zeros((0, self.dim))
        return np.asarray(points, dtype=float), np.arange(len(points)) >= n_free

    def take(self, index: NDArray[np.integer]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The points at sorted places `index` (k,) and their classes: only the rays that hold
        them are sampled.

        Returns
        -------
        points : ndarray of shape (k, d)
        occupied : ndarray of bool, shape (k,)
        """
        index = np.asarray(index, dtype=np.intp)
        free = index[index < self.n_free]
        ray = np.searchsorted(self._first, free, side="right") - 1
        rays = np.unique(ray)
        counts = self._first[rays + 1] - self._first[rays]
        # Each needed ray's first point among the needed rays' points, then each point's place.
        starts = np.cumsum(counts) - counts
        at = starts[np.searchsorted(rays, ray)] + (free - self._first[ray])
        directions = self._directions[rays]
        made = ray_free_points(np.broadcast_to(self._origin, directions.shape), directions, self._lengths[rays], self.step)[0]
        points = np.concatenate([made[at], self._hits[index[index >= self.n_free] - self.n_free]], axis=0)
        return np.asarray(points, dtype=float), np.arange(len(index)) >= free.size


@dataclass(frozen=True)
class DrawnPoints:
    """Calibration points drawn uniformly from several scans' (:func:`draw_calibration_points`).

    Attributes
    ----------
    points : ndarray of shape (k, d)
    occupied : ndarray of bool, shape (k,)
    scan : ndarray of int, shape (k,)
        Each point's scan, as its place in the scans given.
    total, n_occupied : int
        The scans' points and hits, all of them, drawn or not.
    """

    points: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    scan: NDArray[np.intp]
    total: int
    n_occupied: int


def draw_calibration_points(
    scans: Sequence[Scan | CloudScan],
    n: int,
    seed: int,
    step: float = 0.1,
    no_return_cap: float | None = MapConfig.no_return_cap,
) -> DrawnPoints:
    """At most `n` of the scans' calibration points (:func:`calibration_points`), drawn uniformly
    (:func:`~gpomap.observations.natural_subsample`) from them all in scan order.

    They are counted from each scan's rays (:class:`CalibrationPoints`) and only those drawn are
    made, a scan at a time: a depth frame has about 10 million, a long stretch of a log's scans
    gigabytes of them. Nothing is drawn when the scans hold no point of one class.

    Returns
    -------
    DrawnPoints
    """
    sizes, n_occupied, n_rays = np.zeros(len(scans), dtype=np.intp), 0, 0
    # The counted scans are kept for the draw while they hold at most RUN_POINTS rays between
    # them (a planar stretch's); past that each is made again where drawn (depth frames).
    held: list[CalibrationPoints | None] = []
    for j, scan in enumerate(scans):
        counted = CalibrationPoints(scan, step, no_return_cap)
        sizes[j], n_occupied, n_rays = counted.size, n_occupied + counted.n_occupied, n_rays + counted.n_rays
        held.append(counted if n_rays <= RUN_POINTS else None)
    total = int(sizes.sum())
    if n_occupied in (0, total):
        d = data_dim(scans) if len(scans) else 2
        return DrawnPoints(np.zeros((0, d)), np.zeros(0, dtype=bool), np.zeros(0, dtype=np.intp), total, n_occupied)
    keep = natural_subsample(total, n, seed)  # sorted
    starts = np.concatenate([[0], np.cumsum(sizes)])
    bounds = np.searchsorted(keep, starts)  # scan j's drawn points: keep[bounds[j]:bounds[j + 1]]
    points, occupied, scan_of = [], [], []
    for j, (scan, kept) in enumerate(zip(scans, held, strict=True)):
        lo, hi = int(bounds[j]), int(bounds[j + 1])
        if hi > lo:
            made = kept if kept is not None else CalibrationPoints(scan, step, no_return_cap)
            p, o = made.take(keep[lo:hi] - starts[j])
            points.append(p)
            occupied.append(o)
            scan_of.append(np.full(o.size, j, dtype=np.intp))
    return DrawnPoints(np.concatenate(points), np.concatenate(occupied), np.concatenate(scan_of), total, n_occupied)
