"""Stationary point kernels with hyperparameters in log space (the scikit-learn convention).

Each kernel has two hyperparameters, the signal variance and the length scale; ``theta`` holds
their logarithms and ``bounds`` the log bounds. Calling a kernel returns the Gram matrix and, on
request, its gradient with respect to ``theta``, shape (n, m, 2).
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig

HYPERPARAMETERS: tuple[str, str] = ("variance", "length_scale")


def squared_distances(X: NDArray[np.float64], Y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pairwise squared Euclidean distances, ndarray of shape (n, m), never negative.

    Parameters
    ----------
    X : ndarray of shape (n, d)
    Y : ndarray of shape (m, d)
    """
    # Per-dimension differences: exact (no cancellation from the |x|^2 + |y|^2 - 2xy expansion)
    # and cheap for d = 2.
    d2 = np.zeros((X.shape[0], Y.shape[0]))
    for k in range(X.shape[1]):
        diff = X[:, k, None] - Y[None, :, k]
        d2 += diff * diff
    return d2


class PointKernel(ABC):
    """A stationary kernel ``variance * profile(r / length_scale)`` on points.

    Parameters
    ----------
    variance : float
        Signal variance, k(x, x).
    length_scale : float
        Length scale, in the units of the inputs (metres).
    variance_bounds, length_scale_bounds : (float, float)
        Bounds used by the optimiser (in natural units; ``bounds`` gives their logs).
    """

    name: str = "point"

    def __init__(
        self,
        variance: float = MapConfig.variance,
        length_scale: float = MapConfig.length_scale,
        variance_bounds: tuple[float, float] = (1e-3, 1e3),
        length_scale_bounds: tuple[float, float] = (1e-2, 1e2),
    ) -> None:
        if not (variance > 0 and length_scale > 0):
            raise ValueError(f"variance and length_scale must be positive, got {variance}, {length_scale}")
        self.variance = float(variance)
        self.length_scale = float(length_scale)
        self.variance_bounds = (float(variance_bounds[0]), float(variance_bounds[1]))
        self.length_scale_bounds = (float(length_scale_bounds[0]), float(length_scale_bounds[1]))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(variance={self.variance:.4g}, length_scale={self.length_scale:.4g})"

    @property
    def theta(self) -> NDArray[np.float64]:
        """Log hyperparameters [log variance, log length_scale], ndarray of shape (2,)."""
        return np.log([self.variance, self.length_scale])

    @theta.setter
    def theta(self, value: NDArray[np.float64]) -> None:
        self.variance, self.length_scale = (float(v) for v in np.exp(np.asarray(value, dtype=float)))

    @property
    def bounds(self) -> NDArray[np.float64]:
        """Log bounds of ``theta``, ndarray of shape (2, 2)."""
        return np.log([self.variance_bounds, self.length_scale_bounds])

    def clone_with_theta(self, theta: NDArray[np.float64]) -> PointKernel:
        """A copy of this kernel with hyperparameters `theta`."""
        k = copy.copy(self)
        k.theta = theta
        return k

    @abstractmethod
    def values(
        self, d2: NDArray[np.float64], eval_gradient: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Kernel values for squared distances `d2` (any shape), and their derivative with
        respect to log length scale (the one with respect to log variance is the value itself).

        Returns
        -------
        K : ndarray, the shape of `d2`
        dK_dlog_length_scale : ndarray, the shape of `d2`, or None without `eval_gradient`
        """

    def values_into(
        self,
        d2: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        """:meth:`values` written into given arrays (the same numbers), for hot loops over blocks.

        Parameters
        ----------
        d2 : ndarray
            Squared distances; may be overwritten.
        out : ndarray, the shape of `d2`
            Receives the kernel values.
        grad : ndarray, the shape of `d2`, optional
            Receives the derivative with respect to log length scale.
        work : ndarray, the shape of `d2`, optional
            Scratch space.
        """
        K, dl = self.values(d2, grad is not None)
        out[...] = K
        if grad is not None:
            assert dl is not None  # values() returns the derivative when asked for it
            grad[...] = dl

    @property
    def unit_scale(self) -> float | None:
        """c such that k(r) = variance * profile((c r)^2), or None when the kernel has no such form.

        Hot loops (:mod:`gpomap.kernels.tensor`) scale the coordinates by c once and evaluate
        :meth:`unit_profile_into`, which saves the per-entry scaling of :meth:`values`.
        """
        return None

    def unit_profile_into(
        self,
        u2: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        """The profile at scaled squared distances `u2` (kernel values over the variance), into `out`.

        Parameters
        ----------
        u2 : ndarray
            Squared distances of coordinates scaled by :attr:`unit_scale`; may be overwritten.
        out : ndarray, the shape of `u2`
            Receives profile(u2).
        grad : ndarray, the shape of `u2`, optional
            Receives its derivative with respect to log length scale (over the variance).
        work : ndarray, the shape of `u2`, optional
            Scratch space.
        """
        raise NotImplementedError(f"{type(self).__name__} has no unit profile (unit_scale is None)")

    def unit_profile_from_negated_distance_into(
        self,
        v: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        """:meth:`unit_profile_into` from negated scaled distances ``v = -u`` (not squared), into `out`.

        For hot loops that have the distances already (:func:`gpomap.kernels.tensor.tensor_distances`
        keeps them negated): kernels of the distance itself (Matern 3/2) then need neither a
        square root nor a negation before their exponential.

        Parameters
        ----------
        v : ndarray
            Minus the distances of coordinates scaled by :attr:`unit_scale`; may be overwritten.
        out, grad, work : ndarray
            As for :meth:`unit_profile_into`.
        """
        np.multiply(v, v, out=v)
        self.unit_profile_into(v, out, grad, work)

    def from_sqdist(
        self, d2: NDArray[np.float64], eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Kernel values for squared distances `d2` (any shape), and optionally the gradient.

        Returns
        -------
        K : ndarray, the shape of `d2`
        dK : ndarray of shape ``d2.shape + (2,)``, only with `eval_gradient`
            Derivatives with respect to log variance and log length scale.
        """
        K, dl = self.values(d2, eval_gradient)
        if not eval_gradient:
            return K
        assert dl is not None  # values() returns the derivative when asked for it
        return K, np.stack([K, dl], axis=-1)

    def __call__(
        self, X: NDArray[np.float64], Y: NDArray[np.float64] | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Gram matrix between point sets.

        Parameters
        ----------
        X : ndarray of shape (n, d)
        Y : ndarray of shape (m, d), optional
            Defaults to `X`.
        eval_gradient : bool
            Also return dK/dtheta, ndarray of shape (n, m, 2).

        Returns
        -------
        K : ndarray of shape (n, m)
        dK : ndarray of shape (n, m, 2), only with `eval_gradient`
        """
        X = np.atleast_2d(np.asarray(X, dtype=float))
        Y = X if Y is None else np.atleast_2d(np.asarray(Y, dtype=float))
        return self.from_sqdist(squared_distances(X, Y), eval_gradient)

    def diag(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """k(x, x) for each row of `X`, ndarray of shape (n,)."""
        return np.full(np.atleast_2d(X).shape[0], self.variance)

    def cutoff(self, tol: float = 1e-10) -> float:
        """Distance beyond which the kernel is below `tol` times its variance (to 0.1 %)."""

        def above(r: float) -> bool:
            return bool(self.values(np.array(r * r))[0] > tol * self.variance)

        lo, hi = 0.0, self.length_scale
        while above(hi):
            lo, hi = hi, 2.0 * hi
        # Both profiles decrease with distance: bisect down to a 0.1 % bracket, keep the far end.
        while hi - lo > 1e-3 * hi:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if above(mid) else (lo, mid)
        return hi


class SquaredExponential(PointKernel):
    """k(r) = variance * exp(-r^2 / (2 l^2))."""

    name = "se"

    def values(
        self, d2: NDArray[np.float64], eval_gradient: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        l2 = self.length_scale**2
        K = self.variance * np.exp(-0.5 * d2 / l2)
        # d/dlog(l) = K * r^2 / l^2.
        return K, (K * (d2 / l2) if eval_gradient else None)

    @property
    def unit_scale(self) -> float:
        """1 / l: k = variance * exp(-u^2 / 2) with u = r / l (see :meth:`PointKernel.unit_scale`)."""
        return 1.0 / self.length_scale

    def unit_profile_into(
        self,
        u2: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        np.multiply(u2, -0.5, out=out)
        np.exp(out, out=out)
        if grad is not None:
            # d/dlog(l) of exp(-u^2 / 2) with u = r / l is u^2 exp(-u^2 / 2).
            np.multiply(out, u2, out=grad)


class Matern32(PointKernel):
    """k(r) = variance * (1 + sqrt(3) r / l) * exp(-sqrt(3) r / l)."""

    name = "matern32"

    def values(
        self, d2: NDArray[np.float64], eval_gradient: bool = False
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        s = np.sqrt(3.0 * d2) / self.length_scale
        e = np.exp(-s)
        K = self.variance * (1.0 + s) * e
        # d/dl of (1 + s) e^-s with ds/dl = -s/l is s^2 e^-s / l; times l for log space.
        return K, (self.variance * s * s * e if eval_gradient else None)

    @property
    def unit_scale(self) -> float:
        """sqrt(3) / l: k = variance * (1 + u) exp(-u) with u = sqrt(3) r / l (see :meth:`PointKernel.unit_scale`)."""
        return math.sqrt(3.0) / self.length_scale

    def unit_profile_into(
        self,
        u2: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        u = np.empty_like(u2) if work is None else work
        np.sqrt(u2, out=u)
        # e^-u into grad when the gradient is asked for (it needs u^2 after), else where u^2 was.
        e = u2 if grad is None else grad
        np.negative(u, out=e)
        np.exp(e, out=e)
        np.add(u, 1.0, out=out)
        out *= e
        if grad is not None:
            # d/dlog(l) of (1 + u) e^-u with du/dlog(l) = -u is u^2 e^-u.
            grad *= u2

    def unit_profile_from_negated_distance_into(
        self,
        v: NDArray[np.float64],
        out: NDArray[np.float64],
        grad: NDArray[np.float64] | None = None,
        work: NDArray[np.float64] | None = None,
    ) -> None:
        e = np.empty_like(v) if work is None else work
        np.exp(v, out=e)
        # (1 + u) e^-u = e^-u - v e^-u and u^2 e^-u = (v e^-u) v, with v = -u.
        t = out if grad is None else grad
        np.multiply(v, e, out=t)
        np.subtract(e, t, out=out)
        if grad is not None:
            grad *= v


KERNELS: dict[str, type[PointKernel]] = {
    "se": SquaredExponential,
    "sqexp": SquaredExponential,
    "squared_exponential": SquaredExponential,
    "matern32": Matern32,
    "matern3": Matern32,
}


def make_point_kernel(name: str | PointKernel, **params: Any) -> PointKernel:
    """A point kernel from its name ("se" or "matern32"), or the kernel itself if given one."""
    if isinstance(name, PointKernel):
        return name
    try:
        cls = KERNELS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown kernel {name!r}; expected one of 'se', 'matern32'") from None
    return cls(**params)
