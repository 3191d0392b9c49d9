"""The multi-support ("area") kernel: covariances between cells, between cells and points, and
between points, through one point kernel (the paper's eqs. 10-14).

Three ways to compute the average of a point kernel over a pair of inputs:

- ``"exact"``: closed form, squared exponential only (:mod:`gpomap.kernels.closed_form`).
- ``"quadrature"``: a fixed Gauss-Legendre rule per box, for any kernel; the cost no longer
  depends on how many points a cell holds.
- ``"summed"``: the paper's eqs. 12-13, over each cell's member points.

Two normalisations: ``"mean"`` uses the average itself, so a cell's target reads as the mean
occupancy over it; ``"sum"`` multiplies by the member counts of both inputs, which reproduces the
paper's sums (eq. 13 is count_A * count_B times the mean over member pairs).
"""

from __future__ import annotations

import copy
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig
from gpomap.kernels.box_points import BoxPointFactors, se_box_point_average
from gpomap.kernels.closed_form import se_box_average, se_box_gram, se_box_self_average
from gpomap.kernels.nodes import NodeSet, member_nodes, quadrature_nodes, weighted_gram, weighted_self
from gpomap.kernels.point import PointKernel, SquaredExponential, make_point_kernel
from gpomap.kernels.tensor import TensorDistances, tensor_distances, tensor_gram, tensor_gram_length_scale, tensor_self
from gpomap.supports import Supports

AREA_METHODS = ("exact", "quadrature", "summed")
NORMALISATIONS = ("mean", "sum")

#: Dimensions whose quadrature kernel is evaluated through the rule's tensor structure
#: (:mod:`gpomap.kernels.tensor`: the same node values, summed in another order, several times
#: faster with the same written map to round-off; docs/choices.md, "Measured for the code"). The node sums
#: (:func:`~gpomap.kernels.nodes.weighted_gram`) stay as the tests' reference.
TENSOR_DIMS: tuple[int, ...] = (2, 3)


