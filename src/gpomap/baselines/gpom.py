"""GPOM (O'Callaghan & Ramos 2012): the same GP as MSK-GPOM, on point inputs.

Free samples along the beams and the hits are the GP's inputs, one point each, with targets -1
and +1. The GP core (:class:`gpomap.gp.SupportGP`: hyperparameter objective, noise, probit
squash) is the one MSK-GPOM uses, so the comparison isolates the choice of inputs. A dense GP is
O(n^3) in the points, so ``max_points`` caps them (a seeded random subsample; see
:meth:`GPOM.fit`).

:class:`GPBaseline` holds what GPOM and GPOMIK share: the estimator protocol of
:class:`gpomap.mapping.AreaGPOM` (``predict``, ``predict_proba``, ``grid``, ``summary``...).
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import EmptyDataError, NotFittedError
from gpomap.gp import SupportGP
from gpomap.grid import DEFAULT_THRESHOLDS, GridSpec, OccupancyMap, ternary
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.point import make_point_kernel
from gpomap.observations import Observations, observations_from_scans
from gpomap.scans import Scan
from gpomap.supports import Supports


def as_points(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """`points` as a float ndarray of shape (m, 2), or a ValueError saying what was wrong."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must have shape (m, 2), got {p.shape}")
    return p


class GPBaseline:
    """What the GP baselines share: parameters protocol, prediction, grid and summary.

    Subclasses set ``gp_`` (a fitted :class:`SupportGP`), ``timings_``, ``extent_points_``
    (points whose bounding box is the default grid extent), ``path_`` and ``n_inputs_``, and
    implement :meth:`_queries` (query points as the GP's input type) and :meth:`_summary_extra`.
    """

    method_name = "gp"
    chunk_size: int = 4096
    thresholds: tuple[float, float] = DEFAULT_THRESHOLDS

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name."""
        names = [p for p in inspect.signature(type(self).__init__).parameters if p != "self"]
        return {n: getattr(self, n) for n in names}

    def set_params(self, **params: Any) -> GPBaseline:
        """Set constructor arguments by name; returns self."""
        valid = self.get_params()
        for k, v in params.items():
            if k not in valid:
                raise ValueError(f"unknown parameter {k!r} for {type(self).__name__}")
            setattr(self, k, v)
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "gp_"):
            raise NotFittedError(f"this {type(self).__name__} is not fitted yet: call fit() first")

    def _make_gp(self, kernel: Any) -> SupportGP:
        return SupportGP(
            kernel,
            noise=self.noise,
            noise_bounds=self.noise_bounds,
            noise_model=self.noise_model,
            objective=self.objective,
            optimise=self.optimise,
            n_restarts=self.n_restarts,
            seed=self.seed,
        )

    def _queries(self, points: NDArray[np.float64]) -> Any:
        raise NotImplementedError

    def _summary_extra(self) -> dict[str, Any]:
        return {}

    @property
    def hyperparameters_(self) -> dict[str, float]:
        """Learnt hyperparameters: signal variance, length scale, noise, alpha and beta."""
        self._check_fitted()
        gp = self.gp_
        return {
            "variance": gp.kernel.base.variance,
            "length_scale": gp.kernel.base.length_scale,
            "noise": gp.noise,
            "alpha": gp.squash.alpha,
            "beta": gp.squash.beta,
        }

    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latent GP mean (and variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        self._check_fitted()
        t = time.perf_counter()
        mean, var = self.gp_.predict_latent(self._queries(as_points(points)), return_var, self.chunk_size)
        self.timings_["prediction"] = time.perf_counter() - t
        return (mean, var) if return_var else mean

    def predict_proba(self, points: NDArray[np.float64], return_var: bool = False):
        """Occupancy probability at points (the calibrated probit of the latent GP).

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool
            Also return the latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        mean, var = self.predict(points, return_var=True)
        p = self.gp_.squash(mean, var)
        return (p, var) if return_var else p

    def predict_ternary(self, points: NDArray[np.float64]) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, ndarray of shape (m,)."""
        return ternary(self.predict_proba(points), self.thresholds)

    def grid(self, resolution: float, extent: tuple[float, float, float, float] | None = None) -> OccupancyMap:
        """The map sampled at cell centres of a regular grid.

        Parameters
        ----------
        resolution : float
            Grid cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
            Defaults to the bounding box of the training inputs.

        Returns
        -------
        OccupancyMap
        """
        self._check_fitted()
        if extent is None:
            lo = self.extent_points_.min(axis=0)
            hi = self.extent_points_.max(axis=0)
            extent = (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
        spec = GridSpec.from_extent(extent, resolution)
        p, var = self.predict_proba(spec.centres(), return_var=True)
        return OccupancyMap(
            grid=spec,
            probability=p.reshape(spec.shape),
            variance=var.reshape(spec.shape),
            thresholds=self.thresholds,
            path=self.path_,
            info=self.summary(),
        )

    def summary(self) -> dict[str, Any]:
        """What was fitted: settings, data sizes, hyperparameters and stage timings."""
        self._check_fitted()
        out = {
            "method": self.method_name,
            "kernel": make_point_kernel(self.kernel).name,
            "objective": self.objective,
            "noise_model": self.noise_model,
            "n_inputs": self.n_inputs_,
        }
        out.update(self._summary_extra())
        out["hyperparameters"] = self.hyperparameters_
        out["timings"] = dict(self.timings_)
        return out


class GPOM(GPBaseline):
    """GP occupancy map on point inputs (free samples and hits).

    Parameters
    ----------
    kernel : {"se", "matern32"}
        Point kernel.
    free_step : float
        Spacing of free points along beams, metres.
    hit_margin : float, optional
        Free points stop this short of a hit (default half of `free_step`).
    no_return_cap : float, optional
        Free points along a no-return beam go this far (10 m by default, as MSK-GPOM; None: the
        sensor's max range).
    max_points : int, optional
        Most GP inputs. Above it, a seeded random subsample is kept: all hits if they are at most
        half the cap (otherwise half the cap of them, at random), free points for the rest.
        None: no cap (a dense GP on every point; O(n^3) time, O(n^2) memory). Default 2000.
    seed : int
        Seed of the subsample and of the hyperparameter restarts.
    variance, length_scale, noise, length_scale_bounds, noise_bounds, noise_model, objective,
    optimise, n_restarts, thresholds, chunk_size
        As in :class:`gpomap.mapping.AreaGPOM`.
    """

    method_name = "gpom"

    def __init__(
        self,
        kernel: str = "matern32",
        free_step: float = 0.2,
        hit_margin: float | None = None,
        no_return_cap: float | None = 10.0,
        max_points: int | None = 2000,
        seed: int = 0,
        variance: float = 1.0,
        length_scale: float = 1.0,
        noise: float = 0.1,
        length_scale_bounds: tuple[float, float] = (0.05, 20.0),
        noise_bounds: tuple[float, float] = (1e-4, 10.0),
        noise_model: str = "constant",
        objective: str = "loo",
        optimise: bool = True,
        n_restarts: int = 2,
        thresholds: tuple[float, float] = DEFAULT_THRESHOLDS,
        chunk_size: int = 4096,
    ) -> None:
        self.kernel = kernel
        self.free_step = free_step
        self.hit_margin = hit_margin
        self.no_return_cap = no_return_cap
        self.max_points = max_points
        self.seed = seed
        self.variance = variance
        self.length_scale = length_scale
        self.noise = noise
        self.length_scale_bounds = length_scale_bounds
        self.noise_bounds = noise_bounds
        self.noise_model = noise_model
        self.objective = objective
        self.optimise = optimise
        self.n_restarts = n_restarts
        self.thresholds = thresholds
        self.chunk_size = chunk_size

    def __repr__(self) -> str:
        return f"GPOM(kernel={self.kernel!r}, free_step={self.free_step}, max_points={self.max_points})"

    def make_kernel(self) -> AreaKernel:
        """The point kernel (as an area kernel on zero-width supports), at the starting values."""
        base = make_point_kernel(
            self.kernel, variance=self.variance, length_scale=self.length_scale, length_scale_bounds=self.length_scale_bounds
        )
        # On points every area method is the point kernel itself; "exact" is the cheapest for SE.
        return AreaKernel(base, "exact" if base.name == "se" else "quadrature", "mean", 1)

    def subsample(self, occupied: NDArray[np.bool_]) -> NDArray[np.intp]:
        """Indices of the points kept under ``max_points`` (all of them without a cap), sorted.

        Parameters
        ----------
        occupied : ndarray of bool, shape (n,)
        """
        n = occupied.size
        if self.max_points is None or n <= self.max_points:
            return np.arange(n, dtype=np.intp)
        cap = int(self.max_points)
        if cap < 2:
            raise ValueError(f"max_points must be at least 2 (one free, one occupied), got {cap}")
        rng = np.random.default_rng(self.seed)
        hits, free = np.flatnonzero(occupied), np.flatnonzero(~occupied)
        n_hit = min(hits.size, cap // 2)
        n_free = min(free.size, cap - n_hit)
        keep_h = hits if n_hit == hits.size else rng.choice(hits, n_hit, replace=False)
        keep_f = rng.choice(free, n_free, replace=False)
        return np.sort(np.concatenate([keep_h, keep_f]))

    def fit(self, data: Sequence[Scan] | Observations) -> GPOM:
        """Build the map from scans (or from labelled points).

        Parameters
        ----------
        data : sequence of Scan, or Observations

        Returns
        -------
        self
        """
        timings: dict[str, float] = {}
        t = time.perf_counter()
        if isinstance(data, Observations):
            obs = data
        else:
            obs = observations_from_scans(data, self.free_step, self.hit_margin, self.no_return_cap)
        if obs.n_occupied == 0 or obs.n_free == 0:
            raise EmptyDataError(
                f"need both free and occupied observations, got {obs.n_free} free and {obs.n_occupied} occupied"
            )
        keep = self.subsample(obs.occupied)
        X = Supports.from_points(obs.points[keep])
        y = obs.labels[keep]
        timings["observations"] = time.perf_counter() - t
        gp = self._make_gp(self.make_kernel())
        gp.fit(X, y)
        timings.update(gp.timings_)
        self.observations_ = obs
        self.kept_ = keep
        self.gp_ = gp
        self.timings_ = timings
        self.extent_points_ = obs.points
        self.path_ = None if isinstance(data, Observations) else np.array([s.pose[:2] for s in data])
        return self

    @property
    def n_inputs_(self) -> int:
        """Number of GP inputs (points kept)."""
        self._check_fitted()
        return int(self.kept_.size)

    def _queries(self, points: NDArray[np.float64]) -> Supports:
        return Supports.from_points(points)

    def _summary_extra(self) -> dict[str, Any]:
        obs = self.observations_
        occ = obs.occupied[self.kept_]
        return {
            "free_step": self.free_step,
            "max_points": self.max_points,
            "n_free_points": obs.n_free,
            "n_occupied_points": obs.n_occupied,
            "n_free_inputs": int((~occ).sum()),
            "n_occupied_inputs": int(occ.sum()),
            "subsampled": bool(self.kept_.size < obs.points.shape[0]),
            "n_invalid_readings": obs.n_invalid,
            "n_no_return_readings": obs.n_no_return,
        }
