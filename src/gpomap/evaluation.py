"""The evaluation protocol: hold out scans, test on their hits and free space, score and time.

1. ``scan_range`` (a ``"FIRST:LAST"`` window, Python slice semantics: LAST excluded) picks the
   part of the log to use.
2. :func:`holdout_split` holds out scans, never trained on: every K-th scan (``"every:K"``) or
   blocks of consecutive scans (``"blocks:LEN"`` or ``"blocks:LEN:K"``), as Hilbert maps does.
3. The training scans are thinned to ``n_scans`` evenly spaced scans of ``n_beams`` evenly
   spaced beams (:func:`gpomap.scans.select_scans`); the test scans are used whole.
4. :func:`test_points`: the held-out hits (occupied) and free points along the held-out beams,
   classes balanced by seeded subsampling.
5. :func:`evaluate` fits a method, predicts at the test points and reports ROC AUC, FPR at
   95 % TPR, log loss and the wall time of each stage.

On simulated worlds :func:`score_against_truth` also scores a fitted map against the true
geometry on a grid.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError
from gpomap.grid import GridSpec
from gpomap.metrics import fpr_at_tpr, log_loss, roc_auc, roc_curve
from gpomap.observations import observations_from_scans
from gpomap.scans import Scan, select_scans
from gpomap.tiles import DEFAULT_MAX_CELLS, area_gpom_for

METHODS = ("msk", "gpomik", "gpom", "ogm")

#: Fraction held out by "blocks:LEN" without K: one block in five.
DEFAULT_BLOCK_PERIOD = 5


def _parse_holdout(holdout: str) -> tuple[str, int, int]:
    parts = str(holdout).split(":")
    try:
        if parts[0] == "every" and len(parts) == 2:
            return "every", int(parts[1]), 1
        if parts[0] == "blocks" and len(parts) in (2, 3):
            return "blocks", int(parts[1]), int(parts[2]) if len(parts) == 3 else DEFAULT_BLOCK_PERIOD
    except ValueError:
        pass
    raise ValueError(f"holdout must be 'every:K', 'blocks:LEN' or 'blocks:LEN:K' with integers, got {holdout!r}")


def holdout_split(n_scans: int, holdout: str = "every:5", seed: int = 0) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Split scan indices into training and held-out (test) scans; the two never overlap.

    Parameters
    ----------
    n_scans : int
        Number of scans (at least 2).
    holdout : str
        ``"every:K"``: hold out every K-th scan, starting at a seeded phase in ``[0, K)``
        (about 1/K of the scans). ``"blocks:LEN"`` / ``"blocks:LEN:K"``: cut the sequence into
        consecutive blocks of LEN scans (the first block shortened by a seeded offset in
        ``[0, LEN)``) and hold out every K-th block (default K = 5, so about a fifth), starting at
        a seeded block phase. Held-out blocks keep whole stretches of the trajectory unseen, which
        tests extrapolation more than every-K-th interleaving does.
    seed : int

    Returns
    -------
    train_idx, test_idx : ndarray of int
        Sorted, disjoint, together ``arange(n_scans)``; both non-empty.
    """
    mode, size, period = _parse_holdout(holdout)
    if n_scans < 2:
        raise EmptyDataError(f"a hold-out split needs at least 2 scans, got {n_scans}")
    if size < 1 or (mode == "blocks" and period < 2):
        raise ValueError(f"hold-out sizes must be >= 1 and periods >= 2, got {holdout!r}")
    rng = np.random.default_rng(seed)
    idx = np.arange(n_scans)
    if mode == "every":
        if size < 2:
            raise ValueError(f"'every:K' needs K >= 2, got {holdout!r}")
        phase = int(rng.integers(size))
        test = (idx - phase) % size == 0
    else:
        offset = int(rng.integers(size))
        phase = int(rng.integers(period))
        block = (idx + offset) // size
        test = block % period == phase
    # Tiny logs: guarantee both sides are non-empty without breaking disjointness.
    if not test.any():
        test[int(rng.integers(n_scans))] = True
    if test.all():
        test[int(rng.integers(n_scans))] = False
    return np.flatnonzero(~test), np.flatnonzero(test)


