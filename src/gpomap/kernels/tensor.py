"""The quadrature area kernel evaluated through its tensor-product structure.

A box's Gauss-Legendre rule is a tensor product: along each axis its nodes take only ``order``
coordinates. So the squared distance between a node of box A and a node of box B is a sum over
axes of one of ``order * order`` squared coordinate differences per axis, and those are computed
once per axis instead of once per node pair. With 3-D boxes at order 2 and point queries that is
6 per-axis differences per box-query pair instead of 24, and the node-pair values are then
averaged in cache-sized blocks (a block of pairs is formed, turned into kernel values and reduced
while it is still in cache, instead of streaming arrays of millions of pairs through memory).

The nodes are those of :func:`gpomap.kernels.nodes.quadrature_nodes` and the result is the
average :func:`gpomap.kernels.nodes.weighted_gram` takes, to round-off (``tests/test_tensor_kernel.py``
checks it against that reference): the coordinates are scaled by the kernel's own scale
(:attr:`~gpomap.kernels.point.PointKernel.unit_scale`, so a block needs only the kernel's profile)
and the weighted sums are taken in another order. A point (a zero-width input) has one node of
weight one, as there. Kernels without a unit form go through
:meth:`~gpomap.kernels.point.PointKernel.values_into`, the very numbers of ``values``.

Kernels whose unit profile is compiled (Matern 3/2 and the squared exponential) take
:func:`gpomap.kernels._compiled.group_gram` instead of the numpy blocks below when numba imports
(``_compiled.ENABLED``): the same sums in one loop, the same numbers to round-off. The numpy
blocks stay as the reference and for every other kernel.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.kernels import _compiled
from gpomap.kernels.point import PointKernel
from gpomap.supports import Supports

#: Node pairs formed at once. About 64k doubles (0.5 MB) per array: the few arrays of one block
#: stay in a core's L2 cache; smaller and larger blocks were slower (docs/choices.md, "Measured
#: for the code").
BLOCK_PAIRS: int = 1 << 16


@dataclass(frozen=True)
class TensorRule:
    """One group of inputs sharing a tensor rule: each input's node coordinates per axis.

    Attributes
    ----------
    coords : ndarray of shape (d, o, n)
        ``coords[k, i, j]``: the i-th node coordinate of input j along axis k.
    weights : ndarray of shape (o ** d,)
        The rule's weights (summing to one), nodes in row-major order of their axis indices.
    """

    coords: NDArray[np.float64]
    weights: NDArray[np.float64]

    @property
    def order(self) -> int:
        """Nodes per axis."""
        return int(self.coords.shape[1])

    @property
    def dim(self) -> int:
        """Number of axes."""
        return int(self.coords.shape[0])

    def __len__(self) -> int:
        return int(self.coords.shape[2])

    def scaled(self, factor: float) -> TensorRule:
        """The same rule with every coordinate multiplied by `factor`."""
        return TensorRule(self.coords * factor, self.weights)


@functools.lru_cache(maxsize=16)
def _unit_rule(order: int, d: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gauss-Legendre nodes on [0, 1], shape (order,), and the weights of their d-fold product, shape (order**d,).

    Cached: every kernel call on boxes needs them, and the eigenvalue problem that gives the
    nodes costs more than a small block's arithmetic. Read-only, since they are shared.
    """
    x, w = np.polynomial.legendre.leggauss(order)
    unit, unit_w = 0.5 * (x + 1.0), 0.5 * w
    # The d-fold product of the 1-D weights, nodes in row-major order of their axis indices (as
    # quadrature_nodes' meshgrid with indexing "ij").
    grids = np.meshgrid(*([unit_w] * d), indexing="ij")
    box_w = np.prod(np.column_stack([g.ravel() for g in grids]), axis=1)
    unit.flags.writeable = False
    box_w.flags.writeable = False
    return unit, box_w


