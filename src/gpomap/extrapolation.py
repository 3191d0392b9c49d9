"""How sure the GP may be where no beam went: its variance scale, fitted on held-out stretches of the log.

The probit squash is fitted on leave-one-out moments of the cells (:mod:`gpomap.squash`). A cell
left out has its neighbours on every side, so those moments describe interpolation, and the
squash comes out sure of itself (alpha often at its cap). Where no beam went, behind a wall or in
a room seen only later, the GP extrapolates, and its latent variance there understates how wrong
its mean can be: measured before this step, the Stage arena's written map called the unseen space
behind its outer wall occupied at p ~ 0.97, and on Belgioioso's held-out stretches the GP alone
scored AUC 0.62 where no training beam went, with a log loss of 1.4.

So the squash gets one more parameter, a variance scale kappa:

    p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 kappa v)),

fitted where the question is the same as a user's: the log's scans are cut into contiguous
stretches, every third stretch is held out, a GP with the map's hyperparameters is fitted on the
rest, and kappa maximises the class-balanced likelihood of the held-out stretches' hits and free
points (the evaluation protocol's points) that lie where no kept beam went. Near the data the
latent variance is small and kappa changes little; far from it p tends to 1/2 sooner.

Where no beam went but a beam ended close by, the space is mostly the same surface going on: a
wall past the last metre a scan saw of it, the far side of an obstacle. On the evaluation's blocks
splits of ACES and Belgioioso, such points within 0.5 m of a training hit were 73-100 % occupied, and the GP,
pulled by the free cells on the seen side, gave them 0.32-0.68. In planar maps (:data:`HIT_GAIN`)
the same held-out points fit a gain of the probit near hits with kappa
(:class:`gpomap.fusion.HitProximity`):

    p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 kappa v) + shift exp(-d / reach)),

d the distance from the point to the nearest centre of a cell a kept beam ended in. The gain is never
negative, has a normal prior (a few dozen points of one room do not make unseen space next to
walls certain), and its reach is at most 1 m, so that far from all data p is still 1/2.

To bound the cost, the held-in GP covers one square region of side ``2 * region_half`` round a
given centre (the hyperparameter sample's), and only points well inside it are used; where it
holds fewer than :data:`REGION_POINTS_PER_CLASS` of a class, a wider square is taken, and where
that holds too few as well, a square of the first's size where the held-out stretches saw most
new ground next to what the kept ones saw (:func:`new_ground_centre`: on MIT's infinite corridor
the robot passes the sample's square in every stretch, which left no unseen point there). When one
pattern of held-out stretches finds too few such points of a class (on Intel, CSAIL and FR079
with blocks of their scans held out, 24-27), the other two patterns (the stretches after, then
the rest) are tried in turn and their points pooled, each with its own held-in GP: a robot that
enters new space only once in its log is unseen in one pattern alone. With too few points in
all three (a short log, a robot that never left one room), kappa stays 1.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial import cKDTree
from scipy.special import log_ndtr

from gpomap.errors import EmptyDataError
from gpomap.evidence import RayEvidence, lattice_grid
from gpomap.fusion import HIT_DISTANCE_REACHES, HitCells, HitProximity, calibration_points
from gpomap.lattice import bounds_extent, column_bounds, flat_index, in_box
from gpomap.observations import Observations, beams_reach, data_dim, free_near_hits, natural_subsample
from gpomap.squash import unseen_probit

#: The log is cut into this many contiguous stretches (or one per scan, when shorter) ...
N_STRETCHES: int = 10
#: ... and every this-many-th stretch is held out (3 of 10, starting at the second) ...
HOLDOUT_EVERY: int = 3
#: ... starting at these stretches in turn, while fewer than MIN_POINTS_PER_CLASS points are found.
FOLD_STARTS: tuple[int, ...] = (1, 2, 0)
#: Fewest held-out points of each class where no kept beam went for kappa to be fitted.
MIN_POINTS_PER_CLASS: int = 50
#: Most points of each class used (the held-in GP's prediction at them is the cost).
MAX_POINTS_PER_CLASS: int = 5_000
#: Search bounds of kappa.
VARIANCE_SCALE_BOUNDS: tuple[float, float] = (0.1, 1e4)
#: Bounds of the probit gain of unseen space at a hit's cell (:class:`gpomap.fusion.HitProximity`);
#: never negative: a surface nearby does not make space freer.
HIT_SHIFT_BOUNDS: tuple[float, float] = (0.0, 5.0)
#: Bounds of the distance over which that gain falls by e, metres. At most 1 m, so that 5 m from
#: every hit (where the map must return its prior) the largest gain is 5 e^-5 = 0.034 in probit,
#: 0.013 in probability.
HIT_REACH_BOUNDS: tuple[float, float] = (0.05, 1.0)
#: Standard deviation of the zero-mean normal prior on that gain (probit units): the penalty is
#: the prior's log density per point fitted, so it fades as the points grow in number.
HIT_SHIFT_PRIOR_STD: float = 1.0
#: Whether the gain near hits is fitted, per dimension of the data. Off: fitted on held-out points
#: at their natural frequencies it comes out nil (docs/choices.md, the stage ablation).
HIT_GAIN: dict[int, bool] = {2: False, 3: False}
#: Fewest held-out points of each class where no kept beam went for the held-in GP's square round
#: the hyperparameter sample to be enough; with fewer, a square twice as wide is taken (or the
#: whole map, when that is smaller). Kappa needs few; the gain near hits is fitted with it.
REGION_POINTS_PER_CLASS: int = 500
#: A held-out hit farther than this from every kept hit saw new ground (metres): where the first
#: regions hold too few unseen points, the square where held-out stretches saw most of it is
#: tried (:func:`new_ground_centre`).
NEW_HIT_DISTANCE: float = 1.0
#: Cell side of the lattice on which "no kept beam went" is decided, as the evaluation's
#: reference grid decides it, metres (planar maps; voxel maps use 0.1 m).
UNSEEN_RESOLUTION: dict[int, float] = {2: 0.05, 3: 0.1}


def holdout_stretches(n_scans: int, first: int = FOLD_STARTS[0]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices of the kept and the held-out scans: every third of ten contiguous stretches held out.

    Parameters
    ----------
    n_scans : int
    first : int
        The first stretch held out (0-based); then every :data:`HOLDOUT_EVERY`-th.

    Returns
    -------
    kept, held_out : ndarray of int
        Sorted; together they are ``0 .. n_scans - 1``. Fewer than 3 scans: nothing held out.
    """
    idx = np.arange(n_scans)
    if n_scans < HOLDOUT_EVERY:
        return idx, idx[:0]
    stretches = np.array_split(idx, min(N_STRETCHES, n_scans))
    held = np.zeros(n_scans, bool)
    for s in stretches[first::HOLDOUT_EVERY]:
        held[s] = True
    return idx[~held], idx[held]


