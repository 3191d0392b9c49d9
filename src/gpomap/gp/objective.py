"""A GP's hyperparameter objectives: the log marginal likelihood and the leave-one-out probit likelihood.

Both take the hyperparameters in log space and give analytic gradients; both sum over compact
groups of the inputs (:func:`compact_groups`), each its own GP, evaluated in turn or on threads.
:class:`HyperparameterObjective` is what :class:`~gpomap.gp.SupportGP` searches with.
"""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap import lapack
from gpomap.gp.linalg import (
    _inverse_in_place,
    _trace_product_upper,
    _weighted_outer_upper,
    cholesky_solve,
    noisy_cholesky,
)
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.tensor import TensorDistances
from gpomap.lattice import column_bounds
from gpomap.squash import ProbitSquash, class_weights, loo_probit, probit_gradient_in_shift
from gpomap.supports import Supports

OBJECTIVES = ("loo", "lml")
NOISE_MODELS = ("constant", "per_count")

#: One group of a hyperparameter objective: its inputs, their +-1 targets, and the kernel's
#: ``prepare`` of those inputs (None where the kernel has none).
ObjectivePart = tuple[Supports, NDArray[np.float64], TensorDistances | None]

#: How an objective evaluates its groups: ``run(fn, items)`` is ``[fn(x) for x in items]``, in
#: that order, perhaps on threads (:meth:`SupportGP._group_runner`).
GroupMap = Callable[[Callable[[Any], Any], Sequence[Any]], list[Any]]


def _in_turn(fn: Callable[[Any], Any], items: Sequence[Any]) -> list[Any]:
    """``[fn(x) for x in items]``: the groups of an objective evaluated one after another."""
    return [fn(x) for x in items]


def compact_groups(centres: NDArray[np.float64], max_size: int) -> list[NDArray[np.intp]]:
    """Split points into spatially compact groups of at most `max_size`, by halving at the median.

    A group larger than `max_size` is cut at the median of its widest coordinate into two halves
    (sizes differing by at most one), and each half is split again, so 800 points with
    ``max_size = 200`` give four groups of 200, each a compact patch.

    Parameters
    ----------
    centres : ndarray of shape (n, d)
    max_size : int
        At least 1.

    Returns
    -------
    list of ndarray of int
        Sorted indices into `centres`; every index in exactly one group.
    """
    if max_size < 1:
        raise ValueError(f"max_size must be at least 1, got {max_size}")
    pending = [np.arange(centres.shape[0])]
    groups: list[NDArray[np.intp]] = []
    while pending:
        idx = pending.pop()
        if idx.size <= max_size:
            if idx.size:
                groups.append(np.sort(idx))
            continue
        c = centres[idx]
        c_lo, c_hi = column_bounds(c)
        axis = int(np.argmax(c_hi - c_lo))
        order = np.argsort(c[:, axis], kind="stable")
        half = idx.size // 2
        pending += [idx[order[half:]], idx[order[:half]]]
    return groups


