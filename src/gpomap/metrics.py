"""Scores for occupancy predictions: ROC curve, its area, FPR at a target TPR, log loss,
calibration (expected calibration error and the reliability diagram's bins) and IoU.

Labels are booleans (True = occupied = the positive class); scores are anything that ranks
points by how occupied they look (probabilities, latent means). Only numpy is used.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.errors import EmptyDataError


def _check(labels: ArrayLike, scores: ArrayLike, need_both: bool = True) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    y = np.asarray(labels).reshape(-1)
    s = np.asarray(scores, dtype=float).reshape(-1)
    if y.shape != s.shape:
        raise ValueError(f"labels and scores must have the same length, got {y.size} and {s.size}")
    if y.dtype != bool:
        if not np.isin(y, [0, 1]).all():
            raise ValueError("labels must be boolean or 0/1 (True / 1 = occupied)")
        y = y.astype(bool)
    if np.isnan(s).any():
        raise ValueError("scores contain NaN")
    if need_both:
        n_pos = int(y.sum())
        if n_pos == 0 or n_pos == y.size:
            raise EmptyDataError(f"ROC needs both classes, got {n_pos} positive and {y.size - n_pos} negative labels")
    return y, s


def roc_curve(labels: ArrayLike, scores: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Receiver operating characteristic.

    A point is called positive when its score is >= the threshold. Thresholds are the distinct
    scores in decreasing order, so points with tied scores always change class together: a tie
    between positives and negatives is one diagonal step of the curve.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
        True (or 1) for the positive class.
    scores : array_like of shape (n,)
        Higher means more likely positive.

    Returns
    -------
    fpr : ndarray of shape (m + 1,)
        False positive rate at each operating point, from 0 up to 1.
    tpr : ndarray of shape (m + 1,)
        True positive rate at each operating point, from 0 up to 1.
    thresholds : ndarray of shape (m + 1,)
        ``inf`` (nothing positive) followed by the m distinct scores, decreasing.

    Raises
    ------
    EmptyDataError (a ValueError)
        If only one class is present.
    """
    y, s = _check(labels, scores)
    order = np.argsort(-s, kind="mergesort")
    s, y = s[order], y[order]
    # Last index of each run of equal scores: the operating point after that threshold.
    last = np.flatnonzero(np.r_[s[1:] != s[:-1], True])
    tp = np.cumsum(y)[last]
    fp = (last + 1) - tp
    tpr = np.r_[0.0, tp / tp[-1]]
    fpr = np.r_[0.0, fp / fp[-1]]
    return fpr, tpr, np.r_[np.inf, s[last]]


def roc_auc(labels: ArrayLike, scores: ArrayLike) -> float:
    """Area under the ROC curve (trapezoidal, ties as diagonal steps).

    Equal to the Mann-Whitney probability that a random positive scores above a random
    negative, with ties counted one half.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    scores : array_like of shape (n,)

    Returns
    -------
    float in [0, 1]
    """
    fpr, tpr, _ = roc_curve(labels, scores)
    return float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))


def fpr_at_tpr(labels: ArrayLike, scores: ArrayLike, tpr: float = 0.95) -> float:
    """False positive rate at a target true positive rate.

    Convention: the smallest FPR among the ROC operating points (thresholds at the distinct
    scores, see :func:`roc_curve`) whose TPR is at least `tpr`. No interpolation between
    operating points: with tied scores one cannot reach a TPR inside a tie without taking the
    whole tie, so the result is what a threshold on the scores actually achieves.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    scores : array_like of shape (n,)
    tpr : float in (0, 1]
        Target true positive rate (the paper reports FPR at 95 % TPR).

    Returns
    -------
    float in [0, 1]
    """
    if not 0.0 < tpr <= 1.0:
        raise ValueError(f"target tpr must be in (0, 1], got {tpr}")
    fpr, tprs, _ = roc_curve(labels, scores)
    # A small slack so a TPR such as 19/20 counts as reaching 0.95 despite rounding.
    return float(fpr[tprs >= tpr - 1e-12].min())


#: Probabilities are clipped to [LOG_LOSS_EPS, 1 - LOG_LOSS_EPS] by :func:`log_loss`: a grid's
#: hard 0 / 1 (or a GP's 1e-15) would otherwise dominate the mean with one confident mistake.
LOG_LOSS_EPS = 1e-6


