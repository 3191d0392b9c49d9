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
new ground next to what the kept ones saw (:func:`new_ground_centre`: a robot that passes the
sample's square in every stretch leaves no unseen point there). When one pattern of held-out
stretches finds too few such points of a class, the other two patterns (the stretches after, then
the rest) are tried in turn and their points pooled, each with its own held-in GP: a robot that
enters new space only once in its log is unseen in one pattern alone (the logs where each case
arose: docs/choices.md, "Where no beam went" and its subsections). With too few points in
all three (a short log, a robot that never left one room), kappa stays 1.

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
from scipy.spatial import cKDTree
from scipy.special import log_ndtr, ndtr

from gpomap.config import PROFILES, MapConfig
from gpomap.errors import EmptyDataError
from gpomap.evidence import RayEvidence, lattice_grid
from gpomap.heldout import FOLD_STARTS, HOLDOUT_EVERY, CalibrationPoints, holdout_stretches
from gpomap.lattice import bounds_extent, column_bounds, flat_index, in_box
from gpomap.observations import Observations, ScanPoints, beams_reach, data_dim, free_near_hits, natural_subsample
from gpomap.resources import POINT_MEMORY, release_freed_memory
from gpomap.squash import unseen_probit
from gpomap.stages import CalibratedMoments, GPProbability

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
#: A held-out hit farther than this from every kept hit saw new ground (metres): where the first
#: regions hold too few unseen points, the square where held-out stretches saw most of it is
#: tried (:func:`new_ground_centre`).
NEW_HIT_DISTANCE: float = 1.0
#: Cell side of the lattice on which "no kept beam went" is decided, as the evaluation's
#: reference grid decides it, metres (planar maps; voxel maps use 0.1 m).
UNSEEN_RESOLUTION: dict[int, float] = {d: p.unseen_resolution for d, p in PROFILES.items()}


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


def _in_square(
    points: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64], grow: float = 0.0
) -> NDArray[np.bool_]:
    """Which points (m, d) lie in the square lo..hi (x, y) grown by `grow` on every side (negative: shrunk)."""
    return in_box(points, np.asarray(lo)[:2] - grow, np.asarray(hi)[:2] + grow)


class _HeldPoints:
    """Labelled points held in memory, asked as :class:`~gpomap.observations.ScanPoints` is (their
    bounds, their parts)."""

    def __init__(self, obs: Observations) -> None:
        self.obs = obs
        self.lower, self.upper = column_bounds(obs.points)

    def parts(self) -> Iterator[Observations]:
        yield self.obs


def _source(observations: Observations | ScanPoints) -> ScanPoints | _HeldPoints:
    return observations if isinstance(observations, ScanPoints) else _HeldPoints(observations)


def region_observations(
    obs: Observations, kept: NDArray[np.intp], lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float
) -> Observations:
    """The kept scans' labelled points in a square, from the map's points before the clearance.

    Equal to observing the kept scans alone (with the clearance) and keeping the points in the
    square: a free point there is cleared only by a kept hit within `clearance`, which lies in
    the square grown by `clearance`; so only that much of the map is looked at.

    Parameters
    ----------
    obs : Observations
        The map's points from all its scans, no clearance applied; ``scan_index`` numbers the scans.
    kept : ndarray of int
        Indices of the kept scans.
    lo, hi : ndarray of shape (2,)
        Corners of the square (x, y); in 3-D a column.
    clearance : float
        The map's free clearance, metres.

    Returns
    -------
    Observations
    """
    grown = _from_kept(obs.scan_index, kept) & _in_square(obs.points, lo, hi, clearance)
    return _cleared(Observations(obs.points[grown], obs.occupied[grown], obs.scan_index[grown]), lo, hi, clearance)


def _cleared(grown: Observations, lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float) -> Observations:
    """Of points in the square `lo`..`hi` grown by `clearance`, those in the square that the
    clearance keeps (:func:`region_observations`)."""
    keep = ~free_near_hits(grown.points, grown.occupied, clearance) & _in_square(grown.points, lo, hi)
    return Observations(grown.points[keep], grown.occupied[keep], grown.scan_index[keep])