def _nll(
    kappa: float, mu, var, occupied, alpha: float, beta: float, distance=None, shift: float = 0.0, reach: float = 1.0
) -> float:
    """Mean negative log probit likelihood at variance scale `kappa`, with the gain ``shift *
    exp(-distance / reach)`` near hits (:class:`gpomap.fusion.HitProximity`); the classes are
    balanced by subsampling. The probit is the map's where no beam went before its cut of the
    lean towards free (:func:`gpomap.squash.unseen_probit`), which is a prior, not fitted."""
    z = unseen_probit(alpha * mu + beta, alpha * alpha * var, kappa)
    if shift != 0.0 and distance is not None:
        z = z + HitProximity(shift, reach).gain(distance)
    return float(-np.mean(np.where(occupied, log_ndtr(z), log_ndtr(-z))))


def whole_map_region(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Centre (x, y) and half side of a square holding every point with a metre to spare.

    A held-in GP over it has the whole map, so no point is near an edge the data do not have
    (``margin`` 0 in :func:`fit_variance_scale`).
    """
    xy = np.asarray(points, dtype=float)[:, :2]
    lo, hi = column_bounds(xy)
    return 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 1.0


def _in_square(
    points: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64], grow: float = 0.0
) -> NDArray[np.bool_]:
    """Which points (m, d) lie in the square lo..hi (x, y) grown by `grow` on every side (negative: shrunk)."""
    return in_box(points, np.asarray(lo)[:2] - grow, np.asarray(hi)[:2] + grow)


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
    points, occupied, scan_index = obs.points[grown], obs.occupied[grown], obs.scan_index[grown]
    keep = ~free_near_hits(points, occupied, clearance) & _in_square(points, lo, hi)
    return Observations(points[keep], occupied[keep], scan_index[keep])


def fit_variance_scale(
    scans: Sequence[Any],
    hyperparameters: dict[str, float],
    observations: Observations,
    free_clearance: float,
    fit_held_in: Callable[[Observations], Any],
    centre: NDArray[np.float64],
    region_half: float,
    margin: float,
    no_return_cap: float | None = 10.0,
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
    observations : Observations
        The map's labelled points from `scans` (its free step, ...), before the clearance; each
        pattern's held-in points are cut from them (:func:`region_observations`).
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
        ``"kappa"``, ``"hit_shift"`` and ``"hit_reach"`` (the gain near hits),
        ``"n_points"`` (per class), ``"n_patterns"``, ``"region_centre"`` and ``"region_half"``
        (the square used), ``"log_loss_at_1"`` and ``"log_loss"`` (balanced, at kappa = 1 and
        at the fit), or ``"reason"`` when kappa stays 1.
    """
    if len(scans) < HOLDOUT_EVERY:
        return 1.0, {"kappa": 1.0, "reason": f"only {len(scans)} scans"}

    first = (np.asarray(centre, dtype=float)[:2], float(region_half), float(margin))

    def regions() -> Iterator[tuple[NDArray[np.float64], float, float]]:
        yield first
        if wider is None:
            return  # the first region is the whole map
        yield np.asarray(wider[0], dtype=float)[:2], float(wider[1]), float(wider[2])
        # A robot that passes the sample's square in every stretch (MIT's infinite corridor):
        # where held-out stretches saw new ground, the square is first's size.
        ground = new_ground_centre(observations, len(scans), 2.0 * first[1])
        if ground is not None:
            yield ground, first[1], first[2]

    # The first region with enough points, else the one with the most (the first of equals).
    tried: list[tuple[int, NDArray[np.float64], float, float, list[Any]]] = []
    for c, h, g in regions():
        lo, hi = c - h, c + h
        observes = functools.partial(_observes_both, observations, _in_square(observations.points, lo, hi))
        folds, n = _region_folds(scans, lo, hi, g, no_return_cap, observes)
        tried.append((n, c, h, g, folds))
        if n >= REGION_POINTS_PER_CLASS:
            break
    n, centre, region_half, margin, folds = max(tried, key=lambda t: t[0])
    lo, hi = centre - region_half, centre + region_half
    if n < MIN_POINTS_PER_CLASS:
        reason = f"{n} held-out points of a class where no kept beam went, in {len(folds)} patterns of held-out stretches"
        return 1.0, {"kappa": 1.0, "reason": reason}
    pts = np.concatenate([f[1] for f in folds])
    occ = np.concatenate([f[2] for f in folds])
    dist = np.concatenate([f[3] for f in folds])
    fold_of = np.concatenate([np.full(f[2].size, k) for k, f in enumerate(folds)])
    keep = natural_subsample(occ.size, 2 * n, seed)
    pts, occ, fold_of, dist = pts[keep], occ[keep], fold_of[keep], dist[keep]
    # The region's points (grown by the clearance) cut once for every pattern: a whole log has
    # tens of millions.
    near = _in_square(observations.points, lo, hi, free_clearance)
    observations = Observations(observations.points[near], observations.occupied[near], observations.scan_index[near])
    # Each pattern's points are predicted by the GP of that pattern's kept scans.
    mu, var = np.empty(occ.size), np.empty(occ.size)
    for k, (kept, _, _, _) in enumerate(folds):
        sel = fold_of == k
        if not sel.any():
            continue
        obs = region_observations(observations, kept, lo, hi, free_clearance)
        if obs.n_occupied == 0 or obs.n_free == 0:  # every kept free point cleared (see _observes_both)
            return 1.0, {"kappa": 1.0, "reason": "no kept observations of a class in the region"}
        try:
            model = fit_held_in(obs)
        except EmptyDataError as err:
            return 1.0, {"kappa": 1.0, "reason": str(err)}
        mu[sel], var[sel] = model.predict(pts[sel], return_var=True)
    a, b = float(hyperparameters["alpha"]), float(hyperparameters["beta"])
    # Without the gain, its distances are inf: kappa alone.
    gain = HIT_GAIN.get(pts.shape[1], False)
    kappa, shift, reach, loss = fit_unseen_squash(mu, var, occ, dist if gain else np.full(occ.size, np.inf), a, b)
    return kappa, {
        "kappa": kappa,
        "hit_shift": shift,
        "hit_reach": reach,
        "n_points": n,
        "n_patterns": len(folds),
        "region_centre": [float(v) for v in centre],
        "region_half": float(region_half),
        "log_loss_at_1": _nll(1.0, mu, var, occ, a, b),
        "log_loss": loss,
    }


def new_ground_centre(observations: Observations, n_scans: int, side: float) -> NDArray[np.float64] | None:
    """Where the first pattern's held-out stretches saw most that its kept stretches did not.

    The centre (x, y) of the square of side `side` (on a lattice from the origin) that holds the
    most new hits, held-out hits farther than :data:`NEW_HIT_DISTANCE` from every kept hit, among
    the squares where the kept scans have a hit and a free point (elsewhere a held-in GP would
    only give its prior). None when there is no such square.

    Parameters
    ----------
    observations : Observations
        The map's labelled points; ``scan_index`` numbers the scans.
    n_scans : int
        Scans in the log.
    side : float
        Side of the squares, metres.

    Returns
    -------
    ndarray of shape (2,) or None
    """
    from_kept = _from_kept(observations.scan_index, holdout_stretches(n_scans, FOLD_STARTS[0])[0])
    xy, occupied = observations.points[:, :2], observations.occupied
    hits_kept, hits_held = xy[occupied & from_kept], xy[occupied & ~from_kept]
    if hits_kept.size == 0 or hits_held.size == 0:
        return None
    # Kept hits to the decimetre: a whole log repeats each wall thousands of times.
    distance, _ = cKDTree(np.unique(np.round(hits_kept, 1), axis=0)).query(hits_held, distance_upper_bound=NEW_HIT_DISTANCE)
    squares = _SquareLattice(xy, side)
    counts = np.bincount(squares.index(hits_held[np.isinf(distance)]), minlength=squares.size)
    # Only squares where the kept scans observed both classes (a few hundred squares per log).
    counts[~(squares.holding(hits_kept) & squares.holding(xy, ~occupied & from_kept))] = 0
    if not counts.any():
        return None
    return squares.centre(int(np.argmax(counts)))


class _SquareLattice:
    """Squares of side `side` on a lattice from the origin, over the extent of some points (n, 2),
    numbered x-major (so the first of equal counts is the one of least x, then least y).

    Squares are marked in a boolean array, not found by sorting: a whole log's tens of millions
    of points took np.unique 37 s on the Freiburg campus."""

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


def _observes_both(obs: Observations, in_square: NDArray[np.bool_], kept: NDArray[np.intp]) -> bool:
    """Whether the kept scans have a hit and a free point among the points `in_square` (a mask
    of `obs`), before the clearance (which could, in principle, clear every free point)."""
    occupied = obs.occupied[in_square & _from_kept(obs.scan_index, kept)]
    return bool(occupied.any() and not occupied.all())


def _region_folds(
    scans: Sequence[Any],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin: float,
    no_return_cap: float | None,
    observes: Callable[[NDArray[np.intp]], bool],
) -> tuple[list[tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]], int]:
    """Per pattern of held-out stretches tried, the kept scans' indices and the held-out points in
    the square where none of them went (:func:`_unseen_points`); and the points per class to use.

    Patterns are tried in the order of :data:`FOLD_STARTS` until their points pooled hold
    :data:`MIN_POINTS_PER_CLASS` of each class. A pattern whose kept scans observed no point of a
    class in the square (`observes` says no) is passed over: its GP there would be its prior,
    whatever the variance scale (a robot that drove past the square once, in a stretch this
    pattern holds out: MIT's infinite corridor kept the scale at 1 so).
    """
    folds: list[tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]] = []
    n = 0
    for first in FOLD_STARTS:
        kept, held = holdout_stretches(len(scans), first)
        if not observes(kept):
            continue
        pts, occ, dist = _unseen_points([scans[i] for i in kept], [scans[i] for i in held], lo, hi, margin, no_return_cap)
        folds.append((kept, pts, occ, dist))
        n_occ = sum(int(f[2].sum()) for f in folds)
        n = min(n_occ, sum(f[2].size for f in folds) - n_occ, MAX_POINTS_PER_CLASS)
        if n >= MIN_POINTS_PER_CLASS:
            break
    return folds, n


