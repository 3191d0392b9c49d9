"""Held-out data for the calibrations: which scans are held out, and the points their beams observed.

Every fitted calibration (the ray-count weights in :mod:`gpomap.fusion`, the variance scale in
:mod:`gpomap.extrapolation`, the later-visit recalibration in :mod:`gpomap.revisit`) scores a map
on scans it did not see, at the points those scans' beams observed, as the evaluation protocol
does: hits, and free points along each beam up to a lidar's range noise short of the hit, at
their natural frequencies.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.config import MapConfig
from gpomap.errors import EmptyDataError
from gpomap.observations import data_dim, observations_from_scans
from gpomap.scans import Scan

__all__ = [
    "CALIBRATION_HIT_MARGIN",
    "FOLD_STARTS",
    "HOLDOUT_EVERY",
    "N_STRETCHES",
    "calibration_points",
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
