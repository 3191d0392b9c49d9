"""The GP map as the prior of a fine grid: the GP's probability updated by each cell's ray counts.

The GP is smooth and carries the map across gaps; the counts of :mod:`gpomap.evidence` are what
make walls as sharp as the cells where beams went. Each fine cell's probability is the posterior
mean of a Beta prior centred on the GP's probability p_gp, with n0 the prior's weight, updated by
its weighted hits and misses (:class:`EvidenceCalibration`):

    p = (hit_weight * hits + near_hit_weight * near misses + n0 * p_gp)
        / (hit_weight * hits + near_hit_weight * near misses + far misses
           + surface_weight * surface misses + near_weight * near misses + n0),

the far misses here those that are not surface misses (:func:`surface_misses`); each step of the
robot's path through a cell adds :data:`PATH_HITS` hits' worth of misses. Where no beam went, p
is the GP's probability for unseen space (:mod:`gpomap.extrapolation`); far from all data, 0.5.
Every probability is then mixed with a surprise rate (:func:`with_surprises`) and mapped
through a later visit's recalibration (:mod:`gpomap.revisit`).

The weights are fitted on the map's own scans, a sample of them held out in turn from the
counts (exact: counts add over scans), never on a test set (:func:`fit_calibration`). The GP's
own probability is not re-tempered there, as its points were the GP's training data, and its
variance scale for unseen space is kept to the cells it was fitted for. :class:`EvidenceLayer`
keeps the counts on a growing lattice, adds scans and writes grids.

Why each part, and what it was measured to be worth: docs/choices.md, "The map is the GP as the
prior of a fine grid" and the sections after it ("Shared updates", "Near misses", "A near miss is
part of a hit too", "A far miss beside a hit is weighed apart", "The robot's body round its
path"), "One observation in a hundred is a surprise" and "The map's probabilities for a later
visit"; for point clouds, docs/3d.md.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq, minimize

from gpomap.clouds import CloudScan
from gpomap.evidence import PATH_RADIUS, RayCounts, RayEvidence, lattice_grid, next_to_hits, path_steps
from gpomap.grid import CALIBRATED_THRESHOLDS, DEFAULT_THRESHOLDS, GridSpec, row_bands
from gpomap.heldout import calibration_points, calibration_scans
from gpomap.lattice import (
    AnyGrid,
    bounds_extent,
    cell_offset,
    coarse,
    column_bounds,
    extent_bounds,
    flat_index,
    grid_centres,
    grid_dim,
    grid_extent,
    interpolate,
    interpolation_block,
    overlap,
)
from gpomap.observations import ScanData, data_dim, natural_subsample
from gpomap.resources import WRITTEN_BAND_CELLS, SpillFile, release_freed_memory
from gpomap.revisit import RevisitCalibration
from gpomap.scans import Scan

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
FIT_SURPRISE_RATE: dict[int, bool] = {2: True, 3: False}


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


#: Where ray counts give a written grid its detail, the GP under them is sampled this many times
#: per length scale (at most :data:`MAX_GP_STEP_CELLS` output cells apart) and interpolated
#: bilinearly: a GP varies little within a third of its length scale, and its prediction is the
#: costly part of a fine grid.
GP_SAMPLES_PER_LENGTH_SCALE: int = 3
MAX_GP_STEP_CELLS: int = 4


def gp_sampling_factor(length_scale: float, resolution: float) -> int:
    """Output cells between GP samples of a written grid, from 1 (every cell) to :data:`MAX_GP_STEP_CELLS`."""
    step = length_scale / GP_SAMPLES_PER_LENGTH_SCALE
    return int(min(MAX_GP_STEP_CELLS, max(1, np.floor(step / resolution + 1e-9))))


#: Hits one step of the robot's path through a cell outweighs (as misses, :meth:`EvidenceCalibration.misses`).
#: The robot's body was there, which no beam can say; but a pose error or a cell shared with a
#: wall's edge should not be cleared outright. One hit's worth left the path cells that held a
#: few hits occupied; ten clear them (docs/choices.md, "The robot's body round its path").
PATH_HITS: float = 10.0

#: Whether the ternary map, per dimension of the data, never calls occupied a cell no beam ended in
#: (:func:`gpomap.grid.ternary`'s ``seen_through``), as neither occupancy grid would: one beams or
#: the robot crossed, or one nothing reached, that the map thinks likely occupied (a surface beside
#: it, the GP's guess) is unknown instead. Planar maps: grazing beams cross the cells in front of
#: walls, and unexplored space round a building takes the GP's guess (docs/choices.md). Point clouds
#: mark what no ray reached in their outputs instead (:attr:`gpomap.voxels.VoxelMap.observed`).
SEEN_THROUGH_NOT_OCCUPIED: dict[int, bool] = {2: True, 3: False}

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
FIT_SURFACE_WEIGHT: dict[int, bool] = {2: True, 3: False}


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
    """

    hit_weight: float = 1.0
    prior_weight: float = 2.0
    near_weight: float = 1.0
    near_hit_weight: float = 0.0
    surface_weight: float = 1.0
    surprise_rate: float = SURPRISE_RATE

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


