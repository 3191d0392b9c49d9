"""The calibration of the ray counts: how much a hit, a miss, a near miss, a surface miss and the GP weigh.

:class:`EvidenceCalibration` turns a fine cell's counts and the GP's probability there into the
cell's probability (the formula in :mod:`gpomap.fusion`): the map's fitted stage after the squash
(:mod:`gpomap.stages`; :meth:`EvidenceCalibration.apply`). :func:`fit_calibration` draws points
from the map's own scans held out one at a time, with the other scans' counts in their cells, and
fits the weights on them (:meth:`EvidenceCalibration.fit`), then the surprise rate
(:func:`with_surprises`, :func:`fit_surprise_rate`) on a GP that never saw them. The rate of
cells only beams that returned nothing reached (:func:`only_silent`, :func:`fit_silent_rate`) is
fitted with the later visit's points, by :meth:`gpomap.fusion.EvidenceLayer.fit_revisit`. Why
each weight, and what it was measured to be worth: docs/choices.md.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq, minimize

from gpomap.config import PROFILES, MapConfig
from gpomap.evidence import RayCounts, RayEvidence
from gpomap.heldout import calibration_scans, draw_calibration_points
from gpomap.lattice import AnyGrid, flat_index
from gpomap.observations import ScanData
from gpomap.stages import Counted

#: The share of observations that are surprises the counts cannot foresee (a person standing where
#: every scan saw free space, a door, a pose error), so a map's probabilities are
#: ``SURPRISE_RATE / 2 + (1 - SURPRISE_RATE) * p``, as OctoMap clamps its log-odds, if far less
#: tightly. A prior, not a fit: the training log does not show the visitors a later stretch
#: meets. Chosen across logs for the lowest mean held-out log loss of the written maps
#: (docs/choices.md, "One observation in a hundred is a surprise").
SURPRISE_RATE: float = 1e-2

#: Largest surprise rate a map may fit (:func:`fit_surprise_rate`); its floor is :data:`SURPRISE_RATE`.
MAX_SURPRISE_RATE: float = 0.3

#: Whether a map of this dimension can fit its surprise rate on its own scans, when its settings ask
#: (``fit_surprise_rate``; :func:`fit_surprise_rate`). The calibration's leave-one-scan-out points,
#: predicted by a GP fitted without those scans, show how often a log's observations are surprises:
#: above the prior where visitors crowd a log, where the prior had made the map too sure of cells
#: they later stood in (docs/choices.md, "The surprise rate, fitted per map"). Planar maps: not
#: measured on point clouds, which keep the prior.
FIT_SURPRISE_RATE: dict[int, bool] = {d: p.surprise_rate_fitted for d, p in PROFILES.items()}


def with_surprises(p: ArrayLike, rate: float = SURPRISE_RATE) -> NDArray[np.float64]:
    """Probabilities (any shape) mixed with `rate` of chance: ``rate / 2 + (1 - rate) p``."""
    return rate / 2 + (1.0 - rate) * np.asarray(p, dtype=float)


def fit_surprise_rate(
    p: ArrayLike, occupied: ArrayLike, bounds: tuple[float, float] = (SURPRISE_RATE, MAX_SURPRISE_RATE)
) -> float:
    """The surprise rate that maximises the likelihood of held-out points, within `bounds`.

    The mean log likelihood of ``rate / 2 + (1 - rate) p`` is concave in the rate (a log of an affine
    function, summed), so the bounded maximum is the unbounded one clipped to `bounds`.

    Parameters
    ----------
    p : array_like of shape (n,)
        The points' probabilities before any surprise rate.
    occupied : array_like of bool, shape (n,)
    bounds : (float, float)

    Returns
    -------
    float
    """
    q = np.asarray(p, dtype=float).ravel()
    y = np.asarray(occupied, dtype=bool).ravel()
    # Each point's chance of its class without surprises; a surprise gives either class 1/2.
    right = np.where(y, q, 1.0 - q)

    def slope(rate: float) -> float:  # d/d rate of the summed log likelihood, decreasing in rate
        return float(np.sum((0.5 - right) / (rate / 2 + (1.0 - rate) * right)))

    lo, hi = bounds
    if q.size == 0 or slope(lo) <= 0.0:
        return float(lo)
    if slope(hi) >= 0.0:
        return float(hi)
    return float(brentq(slope, lo, hi, xtol=1e-12))


#: Fewest held-out points in cells only beams that returned nothing reached (:func:`only_silent`)
#: for their rate to be fitted (:func:`fit_silent_rate`); with fewer the map's probability stays.
#: Of the later visit's 20,000 points (:mod:`gpomap.revisit`) that is half a per cent.
SILENT_FIT_POINTS: int = 100


def only_silent(hits: ArrayLike, misses: ArrayLike, silent: ArrayLike, path: ArrayLike = 0) -> NDArray[np.bool_]:
    """Cells only beams that returned nothing reached (matching shapes): no hit, no step of the
    robot's path, and every update a silent one (:attr:`gpomap.evidence.RayCounts.silent`).

    Such a beam is taken as free to the no-return cap, through whatever it passed: glass, a dark
    or distant wall, a dropped return. No beam that saw a surface says anything of these cells,
    and the GP's probability there is learnt from their own misses.
    """
    m = np.asarray(misses)
    return (np.asarray(hits) == 0) & (m > 0) & (np.asarray(silent) >= m) & (np.asarray(path) == 0)


def fit_silent_rate(p: ArrayLike, occupied: ArrayLike) -> tuple[float, float]:
    """The rate and its weight that, mixed into probabilities as ``(1 - mix) p + mix rate``,
    maximise the likelihood of held-out points (see :attr:`EvidenceCalibration.silent_rate`).

    Parameters
    ----------
    p : array_like of shape (n,)
        The points' probabilities before the mix.
    occupied : array_like of bool, shape (n,)

    Returns
    -------
    rate, mix : float
        ``(0.0, 0.0)``, the probabilities as they are, for fewer than :data:`SILENT_FIT_POINTS` points.
    """
    q = np.asarray(p, dtype=float).ravel()
    y = np.asarray(occupied, dtype=bool).ravel()
    if q.size < SILENT_FIT_POINTS:
        return 0.0, 0.0

    def loss(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        mix, rate = theta
        mixed = np.clip((1.0 - mix) * q + mix * rate, 1e-12, 1.0 - 1e-12)
        dq = np.where(y, -1.0 / mixed, 1.0 / (1.0 - mixed)) / q.size
        value = float(-np.mean(np.where(y, np.log(mixed), np.log1p(-mixed))))
        return value, np.array([dq @ (rate - q), dq.sum() * mix])

    # The rate's floor keeps a later hit there from costing more than a surprise would.
    start = np.array([0.5, min(max(float(y.mean()), SURPRISE_RATE), 0.5)])
    res = minimize(loss, start, jac=True, method="L-BFGS-B", bounds=((0.0, 1.0), (SURPRISE_RATE / 2, 0.5)))
    mix, rate = (float(v) for v in res.x)
    return (rate, mix) if mix > 0.0 else (0.0, 0.0)


#: Hits one step of the robot's path through a cell outweighs (as misses, :meth:`EvidenceCalibration.misses`).
#: The robot's body was there, which no beam can say; but a pose error or a cell shared with a
#: wall's edge should not be cleared outright. One hit's worth left the path cells that held a
#: few hits occupied; ten clear them (docs/choices.md, "The robot's body round its path").
PATH_HITS: float = 10.0

#: Most calibration points, drawn uniformly so each class keeps its share: a few per cent are
#: hits, and five weights need a thousand or so of them; the GP's prediction at the points is the
#: calibration's cost.
CALIBRATION_POINTS: int = 40_000

#: Search bounds (log space) of the hit weight, the prior weight, the near-miss weight, the
#: near miss's weight as a surface (whose floor, 1e-3 of an observation, is nothing against the
#: counts a log gives) and the surface miss's weight.
CALIBRATION_BOUNDS: tuple[tuple[float, float], ...] = (
    (np.log(0.1), np.log(1e3)),
    (np.log(0.1), np.log(1e2)),
    (np.log(1e-3), np.log(10.0)),
    (np.log(1e-3), np.log(1e2)),
    (np.log(1e-3), np.log(10.0)),
)

#: Whether the calibration weighs surface misses apart (:attr:`EvidenceCalibration.surface_weight`),
#: per dimension of the data; where not, a surface miss is a miss. Planar maps: measured on the
#: shared and unseen logs (docs/choices.md). Not for point clouds, where it was not.
FIT_SURFACE_WEIGHT: dict[int, bool] = {d: p.fit_surface_weight for d, p in PROFILES.items()}


@dataclass(frozen=True)
class EvidenceCalibration:
    """How much a hit, a miss, a near miss and the GP prior weigh in a cell's probability.

    The defaults (one hit = one miss = one near miss, the GP worth two observations, a near miss no
    hit) make the counting grid p = (hits + 1) / (hits + misses + 2) with the GP's probability in
    place of its 1/2.

    Parameters
    ----------
    hit_weight : float
        Observations one hit counts as (a miss counts as one).
    prior_weight : float
        Equivalent sample size n0 of the GP's probability.
    near_weight : float
        Misses one near miss counts as.
    near_hit_weight : float
        Observations of a surface one near miss adds besides (a hit adds ``hit_weight``): a beam
        that ended its return within :data:`~gpomap.evidence.NEAR_END` of a cell says a surface
        is near it, and with range noise and pose error, often in it.
    surface_weight : float
        Misses one surface miss counts as: a far miss (not near) of a cell that a beam of another
        scan ended in, or next to one (:func:`gpomap.evidence.next_to_hits`). Such a cell holds
        part of a surface more often than its misses say: a beam passing along a wall crosses the
        cell in front of it, which a beam from elsewhere ends in.
    surprise_rate : float
        Share of observations the counts cannot foresee (:func:`with_surprises`).
    silent_rate, silent_mix : float
        In cells only beams that returned nothing reached (:func:`only_silent`), the probability
        is ``(1 - silent_mix) p + silent_mix * silent_rate``, fitted on held-out points
        (:func:`fit_silent_rate`): such beams cross walls as well as free space, and their misses
        alone cannot tell the two apart. The fit often puts the rate at its bound of 1/2, where
        the mix is a floor added to a map whose ranking there it keeps. A mix of 0 leaves the map
        as it is.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.fusion"

    hit_weight: float = 1.0
    prior_weight: float = 2.0
    near_weight: float = 1.0
    near_hit_weight: float = 0.0
    surface_weight: float = 1.0
    surprise_rate: float = SURPRISE_RATE
    silent_rate: float = 0.0
    silent_mix: float = 0.0

    def hits(self, hits: ArrayLike, near: ArrayLike) -> NDArray[np.float64]:
        """Weighted hits of cells: each hit ``hit_weight``, each near miss ``near_hit_weight``
        (matching shapes)."""
        return self.hit_weight * np.asarray(hits, dtype=float) + self.near_hit_weight * np.asarray(near, dtype=float)

    def misses(self, misses: ArrayLike, near: ArrayLike, path: ArrayLike = 0, surface: ArrayLike = 0) -> NDArray[np.float64]:
        """Weighted misses of cells: each miss one, each near miss (counted among `misses`)
        ``near_weight``, each surface miss (counted among `misses`, :func:`surface_misses`)
        ``surface_weight``, each step of the robot's path :data:`PATH_HITS` times ``hit_weight``
        (matching shapes)."""
        near = np.asarray(near, dtype=float)
        path_weight = PATH_HITS * self.hit_weight
        return (
            np.asarray(misses, dtype=float)
            + (self.near_weight - 1.0) * near
            + (self.surface_weight - 1.0) * np.asarray(surface, dtype=float)
            + path_weight * np.asarray(path, dtype=float)
        )

    def posterior_mean(self, p_gp: ArrayLike, hits: ArrayLike, misses: ArrayLike) -> NDArray[np.float64]:
        """The Beta-binomial posterior mean from the GP's probability, the weighted hits
        (:meth:`hits`) and the weighted misses (:meth:`misses`) (matching shapes), before
        :func:`with_surprises`."""
        wh = np.asarray(hits, dtype=float)
        return (wh + self.prior_weight * np.asarray(p_gp, dtype=float)) / (
            wh + np.asarray(misses, dtype=float) + self.prior_weight
        )

    def __call__(self, p_gp: ArrayLike, hits: ArrayLike, misses: ArrayLike) -> NDArray[np.float64]:
        """Cell probability: :meth:`posterior_mean` mixed with the surprise rate (:func:`with_surprises`)."""
        return with_surprises(self.posterior_mean(p_gp, hits, misses), self.surprise_rate)

    def apply(self, counted: Counted) -> NDArray[np.float64]:
        """The fusion stage (:class:`gpomap.stages.Stage`): the probability of each point's or
        cell's (any matching shapes) from the GP's and its weighted counts; where the cell has no
        count at all, the GP's probability for unseen space (when given) with the surprise rate.

        Parameters
        ----------
        counted : Counted
            The GP's probability and probability for unseen space, the weighted hits and
            misses (:meth:`hits`, :meth:`misses`) and the cells only beams that returned nothing
            reached.

        Returns
        -------
        ndarray
            The shape of ``counted.probability``.
        """
        p = self.with_silent(self(counted.probability, counted.hits, counted.misses), counted.silent)
        return _unseen_where_empty(p, counted.hits, counted.misses, counted.unseen, self.surprise_rate)

    def with_silent(self, p: NDArray[np.float64], silent: ArrayLike | None) -> NDArray[np.float64]:
        """`p` with the silent rate mixed in where `silent` (:attr:`silent_rate`; matching shapes)."""
        if silent is None or self.silent_mix == 0.0:
            return p
        return np.where(np.asarray(silent, dtype=bool), (1.0 - self.silent_mix) * p + self.silent_mix * self.silent_rate, p)

    @classmethod
    def fit(
        cls,
        p_gp: NDArray[np.float64],
        hits: NDArray[np.float64],
        misses: NDArray[np.float64],
        near: NDArray[np.float64],
        surface: NDArray[np.float64],
        occupied: NDArray[np.bool_],
        n_points: int | None = None,
        fit_surface: bool = True,
    ) -> EvidenceCalibration:
        """The five weights that maximise the likelihood of points, at the prior surprise rate.

        The points are a sample drawn at their natural frequencies from scans held out one at a
        time (:func:`fit_calibration`), each with the counts that the other scans made in its
        cell; a point of the sample no other scan counted has the GP's probability whatever the
        weights, so it is left out and counted in `n_points` alone.

        Parameters
        ----------
        p_gp : ndarray of shape (m,)
            The GP's probability at the counted points.
        hits, misses, near, surface : ndarray of shape (m,)
            The other scans' hits, misses, near misses and surface misses (:func:`surface_misses`)
            in each point's cell, unweighted.
        occupied : ndarray of bool, shape (m,)
        n_points : int, optional
            The sample's size with the points left out (default m): the loss is summed over the
            counted points and divided by it, the mean over the whole sample less a constant.
        fit_surface : bool
            Whether the surface miss's weight is fitted; else it is held at a miss's.

        Returns
        -------
        EvidenceCalibration
            Its surprise rate the prior's (:data:`SURPRISE_RATE`).
        """
        loss = _weights_loss(p_gp, hits, misses, near, surface, occupied, occupied.size if n_points is None else n_points)
        # Where surface misses are not weighed apart, their weight is held at a miss's.
        bounds = CALIBRATION_BOUNDS if fit_surface else (*CALIBRATION_BOUNDS[:4], (0.0, 0.0))
        # With the exact gradient and a tight tolerance the weights are the optimum's, not where a
        # search on finite differences stopped, which moved with the GP's round-off (tile factors of
        # another BLAS thread count; docs/choices.md, "Measured for the code").
        res = minimize(
            lambda theta: loss(cls(*np.exp(theta))),
            _log_start(),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"ftol": 1e-15, "gtol": 1e-10},
        )
        return cls(*(float(v) for v in np.exp(res.x)))


