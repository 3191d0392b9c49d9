"""The 2-D range scan: sensor pose, beam angles, ranges and maximum range.

A scan is what one sweep of a planar laser gives: ``n`` beams cast from the sensor pose
``(x, y, theta)`` at angles relative to the sensor heading. Readers (CARMEN, ROS bags, arrays)
and the simulator all produce lists of :class:`Scan`; everything downstream consumes them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError


def usable_ranges(ranges: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which readings are usable at all (finite and positive), of any shape: :meth:`Scan.valid`'s
    rule, for one scan's ranges or many scans' joined."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(ranges) & (ranges > 0)


def beyond_range(ranges: NDArray[np.float64], max_range: float | NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which readings lie at or beyond the maximum range (no return), of any shape; `max_range`
    a number or one per reading: :meth:`Scan.no_return`'s rule before the validity test."""
    with np.errstate(invalid="ignore"):
        return ranges >= max_range


@dataclass(frozen=True)
class Scan:
    """One planar laser scan.

    Parameters
    ----------
    pose : ndarray of shape (3,)
        Sensor pose in the map frame: x, y (metres) and heading theta (radians).
    angles : ndarray of shape (n,)
        Beam angles relative to the sensor heading, radians.
    ranges : ndarray of shape (n,)
        Measured ranges, metres. NaN, inf and non-positive values are invalid readings;
        values at or above `max_range` are no-return beams (free space, never a hit).
    max_range : float
        The sensor's maximum range, metres.
    time : float, optional
        Time stamp in seconds, where the source has a usable one.
    """

    pose: NDArray[np.float64]
    angles: NDArray[np.float64]
    ranges: NDArray[np.float64]
    max_range: float
    time: float | None = None
    meta: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        pose = np.asarray(self.pose, dtype=float).reshape(-1)
        angles = np.asarray(self.angles, dtype=float).reshape(-1)
        ranges = np.asarray(self.ranges, dtype=float).reshape(-1)
        if pose.shape != (3,):
            raise InputFormatError(f"scan pose must have 3 values (x, y, theta), got {pose.size}")
        if angles.shape != ranges.shape:
            raise InputFormatError(f"scan has {angles.size} beam angles but {ranges.size} ranges; expected equal counts")
        if not np.isfinite(pose).all():
            raise InputFormatError(f"scan pose must be finite, got {pose.tolist()}")
        if not (np.isfinite(self.max_range) and self.max_range > 0):
            raise InputFormatError(f"scan max_range must be a positive number, got {self.max_range}")
        object.__setattr__(self, "pose", pose)
        object.__setattr__(self, "angles", angles)
        object.__setattr__(self, "ranges", ranges)
        object.__setattr__(self, "max_range", float(self.max_range))

    @property
    def n_beams(self) -> int:
        """Number of beams in the scan."""
        return int(self.ranges.size)

    def world_angles(self) -> NDArray[np.float64]:
        """Beam directions in the map frame, ndarray of shape (n,)."""
        return self.pose[2] + self.angles

    def valid(self) -> NDArray[np.bool_]:
        """Mask of readings that are usable at all (finite and positive), shape (n,)."""
        return usable_ranges(self.ranges)

    def no_return(self) -> NDArray[np.bool_]:
        """Mask of valid readings at or beyond the maximum range, shape (n,)."""
        return self.valid() & beyond_range(self.ranges, self.max_range)

    def endpoints(self) -> NDArray[np.float64]:
        """Beam end points in the map frame for every beam, ndarray of shape (n, 2).

        Invalid ranges give NaN end points; no-return beams end at their recorded range.
        """
        a = self.world_angles()
        r = np.where(self.valid(), self.ranges, np.nan)
        return np.column_stack([self.pose[0] + r * np.cos(a), self.pose[1] + r * np.sin(a)])

    def hits(self) -> NDArray[np.float64]:
        """End points of the beams that returned (valid and below max range), shape (h, 2)."""
        keep = self.valid() & ~self.no_return()
        return self.endpoints()[keep]

    def select_beams(self, indices: NDArray[np.intp] | Sequence[int]) -> Scan:
        """A new scan with only the beams at `indices`."""
        idx = np.asarray(indices, dtype=np.intp)
        return Scan(self.pose, self.angles[idx], self.ranges[idx], self.max_range, self.time, self.meta)


def evenly_spaced(n_total: int, n_keep: int | None) -> NDArray[np.intp]:
    """Indices of `n_keep` items evenly spaced over `n_total`, first and last included.

    Parameters
    ----------
    n_total : int
        How many items there are.
    n_keep : int or None
        How many to keep; None (or >= n_total) keeps all.

    Returns
    -------
    ndarray of shape (min(n_keep, n_total),)
        Sorted unique indices.
    """
    if n_keep is None or n_keep >= n_total:
        return np.arange(n_total, dtype=np.intp)
    if n_keep <= 0:
        raise ValueError(f"number of items to keep must be positive, got {n_keep}")
    if n_keep == 1:
        return np.array([0], dtype=np.intp)
    return np.unique(np.round(np.linspace(0, n_total - 1, n_keep)).astype(np.intp))


def select_scans(scans: Sequence[Scan], n_scans: int | None = None, n_beams: int | None = None) -> list[Scan]:
    """Thin a sequence of scans to `n_scans` evenly spaced scans of `n_beams` evenly spaced beams.

    The paper trains on 52 of its real log's 395 poses with 37 of their 361 beams:
    ``select_scans(scans, 52, 37)``.

    Parameters
    ----------
    scans : sequence of Scan
    n_scans : int, optional
        Scans to keep (evenly spaced, first and last included); None keeps all.
    n_beams : int, optional
        Beams to keep in each scan (evenly spaced over the scan's beams); None keeps all.

    Returns
    -------
    list of Scan
    """
    chosen = [scans[i] for i in evenly_spaced(len(scans), n_scans)]
    if n_beams is None:
        return chosen
    return [s.select_beams(evenly_spaced(s.n_beams, n_beams)) for s in chosen]


def scan_extent(
    scans: Sequence[Scan], include_no_return: bool = False, no_return_cap: float | None = None
) -> tuple[float, float, float, float]:
    """Bounding box of sensor positions and hits: (xmin, xmax, ymin, ymax).

    With `include_no_return`, no-return beams' ends count too: at `no_return_cap` metres when it
    is given and shorter (how far they clear free space), else at their recorded range.
    """
    pts = [s.pose[None, :2] for s in scans]
    for s in scans:
        if not include_no_return:
            pts.append(s.hits())
            continue
        ends = s.endpoints()
        if no_return_cap is not None:
            nr = s.no_return()
            a = s.world_angles()[nr]
            r = np.minimum(s.ranges[nr], no_return_cap)
            ends[nr] = s.pose[:2] + r[:, None] * np.column_stack([np.cos(a), np.sin(a)])
        pts.append(ends[s.valid()])
    allp = np.concatenate(pts, axis=0)
    return (float(allp[:, 0].min()), float(allp[:, 0].max()), float(allp[:, 1].min()), float(allp[:, 1].max()))