def surface_misses(misses: ArrayLike, near: ArrayLike, at_surface: ArrayLike) -> NDArray[np.float64]:
    """Surface misses of cells (:attr:`EvidenceCalibration.surface_weight`): their far misses
    (`misses` less `near`) where `at_surface` (a hit in the cell or next to it), else 0 (matching
    shapes)."""
    far = np.maximum(np.asarray(misses, dtype=float) - np.asarray(near, dtype=float), 0.0)
    return np.where(np.asarray(at_surface, dtype=bool), far, 0.0)


def without_hits(hits: ArrayLike) -> NDArray[np.bool_]:
    """Cells no beam ended in (no `hits`), which the ternary map never calls occupied
    (:data:`SEEN_THROUGH_NOT_OCCUPIED`; the shape of `hits`)."""
    return np.asarray(hits) == 0


class CalibrationSample(NamedTuple):
    """A calibration's leave-one-scan-out points that other scans counted: the fitted
    calibration's probability at each, and its class (each of shape (m,))."""

    probability: NDArray[np.float64] = np.zeros(0)
    occupied: NDArray[np.bool_] = np.zeros(0, dtype=bool)


def ternary_thresholds(given: tuple[float, float] | None, evidence: EvidenceLayer | None) -> tuple[float, float]:
    """A map's ternary (free below, occupied above) thresholds on the probabilities it gives: those
    `given`, else a calibrated map's (with ray evidence, :data:`gpomap.grid.CALIBRATED_THRESHOLDS`),
    else the paper's (:data:`gpomap.grid.DEFAULT_THRESHOLDS`)."""
    if given is not None:
        return given
    return CALIBRATED_THRESHOLDS if evidence is not None else DEFAULT_THRESHOLDS


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
    no_return_cap: float | None = 10.0,
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
        and their classes (empty when nothing was fitted).
    """
    whole = evidence.counts(grid) if counts is None else counts
    picked = calibration_scans(len(scans), n_scans)
    pts_all, occ_all, scan_all = [], [], []
    for k in picked:
        pts, occ = calibration_points(scans[k], step, no_return_cap)
        if pts.size == 0:
            continue
        pts_all.append(pts)
        occ_all.append(occ)
        scan_all.append(np.full(occ.size, k, dtype=np.intp))
    default = EvidenceCalibration()
    if not pts_all:
        return default, {"n_points": 0}, CalibrationSample()
    pts, occ, scan_of = np.concatenate(pts_all), np.concatenate(occ_all), np.concatenate(scan_all)
    if occ.all() or not occ.any():
        return default, {"n_points": int(occ.size)}, CalibrationSample()
    # A uniform sample keeps each class's share (docs/choices.md); the counts are then looked up at the sample only.
    keep = natural_subsample(occ.size, CALIBRATION_POINTS, seed)
    pts, occ = pts[keep], occ[keep]
    fit_surface = FIT_SURFACE_WEIGHT.get(pts.shape[1], False)
    h, m, near, surface = _other_scans_counts(evidence, grid, whole, pts, scan_of[keep], fit_surface)
    # A point no other scan counted (no hit, no miss) has p = p_gp whatever the weights: a constant
    # of the loss, so the GP is not predicted there (most of a point cloud's points; docs/3d.md).
    # The loss below is the whole sample's mean less that constant: the same minimiser, the same
    # optimiser steps.
    counted = (h > 0) | (m > 0)
    n_points = int(occ.size)
    if not counted.any():
        return default, {"n_points": n_points, "n_predicted": 0}, CalibrationSample()
    sample_pts, sample_occ = pts, occ
    occ, h, m, near, surface = occ[counted], h[counted], m[counted], near[counted], surface[counted]
    p_gp = np.asarray(predict_gp(pts[counted]), dtype=float)

    def loss(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        cal = EvidenceCalibration(*np.exp(theta))
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

    # The weights are fitted at the prior surprise rate (with_surprises' default), the rate after them.
    # The counting grid's weights, but for the near miss's hit weight: its floor (log space has no 0).
    x0 = np.log(
        [default.hit_weight, default.prior_weight, default.near_weight, np.exp(CALIBRATION_BOUNDS[3][0]), default.surface_weight]
    )
    # Where surface misses are not weighed apart, their weight is held at a miss's.
    bounds = CALIBRATION_BOUNDS if fit_surface else (*CALIBRATION_BOUNDS[:4], (0.0, 0.0))
    # With the exact gradient and a tight tolerance the weights are the optimum's, not where a
    # search on finite differences stopped, which moved with the GP's round-off (tile factors of
    # another BLAS thread count; docs/choices.md, "Measured for the code").
    res = minimize(loss, x0, jac=True, method="L-BFGS-B", bounds=bounds, options={"ftol": 1e-15, "gtol": 1e-10})
    fitted = EvidenceCalibration(*(float(v) for v in np.exp(res.x)))
    scale = n_points / occ.size  # from the sample's sum to the mean over the counted points
    report = {
        "n_points": n_points,
        "n_predicted": int(occ.size),
        "log_loss_default": loss(x0)[0] * scale,
        "log_loss": float(res.fun) * scale,
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
    return fitted, report, CalibrationSample(p, occ)


def _other_scans_counts(
    evidence: RayEvidence,
    grid: AnyGrid,
    whole: RayCounts,
    points: NDArray[np.float64],
    scan_of: NDArray[np.intp],
    surface: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Hits, misses, near misses and surface misses that the scans other than each point's own counted in its cell.

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
    hits, misses, near, surface : ndarray of shape (n,)
        0 outside `grid`. Never below zero: a scan counted before the lattice grew can fall one
        cell apart when recounted on the grown one, for a beam ending exactly on a cell border
        (the two origins round differently), and a negative count would make the calibration's
        loss NaN and leave the weights at their defaults. `surface`: the far misses of cells
        that the other scans' hits put next to a surface (:func:`surface_misses`), so that a
        point's own hit does not make its neighbours' misses surface misses.
    """
    cell, inside = flat_index(grid, points)
    n = points.shape[0]
    hits, misses, near, surface_count = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    index = np.unravel_index(cell, grid.shape)
    whole_hits = whole.hits.reshape(-1)
    for k in np.unique(scan_of):
        sel = np.flatnonzero(scan_of == k)
        own = evidence.scan_counts_at(grid, int(k), cell[sel])
        for total, mine, dest in zip(whole, own, (hits, misses, near), strict=True):
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
    return hits, misses, near, surface_count


