"""GPOM (O'Callaghan & Ramos 2012): the same GP as MSK-GPOM, on point inputs.

Free samples along the beams and the hits are the GP's inputs, one point each, with targets -1
and +1. The GP core (:class:`gpomap.gp.SupportGP`: hyperparameter objective, noise, probit
squash) is the one MSK-GPOM uses, so the comparison isolates the choice of inputs. A dense GP is
O(n^3) in the points, so ``max_points`` caps them (a seeded random subsample; see
:meth:`GPOM.fit`).

:class:`gpomap.estimator.GPMapEstimator` gives it the estimator protocol of
:class:`gpomap.mapping.AreaGPOM` (``predict``, ``predict_proba``, ``grid``, ``summary``...).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.estimator import GPMapEstimator
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.point import make_point_kernel
from gpomap.observations import Observations
from gpomap.scans import Scan
from gpomap.supports import Supports


class GPOM(GPMapEstimator):
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
        As in :class:`gpomap.settings.MapSettings`.
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
        # On points every area method is the point kernel itself; the one-node quadrature takes the
        # compiled tensor path for both kernels (SE's closed form costs erfs per pair, far slower).
        return AreaKernel(base, "quadrature", "mean", 1)

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
        obs = self.make_observations(data)
        keep = self.subsample(obs.occupied)
        X = Supports.from_points(obs.points[keep])
        y = obs.labels[keep]
        timings["observations"] = time.perf_counter() - t
        gp = self._make_gp(self.make_kernel())
        self._fit_gp(gp, X, y)
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