class HyperparameterObjective:
    """The objectives a :class:`~gpomap.gp.SupportGP` learns its hyperparameters by, over its
    kernel, noise and class weights (the attributes below, set by the GP)."""

    kernel: AreaKernel
    noise: float
    noise_model: str
    class_weight: str | None
    n_threads: int

    def _noise_scale(self, X: Supports) -> NDArray[np.float64]:
        if self.noise_model == "per_count":
            return 1.0 / np.maximum(X.counts, 1.0)
        return np.ones(len(X))

    def _factor(self, X: Supports) -> tuple[NDArray[np.float64], float]:
        """Lower Cholesky factor of K + noise at the current hyperparameters, and the jitter it took."""
        # The noise through log space, as the search holds it (the tiles form it the same way,
        # so a map of one tile is this GP to the last bit).
        noise = np.exp(np.log(self.noise)) * self._noise_scale(X)
        return noisy_cholesky(self.kernel(X), noise, lambda: self.kernel(X))

    def _objective_factor(
        self,
        theta: NDArray[np.float64],
        log_noise: float,
        X: Supports,
        eval_gradient: bool,
        prepared: TensorDistances | None = None,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64]]:
        """The objectives' covariance, factorised: what :meth:`_factor` gives, laid out for the gradients.

        `prepared`: the kernel's ``prepare(X)``, reused by its gradient evaluation.

        Returns
        -------
        L : ndarray of shape (n, n), Fortran-ordered
            Lower Cholesky factor of the noisy covariance in its lower triangle; the strict upper
            triangle holds leftovers (LAPACK reads the lower one only).
        K : ndarray of shape (n, n)
            The noise-free covariance, exactly symmetric: dK / dlog(variance).
        dK_dlog_length_scale : ndarray of shape (n, n) or None
            Only with `eval_gradient`; contiguous, unlike a slice of an (n, n, 2) array.
        nvec : ndarray of shape (n,)
            Noise variance of each input: dK / dlog(noise) is diag(nvec).
        """
        kern = self.kernel.clone_with_theta(theta)
        dL: NDArray[np.float64] | None = None
        if hasattr(kern, "gram_and_length_scale_gradient"):
            # Exactly symmetric by construction.
            if eval_gradient:
                K, dL = kern.gram_and_length_scale_gradient(X, prepared)
            else:
                K = kern(X)
        else:
            if eval_gradient:
                K, dK = kern(X, eval_gradient=True)
                dL = np.ascontiguousarray(dK[:, :, 1])
            else:
                K = kern(X)
            K = 0.5 * (K + K.T)
        nvec = np.exp(log_noise) * self._noise_scale(X)
        # Factorised in a copy, which keeps K for the gradient; the upper triangle is not read.
        L, _ = noisy_cholesky(K.copy(), nvec, K.copy, clean=False)
        return L, K, dL, nvec

    @overload
    def log_marginal_likelihood(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: Literal[False] = False
    ) -> float: ...

    @overload
    def log_marginal_likelihood(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: Literal[True]
    ) -> tuple[float, NDArray[np.float64]]: ...

    @overload
    def log_marginal_likelihood(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: bool = False
    ) -> float | tuple[float, NDArray[np.float64]]: ...

    def log_marginal_likelihood(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: bool = False
    ) -> float | tuple[float, NDArray[np.float64]]:
        """Log marginal likelihood at ``params = [log variance, log length_scale, log noise]``.

        Returns
        -------
        value : float
        grad : ndarray of shape (3,), only with `eval_gradient`
        """
        return self._log_marginal_likelihood(X, y, params, eval_gradient)

    def _log_marginal_likelihood(
        self,
        X: Supports,
        y: NDArray[np.float64],
        params: NDArray[np.float64],
        eval_gradient: bool,
        prepared: TensorDistances | None = None,
    ) -> float | tuple[float, NDArray[np.float64]]:
        """:meth:`log_marginal_likelihood`, with the kernel's ``prepare(X)`` (see :meth:`_objective_factor`)."""
        return self._parts_log_marginal_likelihood([(X, y, prepared)], params, eval_gradient)

    def _parts_log_marginal_likelihood(
        self, parts: list[ObjectivePart], params: NDArray[np.float64], eval_gradient: bool, run: GroupMap | None = None
    ) -> float | tuple[float, NDArray[np.float64]]:
        """The log marginal likelihood of independent groups of inputs: the sum of theirs (a block-diagonal K).

        `run`: how the groups are evaluated (:meth:`_group_runner`); default in turn.
        """

        def group(part: ObjectivePart) -> tuple[float, NDArray[np.float64]]:
            X, y, prepared = part
            grad = np.zeros(3)
            L, K, dL, nvec = self._objective_factor(params[:2], params[2], X, eval_gradient, prepared)
            a = cholesky_solve(L, y)
            value = float(-0.5 * y @ a - np.log(np.diag(L)).sum() - 0.5 * y.size * np.log(2 * np.pi))
            if not eval_gradient:
                return value, grad
            assert dL is not None  # asked for with eval_gradient
            K_inv = _inverse_in_place(L)
            # R&W eq. 5.9: 0.5 tr((a a^T - K^-1) dK/dtheta_j), without forming a a^T;
            # dK/dlog(variance) is K itself.
            for j, dK in enumerate((K, dL)):
                grad[j] = 0.5 * (a @ (dK @ a) - np.vdot(K_inv, dK))
            grad[2] = 0.5 * (np.sum(a * a * nvec) - np.sum(np.diag(K_inv) * nvec))
            return value, grad

        terms = (run or _in_turn)(group, parts)
        total = float(sum(t[0] for t in terms))
        return (total, np.sum([t[1] for t in terms], axis=0)) if eval_gradient else total

    @overload
    def loo_objective(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: Literal[False] = False
    ) -> float: ...

    @overload
    def loo_objective(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: Literal[True]
    ) -> tuple[float, NDArray[np.float64]]: ...

    @overload
    def loo_objective(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: bool = False
    ) -> float | tuple[float, NDArray[np.float64]]: ...

    def loo_objective(
        self, X: Supports, y: NDArray[np.float64], params: NDArray[np.float64], eval_gradient: bool = False
    ) -> float | tuple[float, NDArray[np.float64]]:
        """LOO probit log predictive probability at
        ``params = [log variance, log length_scale, log noise, log alpha, beta / alpha]``.

        Returns
        -------
        value : float
        grad : ndarray of shape (5,), only with `eval_gradient`
        """
        return self._loo_objective(X, y, params, eval_gradient)

    def _loo_objective(
        self,
        X: Supports,
        y: NDArray[np.float64],
        params: NDArray[np.float64],
        eval_gradient: bool,
        prepared: TensorDistances | None = None,
        squash: ProbitSquash | None = None,
    ) -> float | tuple[float, NDArray[np.float64]]:
        """:meth:`loo_objective`, with the kernel's ``prepare(X)`` (see :meth:`_objective_factor`).

        With `squash`, alpha and beta are not read from `params`: `squash` is fitted to this
        evaluation's leave-one-out moments (from its own alpha and beta) and they are taken from
        it, so the value is the objective maximised over the squash, and its gradient in the
        kernel's and the noise's parameters that of the maximised objective.
        """
        return self._parts_loo_objective([(X, y, prepared)], params, eval_gradient, squash)

    def _parts_loo_objective(
        self,
        parts: list[ObjectivePart],
        params: NDArray[np.float64],
        eval_gradient: bool,
        squash: ProbitSquash | None = None,
        run: GroupMap | None = None,
    ) -> float | tuple[float, NDArray[np.float64]]:
        """:meth:`_loo_objective` over independent groups of inputs (a block-diagonal K).

        Each group's leave-one-out moments come from its own GP; the class weights and the
        profiled squash are those of all groups' moments together, as for one set of inputs.
        `run`: how the groups are evaluated (:meth:`_group_runner`); default in turn.
        """
        run = run or _in_turn

        def factor(part: ObjectivePart) -> tuple[NDArray[np.float64] | None, ...]:
            X, y, prepared = part
            L, K, dL, nvec = self._objective_factor(params[:2], params[2], X, eval_gradient, prepared)
            K_inv = _inverse_in_place(L)
            return K_inv, K, dL, nvec, K_inv @ y, np.diag(K_inv).copy()

        factors = run(factor, parts)
        y = np.concatenate([part[1] for part in parts])
        a = np.concatenate([f[4] for f in factors])
        d = np.concatenate([f[5] for f in factors])
        mu, var = y - a / d, 1.0 / d
        weights = class_weights(y, self.class_weight)
        if squash is not None:
            squash.fit(y, mu, var, weights)
            alpha, shift = squash.alpha, squash.beta / squash.alpha
        else:
            alpha, shift = float(np.exp(params[3])), float(params[4])
        value, g = loo_probit(y, mu, var, alpha, alpha * shift, weights)
        if not eval_gradient:
            return value
        # R&W section 5.4.2: with Z_j = K^-1 dK_j,
        #   dmu_i = [Z_j a]_i / d_i - a_i [Z_j K^-1]_ii / d_i^2,  dvar_i = [Z_j K^-1]_ii / d_i^2.
        # Summed against the objective's partials g_mu and g_var, with u = g_mu / d and
        # w = (g_var - g_mu a) / d^2 that is
        #   grad_j = (K^-1 u)^T dK_j a + tr(dK_j M),  M = K^-1 diag(w) K^-1,
        # so one n^3 product (M) serves every hyperparameter, each then costing n^2; a
        # block-diagonal K adds its groups' terms.
        gmu_all, gvar_all = np.asarray(g["mu"]), np.asarray(g["var"])
        ends = np.cumsum([0] + [f[4].size for f in factors])

        def gradient(i: int) -> NDArray[np.float64]:
            K_inv, K, dL, nvec, a_g, d_g = factors[i]
            assert dL is not None  # asked for with eval_gradient
            gmu, gvar = gmu_all[ends[i] : ends[i + 1]], gvar_all[ends[i] : ends[i + 1]]
            b = K_inv @ (gmu / d_g)
            M = _weighted_outer_upper(K_inv, (gvar - gmu * a_g) / d_g**2)
            part = np.zeros(3)
            for j, dK in enumerate((K, dL)):
                part[j] = b @ (dK @ a_g) + _trace_product_upper(dK, M)
            # Noise: dK = diag(nvec).
            part[2] = nvec @ (b * a_g + np.diagonal(M))
            return part

        grad = np.zeros(5)
        for part in run(gradient, range(len(factors))):
            grad[:3] += part
        grad[3], grad[4] = probit_gradient_in_shift(g, alpha, shift)
        return value, grad

    @contextmanager
    def _group_runner(self, n_groups: int) -> Iterator[GroupMap]:
        """How a search evaluates its `n_groups` groups: on up to :attr:`n_threads` threads, BLAS held
        to the cores' share of each meanwhile, or in turn. Results come back in the groups' order."""
        threads = min(self.n_threads, n_groups)
        if threads <= 1:
            yield _in_turn
            return
        with lapack.blas_limited(lapack.cores_share(threads)), cf.ThreadPoolExecutor(threads) as pool:
            yield lambda fn, items: list(pool.map(fn, items))