def _unseen_where_empty(
    p: NDArray[np.float64],
    hits: NDArray[np.float64],
    misses: NDArray[np.float64],
    p_unseen: NDArray[np.float64] | None,
    surprise_rate: float = SURPRISE_RATE,
) -> NDArray[np.float64]:
    """`p`, with `p_unseen` (mixed with `surprise_rate`, as the counted cells are) where a cell has
    no count at all (matching shapes): the GP's probability for unseen space as it is, near
    surfaces too (see the module docstring)."""
    if p_unseen is None:
        return p
    return np.where((hits == 0) & (misses == 0), with_surprises(p_unseen, surprise_rate), p)


#: A planar written map's GP variance is predicted this many GP samples apart and interpolated;
#: its mean at every sample. The variance is what a tile's prediction costs (the whitened
#: cross-covariances, n^2 per point against n for the mean), and it varies over the distance to
#: the data, not over the walls' detail that the mean and the counts carry.
VARIANCE_STEP_SAMPLES: int = 2


class BlendedMoments(Protocol):
    """A GP map's calibrated latent moments and their squash (:class:`gpomap.tiles.TiledGPOM`)."""

    def blended_moments(
        self, points: NDArray[np.float64], variance: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64] | None]: ...

    def squash_moments(
        self, num: NDArray[np.float64], den: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def forget_below(self, y: float) -> None: ...


def _variance_apart(moments: BlendedMoments, sampled: AnyGrid) -> tuple[NDArray[np.float64], ...]:
    """The GP's probability, latent variance and probability for unseen space at `sampled`'s
    centres, each (size,), the variances predicted :data:`VARIANCE_STEP_SAMPLES` samples apart."""
    num, _, _, _ = moments.blended_moments(grid_centres(sampled), variance=False)
    apart = coarse(sampled, VARIANCE_STEP_SAMPLES)
    _, den_apart, _, var_apart = moments.blended_moments(grid_centres(apart))
    assert den_apart is not None and var_apart is not None
    den = interpolate(den_apart, apart, sampled).reshape(-1)
    p, p_unseen = moments.squash_moments(num, den)
    return p, interpolate(var_apart, apart, sampled).reshape(-1), p_unseen


def _predict_block(
    predict_gp: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], ...]],
    centres: NDArray[np.float64],
    sampled: AnyGrid,
    block: tuple[slice, ...],
) -> tuple[NDArray[np.float64], ...]:
    """`predict_gp` at the centres of `block` of `sampled` only, each result of shape sampled.shape.

    The cells outside the block (the :func:`~gpomap.lattice.coarse` lattice's outer samples,
    which the interpolation reads with weight 0 or not at all; their share is in docs/3d.md)
    take their nearest block cell's values, so that they are finite and the interpolated grid is
    the same as with every sample predicted.

    Parameters
    ----------
    predict_gp : callable
        Points (m, d) to arrays of shape (m,).
    centres : ndarray of shape (sampled size, d)
        `sampled`'s cell centres in row-major order (:func:`~gpomap.lattice.grid_centres`).
    sampled : GridSpec or VoxelSpec
    block : tuple of slice
        One per array axis (:func:`~gpomap.lattice.interpolation_block`).
    """
    d = centres.shape[1]
    inner = centres.reshape(*sampled.shape, d)[block].reshape(-1, d)
    shape = tuple(s.stop - s.start for s in block)
    pad = [(s.start, n - s.stop) for s, n in zip(block, sampled.shape, strict=True)]
    return tuple(np.pad(np.asarray(v, dtype=float).reshape(shape), pad, mode="edge").reshape(-1) for v in predict_gp(inner))