class AreaKernel:
    """A point kernel lifted to boxes and points.

    Parameters
    ----------
    base : PointKernel or str
        The point kernel ("se", "matern32" or an instance).
    method : {"exact", "quadrature", "summed"}
        How averages over boxes are computed; "exact" needs the squared exponential.
    normalisation : {"mean", "sum"}
        Average over the inputs' extents, or sum over their members (see module docstring).
    quadrature_order : int
        Gauss-Legendre nodes per box side for "quadrature".
    max_block : int
        Most kernel entries evaluated at once; bounds memory.
    """

    def __init__(
        self,
        base: PointKernel | str = "se",
        method: str = "exact",
        normalisation: str = MapConfig.normalisation,
        quadrature_order: int = 3,
        max_block: int = 4_000_000,
    ) -> None:
        self.base = make_point_kernel(base)
        if method not in AREA_METHODS:
            raise ValueError(f"area method must be one of {AREA_METHODS}, got {method!r}")
        if normalisation not in NORMALISATIONS:
            raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}")
        if method == "exact" and not isinstance(self.base, SquaredExponential):
            raise ValueError(
                f"the exact area kernel has a closed form only for the squared exponential; "
                f"use method='quadrature' or 'summed' with {type(self.base).__name__}"
            )
        self.method = method
        self.normalisation = normalisation
        self.quadrature_order = int(quadrature_order)
        self.max_block = int(max_block)

    def __repr__(self) -> str:
        return f"AreaKernel({self.base!r}, method={self.method!r}, normalisation={self.normalisation!r})"

    # Hyperparameters are the base kernel's.
    @property
    def theta(self) -> NDArray[np.float64]:
        """Log hyperparameters of the base kernel, ndarray of shape (2,)."""
        return self.base.theta

    @theta.setter
    def theta(self, value: NDArray[np.float64]) -> None:
        self.base.theta = value

    @property
    def bounds(self) -> NDArray[np.float64]:
        """Log bounds, ndarray of shape (2, 2)."""
        return self.base.bounds

    def clone_with_theta(self, theta: NDArray[np.float64]) -> AreaKernel:
        """A copy with hyperparameters `theta`."""
        k = copy.copy(self)
        k.base = self.base.clone_with_theta(theta)
        return k

    def nodes(self, supports: Supports) -> NodeSet:
        """The weighted nodes this kernel averages over for `supports` (quadrature / summed)."""
        if self.method == "summed":
            return member_nodes(supports)
        return quadrature_nodes(supports, self.quadrature_order)

    @overload
    def __call__(self, A: Supports, B: Supports | None = None, eval_gradient: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def __call__(
        self, A: Supports, B: Supports | None = None, *, eval_gradient: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def __call__(
        self, A: Supports, B: Supports | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def __call__(
        self, A: Supports, B: Supports | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Covariances between two sets of inputs.

        Parameters
        ----------
        A : Supports
            n inputs.
        B : Supports, optional
            m inputs; defaults to `A`.
        eval_gradient : bool
            Also return dK/dtheta.

        Returns
        -------
        K : ndarray of shape (n, m)
        dK : ndarray of shape (n, m, 2), only with `eval_gradient`
        """
        if B is None:
            # One set against itself: exactly symmetric, with the length-scale derivative alone.
            K, dL = self._gram(A, eval_gradient)
            if dL is None:
                return K
            # d/dlog(variance) of a variance-scaled kernel is the kernel itself.
            return K, np.stack([K, dL], axis=-1)
        if self.method == "exact":
            K, dK = self._exact(A, B, eval_gradient)
        elif self.method == "quadrature" and A.dim in TENSOR_DIMS:
            K, dK = tensor_gram(self.base, A, B, self.quadrature_order, eval_gradient)
        else:
            K, dK = weighted_gram(self.base, self.nodes(A), self.nodes(B), eval_gradient, self.max_block)
        if self.normalisation == "sum":
            scale = np.outer(A.counts, B.counts)
            K = K * scale
            if dK is not None:  # with eval_gradient
                dK = dK * scale[:, :, None]
        if not eval_gradient:
            return K
        assert dK is not None  # returned with eval_gradient
        return K, dK

    def prepare(self, A: Supports) -> TensorDistances | None:
        """What :meth:`gram_and_length_scale_gradient` of `A` can reuse from one set of hyperparameters to the next.

        The quadrature kernel's node-pair distances (:func:`~gpomap.kernels.tensor.tensor_distances`,
        up to its memory bound); None for the other methods (the exact kernel's work depends on
        the length scale throughout) or when there are too many. Hold it only while `A` is
        evaluated again and again (a hyperparameter search): it costs memory.
        """
        # Only kernels with a unit form evaluate from scaled distances.
        if self.method == "quadrature" and A.dim in TENSOR_DIMS and self.base.unit_scale is not None:
            return tensor_distances(A, self.quadrature_order)
        return None

    def gram_and_length_scale_gradient(
        self, A: Supports, prepared: TensorDistances | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The Gram matrix of `A` and its derivative with respect to log length scale.

        The same numbers as ``self(A, eval_gradient=True)``, without the derivative with respect
        to log variance (it is `K` itself): two contiguous arrays instead of one of shape
        (n, n, 2), whose strided slices make every product with them slow.

        Parameters
        ----------
        A : Supports
            n inputs.
        prepared : optional
            :meth:`prepare` of `A` (the same numbers to round-off, faster).

        Returns
        -------
        K : ndarray of shape (n, n)
            Exactly symmetric.
        dK_dlog_length_scale : ndarray of shape (n, n)
            Exactly symmetric.
        """
        K, dL = self._gram(A, True, prepared)
        assert dL is not None  # asked for
        return K, dL

    def _gram(
        self, A: Supports, eval_gradient: bool, prepared: TensorDistances | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """K(A, A), exactly symmetric, and (with `eval_gradient`) dK / dlog(length_scale), both (n, n)."""
        dL: NDArray[np.float64] | None
        if self.method == "exact":
            K, dL = se_box_gram(A.lower, A.upper, self.base.variance, self.base.length_scale, eval_gradient, self.max_block)
        elif self.method == "quadrature" and A.dim in TENSOR_DIMS:
            K, dL = tensor_gram_length_scale(self.base, A, None, self.quadrature_order, eval_gradient, distances=prepared)
        else:
            na = self.nodes(A)
            K, dK = weighted_gram(self.base, na, na, eval_gradient, self.max_block)
            # Symmetric by construction; remove the rounding asymmetry.
            K = 0.5 * (K + K.T)
            dL = None if dK is None else 0.5 * (dK[:, :, 1] + dK[:, :, 1].T)
        if self.normalisation == "sum":
            scale = np.outer(A.counts, A.counts)  # exactly symmetric: c_i c_j is c_j c_i
            K *= scale
            if dL is not None:
                dL *= scale
        return K, dL

    def point_blocks(self, A: Supports, points: NDArray[np.float64]) -> BoxPointFactors | _GenericPointBlocks:
        """Covariances between inputs and points, to be evaluated block by block (local prediction).

        ``point_blocks(A, points).block(rows, cols)`` is ``self(A', P')`` for the inputs
        ``A.lower[rows]``, ``A.upper[rows]`` (counts, no members) and the points ``points[cols]``,
        the same numbers; the exact kernel does the work common to all blocks once
        (:class:`~gpomap.kernels.box_points.BoxPointFactors`).

        Parameters
        ----------
        A : Supports
            n inputs.
        points : ndarray of shape (m, d)
        """
        if self.method == "exact" and self.normalisation == "mean":
            return BoxPointFactors(A.lower, A.upper, points, self.base.variance, self.base.length_scale)
        return _GenericPointBlocks(self, A, points)

    def _exact_points(
        self, lower: NDArray[np.float64], upper: NDArray[np.float64], points: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """The exact kernel between boxes (n, d) and points (m, d), (n, m), in blocks of at most `max_block` entries."""
        n, m = lower.shape[0], points.shape[0]
        cols = max(1, self.max_block // max(n, 1))
        if cols >= m:
            return se_box_point_average(lower, upper, points, self.base.variance, self.base.length_scale)
        K = np.empty((n, m))
        for s in range(0, m, cols):
            K[:, s : s + cols] = se_box_point_average(
                lower, upper, points[s : s + cols], self.base.variance, self.base.length_scale
            )
        return K

    def _exact(self, A: Supports, B: Supports, eval_gradient: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        if not eval_gradient and len(A) and len(B):
            # Boxes against points (prediction): one erf table per axis, the same numbers.
            if np.array_equal(B.lower, B.upper):
                return self._exact_points(A.lower, A.upper, B.lower), None
            if np.array_equal(A.lower, A.upper):
                return self._exact_points(B.lower, B.upper, A.lower).T, None
        n = len(A)
        K = np.empty((n, len(B)))
        dK = np.empty((n, len(B), 2)) if eval_gradient else None
        rows = max(1, self.max_block // max(len(B), 1))
        for s in range(0, n, rows):
            e = min(n, s + rows)
            k, dk = se_box_average(
                A.lower[s:e], A.upper[s:e], B.lower, B.upper, self.base.variance, self.base.length_scale, eval_gradient
            )
            K[s:e] = k
            if dK is not None:
                dK[s:e] = dk
        return K, dK

    def diag(self, A: Supports) -> NDArray[np.float64]:
        """k(a, a) for each input, ndarray of shape (n,)."""
        if self.method == "exact":
            d = se_box_self_average(A.lower, A.upper, self.base.variance, self.base.length_scale)
        elif self.method == "quadrature" and A.dim in TENSOR_DIMS:
            d = tensor_self(self.base, A, self.quadrature_order)
        else:
            d = weighted_self(self.base, self.nodes(A), self.max_block)
        if self.normalisation == "sum":
            d = d * A.counts**2
        return d


class _GenericPointBlocks:
    """:meth:`AreaKernel.point_blocks` for every kernel: each block evaluated through ``kernel(A', P')``."""

    def __init__(self, kernel: AreaKernel, A: Supports, points: NDArray[np.float64]) -> None:
        self.kernel, self.A, self.points = kernel, A, points

    def block(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.float64]:
        """K between inputs `rows` and points `cols`, ndarray of shape (len(rows), len(cols))."""
        A, p = self.A, self.points[cols]
        return self.kernel(Supports(A.lower[rows], A.upper[rows], A.counts[rows]), Supports(p, p, np.ones(cols.size)))
