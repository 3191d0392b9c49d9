"""How well a converted map keeps the labels of the source's known pixels or voxels."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.grid import FREE, OCCUPIED, ternary
from gpomap.metrics import roc_auc

__all__ = ["label_agreement"]


def label_agreement(
    probability: NDArray[np.float64], occupied: NDArray[np.bool_], thresholds: tuple[float, float]
) -> dict[str, float]:
    """How well probabilities at known pixels reproduce their labels.

    Parameters
    ----------
    probability : ndarray of shape (n,)
    occupied : ndarray of bool, shape (n,)
        Known labels (a class absent gives NaN for it and for the AUC).
    thresholds : (float, float)
        Ternary thresholds; a pixel agrees when its ternary label equals its known label (an
        "unknown" answer never agrees).

    Returns
    -------
    dict
        ``ternary``, ``free``, ``occupied`` (fractions) and ``auc``.
    """
    lab = ternary(probability, thresholds)
    truth = np.where(occupied, OCCUPIED, FREE)
    match = lab == truth
    both = bool(occupied.any() and not occupied.all())
    return {
        "ternary": float(match.mean()) if match.size else math.nan,
        "free": float(match[~occupied].mean()) if (~occupied).any() else math.nan,
        "occupied": float(match[occupied].mean()) if occupied.any() else math.nan,
        "auc": float(roc_auc(occupied, probability)) if both else math.nan,
    }
