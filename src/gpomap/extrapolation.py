"""How sure the GP may be where no beam went: its variance scale, fitted on held-out stretches of the log.

The probit squash is fitted on leave-one-out moments of the cells (:mod:`gpomap.squash`). A cell
left out has its neighbours on every side, so those moments describe interpolation, and the
squash comes out sure of itself (alpha often at its cap). Where no beam went, behind a wall or in
a room seen only later, the GP extrapolates, and its latent variance there understates how wrong
its mean can be: before this step, maps called unseen space confidently occupied or free
(docs/choices.md, "Where no beam went").

So the squash gets one more parameter, a variance scale kappa:

    p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 kappa v)),

fitted where the question is the same as a user's: the log's scans are cut into contiguous
stretches, every third stretch is held out, a GP with the map's hyperparameters is fitted on the
rest, and kappa maximises the likelihood of the held-out stretches' hits and free points (the
evaluation protocol's points, at their natural frequencies) that lie where no kept beam went. Near the data the
latent variance is small and kappa changes little; far from it p tends to 1/2 sooner. Kappa is
all that is fitted: unseen space next to where beams ended gets no gain of its own, which fitted
on held-out points at their natural frequencies came out nil (docs/choices.md).

To bound the cost, the held-in GP covers one square region of side ``2 * region_half`` round a
given centre (the hyperparameter sample's), and only points well inside it are used; where it
holds fewer than :data:`REGION_POINTS_PER_CLASS` of a class, a wider square is taken, and where
that holds too few as well, a square of the first's size where the held-out stretches saw most
new ground next to what the kept ones saw (:func:`~gpomap.unseen.new_ground_centre`: a robot that passes the
sample's square in every stretch leaves no unseen point there). When one pattern of held-out
stretches finds too few such points of a class, the other two patterns (the stretches after, then
the rest) are tried in turn and their points pooled, each with its own held-in GP: a robot that
enters new space only once in its log is unseen in one pattern alone (the logs where each case
arose: docs/choices.md, "Where no beam went" and its subsections). With too few points in
all three (a short log, a robot that never left one room), kappa stays 1; so it does for voxel
maps (:data:`FIT_VARIANCE_SCALE`), whose few frames' held-out stretches fitted it to their cost.
The points themselves (the held-out points where no kept beam went, the kept scans' points in a
square, where new ground was seen) are made by :mod:`gpomap.unseen`; this module fits kappa on them.

The squash with its variance scale is the map's first fitted stage (:mod:`gpomap.stages`):
:class:`VarianceScale`, fitted on the unseen points (:meth:`VarianceScale.fit`) and applied to the
GP's calibrated moments (:meth:`VarianceScale.apply`), which a tiled map blends over its tiles.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize_scalar
from scipy.special import log_ndtr, ndtr

from gpomap.config import PROFILES, MapConfig
from gpomap.errors import EmptyDataError
from gpomap.heldout import FOLD_STARTS, HOLDOUT_EVERY, holdout_stretches
from gpomap.lattice import column_bounds
from gpomap.observations import Observations, ScanPoints, natural_subsample

# Each "name as name" import keeps a name importable from here, its first home: the points where
# no kept beam went, and their memory budget, are gpomap.unseen's now.
from gpomap.resources import POINT_MEMORY as POINT_MEMORY
from gpomap.resources import release_freed_memory
from gpomap.squash import unseen_probit
from gpomap.stages import CalibratedMoments, GPProbability
from gpomap.unseen import NEW_HIT_DISTANCE as NEW_HIT_DISTANCE
from gpomap.unseen import UNSEEN_RESOLUTION as UNSEEN_RESOLUTION
from gpomap.unseen import PointSource, _kept_region, _observes_both, _source, _unseen_points, _UnseenPoints, new_ground_centre
from gpomap.unseen import _HeldPoints as _HeldPoints
from gpomap.unseen import _SquareLattice as _SquareLattice
from gpomap.unseen import region_observations as region_observations

#: Whether a map of this dimension fits kappa (voxel maps keep the GP's own variance, kappa = 1).
FIT_VARIANCE_SCALE: dict[int, bool] = {d: p.fit_variance_scale for d, p in PROFILES.items()}
#: Fewest held-out points of each class where no kept beam went for kappa to be fitted.
MIN_POINTS_PER_CLASS: int = 50
#: Most points used, drawn uniformly so each class keeps its share (the held-in GP's prediction at
#: them is the cost).
MAX_POINTS: int = 10_000
#: Search bounds of kappa.
VARIANCE_SCALE_BOUNDS: tuple[float, float] = (0.1, 1e4)
#: Fewest held-out points of each class where no kept beam went for the held-in GP's square round
#: the hyperparameter sample to be enough; with fewer, a square twice as wide is taken (or the
#: whole map, when that is smaller). Kappa needs few.
REGION_POINTS_PER_CLASS: int = 500


def _nll(
    kappa: float, mu: NDArray[np.float64], var: NDArray[np.float64], occupied: NDArray[np.bool_], alpha: float, beta: float
) -> float:
    """Mean negative log probit likelihood at variance scale `kappa`. The probit is the map's
    where no beam went before its cut of the lean towards free
    (:func:`gpomap.squash.unseen_probit`), which is a prior, not fitted."""
    z = unseen_probit(alpha * mu + beta, alpha * alpha * var, kappa)
    return float(-np.mean(np.where(occupied, log_ndtr(z), log_ndtr(-z))))


def whole_map_region(points: NDArray[np.float64] | ScanPoints) -> tuple[NDArray[np.float64], float]:
    """Centre (x, y) and half side of a square holding every point (n, d) with a metre to spare.

    A held-in GP over it has the whole map, so no point is near an edge the data do not have
    (``margin`` 0 in :func:`fit_variance_scale`).
    """
    if isinstance(points, ScanPoints):
        lo, hi = points.lower[:2], points.upper[:2]
    else:
        lo, hi = column_bounds(np.asarray(points, dtype=float)[:, :2])
    return 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 1.0


def fit_variance_scale(
    scans: Sequence[Any],
    hyperparameters: dict[str, float],
    observations: Observations | ScanPoints | PointSource,
    free_clearance: float,
    fit_held_in: Callable[[Observations], Any],
    centre: NDArray[np.float64],
    region_half: float,
    margin: float,
    no_return_cap: float | None = MapConfig.no_return_cap,
    seed: int = 0,
    wider: tuple[NDArray[np.float64], float, float] | None = None,
) -> tuple[float, dict[str, Any]]:
    """Fit kappa on held-out stretches of `scans` (see the module docstring).

    Parameters
    ----------
    scans : sequence of Scan or CloudScan
        The map's scans, in log order.
    hyperparameters : dict
        The map's variance, length_scale, noise, alpha and beta (kept fixed).
    observations : Observations, ScanPoints or PointSource
        The map's labelled points from `scans` (its free step, ...), before the clearance, what
        makes them again a square at a time, or the points as a map filed them
        (:class:`gpomap.unseen.PointSource`); each pattern's held-in points are cut from them
        (:func:`region_observations`).
    free_clearance : float
        The map's free clearance, metres.
    fit_held_in : callable
        The kept scans' points in the region to a GP fitted on them with `hyperparameters` (the
        map's engine, no ray evidence), whose ``predict(points, return_var=True)`` gives the
        latent mean and variance.
    centre : ndarray of shape (2,)
        Centre of the square region (x, y); in 3-D the region is a column.
    region_half : float
        Half the region's side, metres.
    margin : float
        Points closer than this to the region's edge are not used (the held-in GP has no data
        beyond the edge, so they would look unseen when they are not).
    no_return_cap : float or None
        As the map's.
    seed : int
        Seeds the class-balancing subsample.
    wider : (centre, region_half, margin), optional
        A wider region, tried when the first holds fewer than :data:`REGION_POINTS_PER_CLASS`
        points of a class (in every pattern tried); when it holds fewer too, so is a square of
        the first's size where held-out stretches saw new ground (:func:`new_ground_centre`).
        The first region with enough points is used, else the one with the most.

    Returns
    -------
    kappa : float
    report : dict
        ``"kappa"``, ``"n_points"`` (in the sample), ``"n_patterns"``, ``"region_centre"`` and ``"region_half"``
        (the square used), ``"log_loss_at_1"`` and ``"log_loss"`` (at kappa = 1 and
        at the fit) and ``"bounds"`` (of the search), or ``"reason"`` when kappa stays 1.
    """
    if len(scans) < HOLDOUT_EVERY:
        return 1.0, {"kappa": 1.0, "reason": f"only {len(scans)} scans"}

    first = (np.asarray(centre, dtype=float)[:2], float(region_half), float(margin))
    source = _source(observations)

    def regions() -> Iterator[tuple[NDArray[np.float64], float, float]]:
        yield first
        if wider is None:
            return  # the first region is the whole map
        yield np.asarray(wider[0], dtype=float)[:2], float(wider[1]), float(wider[2])
        # A robot that passes the sample's square in every stretch (a long corridor): where
        # held-out stretches saw new ground, the square is first's size.
        ground = new_ground_centre(source, len(scans), 2.0 * first[1])
        if ground is not None:
            yield ground, first[1], first[2]

    # The first region with enough points, else the one with the most (the first of equals).
    tried: list[tuple[int, NDArray[np.float64], float, float, list[Any]]] = []
    for c, h, g in regions():
        lo, hi = c - h, c + h
        folds, n = _region_folds(scans, lo, hi, g, no_return_cap, _observes_both(source, len(scans), lo, hi))
        tried.append((n, c, h, g, folds))
        if n >= REGION_POINTS_PER_CLASS:
            break
    n, centre, region_half, margin, folds = max(tried, key=lambda t: t[0])
    lo, hi = centre - region_half, centre + region_half
    if n < MIN_POINTS_PER_CLASS:
        reason = f"{n} held-out points of a class where no kept beam went, in {len(folds)} patterns of held-out stretches"
        return 1.0, {"kappa": 1.0, "reason": reason}
    # The sample drawn from every pattern's unseen points in turn, only those drawn made.
    starts = np.cumsum([0] + [f[1].size for f in folds])
    keep = natural_subsample(int(starts[-1]), MAX_POINTS, seed)
    cut = np.searchsorted(keep, starts)
    drawn = [f[1].take(keep[a:b] - s) for f, a, b, s in zip(folds, cut[:-1], cut[1:], starts[:-1], strict=True)]
    pts, occ = np.concatenate([d[0] for d in drawn]), np.concatenate([d[1] for d in drawn])
    fold_of = np.concatenate([np.full(d[1].size, k) for k, d in enumerate(drawn)])
    # Each pattern's points are predicted by the GP of that pattern's kept scans, fitted on their
    # points in the region: made again for each pattern, the other scans' never (a whole log
    # has tens of millions of points, a depth frame ten).
    mu, var = np.empty(occ.size), np.empty(occ.size)
    for k, (kept, _) in enumerate(folds):
        sel = fold_of == k
        if not sel.any():
            continue
        obs = _kept_region(source, kept, lo, hi, free_clearance)
        if obs.n_occupied == 0 or obs.n_free == 0:  # every kept free point cleared (see _observes_both)
            return 1.0, {"kappa": 1.0, "reason": "no kept observations of a class in the region"}
        try:
            model = fit_held_in(obs)
        except EmptyDataError as err:
            return 1.0, {"kappa": 1.0, "reason": str(err)}
        mu[sel], var[sel] = model.predict(pts[sel], return_var=True)
        del obs, model
        release_freed_memory()
    a, b = float(hyperparameters["alpha"]), float(hyperparameters["beta"])
    kappa = VarianceScale.fit(mu, var, occ, a, b).kappa
    return kappa, {
        "kappa": kappa,
        "n_points": int(occ.size),
        "n_patterns": len(folds),
        "region_centre": [float(v) for v in centre],
        "region_half": float(region_half),
        "log_loss_at_1": _nll(1.0, mu, var, occ, a, b),
        "log_loss": _nll(kappa, mu, var, occ, a, b),
        "bounds": [float(v) for v in VARIANCE_SCALE_BOUNDS],
    }


def _region_folds(
    scans: Sequence[Any],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin: float,
    no_return_cap: float | None,
    observes: Callable[[NDArray[np.intp]], bool],
) -> tuple[list[tuple[NDArray[np.intp], _UnseenPoints]], int]:
    """Per pattern of held-out stretches tried, the kept scans' indices and the held-out points in
    the square where none of them went (:func:`_unseen_points`); and the smaller class's count.

    Patterns are tried in the order of :data:`FOLD_STARTS` until their points pooled hold
    :data:`MIN_POINTS_PER_CLASS` of each class. A pattern whose kept scans observed no point of a
    class in the square (`observes` says no) is passed over: its GP there would be its prior,
    whatever the variance scale (a robot that drove past the square once, in a stretch this
    pattern holds out, would otherwise keep the scale at 1).
    """
    folds: list[tuple[NDArray[np.intp], _UnseenPoints]] = []
    n = 0
    for first in FOLD_STARTS:
        kept, held = holdout_stretches(len(scans), first)
        if not observes(kept):
            continue
        unseen = _unseen_points([scans[i] for i in kept], [scans[i] for i in held], lo, hi, margin, no_return_cap)
        folds.append((kept, unseen))
        n_occ = sum(f[1].n_occupied for f in folds)
        n = min(n_occ, sum(f[1].size for f in folds) - n_occ)
        if n >= MIN_POINTS_PER_CLASS:
            break
    return folds, n


@dataclass(frozen=True)
class VarianceScale:
    """The squash stage (:class:`gpomap.stages.Stage`): the probit of the GP's calibrated moments,
    its latent variance scaled by kappa where no beam went.

    Parameters
    ----------
    kappa : float
        The factor on the latent variance for unseen space (1: the squash's own variance).
    """

    kappa: float = 1.0

    @classmethod
    def fit(
        cls, mu: NDArray[np.float64], var: NDArray[np.float64], occupied: NDArray[np.bool_], alpha: float, beta: float
    ) -> VarianceScale:
        """The variance scale that maximises the likelihood of unseen points.

        The probability of a point where no beam went is
        ``Phi((alpha mu + beta) / sqrt(1 + alpha^2 kappa var))`` (before the map's cut of the lean
        towards free, :func:`gpomap.squash.unseen_probit`).

        Parameters
        ----------
        mu, var : ndarray of shape (m,)
            The held-in GP's latent mean and variance at held-out points where no kept beam went,
            drawn at their natural frequencies (:func:`fit_variance_scale`).
        occupied : ndarray of bool, shape (m,)
            Their classes.
        alpha, beta : float
            The map's squash.

        Returns
        -------
        VarianceScale
        """
        res = minimize_scalar(
            lambda t: _nll(float(np.exp(t)), mu, var, occupied, alpha, beta),
            bounds=tuple(np.log(VARIANCE_SCALE_BOUNDS)),
            method="bounded",
            # Tight, so kappa is the optimum's and not moved by the last bits of the held-in maps.
            options={"xatol": 1e-10},
        )
        return cls(float(np.exp(res.x)))

    def apply(self, moments: CalibratedMoments) -> GPProbability:
        """The GP's probability, and its probability for unseen space, from its calibrated moments
        (any matching shapes)."""
        num, den = moments
        p = ndtr(num / np.sqrt(1.0 + den))
        # Where no beam went the latent variance is scaled by kappa.
        p_unseen = ndtr(unseen_probit(num, den, self.kappa))
        return GPProbability(p, p_unseen)