def fit_unseen_squash(
    mu: NDArray[np.float64],
    var: NDArray[np.float64],
    occupied: NDArray[np.bool_],
    distance: NDArray[np.float64],
    alpha: float,
    beta: float,
) -> tuple[float, float, float, float]:
    """The variance scale and the gain near hits that maximise the likelihood of unseen points.

    The probability of a point where no beam went is
    ``Phi((alpha mu + beta) / sqrt(1 + alpha^2 kappa var) + shift exp(-distance / reach))``
    (:class:`gpomap.fusion.HitProximity`). Kappa is fitted alone first, then all three together
    from there; the better of the two is kept.

    Parameters
    ----------
    mu, var : ndarray of shape (m,)
        The held-in GP's latent mean and variance at the points.
    occupied : ndarray of bool, shape (m,)
        Their classes, balanced.
    distance : ndarray of shape (m,)
        From each point to the nearest centre of a cell a kept beam ended in, metres (inf: none).
    alpha, beta : float
        The map's squash.

    Returns
    -------
    kappa, shift, reach, log_loss : float
        ``shift`` 0 (and ``reach`` 1) when the gain does not lower the loss.
    """
    a, b, occ, dist = alpha, beta, occupied, distance
    res = minimize_scalar(
        lambda t: _nll(float(np.exp(t)), mu, var, occ, a, b),
        bounds=tuple(np.log(VARIANCE_SCALE_BOUNDS)),
        method="bounded",
        # Tight, so kappa is the optimum's and not moved by the last bits of the held-in maps.
        options={"xatol": 1e-10},
    )
    kappa, loss, shift, reach = float(np.exp(res.x)), float(res.fun), 0.0, 1.0
    if not np.isfinite(dist).any():
        return kappa, shift, reach, loss  # no hit near any point: the gain has no say
    # Then kappa and the gain near hits together, from kappa alone (where the gain is nil and its
    # reach has no say, so the search starts at a gain of 1 over half a metre), the gain under
    # its prior: a few dozen points of one room do not make unseen space next to walls certain.
    prior = 1.0 / (2.0 * HIT_SHIFT_PRIOR_STD**2 * max(occ.size, 1))

    def penalised(t: NDArray[np.float64]) -> float:
        return _nll(float(np.exp(t[0])), mu, var, occ, a, b, dist, float(t[1]), float(np.exp(t[2]))) + prior * t[1] ** 2

    both = minimize(
        penalised,
        np.array([np.log(kappa), 1.0, np.log(0.5)]),
        method="L-BFGS-B",
        bounds=[tuple(np.log(VARIANCE_SCALE_BOUNDS)), HIT_SHIFT_BOUNDS, tuple(np.log(HIT_REACH_BOUNDS))],
    )
    if float(both.fun) < loss:
        kappa, shift, reach = float(np.exp(both.x[0])), float(both.x[1]), float(np.exp(both.x[2]))
        loss = _nll(kappa, mu, var, occ, a, b, dist, shift, reach)
    return kappa, shift, reach, loss