def _square_parts(
    source: ScanPoints | _HeldPoints,
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    grow: float = 0.0,
    among: NDArray[np.intp] | None = None,
) -> Iterator[Observations]:
    """The points in the square `lo`..`hi` grown by `grow`, of every scan or of those `among`
    (sorted indices), a part at a time in the log's order: what ``source.square`` cuts, never
    all held at once."""
    box_lo, box_hi = np.asarray(lo, dtype=float)[:2] - grow, np.asarray(hi, dtype=float)[:2] + grow
    if isinstance(source, _HeldPoints):
        obs = source.obs
        inside = in_box(obs.points, box_lo, box_hi)
        if among is not None:
            inside &= _from_kept(obs.scan_index, among)
        yield Observations(obs.points[inside], obs.occupied[inside], obs.scan_index[inside])
        return
    meets = np.all((source.scan_lower[:, :2] <= box_hi) & (source.scan_upper[:, :2] >= box_lo), axis=1)
    scans = np.flatnonzero(meets) if among is None else among[meets[among]]
    if scans.size == 0:
        return
    for part in source.parts(scans.tolist()):
        inside = in_box(part.points, box_lo, box_hi)
        yield Observations(part.points[inside], part.occupied[inside], part.scan_index[inside])


def _kept_region(
    source: ScanPoints | _HeldPoints, kept: NDArray[np.intp], lo: NDArray[np.float64], hi: NDArray[np.float64], clearance: float
) -> Observations:
    """:func:`region_observations` of the map's points, made again from the kept scans alone
    (or cut from the points held): the other scans' points in the region are never made."""
    cut = list(_square_parts(source, lo, hi, clearance, among=kept))
    d = source.lower.size
    grown = Observations(
        np.concatenate([c.points for c in cut]) if cut else np.zeros((0, d)),
        np.concatenate([c.occupied for c in cut]) if cut else np.zeros(0, dtype=bool),
        np.concatenate([c.scan_index for c in cut]) if cut else np.zeros(0, dtype=np.int32),
    )
    del cut
    return _cleared(grown, lo, hi, clearance)


def fit_variance_scale(
    scans: Sequence[Any],
    hyperparameters: dict[str, float],
    observations: Observations | ScanPoints,
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
    observations : Observations or ScanPoints
        The map's labelled points from `scans` (its free step, ...), before the clearance, or
        what makes them again a square at a time; each pattern's held-in points are cut from
        them (:func:`region_observations`).
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
        at the fit), or ``"reason"`` when kappa stays 1.
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
    }


def new_ground_centre(
    observations: Observations | ScanPoints | _HeldPoints, n_scans: int, side: float
) -> NDArray[np.float64] | None:
    """Where the first pattern's held-out stretches saw most that its kept stretches did not.

    The centre (x, y) of the square of side `side` (on a lattice from the origin) that holds the
    most new hits, held-out hits farther than :data:`NEW_HIT_DISTANCE` from every kept hit, among
    the squares where the kept scans have a hit and a free point (elsewhere a held-in GP would
    only give its prior). None when there is no such square.

    Parameters
    ----------
    observations : Observations or ScanPoints
        The map's labelled points (or what makes them again, a part at a time); ``scan_index``
        numbers the scans.
    n_scans : int
        Scans in the log.
    side : float
        Side of the squares, metres.

    Returns
    -------
    ndarray of shape (2,) or None
    """
    source = observations if isinstance(observations, (ScanPoints, _HeldPoints)) else _HeldPoints(observations)
    kept = holdout_stretches(n_scans, FOLD_STARTS[0])[0]
    squares = _SquareLattice(np.vstack([source.lower[:2], source.upper[:2]]), side)
    # The hits, and the squares of the kept free points, a part of the log at a time.
    kept_parts, held_parts = [], []
    free_kept = np.zeros(squares.size, dtype=bool)
    for part in source.parts():
        from_kept = _from_kept(part.scan_index, kept)
        xy, occupied = part.points[:, :2], part.occupied
        kept_parts.append(xy[occupied & from_kept])
        held_parts.append(xy[occupied & ~from_kept])
        free_kept |= squares.holding(xy, ~occupied & from_kept)
    hits_kept, hits_held = np.concatenate(kept_parts), np.concatenate(held_parts)
    if hits_kept.size == 0 or hits_held.size == 0:
        return None
    # Kept hits to the decimetre: a whole log repeats each wall thousands of times.
    distance, _ = cKDTree(np.unique(np.round(hits_kept, 1), axis=0)).query(hits_held, distance_upper_bound=NEW_HIT_DISTANCE)
    counts = np.bincount(squares.index(hits_held[np.isinf(distance)]), minlength=squares.size)
    # Only squares where the kept scans observed both classes (a few hundred squares per log).
    counts[~(squares.holding(hits_kept) & free_kept)] = 0
    if not counts.any():
        return None
    return squares.centre(int(np.argmax(counts)))


