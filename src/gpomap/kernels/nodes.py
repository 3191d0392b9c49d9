"""Area kernels as weighted sums of a point kernel over nodes placed in each input.

Both the paper's summed kernel (eqs. 12-13: the member points of a cell, equal weights) and the
quadrature kernel (a fixed Gauss-Legendre rule per box) average a point kernel over weighted
nodes:

    K(A, B) = sum_{p in A} sum_{q in B} w_p w_q k(x_p, x_q),    sum_{p in A} w_p = 1.

Blocks of node pairs are evaluated at a time and reduced per input with ``np.add.reduceat``, so
memory stays bounded whatever the number of nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.kernels.point import PointKernel, squared_distances
from gpomap.supports import Supports


@dataclass(frozen=True)
class NodeSet:
    """Weighted nodes standing for each input of a :class:`Supports`.

    Attributes
    ----------
    nodes : ndarray of shape (p, d)
    weights : ndarray of shape (p,)
        Sum to one within each input.
    offsets : ndarray of int, shape (n + 1,)
        Nodes of input ``i`` are ``nodes[offsets[i]:offsets[i + 1]]``; every input has at least one.
    """

    nodes: NDArray[np.float64]
    weights: NDArray[np.float64]
    offsets: NDArray[np.intp]

    def __len__(self) -> int:
        return int(self.offsets.size - 1)

    def slice(self, start: int, stop: int) -> NodeSet:
        """The nodes of inputs ``start .. stop - 1``, with offsets rebased to zero."""
        a, b = int(self.offsets[start]), int(self.offsets[stop])
        return NodeSet(self.nodes[a:b], self.weights[a:b], self.offsets[start : stop + 1] - a)


def member_nodes(supports: Supports) -> NodeSet:
    """Nodes at each input's member points with equal weights (the summed kernel)."""
    points, off = supports.member_points, supports.member_offsets
    if points is None or off is None:
        raise ValueError("the summed area kernel needs the member points of each input")
    sizes = np.diff(off)
    if np.any(sizes == 0):
        raise ValueError("every input needs at least one member point for the summed area kernel")
    return NodeSet(points, np.repeat(1.0 / sizes, sizes), off)


def quadrature_nodes(supports: Supports, order: int) -> NodeSet:
    """Tensor Gauss-Legendre nodes, `order` per side of each box; one node for a point.

    Parameters
    ----------
    supports : Supports
    order : int
        Nodes per dimension (the rule integrates polynomials of degree 2 order - 1 exactly).
    """
    if order < 1:
        raise ValueError(f"quadrature order must be at least 1, got {order}")
    d = supports.dim
    x, w = np.polynomial.legendre.leggauss(order)
    # Tensor rule on [0, 1]^d with weights summing to one.
    grids = np.meshgrid(*([0.5 * (x + 1.0)] * d), indexing="ij")
    unit = np.column_stack([g.ravel() for g in grids])
    wgrids = np.meshgrid(*([0.5 * w] * d), indexing="ij")
    unit_w = np.prod(np.column_stack([g.ravel() for g in wgrids]), axis=1)

    is_point = supports.is_point
    sizes = np.where(is_point, 1, unit.shape[0])
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.intp)
    nodes = np.empty((int(offsets[-1]), d))
    weights = np.empty(int(offsets[-1]))

    pts = np.flatnonzero(is_point)
    nodes[offsets[pts]] = supports.lower[pts]
    weights[offsets[pts]] = 1.0

    boxes = np.flatnonzero(~is_point)
    if boxes.size:
        lo = supports.lower[boxes][:, None, :]
        wd = supports.widths[boxes][:, None, :]
        where = offsets[boxes][:, None] + np.arange(unit.shape[0])[None, :]
        nodes[where.ravel()] = (lo + wd * unit[None, :, :]).reshape(-1, d)
        weights[where.ravel()] = np.tile(unit_w, boxes.size)
    return NodeSet(nodes, weights, offsets)