def tensor_rules(supports: Supports, order: int) -> tuple[list[NDArray[np.intp]], list[TensorRule]]:
    """The inputs of `supports` in groups: boxes with `order` Gauss-Legendre nodes per axis, points with one.

    Parameters
    ----------
    supports : Supports
    order : int
        Nodes per box side.

    Returns
    -------
    index : list of ndarray of int
        The inputs of each group (boxes first; groups without inputs are left out).
    rules : list of TensorRule
        Their node coordinates and weights.
    """
    if order < 1:
        raise ValueError(f"quadrature order must be at least 1, got {order}")
    unit, box_w = _unit_rule(order, supports.dim)
    is_point = supports.is_point
    index: list[NDArray[np.intp]] = []
    rules: list[TensorRule] = []
    boxes = np.flatnonzero(~is_point)
    if boxes.size:
        lo, wd = supports.lower[boxes].T, supports.widths[boxes].T  # (d, n)
        coords = lo[:, None, :] + wd[:, None, :] * unit[None, :, None]
        index.append(boxes)
        rules.append(TensorRule(np.ascontiguousarray(coords), box_w))
    points = np.flatnonzero(is_point)
    if points.size:
        index.append(points)
        rules.append(TensorRule(np.ascontiguousarray(supports.lower[points].T[:, None, :]), np.ones(1)))
    return index, rules


class _Work:
    """Scratch arrays for blocks of up to `size` node pairs, reused from block to block.

    Fresh arrays per block would cost more than the arithmetic: the allocator hands blocks of
    this size back to the system when freed, and every new one page-faults on first use
    (docs/choices.md, "Measured for the code").
    """

    def __init__(self, size: int, term_size: int, d: int, gradient: bool) -> None:
        self.d2 = np.empty(size)
        self.work = np.empty(size)
        self.value = np.empty(size)
        self.grad = np.empty(size) if gradient else None
        self.terms = [np.empty(term_size) for _ in range(d)]

    @staticmethod
    def view(buf: NDArray[np.float64], shape: tuple[int, ...]) -> NDArray[np.float64]:
        """The first ``prod(shape)`` entries of `buf` in that shape."""
        return buf[: math.prod(shape)].reshape(shape)


def _squared_distances(
    a: TensorRule, b: TensorRule, rows: slice, cols: slice, out: NDArray[np.float64], work: _Work
) -> NDArray[np.float64]:
    """Squared distances between the nodes of inputs `rows` of `a` and `cols` of `b`.

    Returns `out` filled, shape (oa, ..., oa, ob, ..., ob, r, c): d axes of `a`'s node indices,
    d of `b`'s, then the inputs.
    """
    d, oa, ob = a.dim, a.order, b.order
    r = a.coords[:, :, rows]
    c = b.coords[:, :, cols]
    terms = []
    for k in range(d):
        diff = work.view(work.terms[k], (oa, ob, r.shape[2], c.shape[2]))
        np.subtract(r[k][:, None, :, None], c[k][None, :, None, :], out=diff)
        diff *= diff
        # Axis k's node index of a sits at position k, of b at d + k; the others broadcast.
        view = [1] * (2 * d) + list(diff.shape[2:])
        view[k], view[d + k] = oa, ob
        terms.append(diff.reshape(view))
    # Summed over axes in order, as squared_distances does from zero (0 + x is x exactly).
    if d == 1:
        np.copyto(out, np.broadcast_to(terms[0], out.shape))
    elif d == 3:
        # The x + y sums once per (x, y) node pair, in scratch; then + z over the whole block.
        xy = work.view(work.work, np.broadcast_shapes(terms[0].shape, terms[1].shape))
        np.add(terms[0], terms[1], out=xy)
        np.add(xy, terms[2], out=out)
    else:
        np.add(terms[0], terms[1], out=out)
        for term in terms[2:]:
            np.add(out, term, out=out)
    return out


def _as_slice(index: NDArray[np.intp]) -> slice | NDArray[np.intp]:
    """`index` as a slice when it is a run of consecutive integers (plain, copy-free writes)."""
    if index.size and index[-1] - index[0] == index.size - 1:
        return slice(int(index[0]), int(index[-1]) + 1)
    return index


