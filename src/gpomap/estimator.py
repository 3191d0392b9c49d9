"""What every GP occupancy-map estimator shares: the scikit-learn style protocol.

:class:`GPMapEstimator` gives the estimators built on one dense GP (the GP baselines GPOM and
GPOMIK, and grid conversion's :class:`gpomap.convert.GridGPOM`) one interface: ``get_params`` /
``set_params``, the learnt ``hyperparameters_``, and the fitted map ``map_``
(:class:`~gpomap.fitted.FittedMap`, over a :class:`DenseField`) whose answers (``predict``,
``predict_proba``, ``predict_ternary``, ``grid``) are the estimator's.
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig
from gpomap.errors import NotFittedError
from gpomap.extrapolation import VarianceScale
from gpomap.fitted import FittedMap, GPHyperparameters, MapAnswers, as_points
from gpomap.gp import SupportGP
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.kernels.point import make_point_kernel
from gpomap.lapack import blas_on
from gpomap.observations import Observations, labelled_observations
from gpomap.squash import ProbitSquash
from gpomap.stages import CalibratedMoments, GPProbability

if TYPE_CHECKING:
    from gpomap.fusion import EvidenceLayer

__all__ = ["DenseField", "GPMapEstimator", "as_points", "squash_latent"]


def squash_latent(squash: ProbitSquash, mean: NDArray[np.float64], var: NDArray[np.float64]) -> GPProbability:
    """One GP's probabilities from its latent moments, through the map's squash stage
    (:class:`gpomap.extrapolation.VarianceScale`, at the squash's variance scale) on the moments
    calibrated by its squash (:meth:`gpomap.squash.ProbitSquash.calibrated`).

    Parameters
    ----------
    squash : ProbitSquash
        The GP's.
    mean, var : ndarray
        Latent mean and variance, matching shapes.

    Returns
    -------
    GPProbability
        The probability and the probability for unseen space, each of the shape of `mean`.
    """
    return VarianceScale(squash.variance_scale).apply(CalibratedMoments(*squash.calibrated(mean, var)))


class DenseField:
    """One dense GP, as a fitted map asks it (:class:`~gpomap.fitted.LatentField`).

    Parameters
    ----------
    gp : SupportGP
        The fitted GP.
    queries : callable
        Points of shape (m, d) to the GP's inputs (points, or zero-size supports).
    dim : int
        The map's dimension d.
    chunk_size : int
        Points predicted at once.
    """

    def __init__(self, gp: SupportGP, queries: Callable[[NDArray[np.float64]], Any], dim: int, chunk_size: int) -> None:
        self.gp = gp
        self._queries = queries
        self._dim = dim
        self._chunk_size = chunk_size

    @property
    def dim(self) -> int:
        """2 for a planar map, 3 for point clouds."""
        return self._dim

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """The GP's hyperparameters."""
        return GPHyperparameters(self.gp.kernel.base.variance, self.gp.kernel.base.length_scale, self.gp.noise)

    @property
    def squash(self) -> ProbitSquash:
        """The GP's calibrated probit."""
        return self.gp.squash

    @property
    def blended(self) -> None:
        """None: a dense GP's written grid takes its variance at every sample."""
        return None

    def latent(self, points: NDArray[np.float64], return_var: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Latent mean at points, shape (m,), and variance (m,) when asked."""
        return self.gp.predict_latent(self._queries(points), return_var, self._chunk_size)

    def gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The GP's probability, latent variance and probability for unseen space, each (m,)."""
        mean, var = self.latent(points, True)
        assert var is not None  # asked for
        gp = squash_latent(self.gp.squash, mean, var)
        return gp.probability, var, gp.unseen

    def limited(self) -> contextlib.AbstractContextManager[Any]:
        """The BLAS threads to numpy's library, whose products are most of a dense GP's prediction
        (:func:`gpomap.lapack.blas_on`)."""
        return blas_on("numpy")

    def forget_below(self, y: float) -> None:
        """Nothing to let go of: the GP's factor is its whole state."""

    def grid_done(self) -> None:
        """Nothing to give back."""


class GPMapEstimator(MapAnswers):
    """What the GP map estimators share: parameters protocol, prediction, grid and summary.

    Subclasses set ``gp_`` (a fitted :class:`SupportGP`), ``timings_``, ``extent_points_``
    (points whose bounding box is the default grid extent), ``path_`` and ``n_inputs_``, and
    implement :meth:`_queries` (query points as the GP's input type) and :meth:`_summary_extra`.
    """

    method_name = "gp"
    chunk_size: int = 4096
    thresholds: tuple[float, float] | None = DEFAULT_THRESHOLDS
    # Settings every subclass takes in its constructor, declared for the code shared here.
    kernel: str
    free_step: float
    hit_margin: float | None
    no_return_cap: float | None
    noise: float
    noise_bounds: tuple[float, float]
    noise_model: str
    objective: str
    optimise: bool
    n_restarts: int
    seed: int
    # Settings only MSK-GPOM's (MapSettings) take, which its constructor sets; these are the
    # baselines' fixed choices: hyperparameters learnt on every input, the same weak prior and
    # class balance as MSK-GPOM's defaults, no free clearance.
    hyper_subset: int | None = None
    prior_std: float | None = MapConfig.prior_std
    class_weight: str | None = MapConfig.class_weight
    free_clearance: float | None = 0.0
    # The baselines' searches minimise the objective's sum (see SupportGP's objective_per_input).
    objective_per_input: bool = False
    # What a subclass's fit sets (no ray evidence unless it builds some).
    evidence_: EvidenceLayer | None = None
    gp_: SupportGP
    timings_: dict[str, float]
    extent_points_: NDArray[np.float64]
    path_: NDArray[np.float64] | None

    @property
    def map_(self) -> FittedMap:
        """The fitted map: the dense GP under the ray evidence, if any (:class:`~gpomap.fitted.FittedMap`)."""
        self._check_fitted()
        pts = self.extent_points_
        return FittedMap(
            self._field(),
            self.evidence_,
            self.thresholds,
            pts.min(axis=0),
            pts.max(axis=0),
            self.path_,
            self.summary,
            self.timings_,
        )

    @property
    def n_inputs_(self) -> int:
        """Number of GP inputs (defined by each subclass)."""
        raise NotImplementedError

    @property
    def dim_(self) -> int:
        """Dimension of the fitted map: 2 for planar scans, 3 for point clouds."""
        self._check_fitted()
        return int(self.extent_points_.shape[1])

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name."""
        names = [p for p in inspect.signature(type(self).__init__).parameters if p != "self"]
        return {n: getattr(self, n) for n in names}

    def set_params(self, **params: Any) -> GPMapEstimator:
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
            # Only MSK-GPOM samples cells for its hyperparameters; the baselines use every input.
            hyper_subset=self.hyper_subset,
            prior_std=self.prior_std,
            class_weight=self.class_weight,
            objective_per_input=self.objective_per_input,
        )

    @staticmethod
    def _fit_gp(gp: SupportGP, X: Any, y: NDArray[np.float64]) -> None:
        """Fit the dense GP on inputs `X` (n of them) and targets `y` (n,), the BLAS threads on the
        library its factorisations run in (:func:`gpomap.lapack.blas_on`)."""
        with blas_on("scipy"):
            gp.fit(X, y)

    def _field(self) -> DenseField:
        """The GP under the fitted map (a subclass that answers otherwise gives its own field)."""
        return DenseField(self.gp_, self._queries, self.extent_points_.shape[1], self.chunk_size)

    def make_observations(self, data: Any) -> Observations:
        """Labelled points from scans (this estimator's ``free_step``, ``hit_margin``,
        ``no_return_cap`` and ``free_clearance``), or `data` itself when it already is (given
        points are taken as they are); both classes are required."""
        return labelled_observations(data, self.free_step, self.hit_margin, self.no_return_cap, self.free_clearance or 0.0)

    def _queries(self, points: NDArray[np.float64]) -> Any:
        raise NotImplementedError

    def _summary_extra(self) -> dict[str, Any]:
        return {}

    @property
    def hyperparameters_(self) -> dict[str, float]:
        """Learnt hyperparameters: signal variance, length scale, noise, alpha, beta and the variance scale."""
        self._check_fitted()
        gp = self.gp_
        return {
            "variance": gp.kernel.base.variance,
            "length_scale": gp.kernel.base.length_scale,
            "noise": gp.noise,
            "alpha": gp.squash.alpha,
            "beta": gp.squash.beta,
            "variance_scale": gp.squash.variance_scale,
        }

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