class _SquareLattice:
    """Squares of side `side` on a lattice from the origin, over the extent of some points (n, 2),
    numbered x-major (so the first of equal counts is the one of least x, then least y).

    Squares are marked in a boolean array, not found by sorting: ``np.unique`` over a whole log's
    tens of millions of points takes tens of seconds (docs/choices.md, "Measured for the code")."""

    #: Points handled at a time when marking squares (bounds the temporaries to ~100 MB).
    CHUNK = 1 << 22

    def __init__(self, points: NDArray[np.float64], side: float) -> None:
        lo, hi = column_bounds(points)
        self.side = float(side)
        self.origin = np.floor(lo / self.side).astype(np.int64)
        self.shape = np.floor(hi / self.side).astype(np.int64) - self.origin + 1
        self.size = int(np.prod(self.shape))

    def index(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Flat index of the square holding each point (m, 2), points within the extent."""
        ij = np.floor(points / self.side).astype(np.int64) - self.origin
        return ij[:, 0] * self.shape[1] + ij[:, 1]

    def holding(self, points: NDArray[np.float64], mask: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
        """Whether each square holds any of `points` (those `mask` selects), shape (size,)."""
        marked = np.zeros(self.size, dtype=bool)
        for start in range(0, len(points), self.CHUNK):
            part = points[start : start + self.CHUNK]
            if mask is not None:
                part = part[mask[start : start + self.CHUNK]]
            marked[self.index(part)] = True
        return marked

    def centre(self, k: int) -> NDArray[np.float64]:
        """Centre (x, y) of square `k`."""
        ix, iy = divmod(k, int(self.shape[1]))
        return (self.origin + np.array([ix, iy]) + 0.5) * self.side


def _from_kept(scan_index: NDArray[np.integer], kept: NDArray[np.intp]) -> NDArray[np.bool_]:
    """Which points (by their scan's index) come from the `kept` scans, shape scan_index.shape.

    A table of the scans, not np.isin, which sorts a copy of every point's scan index; kept
    scans with no point (past the last index) mark nothing.
    """
    is_kept = np.zeros(int(scan_index.max(initial=-1)) + 1, dtype=bool)
    is_kept[kept[kept < is_kept.size]] = True
    return is_kept[scan_index]


def _observes_both(
    source: ScanPoints | _HeldPoints, n_scans: int, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> Callable[[NDArray[np.intp]], bool]:
    """Whether given kept scans have a hit and a free point in the square `lo`..`hi`, before the
    clearance (which could, in principle, clear every free point): which scans have either there,
    found a part at a time."""
    hit, free = np.zeros(n_scans, dtype=bool), np.zeros(n_scans, dtype=bool)
    for part in _square_parts(source, lo, hi):
        hit[part.scan_index[part.occupied]] = True
        free[part.scan_index[~part.occupied]] = True

    def observes(kept: NDArray[np.intp]) -> bool:
        return bool(hit[kept].any() and free[kept].any())

    return observes


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


class _UnseenPoints:
    """Held-out scans' calibration points where no kept beam went (:func:`_unseen_points`), in
    order: which of each run of a scan's points they are, a bit each, and those drawn made again
    from their rays (:meth:`take`), so a depth frame's millions are never held at once.

    Attributes
    ----------
    size : int
        How many.
    n_occupied : int
        How many are hits.
    """

    def __init__(self, dim: int, no_return_cap: float | None) -> None:
        self.dim = dim
        self.no_return_cap = no_return_cap
        self.size = self.n_occupied = 0
        # Per run: its scan, its first and last + 1 point in the scan, the bits of those unseen,
        # and how many are.
        self._runs: list[tuple[Any, int, int, NDArray[np.uint8], int]] = []

    def add(self, scan: Any, start: int, stop: int, unseen: NDArray[np.bool_], n_occupied: int) -> None:
        """Mark which of the scan's points `start` .. `stop` - 1 are unseen (`unseen`, shape
        (stop - start,)), `n_occupied` of them hits."""
        n = int(np.count_nonzero(unseen))
        if n:
            self._runs.append((scan, start, stop, np.packbits(unseen), n))
            self.size += n
            self.n_occupied += int(n_occupied)

    def take(self, index: NDArray[np.integer]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """The unseen points at sorted places `index` (k,) among them all: points (k, d), classes (k,)."""
        index = np.asarray(index, dtype=np.intp)
        points, occupied = [np.zeros((0, self.dim))], [np.zeros(0, dtype=bool)]
        first = 0
        held: CalibrationPoints | None = None
        held_scan = None
        for scan, start, stop, bits, n in self._runs:
            lo, hi = np.searchsorted(index, [first, first + n])
            if lo < hi:
                if scan is not held_scan:
                    held, held_scan = CalibrationPoints(scan, no_return_cap=self.no_return_cap), scan
                assert held is not None
                places = np.flatnonzero(np.unpackbits(bits, count=stop - start))[index[lo:hi] - first] + start
                p, o = held.take(places)
                points.append(p)
                occupied.append(o)
            first += n
        return np.concatenate(points), np.concatenate(occupied)


def _unseen_points(
    kept_scans: Sequence[Any],
    held_scans: Sequence[Any],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin: float,
    no_return_cap: float | None,
    memory: int = POINT_MEMORY,
) -> _UnseenPoints:
    """The held-out scans' protocol points in the square `lo`..`hi` (x, y) shrunk by `margin`, where
    no kept beam went.

    Scans whose beams cannot reach the square are passed over (a whole log's scans mostly look
    elsewhere, and would be most of the stage's time). The points are made a run of rays at a
    time (:class:`~gpomap.heldout.CalibrationPoints`), twice: once for the box of those in the
    square, on which "no kept beam went" is decided, then to decide it; those of the first pass
    are kept for the second while they take at most `memory` bytes. What is unseen is kept as a
    bit a point: the points themselves are made again only where drawn.
    """
    unseen = _UnseenPoints(data_dim(held_scans), no_return_cap)
    runs: list[tuple[Any, int, int, NDArray[np.uint8], tuple[NDArray[np.float64], NDArray[np.bool_]] | None]] = []
    bounds: list[NDArray[np.float64]] = []
    kept_bytes = 0
    for scan in held_scans:
        if not beams_reach(scan, lo, hi, no_return_cap):
            continue
        held = CalibrationPoints(scan, no_return_cap=no_return_cap)
        for start, stop in held.spans():
            p, o = held.between(start, stop)
            inside = _in_square(p, lo, hi, -margin)
            if not inside.any():
                continue
            p, o = p[inside], o[inside]
            bounds += column_bounds(p)
            kept_bytes += p.nbytes + o.nbytes
            runs.append((scan, start, stop, np.packbits(inside), (p, o) if kept_bytes <= memory else None))
    if not runs:
        return unseen
    # Where no kept beam went: no hit and no miss on the evaluation's reference lattice.
    box_lo, box_hi = np.min(bounds[0::2], axis=0), np.max(bounds[1::2], axis=0)
    rays = RayEvidence.from_scans([s for s in kept_scans if beams_reach(s, box_lo, box_hi, no_return_cap)], no_return_cap)
    grid = lattice_grid(bounds_extent(box_lo, box_hi), UNSEEN_RESOLUTION[box_lo.size])
    seen_cells = rays.seen(grid).reshape(-1)
    again: CalibrationPoints | None = None
    again_scan = None
    for scan, start, stop, bits, part in runs:
        inside = np.unpackbits(bits, count=stop - start).view(bool)
        if part is None:
            if scan is not again_scan:
                again, again_scan = CalibrationPoints(scan, no_return_cap=no_return_cap), scan
            assert again is not None
            p, o = again.between(start, stop)
            part = p[inside], o[inside]
        cell, ok = flat_index(grid, part[0])
        new = ~(ok & seen_cells[cell])
        marks = np.zeros(stop - start, dtype=bool)
        marks[inside] = new
        unseen.add(scan, start, stop, marks, int(np.count_nonzero(part[1] & new)))
    return unseen