def _unseen_where_empty(
    p: NDArray[np.float64],
    hits: NDArray[np.float64],
    misses: NDArray[np.float64],
    p_unseen: NDArray[np.float64] | None,
    surprise_rate: float = SURPRISE_RATE,
) -> NDArray[np.float64]:
    """`p`, with `p_unseen` (mixed with `surprise_rate`, as the counted cells are) where a cell has
    no count at all (matching shapes): the GP's probability for unseen space as it is, near
    surfaces too (see :mod:`gpomap.fusion`)."""
    if p_unseen is None:
        return p
    return np.where((hits == 0) & (misses == 0), with_surprises(p_unseen, surprise_rate), p)


def _log_start() -> NDArray[np.float64]:
    """Where the search of :meth:`EvidenceCalibration.fit` starts, the log of each weight: the
    counting grid's weights, but for the near miss's hit weight: its floor (log space has no 0)."""
    default = EvidenceCalibration()
    return np.log(
        [default.hit_weight, default.prior_weight, default.near_weight, np.exp(CALIBRATION_BOUNDS[3][0]), default.surface_weight]
    )


def _weights_loss(
    p_gp: NDArray[np.float64],
    h: NDArray[np.float64],
    m: NDArray[np.float64],
    near: NDArray[np.float64],
    surface: NDArray[np.float64],
    occ: NDArray[np.bool_],
    n_points: int,
) -> Callable[[EvidenceCalibration], tuple[float, NDArray[np.float64]]]:
    """The log loss of points (:meth:`EvidenceCalibration.fit`'s, the sum over them divided by
    `n_points`) under a calibration, at the prior surprise rate, and its gradient in the log of
    each of the five weights."""

    def loss(cal: EvidenceCalibration) -> tuple[float, NDArray[np.float64]]:
        n0, a, b, g = cal.prior_weight, cal.near_weight, cal.near_hit_weight, cal.surface_weight
        wh = cal.hit_weight * h
        hits, weighted = cal.hits(h, near), cal.misses(m, near, surface=surface)
        q = cal.posterior_mean(p_gp, hits, weighted)
        p = with_surprises(q)
        den = hits + weighted + n0
        value = float(-np.sum(np.where(occ, np.log(p), np.log1p(-p))) / n_points)
        # d loss / dq (dp / dq = 1 - SURPRISE_RATE); then dq / dlog w, dlog n0, dlog a, dlog b, dlog g.
        dq = np.where(occ, -1.0 / p, 1.0 / (1.0 - p)) * (1.0 - SURPRISE_RATE) / n_points
        grad = np.array(
            [
                dq @ (wh * (1.0 - q) / den),
                dq @ (n0 * (p_gp - q) / den),
                dq @ (-a * near * q / den),
                dq @ (b * near * (1.0 - q) / den),
                dq @ (-g * surface * q / den),
            ]
        )
        return value, grad

    return loss


