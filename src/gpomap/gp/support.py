"""The GP over cells and points (:class:`SupportGP`): its hyperparameter search, factor and squash.

The model is zero-mean GP regression on +-1 targets over :class:`~gpomap.supports.Supports`;
its objectives are in :mod:`gpomap.gp.objective`, the fitted GP it makes in
:mod:`gpomap.gp.posterior`.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from gpomap.config import MapConfig
from gpomap.errors import NotFittedError, NumericalError
from gpomap.gp.linalg import cholesky_solve, inverse_diagonal
from gpomap.gp.objective import NOISE_MODELS, OBJECTIVES, HyperparameterObjective, ObjectivePart, compact_groups
from gpomap.gp.posterior import GPPosterior
from gpomap.kernels.area import AreaKernel
from gpomap.squash import CLASS_WEIGHTS, SQUASH_BOUNDS, ProbitSquash, class_weights
from gpomap.supports import Supports


@dataclass
class FitReport:
    """What hyperparameter learning did: the objective, its value, and the time and evaluations spent."""

    objective: str
    value: float
    n_evaluations: int
    seconds: float
    restarts: list[float] = field(default_factory=list)
    groups: int = 1


class SupportGP(HyperparameterObjective):
    """Zero-mean GP over cells and points, with a calibrated probit squash.

    Parameters
    ----------
    kernel : AreaKernel
        Covariance function; its hyperparameters are the starting point of the search.
    noise : float
        Noise variance (starting point when optimised).
    noise_bounds : (float, float)
        Bounds of the noise variance.
    noise_model : {"constant", "per_count"}
        ``"per_count"`` divides the noise of each input by its member count: a cell averaging
        m observations is m times surer than one point (matches the "mean" normalisation).
    objective : {"loo", "lml"}
        Hyperparameter objective (see module docstring).
    optimise : bool
        Learn hyperparameters; False keeps the given ones (alpha and beta are still fitted).
    n_restarts : int
        Extra random starts (log-uniform within the bounds, seeded) beyond the given one.
    seed : int
        Seed of the restarts.
    max_iter : int
        Iteration cap of each L-BFGS-B run.
    prior_std : float or None
        Standard deviation, in log space, of a weak log-normal prior on the length scale and the
        noise centred on their starting values (added to either objective); None: no prior.
    hyper_subset : int or None
        Learn hyperparameters on at most this many inputs: a spatially compact block (the
        inputs nearest a seeded random one), so the sample keeps the data's density. The final
        model always uses every input. None uses all inputs.
    class_weight : {"balanced", None}
        Weighting of the leave-one-out terms (in the "loo" objective and the squash fit):
        "balanced" gives free and occupied inputs the same total weight (see
        :func:`gpomap.squash.class_weights`); None counts every input once.
    hyper_group : int or None
        Learn hyperparameters on the sample cut into compact groups of at most this many inputs
        (:func:`compact_groups`), each its own GP: the objective sums the groups' terms, as if
        inputs of different groups did not covary. The O(n^3) work of an evaluation falls by
        the square of the number of groups, while every input of the sample still counts.
        None: one GP over the whole sample.
    objective_per_input : bool
        The search minimises the objective's mean over the inputs instead of its sum: the same
        optimum. L-BFGS-B's first step is the gradient itself (its first quadratic model has unit
        curvature), which on a sum over hundreds of inputs runs to a corner of the bounds; per
        input MSK-GPOM's searches take fewer evaluations (docs/choices.md). False (the sum) for
        the baselines, whose searches it lengthens.
    n_threads : int
        Threads of this process the search's groups are evaluated on (their factorisations,
        inverses and kernel sums run without the GIL), BLAS held to the cores' share of each
        meanwhile; 1 evaluates them in turn. The same numbers either way when BLAS runs on one
        thread (its threads split sums differently).

    Attributes
    ----------
    posterior_ : GPPosterior
        What :meth:`fit` made: the inputs, the factor, the weights, the learnt kernel and squash.
    X_train_, y_train_ : Supports, ndarray of shape (n,)
        The training inputs and targets.
    fit_report_ : FitReport or None
        What the hyperparameter search did (None without ``optimise``).
    timings_ : dict
        Seconds of the fit's stages.
    """

    def __init__(
        self,
        kernel: AreaKernel,
        noise: float = MapConfig.noise,
        noise_bounds: tuple[float, float] = (1e-4, 10.0),
        noise_model: str = "constant",
        objective: str = MapConfig.objective,
        optimise: bool = MapConfig.optimise,
        n_restarts: int = 1,
        seed: int = 0,
        max_iter: int = 100,
        hyper_subset: int | None = MapConfig.hyper_subset,
        prior_std: float | None = MapConfig.prior_std,
        class_weight: str | None = MapConfig.class_weight,
        hyper_group: int | None = None,
        objective_per_input: bool = False,
        n_threads: int = 1,
    ) -> None:
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
        if noise_model not in NOISE_MODELS:
            raise ValueError(f"noise_model must be one of {NOISE_MODELS}, got {noise_model!r}")
        if not noise > 0:
            raise ValueError(f"noise variance must be positive, got {noise}")
        self.kernel = kernel
        self.noise = float(noise)
        self.noise_bounds = (float(noise_bounds[0]), float(noise_bounds[1]))
        self.noise_model = noise_model
        self.objective = objective
        self.optimise = optimise
        self.n_restarts = int(n_restarts)
        self.seed = int(seed)
        self.max_iter = int(max_iter)
        self.hyper_subset = hyper_subset
        self.prior_std = prior_std
        if class_weight not in CLASS_WEIGHTS:
            raise ValueError(f"class_weight must be one of {CLASS_WEIGHTS}, got {class_weight!r}")
        self.class_weight = class_weight
        if hyper_group is not None and hyper_group < 1:
            raise ValueError(f"hyper_group must be at least 1, got {hyper_group}")
        self.hyper_group = hyper_group
        self.objective_per_input = objective_per_input
        if n_threads < 1:
            raise ValueError(f"n_threads must be at least 1, got {n_threads}")
        self.n_threads = int(n_threads)
        self.squash = ProbitSquash()

    # ----------------------------------------------------------------- fitting
    def fit(self, X: Supports, y: NDArray[np.float64]) -> SupportGP:
        """Learn hyperparameters (unless ``optimise=False``), factorise, and calibrate the squash.

        Parameters
        ----------
        X : Supports
            n training inputs.
        y : ndarray of shape (n,)
            Targets, +1 occupied and -1 free.

        Returns
        -------
        self
        """
        y = np.asarray(y, dtype=float)
        if y.shape != (len(X),):
            raise ValueError(f"y must have shape ({len(X)},), got {y.shape}")
        self.X_train_ = X
        self.y_train_ = y
        # Learn on a copy: the kernel given to the constructor is the caller's, never changed.
        self.kernel = self.kernel.clone_with_theta(self.kernel.theta)
        t0 = time.perf_counter()
        self.fit_report_ = None
        if self.optimise:
            idx = self.hyperparameter_sample(X)
            self.fit_report_ = self._optimise(X.subset(idx), y[idx])
        t1 = time.perf_counter()
        L, jitter = self._factor(X)
        weights = cholesky_solve(L, y)
        t2 = time.perf_counter()
        # alpha and beta for the full model: from its own leave-one-out moments.
        # Leave-one-out moments (R&W eq. 5.12) need only K^-1 y and diag(K^-1).
        d = inverse_diagonal(L)
        mu, var = y - weights / d, 1.0 / d
        self.squash.fit(y, mu, var, class_weights(y, self.class_weight))
        self.posterior_ = GPPosterior(X, L, weights, self.kernel, self.squash, jitter)
        self.timings_ = {"hyperparameters": t1 - t0, "factorisation": t2 - t1, "squash": time.perf_counter() - t2}
        return self

    def hyperparameter_sample(self, X: Supports) -> NDArray[np.intp]:
        """Indices of the inputs hyperparameters are learnt on, ndarray of shape (k,).

        All inputs when ``hyper_subset`` is None or not smaller than their number; otherwise the
        ``hyper_subset`` inputs nearest (by centre) to one chosen with the seed.
        """
        n = len(X)
        if self.hyper_subset is None or n <= self.hyper_subset:
            return np.arange(n)
        centres = X.centres
        rng = np.random.default_rng(self.seed)
        anchor = centres[rng.integers(n)]
        dist = np.sum((centres - anchor) ** 2, axis=1)
        return np.sort(np.argpartition(dist, self.hyper_subset - 1)[: self.hyper_subset])

    def _optimise(self, X: Supports, y: NDArray[np.float64]) -> FitReport:
        loo = self.objective == "loo"
        k_bounds = self.kernel.bounds
        bounds = [tuple(k_bounds[0]), tuple(k_bounds[1]), tuple(np.log(self.noise_bounds))]
        x0_list = [*self.kernel.theta, np.log(self.noise)]
        free = np.array([True, True, True])
        if loo:
            # Signal variance is not identifiable by LOO (see module docstring): hold it.
            free[0] = False
            bounds += list(SQUASH_BOUNDS)
            x0_list += [np.log(max(self.squash.alpha, 1e-3)), self.squash.beta / max(self.squash.alpha, 1e-3)]
            # The squash is profiled out: at each length scale and noise it is fitted to the
            # leave-one-out moments (O(n) an evaluation, from the last one's alpha), so the search
            # runs over two numbers instead of four, in fewer evaluations of the O(n^3) objective
            # (docs/choices.md, "Measured for the code").
            free = np.concatenate([free, [False, False]])
        x0 = np.asarray(x0_list, dtype=float)
        profiled = ProbitSquash(max(self.squash.alpha, 1e-3), self.squash.beta) if loo else None
        squash_at: dict[bytes, tuple[float, float]] = {}  # the profiled squash of each point evaluated
        # The sample's groups, each with what the kernel can reuse between evaluations on it (the
        # quadrature's node distances), held for this search only.
        groups = [np.arange(len(X))] if self.hyper_group is None else compact_groups(X.centres, self.hyper_group)
        parts: list[ObjectivePart] = []
        for g in groups:
            Xg = X if g.size == len(X) else X.subset(g)
            parts.append((Xg, y[g], self.kernel.prepare(Xg) if hasattr(self.kernel, "prepare") else None))
        n_eval = 0
        # What the search minimises is scaled by this (see objective_per_input); the values
        # reported are the objective's own.
        per_input = 1.0 / max(len(y), 1) if self.objective_per_input else 1.0

        def neg(z: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            nonlocal n_eval
            n_eval += 1
            p = x0.copy()
            p[free] = z
            try:
                out = fun(p, True)
                assert isinstance(out, tuple)  # asked for the gradient
                v, g = out
            except NumericalError:
                return 1e25, np.zeros(int(free.sum()))
            if profiled is not None:
                squash_at[z.tobytes()] = (profiled.alpha, profiled.beta)
            if self.prior_std is not None:
                # A weak log-normal prior on length scale and noise, centred on the starting
                # values: where the data pin them down it hardly moves them; where the objective
                # is flat (separable cells) it keeps them from drifting to their bounds.
                d = (p[1:3] - x0[1:3]) / self.prior_std
                v = v - 0.5 * float(d @ d)
                g = g.copy()
                g[1:3] -= d / self.prior_std
            return -v * per_input, -g[free] * per_input

        free_bounds = [b for b, f in zip(bounds, free) if f]
        rng = np.random.default_rng(self.seed)
        starts = [x0[free]]
        for _ in range(self.n_restarts):
            s = x0[free].copy()
            # Restart the kernel and noise hyperparameters anywhere in their bounds; alpha and
            # beta from their defaults.
            for i, (lo, hi) in enumerate(free_bounds[: 2 if loo else 3]):
                s[i] = rng.uniform(lo, hi)
            starts.append(s)
        t0 = time.perf_counter()
        best = None
        values = []
        with self._group_runner(len(groups)) as run:
            fun = (
                functools.partial(self._parts_loo_objective, parts, squash=profiled, run=run)
                if loo
                else functools.partial(self._parts_log_marginal_likelihood, parts, run=run)
            )
            for s in starts:
                res = minimize(
                    neg, s, jac=True, method="L-BFGS-B", bounds=free_bounds, options={"maxiter": self.max_iter, "ftol": 1e-7}
                )
                values.append(float(-res.fun) / per_input)
                if best is None or res.fun < best.fun:
                    best = res
            assert best is not None  # there is always the given start
            if loo and best.x.tobytes() not in squash_at:  # the optimiser's answer is a point it evaluated
                neg(best.x)
        p = x0.copy()
        p[free] = best.x
        self.kernel.theta = p[:2]
        self.noise = float(np.exp(p[2]))
        if loo:
            self.squash = ProbitSquash(*squash_at[best.x.tobytes()])
        return FitReport(self.objective, float(-best.fun) / per_input, n_eval, time.perf_counter() - t0, values, len(groups))

    # ----------------------------------------------------------------- the fitted posterior
    @property
    def L_(self) -> NDArray[np.float64]:
        """Lower Cholesky factor of K + noise over the training inputs, ndarray of shape (n, n)."""
        return self._posterior().L

    @property
    def alpha_(self) -> NDArray[np.float64]:
        """(K + noise)^-1 y, ndarray of shape (n,)."""
        return self._posterior().weights

    def _posterior(self) -> GPPosterior:
        if not hasattr(self, "posterior_"):
            raise NotFittedError("this model is not fitted yet: call fit() first")
        return self.posterior_

    # ----------------------------------------------------------------- prediction
    def predict_latent(
        self, X: Supports, return_var: bool = True, chunk_size: int = MapConfig.chunk_size, local: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Latent mean and variance at new inputs: :meth:`GPPosterior.latent` of the fitted posterior.

        Parameters
        ----------
        X : Supports
            m query inputs (points or cells).
        return_var : bool
        chunk_size : int
            Query inputs per chunk.
        local : bool
            Local prediction where it pays (equal to the dense one to ``LOCAL_TOL``); False:
            always dense.

        Returns
        -------
        mean : ndarray of shape (m,)
        var : ndarray of shape (m,) or None
            Variance of the latent function (without observation noise).
        """
        return self._posterior().latent(X, return_var, local, chunk_size)

    def predict_proba(
        self, X: Supports, chunk_size: int = MapConfig.chunk_size
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability and latent variance at new inputs, each ndarray of shape (m,)."""
        mean, var = self.predict_latent(X, True, chunk_size)
        assert var is not None  # asked for with return_var=True
        return self.squash(mean, var), var