#: How far (metres) the counted lattice reaches beyond the beams when scans arrive outside it: the
#: counts are copied into a larger array then, so a margin keeps that rare as the robot drives on.
LATTICE_GROWTH: float = 10.0

#: The robot's path passes per lattice cell are 16-bit while fewer scans than this are counted: a
#: cell is passed at most once per step of the path, so none can overflow, and a building's lattice
#: (tens of millions of cells) takes half the memory of 32-bit counts. A log that grows past it (a
#: long stream) widens them to 32 bits.
NARROW_COUNT_SCANS: int = 2**16 - 1

#: The type of the lattice's ray counts: shares of one update per scan (:func:`gpomap.evidence.scan_shares`).
COUNT_DTYPE: type[np.floating[Any]] = np.float32


def path_dtype(n_scans: int) -> type[np.integer[Any]]:
    """The lattice's path-pass type for `n_scans` scans: uint16 below :data:`NARROW_COUNT_SCANS`, else int32."""
    return np.uint16 if n_scans < NARROW_COUNT_SCANS else np.int32


class EvidenceLayer:
    """Ray counts and their calibration, applied on top of a fitted GP map.

    Counts add over scans, so new scans are counted on their own and added in
    (:meth:`add_scans`, at a cost proportional to the new beams); the calibration is refitted
    only when asked (:meth:`recalibrate`). Counts taken so equal counts taken at once, except
    where a beam ends exactly on a cell border, which lattices of different origins may round
    to either side (seen only in simulated worlds with walls on multiples of the cell side).

    Parameters
    ----------
    scans : sequence of Scan, or sequence of CloudScan
        The scans the GP was fitted on.
    resolution : float
        Side of the fine cells the counts of exact-point predictions are taken on, metres.
    predict_gp : callable
        Points of shape (m, 2) to the GP's probability, shape (m,) (used to calibrate).
    no_return_cap : float or None
    calibration_scans : int
        Scans held out in turn to fit the calibration.
    seed : int
    gp_apart : callable, optional
        The GP fitted on given scans, its hyperparameters held, that every calibration fits the
        surprise rate against (:func:`fit_calibration`); without it the rate is the prior.
    calibration : EvidenceCalibration, optional
        Taken as it is instead of fitted (a map of part of a log, calibrated as the whole log's).
    """

    def __init__(
        self,
        scans: ScanData,
        resolution: float,
        predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]],
        no_return_cap: float | None = 10.0,
        calibration_scans: int = 25,
        seed: int = 0,
        gp_apart: GPApart | None = None,
        calibration: EvidenceCalibration | None = None,
    ) -> None:
        self.resolution = float(resolution)
        self.gp_apart = gp_apart
        self._at_surface: NDArray[np.bool_] | None = None  # next_to_hits of the counts so far, when asked
        self.no_return_cap = no_return_cap
        self.calibration_scans = int(calibration_scans)
        self.seed = int(seed)
        self.calibration = EvidenceCalibration()
        self.report: dict[str, float] = {}
        self.sample = CalibrationSample()
        self.revisit = RevisitCalibration()
        self._scans: list[Scan | CloudScan] = []
        self._parts: list[RayEvidence] = []
        self._joined: RayEvidence | None = None
        self._dim = 2  # of the scans counted (set by add_scans)
        self.lattice: AnyGrid | None = None
        # Counts per lattice cell (COUNT_DTYPE) and the path's passes (path_dtype: 16-bit for most logs).
        self._hits: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._beam_misses: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._near_misses: NDArray[np.floating[Any]] = np.zeros((0, 0), dtype=COUNT_DTYPE)
        self._path: NDArray[np.integer[Any]] = np.zeros((0, 0), dtype=np.int32)
        self._grid_cache: tuple[AnyGrid, RayCounts, NDArray[np.integer[Any]], NDArray[np.bool_]] | None = None
        self.add_scans(scans)
        if calibration is None:
            self.recalibrate(predict_gp)
        else:
            self.calibration, self.report = calibration, {"given": 1.0}
            for part in self._parts:
                part.forget()

    # ------------------------------------------------------------------ counting
    @property
    def n_scans(self) -> int:
        """Scans counted so far."""
        return len(self._scans)

    @property
    def evidence(self) -> RayEvidence:
        """The beams and path of every scan counted, as one :class:`RayEvidence`."""
        if self._joined is None and len(self._parts) == 1:
            # One part is its own join, with the cells its counts kept for the calibration.
            self._joined = self._parts[0]
        if self._joined is None:
            offsets = np.cumsum([0] + [p.n_scans for p in self._parts[:-1]])
            parts = self._parts
            self._joined = RayEvidence(
                np.concatenate([p.starts for p in parts]).reshape(-1, self._dim),
                np.concatenate([p.ends for p in parts]).reshape(-1, self._dim),
                np.concatenate([p.hit for p in parts]).astype(bool),
                np.concatenate([p.scan + o for p, o in zip(parts, offsets)]).astype(np.intp),
                np.concatenate([p.path for p in parts]).reshape(-1, 2 * self._dim),
            )
            self._parts = [self._joined]
        return self._joined

    def add_scans(self, scans: ScanData) -> None:
        """Count the beams of `scans` (and the path to them from the last scan) and add them in.

        Parameters
        ----------
        scans : sequence of Scan
            Scans that follow those counted so far, in order.
        """
        scans = list(scans)
        if not scans:
            return
        part = RayEvidence.from_scans(scans, self.no_return_cap)
        d = self._dim = data_dim(scans)
        if self._scans:
            # The step from the last scan counted to the first new one is part of the path too.
            link = path_steps([self._scans[-1], scans[0]]).reshape(-1, 2 * d)
            part = RayEvidence(part.starts, part.ends, part.hit, part.scan, np.concatenate([link, part.path]))
        pts = np.concatenate([part.starts, part.ends, part.path[:, :d], part.path[:, d:]])
        if pts.size == 0:
            self._scans.extend(scans)
            self._parts.append(part)
            self._joined = None
            return
        # The margin holds the robot's body round a path at the data's edge.
        margin = self.resolution + PATH_RADIUS
        local = lattice_grid(bounds_extent(*column_bounds(pts)), self.resolution, margin=margin)
        self._cover(local, path_dtype(len(self._scans) + len(scans)))
        # The first scans' counts are on the lattice itself: the calibration's held-out scans keep
        # their cells, so their leave-one-scan-out counts need no second traversal.
        keep = calibration_scans(len(scans), self.calibration_scans) if not self._scans else None
        assert self.lattice is not None
        block = self._block(local)
        if local.shape == self.lattice.shape and all(b.start == 0 for b in block):
            # The lattice is the new scans' own: counted into it, not beside it (a building's
            # lattice is tens of millions of cells, each array of them hundreds of megabytes).
            part.counts(local, keep=keep, out=RayCounts(self._hits, self._beam_misses, self._near_misses))
            part.path_passes(local, out=self._path)
        else:
            counts = part.counts(local, keep=keep)
            for total, new in zip((self._hits, self._beam_misses, self._near_misses), counts, strict=True):
                window = total[block]
                np.add(window, new, out=window, casting="unsafe")
            del counts
            passes = self._path[block]
            np.add(passes, part.path_passes(local), out=passes, casting="unsafe")
        self._scans.extend(scans)
        self._parts.append(part)
        self._joined = None
        self._grid_cache = None
        self._at_surface = None

    def _block(self, grid: AnyGrid) -> tuple[slice, ...]:
        """The slices of the lattice's arrays that `grid` (on the same cell lattice) covers."""
        assert self.lattice is not None
        return tuple(slice(o, o + n) for o, n in zip(cell_offset(grid, self.lattice), grid.shape, strict=True))

    def _cover(self, local: AnyGrid, path: Any = np.int32) -> None:
        """Grow the counted lattice (a copy, with :data:`LATTICE_GROWTH` to spare) to hold `local`,
        its path's passes of type `path` (:func:`path_dtype`) or wider."""
        if self.lattice is None:
            self.lattice = local
            self._hits = np.zeros(local.shape, dtype=COUNT_DTYPE)
            self._beam_misses = np.zeros(local.shape, dtype=COUNT_DTYPE)
            self._near_misses = np.zeros(local.shape, dtype=COUNT_DTYPE)
            self._path = np.zeros(local.shape, dtype=path)
            return
        if np.iinfo(path).max > np.iinfo(self._path.dtype).max:
            self._path = self._path.astype(path)
        offset = cell_offset(local, self.lattice)
        if all(o >= 0 and o + n <= m for o, n, m in zip(offset, local.shape, self.lattice.shape, strict=True)):
            return
        (alo, ahi), (blo, bhi) = extent_bounds(grid_extent(self.lattice)), extent_bounds(grid_extent(local))
        inner = self.resolution / 2  # the old edges, pulled in half a cell so they stay on the lattice
        union = bounds_extent(np.minimum(alo + inner, blo), np.maximum(ahi - inner, bhi))
        grown = lattice_grid(union, self.resolution, margin=LATTICE_GROWTH)
        old = self.lattice
        self.lattice = grown
        block = self._block(old)
        for name in ("_hits", "_beam_misses", "_near_misses", "_path"):
            arr = np.zeros(grown.shape, dtype=getattr(self, name).dtype)
            arr[block] = getattr(self, name)
            setattr(self, name, arr)

    def recalibrate(self, predict_gp: Callable[[NDArray[np.float64]], NDArray[np.float64]]) -> None:
        """Refit the calibration's five weights and surprise rate on the scans counted so far (see :func:`fit_calibration`).

        Parameters
        ----------
        predict_gp : callable
            Points of shape (m, 2) to the GP's probability, shape (m,).
        """
        if self.lattice is None:
            self.calibration, self.report, self.sample = EvidenceCalibration(), {"n_points": 0}, CalibrationSample()
            return
        self.calibration, self.report, self.sample = fit_calibration(
            self._scans,
            self.evidence,
            self.lattice,
            predict_gp,
            self.calibration_scans,
            2 * self.resolution,
            self.no_return_cap,
            self.seed,
            counts=RayCounts(self._hits, self._beam_misses, self._near_misses),
            gp_apart=self.gp_apart,
        )
        # A cached grid's surface cells were found (or not) for the calibration before.
        self._grid_cache = None
        for part in self._parts:
            part.forget()

    # ------------------------------------------------------------------ applying
    def counts_at(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weighted hits (:meth:`EvidenceCalibration.hits`) and weighted misses
        (:meth:`EvidenceCalibration.misses`, path included) of the fine cell holding each point (0
        outside the counted area)."""
        if self.lattice is None:
            n = np.asarray(points).shape[0]
            return np.zeros(n), np.zeros(n)
        cell, inside = flat_index(self.lattice, points)
        hits, beam, near, path = (a.reshape(-1)[cell] for a in (self._hits, self._beam_misses, self._near_misses, self._path))
        surface = surface_misses(beam, near, self.at_surface().reshape(-1)[cell]) if self._weighs_surface() else 0.0
        return np.where(inside, self.calibration.hits(hits, near), 0.0), np.where(
            inside, self.calibration.misses(beam, near, path, surface), 0.0
        )

    def _weighs_surface(self) -> bool:
        """Whether the calibration weighs surface misses apart from other misses (else they need not be found)."""
        return self.calibration.surface_weight != 1.0

    def at_surface(self) -> NDArray[np.bool_]:
        """Cells of the counted lattice a beam ended in or next to one (:func:`gpomap.evidence.next_to_hits`), shape lattice.shape."""
        if self._at_surface is None or self._at_surface.shape != self._hits.shape:
            self._at_surface = next_to_hits(self._hits)
        return self._at_surface

    def proba(
        self, points: NDArray[np.float64], p_gp: NDArray[np.float64], p_unseen: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Probability at points, ndarray of shape (m,), from the GP's probability there.

        `p_unseen`, the GP's probability for unseen space, is taken where no beam (and no step of
        the path) crossed the point's cell; default `p_gp`.
        """
        h, m = self.counts_at(points)
        p = _unseen_where_empty(self.calibration(p_gp, h, m), h, m, p_unseen, self.calibration.surprise_rate)
        return self.revisit(p)

    def seen_through_at(self, points: NDArray[np.float64]) -> NDArray[np.bool_] | None:
        """Whether no beam ended in the fine cell holding each point (True outside the counted
        area), shape (m,); None where the ternary map does not use it (:data:`SEEN_THROUGH_NOT_OCCUPIED`)."""
        if not SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False):
            return None
        if self.lattice is None:
            return np.ones(np.asarray(points).shape[0], dtype=bool)
        cell, inside = flat_index(self.lattice, points)
        return ~inside | without_hits(self._hits.reshape(-1)[cell])

    def grid_seen_through(self, grid: AnyGrid) -> NDArray[np.bool_] | None:
        """:meth:`seen_through_at` per cell of `grid`, counted on its own cells (the counts of
        :meth:`grid_counts`, cached), shape grid.shape; None where not used."""
        if not SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False):
            return None
        if self._grid_cache is None or self._grid_cache[0] != grid:
            self._grid_cache = (grid, *self._raw_grid_counts(grid))
        _, counts, _, _ = self._grid_cache
        return without_hits(counts.hits)

    def _on_lattice(self, grid: AnyGrid) -> bool:
        """Whether `grid`'s cells are cells of the counted lattice (same side, origin on a corner)."""
        if self.lattice is None or not math.isclose(grid.resolution, self.resolution, rel_tol=1e-12):
            return False
        d = (np.asarray(grid.origin) - np.asarray(self.lattice.origin)) / self.resolution
        return bool(np.all(np.abs(d - np.round(d)) < 1e-6))

    def _raw_grid_counts(self, grid: AnyGrid) -> tuple[RayCounts, NDArray[np.integer[Any]], NDArray[np.bool_]]:
        """The beams' counts, the path's passes and the cells at a surface
        (:func:`gpomap.evidence.next_to_hits`) per cell of `grid`."""
        if not self._on_lattice(grid):
            counts = self.evidence.counts(grid)
            at_surface = next_to_hits(counts.hits) if self._weighs_surface() else np.zeros(grid.shape, dtype=bool)
            return counts, self.evidence.path_passes(grid), at_surface
        # The grid's cells are lattice cells: read the running counts (zero beyond them), and
        # whether a cell is at a surface from the whole lattice's hits, its window's edges too.
        assert self.lattice is not None
        out = [np.zeros(grid.shape, dtype=COUNT_DTYPE) for _ in range(3)]
        path = np.zeros(grid.shape, dtype=np.int32)
        at_surface = np.zeros(grid.shape, dtype=bool)
        where = overlap(cell_offset(grid, self.lattice), grid.shape, self.lattice.shape)
        if where is not None:
            for o, a in zip((*out, path), (self._hits, self._beam_misses, self._near_misses, self._path), strict=True):
                o[where[0]] = a[where[1]]
            if self._weighs_surface():
                at_surface[where[0]] = self.at_surface()[where[1]]
        return RayCounts(*out), path, at_surface

    def grid_observed(self, grid: AnyGrid) -> NDArray[np.bool_]:
        """Cells of `grid` a ray crossed or ended in, or the robot's path passed, shape grid.shape."""
        hits, misses = self.grid_counts(grid)
        return np.asarray((hits + misses) > 0)

    def grid_counts(self, grid: AnyGrid) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weighted hits (:meth:`EvidenceCalibration.hits`) and weighted misses
        (:meth:`EvidenceCalibration.misses`, path included) per cell of `grid`, counted on that
        grid's own cells (the last is cached)."""
        if self._grid_cache is None or self._grid_cache[0] != grid:
            self._grid_cache = (grid, *self._raw_grid_counts(grid))
        _, counts, path, at_surface = self._grid_cache
        surface = surface_misses(counts.misses, counts.near, at_surface)
        return self.calibration.hits(counts.hits, counts.near), self.calibration.misses(counts.misses, counts.near, path, surface)

    def grid_proba(
        self, grid: AnyGrid, p_gp: NDArray[np.float64], p_unseen: NDArray[np.float64] | None = None
    ) -> NDArray[np.float64]:
        """Probability per cell of `grid`, shape grid.shape, from the GP's probabilities per cell (see :meth:`proba`)."""
        h, m = self.grid_counts(grid)
        unseen = None if p_unseen is None else np.asarray(p_unseen).reshape(grid.shape)
        p = self.calibration(np.asarray(p_gp).reshape(grid.shape), h, m)
        return self.revisit(_unseen_where_empty(p, h, m, unseen, self.calibration.surprise_rate))

    def written_grid(
        self,
        grid: AnyGrid,
        length_scale: float,
        predict_gp: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
        moments: BlendedMoments | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """Probability and latent variance per cell of `grid`, each of shape grid.shape, and the
        cells beams saw through (:meth:`grid_seen_through`, or None).

        The counts give each cell its detail; the smooth GP under them is sampled more coarsely
        (:func:`gp_sampling_factor`) and interpolated (bi- or trilinearly). A planar grid of more
        than :data:`WRITTEN_BAND_CELLS` cells is built in bands of rows, each on the GP samples
        the whole grid would take (the band's rows a whole number of variance samples): the
        same map, up to the local prediction's tolerance and the round-off of the samples'
        coordinates. That round-off can turn which of two tiles' cores is nearer to a sample
        no tile reaches, when they are as near to it (the nearest predicts it alone), which moves
        a few cells far from the data (docs/choices.md, "The written map in bands of rows").

        Parameters
        ----------
        grid : GridSpec or VoxelSpec
        length_scale : float
            The GP's length scale, metres.
        predict_gp : callable
            Points of shape (m, d) to the GP's probability, its latent variance and its probability
            for unseen space, each (m,).
        moments : BlendedMoments, optional
            The same GP's moments: a planar grid then takes the GP's variance
            :data:`VARIANCE_STEP_SAMPLES` samples apart instead of `predict_gp` at every sample.
        """
        factor = gp_sampling_factor(length_scale, grid.resolution)
        if not isinstance(grid, GridSpec):
            return self._written_block(grid, factor, predict_gp, moments)
        ny, nx = grid.shape
        unit = factor * VARIANCE_STEP_SAMPLES
        rows = max(unit, WRITTEN_BAND_CELLS // nx // unit * unit)
        if ny <= rows:
            return self._written_block(grid, factor, predict_gp, moments)
        seen = SEEN_THROUGH_NOT_OCCUPIED.get(self._dim, False)
        # Each band's rows wait in a temporary file until the last band is done, so the whole
        # grid (16 bytes a cell) and one band's temporaries are never in memory together
        # (docs/choices.md, "Measured for the code").
        done = SpillFile()
        bands: list[tuple[int, int, tuple[int, int], tuple[int, int], tuple[int, int] | None]] = []
        # Cells off the counted lattice are counted afresh, a traversal of every beam: once for
        # the whole grid (16 bytes a cell), not once per band.
        whole = None if self._on_lattice(grid) else self._raw_grid_counts(grid)
        for start, stop, band in row_bands(grid, rows):
            if whole is not None:
                counts, path, at_surface = whole
                self._grid_cache = (band, RayCounts(*(c[start:stop] for c in counts)), path[start:stop], at_surface[start:stop])
            p, var, seen_band = self._written_block(band, factor, predict_gp, moments)
            rows_of = (stop - start, *grid.shape[1:])
            kept = (
                done.put(np.broadcast_to(np.asarray(seen_band, dtype=bool), rows_of)) if seen and seen_band is not None else None
            )
            cells = (np.broadcast_to(np.asarray(a, dtype=np.float64), rows_of) for a in (p, var))
            bands.append((start, stop, done.put(next(cells)), done.put(next(cells)), kept))
            del p, var, seen_band
            if moments is not None:
                # The next band's GP samples, and its variance's, reach at most 4.5 samples below its rows.
                moments.forget_below(grid.origin[1] + (stop - 3 * unit) * grid.resolution)
            release_freed_memory()  # the band's tiles' inverses, freed among what the map keeps
        if moments is not None:
            moments.forget_below(np.inf)
        self._grid_cache = None  # the last band's counts: of no use to the next grid
        self._at_surface = None  # a bool a lattice cell, found again when asked
        whole = None
        release_freed_memory()
        probability, variance = np.empty(grid.shape), np.empty(grid.shape)
        seen_through = np.zeros(grid.shape, dtype=bool) if seen else None
        for start, stop, p_at, var_at, seen_at in bands:
            done.read_into(p_at, probability[start:stop])
            done.read_into(var_at, variance[start:stop])
            if seen_through is not None and seen_at is not None:
                done.read_into(seen_at, seen_through[start:stop])
        done.close()
        return probability, variance, seen_through

    def _written_block(
        self,
        grid: AnyGrid,
        factor: int,
        predict_gp: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
        moments: BlendedMoments | None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """:meth:`written_grid` of a grid in one piece, its GP sampled every `factor` cells."""
        sampled = coarse(grid, factor)
        block = interpolation_block(sampled, grid)
        if grid_dim(grid) == 3 and all(s.stop > s.start for s in block):
            p, var, p_unseen = _predict_block(predict_gp, grid_centres(sampled), sampled, block)
        elif moments is not None and grid_dim(grid) == 2:
            p, var, p_unseen = _variance_apart(moments, sampled)
        else:
            # Every sample, the planar margins too: the tiles' local prediction bins the queries
            # it is given, so another set of queries moves the values by round-off (and a plane's
            # margins are a few rows of hundreds).
            p, var, p_unseen = predict_gp(grid_centres(sampled))
        probability = self.grid_proba(grid, interpolate(p, sampled, grid), interpolate(p_unseen, sampled, grid))
        return probability, interpolate(var, sampled, grid), self.grid_seen_through(grid)

    def summary(self) -> dict[str, float]:
        """The calibration and how it was fitted."""
        c = self.calibration
        return {
            "hit_weight": c.hit_weight,
            "prior_weight": c.prior_weight,
            "near_weight": c.near_weight,
            "near_hit_weight": c.near_hit_weight,
            "surface_weight": c.surface_weight,
            **self.report,
            "surprise_rate": c.surprise_rate,
            "revisit_slope": self.revisit.slope,
            "revisit_shift": self.revisit.shift,
        }