def test_points(
    scans: Sequence[Scan],
    free_step: float = 0.2,
    seed: int = 0,
    max_points: int | None = None,
    hit_margin: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Labelled test points from held-out scans, classes balanced.

    Parameters
    ----------
    scans : sequence of Scan
        The held-out scans.
    free_step : float
        Spacing of free points along the beams (stopping half a step short of each hit).
        No-return beams give free points only.
    seed : int
        Seed of the subsampling.
    max_points : int, optional
        Most test points in all (half each class).
    hit_margin : float, optional
        Free points stop this short of a hit (default half of `free_step`).

    Returns
    -------
    points : ndarray of shape (m, 2)
    labels : ndarray of bool, shape (m,)
        True for occupied (a hit); m / 2 of each class.
    """
    obs = observations_from_scans(scans, free_step, hit_margin)
    occ, free = np.flatnonzero(obs.occupied), np.flatnonzero(~obs.occupied)
    n = min(occ.size, free.size)
    if max_points is not None:
        n = min(n, int(max_points) // 2)
    if n == 0:
        raise EmptyDataError(f"held-out scans give {occ.size} hits and {free.size} free points; need both")
    rng = np.random.default_rng(seed)
    keep = np.sort(np.concatenate([rng.choice(occ, n, replace=False), rng.choice(free, n, replace=False)]))
    return obs.points[keep], obs.occupied[keep]


# Not a pytest test despite its name (the protocol's term).
test_points.__test__ = False  # type: ignore[attr-defined]


def scan_window(scan_range: str | tuple[int | None, int | None] | None) -> slice:
    """The slice of a log that `scan_range` ("FIRST:LAST", a pair, or None) names."""
    if scan_range is None:
        return slice(None)
    if isinstance(scan_range, str):
        try:
            first, last = (int(v) if v.strip() else None for v in scan_range.split(":"))
        except ValueError:
            raise ValueError(f"scan_range must be 'FIRST:LAST' with integers, got {scan_range!r}") from None
    else:
        first, last = scan_range
    return slice(first, last)


def make_model(method: str, kernel: str = "se", seed: int = 0, resolution: float = 0.1, **options: Any) -> Any:
    """The estimator `method` names, with `options` passed to its constructor.

    Parameters
    ----------
    method : {"msk", "gpomik", "gpom", "ogm"}
    kernel : {"se", "matern32"}
        Ignored by "ogm".
    seed : int
        Ignored by "ogm".
    resolution : float
        Cell side of "ogm" (the GP methods predict anywhere).
    """
    if method == "msk":
        from gpomap.mapping import AreaGPOM

        return AreaGPOM(kernel=kernel, seed=seed, **options)
    if method == "gpomik":
        from gpomap.baselines.gpomik import GPOMIK

        return GPOMIK(kernel=kernel, seed=seed, **options)
    if method == "gpom":
        from gpomap.baselines.gpom import GPOM

        return GPOM(kernel=kernel, seed=seed, **options)
    if method == "ogm":
        from gpomap.baselines.ogm import OccupancyGridMapper

        return OccupancyGridMapper(resolution=resolution, **options)
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")


def make_model_for(
    train: Sequence[Scan],
    method: str,
    kernel: str = "se",
    seed: int = 0,
    resolution: float = 0.1,
    max_cells: int | None = DEFAULT_MAX_CELLS,
    n_workers: int | None = None,
    **options: Any,
) -> Any:
    """:func:`make_model`, except that "msk" is built in tiles when `train` gives more than
    `max_cells` cells (:func:`gpomap.tiles.area_gpom_for`), as ``gpomap map`` does."""
    if method != "msk":
        return make_model(method, kernel, seed, resolution, **options)
    model, _ = area_gpom_for(train, max_cells, {"n_workers": n_workers}, kernel=kernel, seed=seed, **options)
    return model


def n_inputs(model: Any) -> int:
    """GP inputs of a fitted model (cells, beams or points); for a grid, the cells it observed."""
    if hasattr(model, "n_inputs_"):
        return int(model.n_inputs_)
    # Occupancy grid: the cells it observed are its "inputs".
    return int((model.observed_ > 0).sum())


def evaluate(
    scans: Sequence[Scan],
    method: str = "msk",
    kernel: str = "se",
    holdout: str = "every:5",
    n_scans: int | None = None,
    n_beams: int | None = None,
    scan_range: str | tuple[int | None, int | None] | None = None,
    seed: int = 0,
    resolution: float = 0.1,
    test_free_step: float = 0.2,
    max_test_points: int | None = None,
    return_roc: bool = False,
    max_cells: int | None = DEFAULT_MAX_CELLS,
    n_workers: int | None = None,
    **method_options: Any,
) -> dict[str, Any]:
    """Fit a method on training scans and score it on held-out scans.

    Parameters
    ----------
    scans : sequence of Scan
        The whole log.
    method : {"msk", "gpomik", "gpom", "ogm"}
    kernel : {"se", "matern32"}
        Point kernel of the GP methods.
    holdout : str
        See :func:`holdout_split`.
    n_scans, n_beams : int, optional
        Thin the training scans to this many evenly spaced scans of this many evenly spaced beams.
    scan_range : "FIRST:LAST" or (first, last), optional
        Window of the log to use (Python slice: LAST excluded), applied before the split.
    seed : int
        Seeds the split, the test-point subsample and the method.
    resolution : float
        Cell side of the occupancy grid ("ogm").
    test_free_step : float
        Spacing of free test points along held-out beams.
    max_test_points : int, optional
        Cap on test points (half each class).
    return_roc : bool
        Also return the ROC curve as ``roc = {"fpr": [...], "tpr": [...]}``.
    max_cells : int or None
        "msk" only: above this many cells the map is built in tiles, as ``gpomap map`` does
        (:func:`gpomap.tiles.area_gpom_for`); None: always one GP.
    n_workers : int, optional
        Worker processes for tiles (default: the CPU count).
    **method_options
        Passed to the method's constructor.

    Returns
    -------
    dict
        JSON-serialisable: ``auc``, ``fpr_at_tpr95``, ``log_loss``, ``seconds`` (``total``,
        ``split``, ``test_points``, ``fit``, ``predict`` and the model's own stages, e.g.
        ``observations``, ``cells``, ``hyperparameters``, ``squash``), ``n_inputs`` (GP inputs;
        for "ogm" the cells observed), ``n_train_scans``, ``n_test_scans``, ``n_test_points``,
        ``hyperparameters`` (GP methods), ``settings`` (every setting used) and, with
        `return_roc`, ``roc``.
    """
    t_all = time.perf_counter()
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    window = list(scans)[scan_window(scan_range)]
    train_idx, test_idx = holdout_split(len(window), holdout, seed)
    train = select_scans([window[i] for i in train_idx], n_scans, n_beams)
    test = [window[i] for i in test_idx]
    seconds["split"] = time.perf_counter() - t
    t = time.perf_counter()
    points, labels = test_points(test, test_free_step, seed, max_test_points)
    seconds["test_points"] = time.perf_counter() - t

    t = time.perf_counter()
    model = make_model_for(train, method, kernel, seed, resolution, max_cells, n_workers, **method_options)
    model.fit(train)
    seconds["fit"] = time.perf_counter() - t
    t = time.perf_counter()
    prob = np.asarray(model.predict_proba(points), dtype=float)
    seconds["predict"] = time.perf_counter() - t
    for stage, value in getattr(model, "timings_", {}).items():
        if stage != "prediction":
            seconds[stage] = float(value)
    seconds["total"] = time.perf_counter() - t_all

    result: dict[str, Any] = {
        "method": method,
        "auc": roc_auc(labels, prob),
        "fpr_at_tpr95": fpr_at_tpr(labels, prob, 0.95),
        "log_loss": log_loss(labels, prob),
        "seconds": seconds,
        "n_inputs": n_inputs(model),
        "n_train_scans": len(train),
        "n_test_scans": len(test),
        "n_test_points": int(labels.size),
        "settings": {
            "method": method,
            "kernel": kernel if method != "ogm" else None,
            "holdout": holdout,
            "n_scans": n_scans,
            "n_beams": n_beams,
            "scan_range": scan_range if scan_range is None or isinstance(scan_range, str) else list(scan_range),
            "n_scans_in_range": len(window),
            "seed": seed,
            "resolution": resolution,
            "test_free_step": test_free_step,
            "max_test_points": max_test_points,
            "tiles": len(model.tiles_) if hasattr(model, "tiles_") else None,
            "test_scan_indices": [int(i) for i in test_idx],
            "method_options": _jsonable(method_options),
        },
    }
    if hasattr(model, "hyperparameters_"):
        result["hyperparameters"] = {k: float(v) for k, v in model.hyperparameters_.items()}
    if return_roc:
        fpr, tpr, _ = roc_curve(labels, prob)
        result["roc"] = {"fpr": fpr.tolist(), "tpr": tpr.tolist()}
    return result


def _jsonable(value: Any) -> Any:
    """`value` with tuples and numpy scalars / arrays turned into JSON types."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def score_against_truth(model: Any, world: Any, grid: GridSpec | float, wall_thickness: float | None = None) -> dict[str, Any]:
    """Score a fitted map against a simulated world's true occupancy on a grid.

    Parameters
    ----------
    model : fitted estimator
        Anything with ``predict_proba(points)``.
    world : gpomap.simulate.World
    grid : GridSpec or float
        The grid to score on; a float is a resolution over the world's bounds.
    wall_thickness : float, optional
        Width of the wall bands counted occupied (default the grid resolution, see
        :meth:`gpomap.simulate.World.true_grid`).

    Returns
    -------
    dict
        ``auc``, ``fpr_at_tpr95``, ``n_cells``, ``n_occupied_cells``, ``resolution``.
    """
    if not isinstance(grid, GridSpec):
        grid = GridSpec.from_extent(world.bounds, float(grid))
    truth = world.true_grid(grid, wall_thickness).ravel()
    prob = np.asarray(model.predict_proba(grid.centres()), dtype=float)
    return {
        "auc": roc_auc(truth, prob),
        "fpr_at_tpr95": fpr_at_tpr(truth, prob, 0.95),
        "n_cells": int(truth.size),
        "n_occupied_cells": int(truth.sum()),
        "resolution": grid.resolution,
    }
