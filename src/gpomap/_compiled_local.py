"""Local prediction at points compiled with numba (:meth:`gpomap.gp.GPPosterior.latent`'s fast path).

A local prediction visits spatial blocks of queries, each with the inputs near it (J): it forms the
exact SE kernel between the block's boxes and points, the mean k_J^T w_J and the variance's
reduction k_I^T (K^-1)_II k_I over its inner inputs I. In numpy each block is some twenty calls (the kernel's distinct
sides and ends, a table of erf, gathers, products), and on the paper's room at 200,000 random
points (971 blocks of about 200 points and 190 inputs) the calls other than the variance's matrix
product took 0.43 of 0.73 s. Here one compiled call per tile walks every block: each axis's
distinct sides and ends of the block found with marks and a sort, one table of G1 over the ends
and the block's distinct coordinates, the kernel's factors multiplied straight into K, the mean
and, through BLAS's matrix product, the reduction. The numbers are the numpy path's to round-off
(libm's erf stands for scipy's; ``tests/test_local_prediction.py`` compares the two).

``ENABLED``: :meth:`gpomap.gp.GPPosterior.latent` takes this path for the exact SE kernel at
points (:func:`gpomap.compiled.compiled_by_default` at import; tests switch it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit
from gpomap.kernels._compiled_box import distinct_sorted

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :meth:`gpomap.gp.GPPosterior.latent` takes the compiled path (read at each call).
ENABLED: bool = compiled_by_default()

_SQRT_HALF_PI = math.sqrt(math.pi / 2.0)


@jit(cache=True, nogil=True)
def _block_kernel(
    side_lo: NDArray[np.float64],
    side_hi: NDArray[np.float64],
    side_of: NDArray[np.int64],
    points: NDArray[np.float64],
    near: NDArray[np.int64],
    queries: NDArray[np.int64],
    length_scale: float,
    variance: float,
    point_width: float,
    local: NDArray[np.int64],
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    """The exact SE kernel between the boxes `near` and the points `queries`, ndarray of shape (|near|, |queries|).

    ``side_of[i, k]`` is box i's side on axis k, an index into `side_lo` and `side_hi` (every axis's
    distinct sides, one after another); `local` is scratch of their size, all -1, left so.
    """
    J, Q, d = near.size, queries.size, points.shape[1]
    K = np.full((J, Q), variance)
    scale = 1.0 / (math.sqrt(2.0) * length_scale)
    g1 = length_scale * _SQRT_HALF_PI
    sides = np.empty(J, dtype=np.int64)
    coords = np.empty(Q)
    for k in range(d):
        for i in range(Q):
            coords[i] = points[queries[i], k]
        values, where = distinct_sorted(coords)
        # The block's distinct sides on this axis, numbered in order of first use.
        n_used = 0
        used = np.empty(J, dtype=np.int64)
        for j in range(J):
            s = side_of[near[j], k]
            if local[s] < 0:
                local[s] = n_used
                used[n_used] = s
                n_used += 1
            sides[j] = local[s]
        # Their distinct ends (sides of the width of a point take the point value instead), and
        # which end each side's lo and hi is: ends[2 t], ends[2 t + 1] are the t-th wide side's.
        ends = np.empty(2 * n_used)
        n_ends = 0
        for u in range(n_used):
            s = used[u]
            if side_hi[s] - side_lo[s] >= point_width * length_scale:
                ends[n_ends] = side_lo[s]
                ends[n_ends + 1] = side_hi[s]
                n_ends += 2
        end_values, end_of = distinct_sorted(ends[:n_ends])
        G = np.empty((end_values.size, values.size))
        for e in range(end_values.size):
            for v in range(values.size):
                G[e, v] = g1 * math.erf((end_values[e] - values[v]) * scale)
        F = np.empty((n_used, values.size))
        wide = 0
        for u in range(n_used):
            s = used[u]
            lo, hi = side_lo[s], side_hi[s]
            w = hi - lo
            if w >= point_width * length_scale:
                a, b = end_of[2 * wide], end_of[2 * wide + 1]
                wide += 1
                for v in range(values.size):
                    F[u, v] = (G[b, v] - G[a, v]) / w
            else:
                c = 0.5 * (lo + hi)
                for v in range(values.size):
                    t = (c - values[v]) / length_scale
                    F[u, v] = math.exp(-0.5 * t * t)
        # The factors in the queries' order first (a few sides), so each row of K is a product
        # of two contiguous rows instead of |J| gathers per query.
        Fq = np.empty((n_used, Q))
        for u in range(n_used):
            for i in range(Q):
                Fq[u, i] = F[u, where[i]]
        for j in range(J):
            row = sides[j]
            for i in range(Q):
                K[j, i] *= Fq[row, i]
        for u in range(n_used):
            local[used[u]] = -1
    return K


@jit(cache=True, nogil=True)
def point_block_moments(
    precision: NDArray[np.float64],
    weights: NDArray[np.float64],
    side_lo: NDArray[np.float64],
    side_hi: NDArray[np.float64],
    side_of: NDArray[np.int64],
    points: NDArray[np.float64],
    query_index: NDArray[np.int64],
    query_start: NDArray[np.int64],
    near_index: NDArray[np.int64],
    near_start: NDArray[np.int64],
    near_inner: NDArray[np.int64],
    length_scale: float,
    variance: float,
    point_width: float,
    with_variance: bool,
    mean: NDArray[np.float64],
    reduction: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """Latent mean and variance reduction at points, block by block, written into `mean` and `reduction`.

    Parameters
    ----------
    precision : ndarray of shape (n, n)
        K^-1 of the inputs (read only with `with_variance`).
    weights : ndarray of shape (n,)
        K^-1 y.
    side_lo, side_hi : ndarray of shape (s,)
        Every axis's distinct box sides, one axis after another.
    side_of : ndarray of int, shape (n, d)
        Each box's side on each axis, an index into `side_lo` and `side_hi`.
    points : ndarray of shape (m, d)
    query_index, query_start : ndarray of int
        Block b's queries are ``query_index[query_start[b]:query_start[b + 1]]``.
    near_index, near_start : ndarray of int
        Block b's inputs, likewise.
    near_inner : ndarray of int, shape (blocks,)
        How many of block b's inputs, its first ones, make the variance.
    length_scale, variance, point_width : float
        The SE kernel's, and the side width (in length scales) below which a side is a point.
    with_variance : bool
        Also the reduction k_I^T (K^-1)_II k_I over the inner inputs I.
    mean, reduction : ndarray of shape (m,)
        Outputs; queries of blocks without inputs are left as they are.
    """
    local = np.full(side_lo.size, -1, dtype=np.int64)
    for b in range(query_start.size - 1):
        queries = query_index[query_start[b] : query_start[b + 1]]
        near = near_index[near_start[b] : near_start[b + 1]]
        J, Q = near.size, queries.size
        if J == 0 or Q == 0:
            continue
        K = _block_kernel(side_lo, side_hi, side_of, points, near, queries, length_scale, variance, point_width, local)
        # Row by row: K is stored by rows.
        acc = np.zeros(Q)
        for j in range(J):
            w = weights[near[j]]
            for i in range(Q):
                acc[i] += w * K[j, i]
        for i in range(Q):
            mean[queries[i]] = acc[i]
        if not with_variance:
            continue
        inner = near_inner[b]
        P = np.empty((inner, inner))
        for r in range(inner):
            for c in range(inner):
                P[r, c] = precision[near[r], near[c]]
        # The inner inputs' rows of K, a contiguous view.
        K_inner = K.ravel()[: inner * Q].reshape((inner, Q))
        T = np.dot(P, K_inner)
        acc[:] = 0.0
        for j in range(inner):
            for i in range(Q):
                acc[i] += K[j, i] * T[j, i]
        for i in range(Q):
            reduction[queries[i]] = acc[i]