def surface_misses(misses: ArrayLike, near: ArrayLike, at_surface: ArrayLike) -> NDArray[np.float64]:
    """Surface misses of cells (:attr:`EvidenceCalibration.surface_weight`): their far misses
    (`misses` less `near`) where `at_surface` (a hit in the cell or next to it), else 0 (matching
    shapes)."""
    far = np.maximum(np.asarray(misses, dtype=float) - np.asarray(near, dtype=float), 0.0)
    return np.where(np.asarray(at_surface, dtype=bool), far, 0.0)


class CalibrationSample(NamedTuple):
    """A calibration's leave-one-scan-out points that other scans counted: the fitted
    calibration's probability at each (before any silent rate), its class, and whether only
    beams that returned nothing reached its cell (:func:`only_silent`) (each of shape (m,))."""

    probability: NDArray[np.float64] = np.zeros(0)
    occupied: NDArray[np.bool_] = np.zeros(0, dtype=bool)
    silent: NDArray[np.bool_] = np.zeros(0, dtype=bool)


# The map file names this class by its package (gpomap.io.mapfile), where it is found by that name
# (set here: a NamedTuple's body holds its fields only).
CalibrationSample.__module__ = "gpomap.fusion"


#: The map's GP fitted on some scans, its hyperparameters held, as a function from points of shape
#: (m, d) to its probability (m,): what :func:`fit_calibration` fits the surprise rate against.
GPApart = Callable[[ScanData], Callable[[NDArray[np.float64]], NDArray[np.float64]]]