def log_loss(labels: ArrayLike, probs: ArrayLike, eps: float = LOG_LOSS_EPS) -> float:
    """Mean negative log-likelihood of the labels under the predicted probabilities.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    probs : array_like of shape (n,)
        Predicted probability of the positive class; clipped to ``[eps, 1 - eps]`` so a
        confident mistake costs ``-log(eps)`` instead of infinity.
    eps : float

    Returns
    -------
    float
        ``-mean(y log p + (1 - y) log(1 - p))``, in nats.
    """
    y, p = _check(labels, probs, need_both=False)
    if y.size == 0:
        raise EmptyDataError("log_loss needs at least one label")
    if ((p < 0) | (p > 1)).any():
        raise ValueError("probabilities must lie in [0, 1]")
    p = np.clip(p, eps, 1 - eps)
    return float(-np.mean(np.where(y, np.log(p), np.log1p(-p))))


def brier_score(labels: ArrayLike, probs: ArrayLike) -> float:
    """Mean squared difference between the predicted probabilities and the labels.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    probs : array_like of shape (n,)
        Predicted probability of the positive class, in [0, 1].

    Returns
    -------
    float
        ``mean((p - y)^2)``: 0 for a certain, right map; 0.25 for p = 1/2 everywhere.
    """
    y, p = _check(labels, probs, need_both=False)
    if y.size == 0:
        raise EmptyDataError("brier_score needs at least one label")
    if ((p < 0) | (p > 1)).any():
        raise ValueError("probabilities must lie in [0, 1]")
    return float(np.mean((p - y) ** 2))


def _check_probs(labels: ArrayLike, probs: ArrayLike) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    y, p = _check(labels, probs, need_both=False)
    if y.size == 0:
        raise EmptyDataError("calibration needs at least one label")
    if ((p < 0) | (p > 1)).any():
        raise ValueError("probabilities must lie in [0, 1]")
    return y, p


def reliability_bins(
    labels: ArrayLike, probs: ArrayLike, n_bins: int = 10
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """The reliability diagram's bins: equal-width probability bins, what was predicted and seen.

    Bin k holds ``k / n_bins <= p < (k + 1) / n_bins``; the last bin also holds p = 1.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    probs : array_like of shape (n,)
        Predicted probability of the positive class, in [0, 1].
    n_bins : int

    Returns
    -------
    mean_prob : ndarray of shape (n_bins,)
        Mean predicted probability in each bin (NaN where empty).
    frac_pos : ndarray of shape (n_bins,)
        Fraction of positives in each bin (NaN where empty).
    counts : ndarray of int, shape (n_bins,)
    """
    y, p = _check_probs(labels, probs)
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    b = np.minimum((p * n_bins).astype(np.intp), n_bins - 1)
    counts = np.bincount(b, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_prob = np.bincount(b, weights=p, minlength=n_bins) / counts
        frac_pos = np.bincount(b, weights=y.astype(float), minlength=n_bins) / counts
    return mean_prob, frac_pos, counts


def expected_calibration_error(labels: ArrayLike, probs: ArrayLike, n_bins: int = 10) -> float:
    """Expected calibration error with equal-width bins.

    ``sum_k (n_k / n) |frac_pos_k - mean_prob_k|`` over the bins of :func:`reliability_bins`:
    how far, on average over the points, the predicted probability is from the frequency of
    occupied points among those given a similar probability.

    Parameters
    ----------
    labels : array_like of bool, shape (n,)
    probs : array_like of shape (n,)
    n_bins : int

    Returns
    -------
    float in [0, 1]
    """
    mean_prob, frac_pos, counts = reliability_bins(labels, probs, n_bins)
    full = counts > 0
    return float(np.sum(counts[full] * np.abs(frac_pos[full] - mean_prob[full])) / counts.sum())


def iou(predicted: ArrayLike, truth: ArrayLike) -> float:
    """Intersection over union of two boolean masks (the occupied class).

    Parameters
    ----------
    predicted, truth : array_like of bool, same shape

    Returns
    -------
    float in [0, 1]
        ``|predicted & truth| / |predicted | truth|``; NaN if both are empty.
    """
    a = np.asarray(predicted, dtype=bool)
    b = np.asarray(truth, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"masks must have the same shape, got {a.shape} and {b.shape}")
    union = int((a | b).sum())
    return float((a & b).sum() / union) if union else float("nan")
