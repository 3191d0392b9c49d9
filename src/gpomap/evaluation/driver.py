"""The evaluation's driver: fit a method on a split's training scans and score what it gives.

:func:`run_method` scores a fitted method's exact-point predictions and its written grid on one
prepared split (:func:`gpomap.evaluation.data.prepare`); :func:`evaluate` prepares the split and
runs one method.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.data import EvalData, prepare
from gpomap.evaluation.gridtruth import Truth, score_truth
from gpomap.evaluation.maps import (
    GRID_RESOLUTION,
    lookup,
    lookup_occupied,
    make_model,
    n_inputs,
    occupied_at,
    written_grid,
)
from gpomap.evaluation.methods import method_named
from gpomap.evaluation.points import TEST_FREE_STEP
from gpomap.evaluation.scoring import path_occupied, score
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.resources import peak_rss_mb
from gpomap.scans import Scan
from gpomap.truth import MAP_SERVER_THRESHOLDS, PlanTruth, score_plan


def _spread(values: NDArray[np.float64]) -> dict[str, Any]:
    """Count, mean and standard deviation (None when empty)."""
    if values.size == 0:
        return {"n": 0, "mean": None, "std": None}
    return {"n": int(values.size), "mean": float(values.mean()), "std": float(values.std())}


def _clock() -> tuple[float, float]:
    """Wall time and CPU time of this process and its reaped children (tile workers), seconds."""
    t = os.times()
    return time.perf_counter(), time.process_time() + t.children_user + t.children_system


def run_method(
    data: EvalData,
    method: str = "msk",
    kernel: str | None = None,
    seed: int = 0,
    resolution: float = 0.1,
    grid_resolution: float = GRID_RESOLUTION,
    n_workers: int | None = None,
    return_roc: bool = False,
    score_grid: bool = True,
    **method_options: Any,
) -> dict[str, Any]:
    """Fit one method on ``data.train`` and score its exact-point and written-grid predictions.

    Parameters
    ----------
    data : EvalData
    method : str
        A name of :data:`gpomap.evaluation.methods.METHODS`.
    kernel : {"se", "matern32"}, optional
        Point kernel of the GP methods (default: the library's).
    seed : int
        Seeds the method.
    resolution : float
        Cell side of the occupancy grids.
    grid_resolution : float
        Resolution of the written map of the GP methods (0.05 m).
    n_workers : int, optional
        Worker processes for tiles (default: the CPU count).
    return_roc : bool
        Also return the ROC curves: each score's ``roc`` (:func:`score`), the exact points' also
        as ``roc``.
    score_grid : bool
        Also build and score the written grid.
    **method_options
        Passed to the method's constructor.

    Returns
    -------
    dict
        JSON-serialisable: ``points`` and ``grid`` (each :func:`score`'s dict, ``grid`` None
        without `score_grid`), ``auc``, ``fpr_at_tpr95``, ``log_loss`` (the exact-point ones),
        ``far`` (mean and spread of the predictions far from the data: at far test points and on
        the far lattice, for both predictions), ``path`` (:func:`path_occupied` of both), ``truth`` (:func:`score_truth` of both, or None),
        ``plan`` (the written map against ``data.plan``, :func:`gpomap.truth.score_plan`, or None),
        ``seconds`` and ``cpu_seconds`` (``fit``, ``predict``, ``grid``; the model's own stages),
        ``peak_rss_mb`` (this process's peak so far), ``n_inputs``, ``n_train_scans``,
        ``n_test_scans``, ``n_test_points``, ``hyperparameters`` (GP methods), ``evidence`` (the ray
        evidence's calibration, MSK-GPOM), ``settings``.
    """
    seconds: dict[str, float] = {}
    cpu: dict[str, float] = {}
    w0, c0 = _clock()
    model = make_model(method, kernel, seed, resolution, n_workers, **method_options)
    # A grid has a cell side and no kernel, and the map it writes is its own cells.
    own_grid = method_named(method).own_grid
    model.fit(data.train)
    w1, c1 = _clock()
    prob = np.asarray(model.predict_proba(data.points), dtype=float)
    w2, c2 = _clock()
    seconds["fit"], cpu["fit"] = w1 - w0, c1 - c0
    seconds["predict"], cpu["predict"] = w2 - w1, c2 - c1
    for stage, value in getattr(model, "timings_", {}).items():
        if stage != "prediction" and isinstance(value, (int, float)):
            seconds[stage] = float(value)
    points_score = score(data.labels, prob, data.masks, roc=return_roc)
    far_lattice = np.asarray(model.predict_proba(data.far_points), dtype=float) if len(data.far_points) else np.zeros(0)
    far = {"test_points": {"points": _spread(prob[data.far_test])}, "lattice": {"points": _spread(far_lattice)}}
    # Each map's own ternary map is judged (MSK-GPOM fits its occupied threshold).
    occupied_above = float(getattr(model, "thresholds_", DEFAULT_THRESHOLDS)[1])
    path = {"points": path_occupied(None, data.path, occupied=occupied_at(model, data.path))}
    truth_out: dict[str, Any] | None = None
    if data.truth is not None:
        centres = data.truth.grid.centres()
        truth_out = {
            "points": score_truth(
                data.truth,
                np.asarray(model.predict_proba(centres), dtype=float),
                data.truth_observed,
                occupied=occupied_at(model, centres),
            )
        }

    grid_score = None
    written_shape = None
    plan_out: dict[str, Any] | None = None
    if score_grid:
        w3, c3 = _clock()
        occupancy_map = written_grid(model, grid_resolution)
        w4, c4 = _clock()
        seconds["grid"], cpu["grid"] = w4 - w3, c4 - c3
        written_shape = list(occupancy_map.grid.shape)
        gprob = lookup(occupancy_map, data.points)
        grid_score = score(data.labels, gprob, data.masks, roc=return_roc)
        far["test_points"]["grid"] = _spread(gprob[data.far_test])
        far["lattice"]["grid"] = _spread(lookup(occupancy_map, data.far_points))
        path["grid"] = path_occupied(None, data.path, occupied=lookup_occupied(occupancy_map, data.path))
        if data.truth is not None and truth_out is not None:
            centres = data.truth.grid.centres()
            truth_out["grid"] = score_truth(
                data.truth,
                lookup(occupancy_map, centres),
                data.truth_observed,
                occupied=lookup_occupied(occupancy_map, centres),
            )
        if data.plan is not None:
            plan_prob = lookup(occupancy_map, data.plan.points)
            # A grid's ternary map as map_server reads it; gpomap's its own.
            plan_occupied = plan_prob > MAP_SERVER_THRESHOLDS[1] if own_grid else lookup_occupied(occupancy_map, data.plan.points)
            plan_out = score_plan(data.plan, plan_prob, plan_occupied)
        del occupancy_map

    result: dict[str, Any] = {
        "method": method,
        "occupied_threshold": occupied_above,
        "auc": points_score["auc"],
        "fpr_at_tpr95": points_score["fpr_at_tpr95"],
        "log_loss": points_score["log_loss"],
        "points": points_score,
        "grid": grid_score,
        "far": far,
        "path": path,
        "truth": truth_out,
        "plan": plan_out,
        "seconds": seconds,
        "cpu_seconds": cpu,
        "peak_rss_mb": peak_rss_mb(),
        "n_inputs": n_inputs(model),
        "n_train_scans": len(data.train),
        "n_test_scans": len(data.test),
        "n_test_points": int(data.labels.size),
        "settings": {
            **data.settings,
            "method": method,
            "kernel": None if own_grid else getattr(model, "kernel", getattr(getattr(model, "base", None), "kernel", kernel)),
            "resolution": resolution if own_grid else None,
            "grid_resolution": (resolution if own_grid else grid_resolution) if score_grid else None,
            "written_grid_shape": written_shape,
            "tiles": len(model.tiles_) if hasattr(model, "tiles_") else None,
            "method_options": _jsonable(method_options),
        },
    }
    if hasattr(model, "hyperparameters_"):
        result["hyperparameters"] = {k: float(v) for k, v in model.hyperparameters_.items()}
    evidence = getattr(model, "evidence_", None)
    if evidence is not None:
        result["evidence"] = _jsonable(evidence.summary())
    if return_roc:
        result["roc"] = points_score["roc"]
    return result


def evaluate(
    scans: Sequence[Scan],
    method: str = "msk",
    kernel: str | None = None,
    holdout: str = "every",
    n_scans: int | None = None,
    n_beams: int | None = None,
    scan_range: str | tuple[int | None, int | None] | None = None,
    seed: int = 0,
    resolution: float = 0.1,
    test_free_step: float = TEST_FREE_STEP,
    max_test_points: int | None = None,
    return_roc: bool = False,
    n_workers: int | None = None,
    grid_resolution: float = GRID_RESOLUTION,
    scan_step: int = 1,
    truth: Truth | None = None,
    score_grid: bool = True,
    plan: PlanTruth | None = None,
    **method_options: Any,
) -> dict[str, Any]:
    """Fit a method on training scans and score it on held-out scans (:func:`prepare` then
    :func:`run_method`; see them for the parameters).

    Returns
    -------
    dict
        :func:`run_method`'s, with ``seconds`` also holding ``split``, ``test_points``,
        ``reference`` and ``total``.
    """
    t = time.perf_counter()
    data = prepare(scans, holdout, scan_range, scan_step, n_scans, n_beams, seed, test_free_step, max_test_points, truth, plan)
    result = run_method(
        data, method, kernel, seed, resolution, grid_resolution, n_workers, return_roc, score_grid, **method_options
    )
    result["seconds"] = {**data.seconds, **result["seconds"], "total": time.perf_counter() - t}
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