def fit_calibration(
    scans: ScanData,
    evidence: RayEvidence,
    grid: AnyGrid,
    predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    n_scans: int = 25,
    step: float = 0.1,
    no_return_cap: float | None = MapConfig.no_return_cap,
    seed: int = 0,
    counts: RayCounts | None = None,
    gp_apart: GPApart | None = None,
) -> tuple[EvidenceCalibration, dict[str, float], CalibrationSample]:
    """Fit the hit, prior, near-miss (as a miss and as a surface) and surface-miss weights by leave-one-scan-out log likelihood, and the surprise rate.

    Parameters
    ----------
    scans : sequence of Scan
        The scans `evidence` was built from, in the same order.
    evidence : RayEvidence
    grid : GridSpec or VoxelSpec
        The lattice the counts are taken on.
    predict_gp : callable
        Points of shape (m, 2) to the GP's probability, shape (m,).
    n_scans : int
        Scans held out in turn (evenly spaced through the log).
    step : float
        Spacing of the free calibration points along each beam.
    no_return_cap : float or None
    seed : int
        Seed of the class-balancing subsample.
    counts : RayCounts, optional
        ``evidence.counts(grid)`` when the caller has it already.
    gp_apart : callable, optional
        The map's GP fitted, its hyperparameters held, on the scans it is given: the held-out
        scans' points were part of the GP's own training data, so a surprise among them (a
        visitor's hit) is one the GP already knows, and the surprise rate is fitted against this
        GP, which never saw them (:data:`FIT_SURPRISE_RATE`). Without it the rate is the prior.

    Returns
    -------
    calibration : EvidenceCalibration
    report : dict
        ``"n_points"`` in the balanced sample, ``"n_predicted"``: those other scans counted,
        where the GP was predicted, and their ``"log_loss"`` (the only points the weights
        change), before (the counting grid's weights, ``"log_loss_default"``) and after the fit;
        with `gp_apart`, the ``"surprise_rate"``.
    sample : CalibrationSample
        The fitted calibration's probabilities at the sample's points that other scans counted,
        their classes, and whether only the other scans' beams that returned nothing reached their
        cells (empty when nothing was fitted). The silent rate is not fitted here
        (:meth:`gpomap.fusion.EvidenceLayer.fit_revisit`).
    """
    whole = evidence.counts(grid) if counts is None else counts
    picked = calibration_scans(len(scans), n_scans)
    # A uniform sample keeps each class's share (docs/choices.md), drawn from the held-out scans'
    # points by number and made only where drawn; the counts are then looked up at the sample only.
    drawn = draw_calibration_points([scans[k] for k in picked], CALIBRATION_POINTS, seed, step, no_return_cap)
    default = EvidenceCalibration()
    if drawn.total == 0:
        return default, {"n_points": 0}, CalibrationSample()
    if drawn.n_occupied in (0, drawn.total):
        return default, {"n_points": drawn.total}, CalibrationSample()
    pts, occ, scan_of = drawn.points, drawn.occupied, picked[drawn.scan]
    fit_surface = FIT_SURFACE_WEIGHT.get(pts.shape[1], False)
    h, m, near, surface, quiet = _other_scans_counts(evidence, grid, whole, pts, scan_of, fit_surface)
    silent = only_silent(h, m, quiet)
    # A point no other scan counted (no hit, no miss) has p = p_gp whatever the weights: a constant
    # of the loss, so the GP is not predicted there (most of a point cloud's points; docs/3d.md).
    # The loss below is the whole sample's mean less that constant: the same minimiser, the same
    # optimiser steps.
    counted = (h > 0) | (m > 0)
    n_points = int(occ.size)
    if not counted.any():
        return default, {"n_points": n_points, "n_predicted": 0}, CalibrationSample()
    sample_pts, sample_occ = pts, occ
    occ, silent = occ[counted], silent[counted]
    h, m, near, surface = h[counted], m[counted], near[counted], surface[counted]
    p_gp = np.asarray(predict_gp(pts[counted]), dtype=float)
    # The weights are fitted at the prior surprise rate (with_surprises' default), the rate after them.
    fitted = EvidenceCalibration.fit(p_gp, h, m, near, surface, occ, n_points, fit_surface)
    loss = _weights_loss(p_gp, h, m, near, surface, occ, n_points)
    scale = n_points / occ.size  # from the sample's sum to the mean over the counted points
    report = {
        "n_points": n_points,
        "n_predicted": int(occ.size),
        "log_loss_default": loss(EvidenceCalibration(*np.exp(_log_start())))[0] * scale,
        "log_loss": loss(fitted)[0] * scale,
    }
    # A GP on fewer scans than were held out is not the map's GP: short logs keep the prior rate.
    if gp_apart is not None and FIT_SURPRISE_RATE.get(pts.shape[1], False) and len(scans) >= 2 * picked.size:
        # Every point of the sample, those no other scan counted at the GP's probability alone.
        held = set(picked.tolist())
        p_apart = np.asarray(gp_apart([s for i, s in enumerate(scans) if i not in held])(sample_pts), dtype=float)
        p_apart[counted] = fitted.posterior_mean(p_apart[counted], fitted.hits(h, near), fitted.misses(m, near, surface=surface))
        fitted = replace(fitted, surprise_rate=fit_surprise_rate(p_apart, sample_occ))
        report["surprise_rate"] = fitted.surprise_rate
    p = fitted(p_gp, fitted.hits(h, near), fitted.misses(m, near, surface=surface))
    return fitted, report, CalibrationSample(p, occ, silent)


