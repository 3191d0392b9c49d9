"""The map's probabilities for a later visit: one recalibration, fitted on a held-out stretch of the log.

A map's calibration is fitted on its own scans held out one at a time (:func:`gpomap.fusion.fit_calibration`):
each held-out scan's neighbours in time are still counted, so the weights learn how a scan taken
*among* the training scans sees the world. A user asks the map about a later visit, and a later
visit meets what appeared since: people, a door that closed, the next room. Scans held out in
blocks find the map's probabilities too low, while scans held out one in ten find them as the
map says (docs/choices.md, "The map's probabilities for a later visit").

So a planar map fits one monotone map of its probabilities,

    logit p' = slope * logit p + shift * (1 - exp(-(logit p)^2 / (2 WIDTH^2))),

which leaves 1/2 at 1/2 (far from all data the map still says it knows nothing) and moves the
confident ends by up to ``shift`` in log-odds. It is fitted by maximum likelihood on two halves
of equal weight: the held-out points of a stretch of the log the map never saw (every third of
ten stretches, :func:`gpomap.heldout.holdout_stretches`), predicted by the same map fitted
on the rest with the same hyperparameters, and the calibration's own leave-one-scan-out points,
which stand for a visit among the training scans. The shift comes out positive on most real
logs (largest where later stretches meet people, doors and new ground), about 0 on some, and
below 0 on simulations, where nothing moves and the map was under-confident (the fitted values:
the same section). A map that grows online (:mod:`gpomap.streaming`) keeps the recalibration of
its last whole fit.

It is the map's last fitted stage (:mod:`gpomap.stages`): :class:`RevisitCalibration`, fitted on
those points (:meth:`RevisitCalibration.fit`) and applied to the ray-count fusion's probabilities
(:meth:`RevisitCalibration.apply`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize
from scipy.special import expit, log_expit, logit

from gpomap.config import PROFILES, MapConfig
from gpomap.heldout import draw_calibration_points, holdout_stretches
from gpomap.observations import data_dim

#: Width, in log-odds, of the band round 1/2 that the shift leaves alone (at logit p = +-WIDTH the
#: shift is 39 % of its full value, at +-2 WIDTH 86 %).
WIDTH: float = 1.0
#: Bounds of the slope.
SLOPE_BOUNDS: tuple[float, float] = (0.5, 2.0)
#: Largest shift, as a multiple of the slope. The map's derivative in log-odds,
#: ``slope + shift * z / WIDTH^2 * exp(-z^2 / (2 WIDTH^2))``, is least at ``z = -+WIDTH``:
#: ``slope - |shift| / (WIDTH sqrt(e))``; at this bound it is still a tenth of the slope, so
#: the map keeps the order of every two probabilities (and the ternary map its classes).
MAX_SHIFT_RATIO: float = 0.9 * WIDTH * math.sqrt(math.e)
#: Whether a map of this dimension fits the recalibration (planar maps: measured on the quality
#: benchmark's log-splits, docs/choices.md, "The map's probabilities for a later visit").
FIT_REVISIT: dict[int, bool] = {d: p.fit_revisit for d, p in PROFILES.items()}
#: Fewest scans a log needs for a held-out stretch to be a visit of its own (shorter logs keep the identity).
MIN_SCANS: int = 100
#: Most held-out points predicted by the map of the rest (a uniform sample: each class keeps its share).
POINTS: int = 20_000
#: Clip of probabilities before the log-odds (a map's probabilities are within [0.005, 0.995] anyway).
_EPS: float = 1e-6


@dataclass(frozen=True)
class RevisitCalibration:
    """A monotone map of probabilities that keeps 1/2: the identity by default.

    Parameters
    ----------
    slope : float
        Factor on the log-odds.
    shift : float
        Log-odds added away from 1/2 (positive: towards occupied).
    """

    slope: float = 1.0
    shift: float = 0.0

    @property
    def identity(self) -> bool:
        """Whether it leaves every probability as it is."""
        return self.slope == 1.0 and self.shift == 0.0

    def apply(self, p: ArrayLike) -> NDArray[np.float64]:
        """The later-visit stage (:class:`gpomap.stages.Stage`): the recalibrated probabilities,
        the shape of `p`."""
        p = np.asarray(p, dtype=float)
        if self.identity:
            return p
        return expit(_log_odds(p, self.slope, self.shift))

    def __call__(self, p: ArrayLike) -> NDArray[np.float64]:
        """:meth:`apply`."""
        return self.apply(p)

    @classmethod
    def fit(
        cls, p_later: ArrayLike, occupied_later: ArrayLike, p_among: ArrayLike, occupied_among: ArrayLike
    ) -> RevisitCalibration:
        """The recalibration that maximises the likelihood of both halves, each weighing one half.

        Parameters
        ----------
        p_later, occupied_later : array_like of shape (m,)
            The map's probabilities at the points of a stretch it never saw (fitted without it,
            :func:`later_visit_points`), and their classes.
        p_among, occupied_among : array_like of shape (k,)
            The same at points of scans held out one at a time (the calibration's own sample,
            :class:`gpomap.fusion.CalibrationSample`), and their classes.

        Returns
        -------
        RevisitCalibration
            The identity when either half lacks a class.
        """
        p_l, y_l = np.asarray(p_later, dtype=float), np.asarray(occupied_later, dtype=bool)
        p_a, y_a = np.asarray(p_among, dtype=float), np.asarray(occupied_among, dtype=bool)
        if any(y.all() or not y.any() for y in (y_l, y_a)):
            return cls()
        p = np.concatenate([p_l, p_a])
        sign = np.where(np.concatenate([y_l, y_a]), 1.0, -1.0)
        weight = np.concatenate([np.full(p_l.size, 0.5 / p_l.size), np.full(p_a.size, 0.5 / p_a.size)])
        z = _logit(p)
        bump = _bump(z)

        def loss(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            # theta = (slope, shift / slope): the ratio's bounds keep the map monotone.
            slope, ratio = theta
            t = sign * (slope * z + slope * ratio * bump)
            # d/dt of -log sigmoid(t) is -(1 - sigmoid(t)) = -sigmoid(-t).
            d = -weight * expit(-t) * sign
            return float(-np.sum(weight * log_expit(t))), np.array([d @ (z + ratio * bump), slope * (d @ bump)])

        res = minimize(
            loss, np.array([1.0, 0.0]), jac=True, method="L-BFGS-B", bounds=[SLOPE_BOUNDS, (-MAX_SHIFT_RATIO, MAX_SHIFT_RATIO)]
        )
        return cls(float(res.x[0]), float(res.x[0] * res.x[1]))


def _logit(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray(logit(np.clip(p, _EPS, 1.0 - _EPS)), dtype=float)


def _bump(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """How much of the shift applies at log-odds `z`: 0 at 1/2, towards 1 at the confident ends."""
    return 1.0 - np.exp(-0.5 * (z / WIDTH) ** 2)


def _log_odds(p: NDArray[np.float64], slope: float, shift: float) -> NDArray[np.float64]:
    z = _logit(p)
    return slope * z + shift * _bump(z)


def later_visit_points(
    scans: Sequence[Any],
    fit_rest: Callable[[list[Any], NDArray[np.float64]], NDArray[np.float64]],
    no_return_cap: float | None = MapConfig.no_return_cap,
    seed: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], dict[str, Any]]:
    """A map's probabilities at the points of a stretch of its log it never saw (the first half of
    :meth:`RevisitCalibration.fit`'s data; see the module docstring).

    Parameters
    ----------
    scans : sequence of Scan
        The map's scans, in log order.
    fit_rest : callable
        ``fit_rest(scans, points)``: the probability at points (shape (m, d); returns (m,)) of the
        same map fitted on `scans` alone, its hyperparameters held and without this recalibration.
    no_return_cap : float or None
        As the map's.
    seed : int
        Seeds the uniform subsample.

    Returns
    -------
    probability : ndarray of shape (n,)
        What the map of the other stretches says at the held-out stretches' hits and free points
        (:func:`gpomap.heldout.calibration_points`), at most :data:`POINTS` of them drawn uniformly.
    occupied : ndarray of bool, shape (n,)
    report : dict
        ``"n_points"`` (n), or ``"reason"`` when there are none (a log under :data:`MIN_SCANS`
        scans, point clouds, a held-out stretch without a class).
    """
    none = np.zeros(0), np.zeros(0, dtype=bool)
    if len(scans) < MIN_SCANS or not FIT_REVISIT.get(data_dim(scans), False):
        return *none, {"reason": f"{len(scans)} scans (fewer than {MIN_SCANS}) or not planar"}
    kept, held = holdout_stretches(len(scans))
    drawn = drawn_points([scans[k] for k in held], no_return_cap, seed)
    if drawn is None:
        return *none, {"reason": "the held-out stretch has no point of a class"}
    pts, occ = drawn
    return np.asarray(fit_rest([scans[i] for i in kept], pts), dtype=float), occ, {"n_points": int(occ.size)}


def drawn_points(
    scans: Sequence[Any], no_return_cap: float | None, seed: int
) -> tuple[NDArray[np.float64], NDArray[np.bool_]] | None:
    """At most :data:`POINTS` of the scans' calibration points (:func:`gpomap.heldout.calibration_points`),
    drawn uniformly (:func:`~gpomap.observations.natural_subsample`) from them all in scan order.

    Only the points drawn are made (:func:`gpomap.heldout.draw_calibration_points`): a long
    stretch's points (gigabytes over a building) never are.

    Parameters
    ----------
    scans : sequence of Scan
    no_return_cap : float or None
        As the map's.
    seed : int
        Seeds the draw.

    Returns
    -------
    (points, occupied) : ndarray of shape (n, d) and bool ndarray of shape (n,), or None
        None when the scans hold no point of one class.
    """
    drawn = draw_calibration_points(scans, POINTS, seed, no_return_cap=no_return_cap)
    if drawn.n_occupied in (0, drawn.total):
        return None
    return drawn.points, drawn.occupied
