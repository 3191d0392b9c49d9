"""What every GP occupancy-map estimator shares: the scikit-learn style protocol.

:class:`GPMapEstimator` gives the estimators built on one dense GP (the GP baselines GPOM and
GPOMIK, and grid conversion's :class:`gpomap.convert.GridGPOM`) one interface: ``get_params`` / ``set_params``, ``predict`` (latent mean and
variance), ``predict_proba``, ``predict_ternary``, ``grid`` and the learnt ``hyperparameters_``.
"""

from __future__ import annotations

import inspect
import time
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig
from gpomap.errors import NotFittedError
from gpomap.fusion import ternary_thresholds
from gpomap.gp import SupportGP
from gpomap.grid import DEFAULT_THRESHOLDS, GridSpec, OccupancyMap, ternary
from gpomap.kernels.point import make_point_kernel
from gpomap.lattice import data_extent, extent_bounds
from gpomap.observations import Observations, labelled_observations

if TYPE_CHECKING:
    from gpomap.fusion import EvidenceLayer
    from gpomap.voxels import VoxelMap


def as_points(points: NDArray[np.float64], dim: int = 2) -> NDArray[np.float64]:
    """`points` as a float ndarray of shape (m, dim), or a ValueError saying what was wrong."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != dim:
        raise ValueError(f"points must have shape (m, {dim}) for this {dim}-D map, got {p.shape}")
    return p


class GPMapEstimator:
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
    free_clearance: float = 0.0
    # The baselines' searches minimise the objective's sum (see SupportGP's objective_per_input).
    objective_per_input: bool = False
    # What a subclass's fit sets (no ray evidence unless it builds some).
    evidence_: EvidenceLayer | None = None
    gp_: SupportGP
    timings_: dict[str, float]
    extent_points_: NDArray[np.float64]
    path_: NDArray[np.float64] | None

    @property
    def thresholds_(self) -> tuple[float, float]:
        """The ternary map's (free below, occupied above) probabilities (:func:`gpomap.fusion.ternary_thresholds`)."""
        return ternary_thresholds(self.thresholds, self.evidence_)

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

    def make_observations(self, data: Any) -> Observations:
        """Labelled points from scans (this estimator's ``free_step``, ``hit_margin``,
        ``no_return_cap`` and ``free_clearance``), or `data` itself when it already is (given
        points are taken as they are); both classes are required."""
        return labelled_observations(data, self.free_step, self.hit_margin, self.no_return_cap, self.free_clearance)

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

    @overload
    def predict(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latent GP mean (and variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, d)
            d the map's dimension (:attr:`dim_`).
        return_var : bool

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        self._check_fitted()
        t = time.perf_counter()
        mean, var = self.gp_.predict_latent(self._queries(as_points(points, self.dim_)), return_var, self.chunk_size)
        self.timings_["prediction"] = time.perf_counter() - t
        if not return_var:
            return mean
        assert var is not None  # predict_latent returns it when asked
        return mean, var

    @overload
    def predict_proba(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability at points (the calibrated probit of the latent GP).

        Parameters
        ----------
        points : ndarray of shape (m, d)
            d the map's dimension (:attr:`dim_`).
        return_var : bool
            Also return the latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = as_points(points, self.dim_)
        evidence = self.evidence_
        if evidence is None:
            return self.predict_proba_gp(pts, return_var=return_var)
        p, var, p_unseen = self._gp_probabilities(pts)
        p = evidence.proba(pts, p, p_unseen)
        return (p, var) if return_var else p

    def _gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The GP's probability, latent variance and probability for unseen space at points, each (m,)."""
        mean, var = self.predict(points, return_var=True)
        return self.gp_.squash(mean, var), var, self.gp_.squash.unseen(mean, var)

    @overload
    def predict_proba_gp(self, points: NDArray[np.float64], return_var: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba_gp(
        self, points: NDArray[np.float64], return_var: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The GP's own probability at points (the calibrated probit, before any ray evidence).

        Parameters
        ----------
        points : ndarray of shape (m, d)
        return_var : bool

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        mean, var = self.predict(points, return_var=True)
        p = self.gp_.squash(mean, var)
        return (p, var) if return_var else p

    def predict_ternary(self, points: NDArray[np.float64]) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, ndarray of shape (m,); never occupied
        in a cell beams saw through (:meth:`gpomap.fusion.EvidenceLayer.seen_through_at`)."""
        seen = self.evidence_.seen_through_at(points) if self.evidence_ is not None else None
        return ternary(self.predict_proba(points), self.thresholds_, seen)

    def grid(self, resolution: float, extent: tuple[float, ...] | None = None, supersample: int = 1) -> Any:
        """The map sampled on a regular grid: an OccupancyMap in 2-D, a VoxelMap (:meth:`voxels`) in 3-D.

        Parameters
        ----------
        resolution : float
            Grid cell side, metres.
        extent : (xmin, xmax, ymin, ymax), optional
            Defaults to the bounding box of the training inputs ((..., zmin, zmax) in 3-D).
        supersample : int
            Samples per cell side. 1 samples each cell's centre. K > 1 samples K x K points
            spread over the cell and keeps the largest probability (a cell is as occupied as its
            most occupied part, as an occupancy grid marks a cell a wall crosses anywhere) and
            the mean variance; it costs K^2 as many predictions.

        Returns
        -------
        OccupancyMap, or VoxelMap for a 3-D map
        """
        self._check_fitted()
        if self.dim_ == 3:
            if supersample != 1:
                raise ValueError("supersample is for 2-D maps; a voxel map samples each voxel's centre")
            return self.voxels(resolution, extent)
        if supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {supersample}")
        aligned = extent is None  # the default grid's cells are the ray counts' (no recount)
        if extent is None:
            extent = data_extent(self.extent_points_.min(axis=0), self.extent_points_.max(axis=0), resolution)
        spec = GridSpec.from_extent((extent[0], extent[1], extent[2], extent[3]), resolution, align=aligned)
        evidence = self.evidence_
        if evidence is not None:
            probability, variance, seen_through = evidence.written_grid(
                spec, self.gp_.kernel.base.length_scale, self._gp_probabilities
            )
            return OccupancyMap(
                grid=spec,
                probability=probability,
                variance=variance,
                thresholds=self.thresholds_,
                path=self.path_,
                info=self.summary(),
                seen_through=seen_through,
            )
        k = int(supersample)
        fine = GridSpec(spec.origin, spec.resolution / k, (spec.shape[0] * k, spec.shape[1] * k))
        p, var = self.predict_proba_gp(fine.centres(), return_var=True)
        # Fine row-major (ny*k, nx*k) -> (ny, k, nx, k): one k x k block per output cell.
        blocks = (spec.shape[0], k, spec.shape[1], k)
        return OccupancyMap(
            grid=spec,
            probability=p.reshape(blocks).max(axis=(1, 3)),
            variance=var.reshape(blocks).mean(axis=(1, 3)),
            thresholds=self.thresholds_,
            path=self.path_,
            info=self.summary(),
        )

    def voxels(self, resolution: float, extent: tuple[float, ...] | None = None) -> VoxelMap:
        """A 3-D map sampled on a voxel grid.

        Parameters
        ----------
        resolution : float
            Voxel side, metres.
        extent : (xmin, xmax, ymin, ymax, zmin, zmax), optional
            Defaults to the bounding box of the training inputs. The voxel faces are put on
            multiples of `resolution`, where OctoMap puts its own.

        Returns
        -------
        VoxelMap
            Probability and latent variance per voxel, each of shape (nz, ny, nx). With ray
            evidence, each voxel's own hit and miss counts update the GP's probability there.
        """
        from gpomap.voxels import VoxelMap, VoxelSpec

        self._check_fitted()
        if self.dim_ != 3:
            raise ValueError(f"voxels() is for 3-D maps; this map is {self.dim_}-D: use grid()")
        lo, hi = extent_bounds(
            data_extent(self.extent_points_.min(axis=0), self.extent_points_.max(axis=0), resolution)
            if extent is None
            else extent
        )
        spec = VoxelSpec.from_extent(lo, hi, resolution)
        evidence = self.evidence_
        if evidence is not None:
            probability, variance, _ = evidence.written_grid(spec, self.gp_.kernel.base.length_scale, self._gp_probabilities)
        else:
            p, var = self.predict_proba_gp(spec.centres(), return_var=True)
            probability, variance = p.reshape(spec.shape), var.reshape(spec.shape)
        observed = evidence.grid_observed(spec) if evidence is not None else None
        return VoxelMap(spec, probability, variance, thresholds=self.thresholds_, info=self.summary(), observed=observed)

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