def _unseen_points(
    kept_scans: Sequence[Any],
    held_scans: Sequence[Any],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    margin: float,
    no_return_cap: float | None,
) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
    """The held-out scans' protocol points in the square `lo`..`hi` (x, y) shrunk by `margin`, where
    no kept beam went: points (m, d), classes (m,), and the distance (m,) from each point to the
    nearest centre of a cell a kept beam ended in, as the map measures it
    (:class:`gpomap.fusion.HitCells`; inf when no kept beam ended).

    Scans whose beams cannot reach the square are passed over (a whole log's scans mostly look
    elsewhere: on FR079 they were most of the stage's time).
    """
    pts_l, occ_l = [], []
    for scan in held_scans:
        if not beams_reach(scan, lo, hi, no_return_cap):
            continue
        p, o = calibration_points(scan, no_return_cap=no_return_cap)
        sel = _in_square(p, lo, hi, -margin) if p.size else np.zeros(0, bool)
        pts_l.append(p[sel])
        occ_l.append(o[sel])
    if not pts_l or sum(len(p) for p in pts_l) == 0:
        return np.zeros((0, data_dim(held_scans))), np.zeros(0, bool), np.zeros(0)
    pts, occ = np.concatenate(pts_l), np.concatenate(occ_l)
    # Where no kept beam went: no hit and no miss on the evaluation's reference lattice.
    box_lo, box_hi = column_bounds(pts)
    rays = RayEvidence.from_scans([s for s in kept_scans if beams_reach(s, box_lo, box_hi, no_return_cap)], no_return_cap)
    grid = lattice_grid(bounds_extent(box_lo, box_hi), UNSEEN_RESOLUTION[pts.shape[1]])
    cell, ok = flat_index(grid, pts)
    seen = ok & rays.seen(grid).reshape(-1)[cell]
    pts, occ = pts[~seen], occ[~seen]
    # Hits farther than the map looks for one (its reach at most, times HIT_DISTANCE_REACHES)
    # change no distance that counts: a whole log's kept scans end millions of beams elsewhere.
    hits = rays.ends[rays.hit]
    hits = hits[_in_square(hits, box_lo, box_hi, HIT_DISTANCE_REACHES * HIT_REACH_BOUNDS[1])]
    return pts, occ, HitCells.of_points(hits, grid.resolution).distance(pts)