def weighted_gram(
    kernel: PointKernel,
    A: NodeSet,
    B: NodeSet,
    eval_gradient: bool = False,
    max_block: int = 4_000_000,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The averaged kernel between the inputs of two node sets.

    Parameters
    ----------
    kernel : PointKernel
    A, B : NodeSet
        With n and m inputs.
    eval_gradient : bool
        Also return the gradient with respect to the kernel's ``theta``.
    max_block : int
        Most node pairs evaluated at once (bounds memory).

    Returns
    -------
    K : ndarray of shape (n, m)
    dK : ndarray of shape (n, m, 2) or None
    """
    symmetric = A is B
    n, m = len(A), len(B)
    K = np.empty((n, m))
    dK = np.empty((n, m, 2)) if eval_gradient else None
    n_b = B.nodes.shape[0]
    start = 0
    while start < n:
        # As many inputs of A as fit in the block (always at least one).
        limit = A.offsets[start] + max(1, max_block // max(n_b, 1))
        stop = int(np.searchsorted(A.offsets, limit, side="right")) - 1
        stop = min(max(stop, start + 1), n)
        a = A.slice(start, stop)
        # For K(A, A) only the columns from this block on are needed: the rest is the
        # transpose of blocks already done.
        first = start if symmetric else 0
        b = B.slice(first, m)
        kp, dkp = kernel.values(squared_distances(a.nodes, b.nodes), eval_gradient)
        K[start:stop, first:] = _reduce(kp, a, b)
        if dK is not None:
            assert dkp is not None  # values() returns the derivative when asked for it
            # d/dlog(variance) of a variance-scaled kernel is the kernel itself.
            dK[start:stop, first:, 1] = _reduce(dkp, a, b)
        if symmetric:
            K[stop:, start:stop] = K[start:stop, stop:].T
            if dK is not None:
                dK[stop:, start:stop, 1] = dK[start:stop, stop:, 1].T
        start = stop
    if dK is not None:
        dK[:, :, 0] = K
    return K, dK


def _uniform_size(nodes: NodeSet) -> int | None:
    """The node count shared by every input, or None when counts differ."""
    sizes = np.diff(nodes.offsets)
    return int(sizes[0]) if sizes.size and np.all(sizes == sizes[0]) else None


def _reduce(kp: NDArray[np.float64], a: NodeSet, b: NodeSet) -> NDArray[np.float64]:
    """Weighted sums of node-pair values per pair of inputs: ``W_a kp W_b^T``, shape (n_a, n_b)."""
    qa, qb = _uniform_size(a), _uniform_size(b)
    if qa is not None and qb is not None:
        # Every input has the same number of nodes (quadrature over boxes): two small matrix
        # products on reshaped views beat segment sums.
        na, nb = len(a), len(b)
        wa, wb = a.weights.reshape(na, qa), b.weights.reshape(nb, qb)
        if np.all(wa == wa[0]) and np.all(wb == wb[0]):
            # One rule for every box: matrix-vector products.
            t = kp.reshape(na * qa * nb, qb) @ wb[0]
            return wa[0] @ t.reshape(na, qa, nb)
        t = (kp.reshape(na * qa, nb, qb) * wb[None]).sum(axis=2)
        return (t.reshape(na, qa, nb) * wa[:, :, None]).sum(axis=1)
    kb = np.add.reduceat(kp * b.weights[None, :], b.offsets[:-1], axis=1)
    return np.add.reduceat(kb * a.weights[:, None], a.offsets[:-1], axis=0)


def weighted_self(kernel: PointKernel, A: NodeSet, max_block: int = 4_000_000) -> NDArray[np.float64]:
    """The averaged kernel of each input with itself, ndarray of shape (n,)."""
    n = len(A)
    sizes = np.diff(A.offsets)
    out = np.empty(n)
    start = 0
    while start < n:
        # Inputs whose node pairs fit in one block.
        pairs = np.cumsum(sizes[start:] ** 2)
        stop = start + max(1, int(np.searchsorted(pairs, max_block, side="right")))
        stop = min(stop, n)
        s = sizes[start:stop]
        owner = np.repeat(np.arange(stop - start), s * s)
        # Every ordered pair (p, q) of nodes within the same input.
        base = A.offsets[start:stop]
        first = np.repeat(base, s * s)
        within = np.arange(int((s * s).sum())) - np.repeat(np.concatenate([[0], np.cumsum(s * s)[:-1]]), s * s)
        rep = np.repeat(s, s * s)
        p = first + within // rep
        q = first + within % rep
        diff = A.nodes[p] - A.nodes[q]
        k, _ = kernel.values(np.sum(diff * diff, axis=1))
        out[start:stop] = np.bincount(owner, weights=k * A.weights[p] * A.weights[q], minlength=stop - start)
        start = stop
    return out
