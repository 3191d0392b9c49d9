"""One split of one log made ready to score any method on: :func:`prepare` and its :class:`EvalData`.

The window of the log, the hold-out split, the thinned training scans, the test points and
their masks (boundary, observed, unobserved), the far field, the robot's path and, where there
is one, the true map: made once, so every method is scored on the same points.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.gridtruth import Truth
from gpomap.evaluation.points import BOUNDARY_RADIUS, NO_RETURN_CAP, TEST_FREE_STEP, TEST_HIT_MARGIN, near, test_points
from gpomap.evaluation.reference import FAR_DISTANCE, FarField, observed_at, path_points, reference_grid
from gpomap.evaluation.splits import holdout_split, resolve_split, scan_window
from gpomap.scans import Scan, select_scans
from gpomap.truth import PlanTruth, TruthPoints


@dataclass
class EvalData:
    """One split of one log, ready to score any method on (see :func:`prepare`).

    Attributes
    ----------
    train, test : list of Scan
        Training scans (thinned as asked) and held-out scans (whole).
    points : ndarray of shape (n, 2)
    labels : ndarray of bool, shape (n,)
        The test points (natural frequencies) and their classes.
    masks : dict of str to ndarray of bool, shape (n,)
        "boundary" (within BOUNDARY_RADIUS of a held-out hit), "observed" and "unobserved" (the
        reference grid's cells).
    far_test : ndarray of bool, shape (n,)
        Test points farther than FAR_DISTANCE from every cell a training beam crossed.
    far_points : ndarray of shape (f, 2)
        Lattice points that far from the data.
    reference : OccupancyGridMapper
        The counting grid of the training scans at REFERENCE_RESOLUTION.
    truth : Truth or None
    truth_observed : ndarray of bool, shape (ny * nx,) or None
        Truth cells the reference grid observed.
    path : ndarray of shape (p, 2)
        Points along the robot's path through the whole window, training and held-out scans
        (:func:`path_points`).
    plan : TruthPoints or None
        A true plan's pixels that the window's scans observed (:mod:`gpomap.truth`).
    settings, seconds : dict
    """

    train: list[Scan]
    test: list[Scan]
    points: NDArray[np.float64]
    labels: NDArray[np.bool_]
    masks: dict[str, NDArray[np.bool_]]
    far_test: NDArray[np.bool_]
    far_points: NDArray[np.float64]
    reference: Any
    truth: Truth | None = None
    truth_observed: NDArray[np.bool_] | None = None
    path: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    plan: TruthPoints | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def prepare(
    scans: Sequence[Scan],
    holdout: str = "every",
    scan_range: str | tuple[int | None, int | None] | None = None,
    scan_step: int = 1,
    n_scans: int | None = None,
    n_beams: int | None = None,
    seed: int = 0,
    test_free_step: float = TEST_FREE_STEP,
    max_test_points: int | None = None,
    truth: Truth | None = None,
    plan: PlanTruth | None = None,
) -> EvalData:
    """Split a log, make the test points and everything scored about them, once for all methods.

    Parameters
    ----------
    scans : sequence of Scan
        The whole log.
    holdout : str
        A split name ("blocks", "every": :data:`SPLITS`) or spec (see :func:`holdout_split`).
    scan_range : "FIRST:LAST" or (first, last), optional
        Window of the log (Python slice), applied first.
    scan_step : int
        Keep every `scan_step`-th scan of the window (before the split).
    n_scans, n_beams : int, optional
        Thin the training scans to this many evenly spaced scans of this many beams.
    seed : int
        Seeds the split and the test-point subsample.
    test_free_step : float
        Spacing of free test points (0.1 m: the protocol).
    max_test_points : int, optional
        Cap on test points, a seeded uniform subsample.
    truth : Truth, optional
        True map to score against, cell by cell.
    plan : PlanTruth, optional
        True plan to score the written maps against, pixel by pixel where the window's scans
        looked (:class:`gpomap.truth.TruthPoints`).

    Returns
    -------
    EvalData
    """
    spec = resolve_split(holdout)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    if scan_step < 1:
        raise ValueError(f"scan_step must be >= 1, got {scan_step}")
    window = list(scans)[scan_window(scan_range)][::scan_step]
    train_idx, test_idx = holdout_split(len(window), spec, seed)
    train = select_scans([window[i] for i in train_idx], n_scans, n_beams)
    test = [window[i] for i in test_idx]
    seconds["split"] = time.perf_counter() - t
    t = time.perf_counter()
    points, labels = test_points(test, test_free_step, seed, max_test_points)
    hits = np.concatenate([s.hits() for s in test])
    seconds["test_points"] = time.perf_counter() - t
    t = time.perf_counter()
    reference = reference_grid(train)
    observed = observed_at(reference, points)
    far = FarField.from_reference(reference)
    masks = {"boundary": near(points, hits, BOUNDARY_RADIUS), "observed": observed, "unobserved": ~observed}
    truth_observed = observed_at(reference, truth.grid.centres()) if truth is not None else None
    seconds["reference"] = time.perf_counter() - t
    t = time.perf_counter()
    plan_points = TruthPoints.of(plan, window) if plan is not None else None
    seconds["plan"] = time.perf_counter() - t
    settings = {
        "holdout": spec,
        "scan_range": scan_range if scan_range is None or isinstance(scan_range, str) else list(scan_range),
        "scan_step": scan_step,
        "n_scans_in_range": len(window),
        "n_scans": n_scans,
        "n_beams": n_beams,
        "seed": seed,
        "test_free_step": test_free_step,
        "test_hit_margin": TEST_HIT_MARGIN,
        "no_return_cap": NO_RETURN_CAP,
        "max_test_points": max_test_points,
        "test_scan_indices": [int(i) for i in test_idx],
    }
    return EvalData(
        train,
        test,
        points,
        labels,
        masks,
        far.distance_at(points) > FAR_DISTANCE,
        far.far_points(seed=seed),
        reference,
        truth,
        truth_observed,
        path_points(window),
        plan_points,
        settings,
        seconds,
    )