def _other_scans_counts(
    evidence: RayEvidence,
    grid: AnyGrid,
    whole: RayCounts,
    points: NDArray[np.float64],
    scan_of: NDArray[np.intp],
    surface: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Hits, misses, near misses, surface misses and silent updates that the scans other than each point's own counted in its cell.

    Parameters
    ----------
    evidence : RayEvidence
    grid : GridSpec or VoxelSpec
    whole : RayCounts
        Every scan's counts on `grid`.
    points : ndarray of shape (n, d)
    scan_of : ndarray of int, shape (n,)
        The scan each point comes from, whose own counts are taken out.
    surface : bool
        Whether to find the surface misses (else they are 0).

    Returns
    -------
    hits, misses, near, surface, silent : ndarray of shape (n,)
        0 outside `grid`. Never below zero: a scan counted before the lattice grew can fall one
        cell apart when recounted on the grown one, for a beam ending exactly on a cell border
        (the two origins round differently), and a negative count would make the calibration's
        loss NaN and leave the weights at their defaults. `surface`: the far misses of cells
        that the other scans' hits put next to a surface (:func:`surface_misses`), so that a
        point's own hit does not make its neighbours' misses surface misses.
    """
    cell, inside = flat_index(grid, points)
    n = points.shape[0]
    hits, misses, near, surface_count, silent = (np.zeros(n) for _ in range(5))
    index = np.unravel_index(cell, grid.shape)
    whole_hits = whole.hits.reshape(-1)
    for k in np.unique(scan_of):
        sel = np.flatnonzero(scan_of == k)
        own = evidence.scan_counts_at(grid, int(k), cell[sel])
        for total, mine, dest in zip(whole, own, (hits, misses, near, silent), strict=True):
            dest[sel] = np.where(inside[sel], np.maximum(total.reshape(-1)[cell[sel]] - mine, 0), 0)
        if not surface:
            continue
        # The other scans' hits in each point's cell and its neighbours: all scans' less its own.
        at_surface = np.zeros(sel.size, dtype=bool)
        for step in itertools.product((-1, 0, 1), repeat=len(grid.shape)):
            nb = tuple(i[sel] + o for i, o in zip(index, step, strict=True))
            ok = inside[sel] & np.all([(j >= 0) & (j < m) for j, m in zip(nb, grid.shape, strict=True)], axis=0)
            flat = np.ravel_multi_index(tuple(np.where(ok, j, 0) for j in nb), grid.shape)
            others = whole_hits[flat] - evidence.scan_counts_at(grid, int(k), flat)[0]
            at_surface |= ok & (others > 0)
        surface_count[sel] = surface_misses(misses[sel], near[sel], at_surface)
    return hits, misses, near, surface_count, silent