def _put(
    out: NDArray[np.float64], rows: slice | NDArray[np.intp], cols: slice | NDArray[np.intp], value: NDArray[np.float64]
) -> None:
    """``out[rows, cols] = value`` for slices or integer arrays."""
    if isinstance(rows, slice) or isinstance(cols, slice):
        out[rows, cols] = value  # one index an array at most: no outer product needed
    else:
        out[np.ix_(rows, cols)] = value


def _symmetrise_leading(value: NDArray[np.float64]) -> None:
    """Replace the leading square of a block on the diagonal of K(A, A) by its symmetric part, in place.

    Its pairs (i, j) and (j, i) were both computed, summed over the node pairs in transposed
    order; their mean is what symmetrising the whole matrix would give, and with the mirrored
    blocks off the diagonal the Gram matrix then comes out exactly symmetric.

    Parameters
    ----------
    value : ndarray of shape (r, c), r <= c
    """
    r = min(value.shape)
    square = value[:, :r]
    square[...] = 0.5 * (square + square.T)


def _group_gram(
    kernel: PointKernel,
    a: TensorRule,
    b: TensorRule,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    K: NDArray[np.float64],
    dL: NDArray[np.float64] | None,
    symmetric: bool,
    mirror: bool,
    block: int,
    distances: list[NDArray[np.float64]] | None = None,
) -> None:
    """The averaged kernel between groups `a` and `b`, written at ``K[rows, cols]`` (and d/dlog l in `dL`).

    `symmetric`: `a` is `b` (each pair of inputs computed once); `mirror`: also write the
    transpose at ``K[cols, rows]`` (the Gram matrix of one set of inputs); `distances`: the
    node-pair distances of each block, in the inputs' units (:func:`tensor_distances`), used
    instead of forming them when the kernel has a unit form (on the numpy path: the compiled one
    forms them itself).
    """
    n, m = len(a), len(b)
    d = a.dim
    w = np.multiply.outer(a.weights, b.weights).ravel()  # (P,)
    scale = kernel.unit_scale
    if scale is not None:
        # Coordinates in units of the kernel's own scale and the variance in the weights: the
        # node pairs then need the profile only (a third fewer passes over each block for
        # Matern 3/2; the same values to round-off).
        scaled_a = a.scaled(scale)
        a, b = scaled_a, (scaled_a if symmetric else b.scaled(scale))
        w = w * kernel.variance
    profile = _compiled.profile_id(kernel) if _compiled.ENABLED else None
    if profile is not None:
        # One compiled loop for the whole group pair (its own chunks; `block` and the cached
        # distances are not needed there): the same numbers to round-off.
        _compiled.group_gram(
            a.coords, b.coords, w, rows, cols, K, K if dL is None else dL, dL is not None, symmetric, mirror, profile
        )
        return
    pairs = w.size
    node_shape = [a.order] * d + [b.order] * d
    cols_per = max(1, min(m, block // pairs))
    rows_per = max(1, min(n, block // (pairs * cols_per)))
    work = _Work(pairs * rows_per * cols_per, a.order * b.order * rows_per * cols_per, d, dL is not None)
    cached = iter(distances) if distances is not None and scale is not None else None
    for r0 in range(0, n, rows_per):
        r1 = min(n, r0 + rows_per)
        rr = _as_slice(rows[r0:r1])
        # K(A, A): the columns from this row block on; the rest is the transpose of blocks done.
        for c0 in range(r0 if symmetric else 0, m, cols_per):
            c1 = min(m, c0 + cols_per)
            cc = _as_slice(cols[c0:c1])
            shape = (*node_shape, r1 - r0, c1 - c0)
            kp = work.view(work.value, shape)
            dkp = None if work.grad is None else work.view(work.grad, shape)
            if cached is not None:
                assert scale is not None  # a cache is only taken with a unit form
                # Scaled distances from the cached ones (negated): no squared differences, no
                # square root.
                v = np.multiply(next(cached), scale, out=work.view(work.d2, shape))
                kernel.unit_profile_from_negated_distance_into(v, kp, dkp, work.view(work.work, shape))
            else:
                d2 = _squared_distances(a, b, slice(r0, r1), slice(c0, c1), work.view(work.d2, shape), work)
                if scale is None:
                    kernel.values_into(d2, kp, dkp, work.view(work.work, shape))
                else:
                    kernel.unit_profile_into(d2, kp, dkp, work.view(work.work, shape))
            value = (w @ kp.reshape(pairs, -1)).reshape(r1 - r0, c1 - c0)
            if symmetric and c0 == r0:
                _symmetrise_leading(value)
            _put(K, rr, cc, value)
            if mirror:
                _put(K, cc, rr, value.T)
            if dL is not None:
                assert dkp is not None  # asked for with dL
                grad = (w @ dkp.reshape(pairs, -1)).reshape(r1 - r0, c1 - c0)
                if symmetric and c0 == r0:
                    _symmetrise_leading(grad)
                _put(dL, rr, cc, grad)
                if mirror:
                    _put(dL, cc, rr, grad.T)


def tensor_gram(
    kernel: PointKernel,
    A: Supports,
    B: Supports | None = None,
    order: int = 2,
    eval_gradient: bool = False,
    block: int = BLOCK_PAIRS,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The quadrature area kernel between two sets of inputs (boxes and points).

    Parameters
    ----------
    kernel : PointKernel
    A : Supports
        n inputs.
    B : Supports, optional
        m inputs; None: `A` (the symmetric Gram matrix, each pair computed once).
    order : int
        Gauss-Legendre nodes per box side.
    eval_gradient : bool
        Also return the gradient with respect to the kernel's ``theta``.
    block : int
        Most node pairs formed at once (bounds memory and keeps a block in cache).

    Returns
    -------
    K : ndarray of shape (n, m)
    dK : ndarray of shape (n, m, 2) or None
        d/dlog variance (K itself) and d/dlog length scale.
    """
    K, dL = tensor_gram_length_scale(kernel, A, B, order, eval_gradient, block)
    if dL is None:
        return K, None
    # d/dlog(variance) of a variance-scaled kernel is the kernel itself.
    return K, np.stack([K, dL], axis=-1)


def tensor_gram_length_scale(
    kernel: PointKernel,
    A: Supports,
    B: Supports | None = None,
    order: int = 2,
    eval_gradient: bool = False,
    block: int = BLOCK_PAIRS,
    distances: TensorDistances | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """:func:`tensor_gram` with only the length-scale derivative, as its own contiguous array.

    The gradient with respect to log variance is `K` itself; leaving it out saves an (n, m, 2)
    array and the strided passes over it. For ``B=None`` both results are exactly symmetric.

    Parameters
    ----------
    kernel, A, B, order, block
        As for :func:`tensor_gram`.
    eval_gradient : bool
        Also return dK / dlog(length_scale).
    distances : TensorDistances, optional
        The node-pair distances of ``K(A, A)`` from :func:`tensor_distances`, reused (for
        ``B=None`` and when they were taken for `A`, `order` and `block`; ignored otherwise).
        The same numbers to round-off.

    Returns
    -------
    K : ndarray of shape (n, m)
    dK_dlog_length_scale : ndarray of shape (n, m) or None
    """
    symmetric = B is None
    ia, ra = tensor_rules(A, order)
    ib, rb = (ia, ra) if B is None else tensor_rules(B, order)
    n, m = len(A), len(A) if B is None else len(B)
    K = np.empty((n, m))
    dL = np.empty((n, m)) if eval_gradient else None
    cached = distances.blocks if distances is not None and symmetric and distances.fits(A, order, block) else None
    for ga, (rows, a) in enumerate(zip(ia, ra, strict=True)):
        for gb, (cols, b) in enumerate(zip(ib, rb, strict=True)):
            if symmetric and gb < ga:
                continue  # the transpose of a block done
            near = None if cached is None else cached[(ga, gb)]
            _group_gram(kernel, a, b, rows, cols, K, dL, symmetric and ga == gb, symmetric, block, near)
    return K, dL


#: Most node-pair distances :func:`tensor_distances` keeps (8 bytes each): 2^23 is 64 MB, enough
#: for the hyperparameter sample of 800 cells at order 2 (5.1 M pairs, 41 MB).
MAX_CACHED_PAIRS: int = 1 << 23


@dataclass(frozen=True)
class TensorDistances:
    """The node-pair distances of the Gram matrix of one set of inputs, block by block, negated.

    They do not depend on the hyperparameters, so a search over them (every evaluation forms
    ``K(A, A)`` anew) forms them once and each evaluation only scales them.

    Attributes
    ----------
    lower, upper : ndarray of shape (n, d)
        The inputs' bounds they were taken for (the very arrays: checked by identity).
    order, block : int
        The rule and the block size they were taken with.
    blocks : dict
        ``(ga, gb)`` (groups of :func:`tensor_rules`) to minus the distances of each block, in
        the order :func:`_group_gram` visits them.
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    order: int
    block: int
    blocks: dict[tuple[int, int], list[NDArray[np.float64]]]

    def fits(self, A: Supports, order: int, block: int) -> bool:
        """Whether these are the distances of `A` with this rule and block size."""
        return A.lower is self.lower and A.upper is self.upper and order == self.order and block == self.block


def tensor_distances(
    A: Supports, order: int = 2, block: int = BLOCK_PAIRS, max_pairs: int = MAX_CACHED_PAIRS
) -> TensorDistances | None:
    """The node-pair distances of ``K(A, A)`` for :func:`tensor_gram_length_scale`, or None when there are more than `max_pairs`.

    Parameters
    ----------
    A : Supports
    order : int
        Gauss-Legendre nodes per box side.
    block : int
        Most node pairs per block (as the Gram matrix will be evaluated with).
    max_pairs : int
        Most distances kept; bounds memory.
    """
    _, rules = tensor_rules(A, order)
    total = 0
    for ga, a in enumerate(rules):
        for b in rules[ga:]:
            pairs = a.order**a.dim * b.order**b.dim
            total += pairs * (len(a) * len(b) if a is not b else len(a) * (len(a) + 1) // 2)
    if total > max_pairs:
        return None
    blocks: dict[tuple[int, int], list[NDArray[np.float64]]] = {}
    for ga, a in enumerate(rules):
        for gb in range(ga, len(rules)):
            blocks[(ga, gb)] = _block_distances(a, rules[gb], ga == gb, block)
    return TensorDistances(A.lower, A.upper, order, block, blocks)


def _block_distances(a: TensorRule, b: TensorRule, symmetric: bool, block: int) -> list[NDArray[np.float64]]:
    """The node-pair distances of each block :func:`_group_gram` forms for groups `a` and `b`, in its order."""
    n, m, d = len(a), len(b), a.dim
    pairs = a.order**d * b.order**d
    node_shape = [a.order] * d + [b.order] * d
    cols_per = max(1, min(m, block // pairs))
    rows_per = max(1, min(n, block // (pairs * cols_per)))
    work = _Work(pairs * rows_per * cols_per, a.order * b.order * rows_per * cols_per, d, False)
    out = []
    for r0 in range(0, n, rows_per):
        r1 = min(n, r0 + rows_per)
        for c0 in range(r0 if symmetric else 0, m, cols_per):
            c1 = min(m, c0 + cols_per)
            shape = (*node_shape, r1 - r0, c1 - c0)
            d2 = _squared_distances(a, b, slice(r0, r1), slice(c0, c1), work.view(work.d2, shape), work)
            # Negated: the profile's exponential then takes their scaled values as they are.
            out.append(-np.sqrt(d2))
    return out


def tensor_self(kernel: PointKernel, A: Supports, order: int = 2) -> NDArray[np.float64]:
    """The quadrature area kernel of each input with itself, ndarray of shape (n,)."""
    out = np.empty(len(A))
    for rows, a in zip(*tensor_rules(A, order), strict=True):
        d, o = a.dim, a.order
        w = np.multiply.outer(a.weights, a.weights).ravel()
        d2 = np.zeros([o] * (2 * d) + [len(a)])
        for k in range(d):
            diff = a.coords[k][:, None, :] - a.coords[k][None, :, :]  # (o, o, n)
            diff *= diff
            view = [1] * (2 * d) + [len(a)]
            view[k], view[d + k] = o, o
            d2 += diff.reshape(view)
        kp, _ = kernel.values(d2)
        out[rows] = w @ kp.reshape(w.size, -1)
    return out
