"""Test points: every held-out hit and free points along held-out beams, at natural frequencies.

Hits are occupied; free points lie every :data:`TEST_FREE_STEP` along each held-out beam up to
:data:`TEST_HIT_MARGIN` short of its hit, with no clearance round other hits (a map that blurs
walls pays for it); no-return beams give free points to :data:`NO_RETURN_CAP`. A seeded uniform
subsample keeps each class at its share (:func:`test_points`). :func:`near` picks the boundary
points: those within :data:`BOUNDARY_RADIUS` of a held-out hit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError
from gpomap.observations import natural_subsample, observations_from_scans
from gpomap.scans import Scan

#: Test points: free every TEST_FREE_STEP along a held-out beam, stopping TEST_HIT_MARGIN short.
TEST_FREE_STEP = 0.1
TEST_HIT_MARGIN = 0.1
#: No-return beams: free to this distance (never beyond the sensor's max range), never a hit.
NO_RETURN_CAP = 10.0
#: Boundary test points: within this distance (m) of a held-out hit.
BOUNDARY_RADIUS = 0.5


def protocol_points(
    scans: Sequence[Scan],
    free_step: float = TEST_FREE_STEP,
    hit_margin: float | None = TEST_HIT_MARGIN,
    no_return_cap: float | None = NO_RETURN_CAP,
) -> Any:
    """Every candidate test point of held-out scans, before balancing (see :func:`test_points`).

    Returns
    -------
    gpomap.observations.Observations
        Hits (occupied) and free points every `free_step` from `free_step` out to `hit_margin`
        short of each hit (no-return beams: to `no_return_cap`); no clearance round hits.
    """
    return observations_from_scans(scans, free_step, hit_margin, no_return_cap, free_clearance=0.0)


def test_points(
    scans: Sequence[Scan],
    free_step: float = TEST_FREE_STEP,
    seed: int = 0,
    max_points: int | None = None,
    hit_margin: float | None = TEST_HIT_MARGIN,
    no_return_cap: float | None = NO_RETURN_CAP,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Labelled test points from held-out scans, at their natural frequencies.

    Parameters
    ----------
    scans : sequence of Scan
        The held-out scans.
    free_step : float
        Spacing of free points along the beams (0.1 m: the protocol).
    seed : int
        Seed of the subsampling.
    max_points : int, optional
        Most test points in all: a uniform, seeded subsample, so each class keeps its share (along
        beams, a few per cent of the points are hits).
    hit_margin : float, optional
        Free points stop this short of a hit (0.1 m: the protocol; None: half of `free_step`).
        No clearance round other hits: a free point next to a wall stays a test point.
    no_return_cap : float, optional
        No-return beams give free points out to this distance (and never beyond the sensor's
        max range), never a hit. None: the max range.

    Returns
    -------
    points : ndarray of shape (m, 2)
    labels : ndarray of bool, shape (m,)
        True for occupied (a hit).
    """
    obs = protocol_points(scans, free_step, hit_margin, no_return_cap)
    n_occ = int(np.count_nonzero(obs.occupied))
    if n_occ == 0 or n_occ == obs.occupied.size:
        raise EmptyDataError(f"held-out scans give {n_occ} hits and {obs.occupied.size - n_occ} free points; need both")
    keep = natural_subsample(obs.occupied.size, obs.occupied.size if max_points is None else int(max_points), seed)
    return obs.points[keep], obs.occupied[keep]


# Not a pytest test despite its name (the protocol's term).
test_points.__test__ = False  # type: ignore[attr-defined]


def near(points: NDArray[np.float64], targets: NDArray[np.float64], radius: float) -> NDArray[np.bool_]:
    """Which points lie within `radius` of any target, ndarray of bool, shape (n,).

    Parameters
    ----------
    points : ndarray of shape (n, 2)
    targets : ndarray of shape (t, 2)
    radius : float
    """
    from scipy.spatial import cKDTree

    if len(targets) == 0:
        return np.zeros(len(points), dtype=bool)
    d, _ = cKDTree(targets).query(points, distance_upper_bound=radius)
    return d <= radius
