"""Scores of one prediction at labelled points: every metric of the protocol.

:func:`score` gives ROC AUC, FPR at TPR 95 %, log loss, Brier score, expected calibration error
and the reliability diagram's bins (:mod:`gpomap.metrics`), and the AUC of named subsets of the
points (boundary, observed, unobserved); :func:`path_occupied` counts the cells of the robot's
own path a map calls occupied.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.evaluation.reference import REFERENCE_RESOLUTION
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.metrics import brier_score, expected_calibration_error, fpr_at_tpr, log_loss, reliability_bins, roc_auc, roc_curve


def path_occupied(
    prob: NDArray[np.float64] | None,
    points: NDArray[np.float64],
    cell: float = REFERENCE_RESOLUTION,
    occupied: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """How much of the robot's own path a map calls occupied (ternary threshold).

    Parameters
    ----------
    prob : ndarray of shape (n,), or None
        The map's probability at `points` (None with `occupied`).
    points : ndarray of shape (n, 2)
        :func:`path_points`.
    cell : float
        Path points are counted per cell of this side (a lattice from the origin), so a long
        stretch of path in one cell counts once.
    occupied : ndarray of bool, shape (n,), optional
        Whether the map's ternary map calls each point occupied (:func:`occupied_at`,
        :func:`lookup_occupied`), in place of `prob` above the paper's occupied threshold.

    Returns
    -------
    dict
        ``n_cells`` on the path, ``n_occupied`` of them with a point the map calls occupied (the
        robot drove through them: they should be none), ``fraction``.
    """
    if occupied is None:
        if prob is None:
            raise ValueError("path_occupied needs the map's probability or its occupied class")
        occupied = np.asarray(prob) > DEFAULT_THRESHOLDS[1]
    keys = np.floor(np.asarray(points, dtype=float) / cell).astype(np.int64)
    _, cell_of = np.unique(keys, axis=0, return_inverse=True)
    cell_of = cell_of.ravel()
    n = int(cell_of.max()) + 1 if cell_of.size else 0
    occupied_cells = np.zeros(n, bool)
    np.logical_or.at(occupied_cells, cell_of, np.asarray(occupied, dtype=bool))
    return {"n_cells": n, "n_occupied": int(occupied_cells.sum()), "fraction": float(occupied_cells.mean()) if n else 0.0}


def auc_or_none(labels: NDArray[np.bool_], prob: NDArray[np.float64]) -> float | None:
    """ROC AUC, or None where a subset holds only one class (JSON null, '-' in tables)."""
    if labels.size == 0 or labels.all() or not labels.any():
        return None
    return roc_auc(labels, prob)


def score(
    labels: NDArray[np.bool_],
    prob: NDArray[np.float64],
    masks: dict[str, NDArray[np.bool_]] | None = None,
    n_bins: int = 10,
    roc: bool = False,
) -> dict[str, Any]:
    """Every protocol metric of one prediction at the test points.

    Parameters
    ----------
    labels : ndarray of bool, shape (n,)
    prob : ndarray of shape (n,)
        Predicted occupancy probabilities (clipped to [0, 1] first).
    masks : dict of str to ndarray of bool, shape (n,), optional
        Subsets scored alone by AUC, as ``<name>_auc`` with ``n_<name>`` (e.g. "boundary",
        "observed", "unobserved"); None where a subset lacks a class.
    n_bins : int
        Bins of the expected calibration error and the reliability diagram.
    roc : bool
        Also return the ROC curve.

    Returns
    -------
    dict
        ``auc``, ``fpr_at_tpr95``, ``log_loss``, ``brier``, ``ece``, the subset AUCs, ``reliability``
        (``mean_prob``, ``frac_pos``, ``counts`` per bin; empty bins None) and, with `roc`,
        ``roc`` (``fpr`` and ``tpr`` lists, one point per distinct probability).
    """
    p = np.clip(np.asarray(prob, dtype=float), 0.0, 1.0)
    mean_p, frac, counts = reliability_bins(labels, p, n_bins)
    out: dict[str, Any] = {
        "auc": roc_auc(labels, p),
        "fpr_at_tpr95": fpr_at_tpr(labels, p, 0.95),
        "log_loss": log_loss(labels, p),
        "brier": brier_score(labels, p),
        "ece": expected_calibration_error(labels, p, n_bins),
    }
    for name, m in (masks or {}).items():
        out[f"{name}_auc"] = auc_or_none(labels[m], p[m])
        out[f"n_{name}"] = int(m.sum())
    out["reliability"] = {
        "mean_prob": [None if np.isnan(v) else float(v) for v in mean_p],
        "frac_pos": [None if np.isnan(v) else float(v) for v in frac],
        "counts": counts.tolist(),
    }
    if roc:
        fpr, tpr, _ = roc_curve(labels, p)
        out["roc"] = {"fpr": fpr.tolist(), "tpr": tpr.tolist()}
    return out
