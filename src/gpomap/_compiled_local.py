"""Local prediction at points compiled with numba (:meth:`gpomap.gp.GPPosterior.latent`'s fast path).

A local prediction visits spatial blocks of queries, each with the inputs near it (J, the inner
ones I first): it forms the exact SE kernel between the block's boxes and points, the mean
k_J^T w_J and the variance's reduction k_I^T (K^-1)_II k_I. In numpy each block is some twenty
calls (the kernel's distinct sides and ends, a table of erf, gathers, products), and those
calls, not the variance's matrix product, took most of the time (docs/choices.md, "Measured for
the code"). Here one compiled call per tile
walks every block: each axis's distinct sides of the block, their factors (one table of G1 over
the sides' distinct ends, at the block's distinct coordinates, or, where the points are
scattered, at a few Chebyshev nodes across the block and interpolated), the factors multiplied
straight into K, the mean and, through BLAS's matrix product, the reduction. The numbers are the
numpy path's to round-off (libm's erf stands for scipy's, the interpolation errs by about 6e-15;
``tests/test_local_prediction.py`` compares the two).

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


#: Error aimed at when a block's factors are interpolated in the query coordinate (a factor is at
#: most 1): below double precision's round-off on the kernel's values.
INTERPOLATION_ERROR: float = 1e-15

#: Chebyshev nodes per axis at most; a block whose coordinates would need more takes the direct table.
MAX_NODES: int = 64


@jit(cache=True, nogil=True)
def chebyshev_nodes_needed(half_width: float, length_scale: float, error: float) -> int:  # pragma: no cover - compiled
    """Nodes for interpolating any 1-D SE factor over an interval of `half_width` to within `error`.

    A factor, the average of exp(-(t - x)^2 / (2 l^2)) over a side (or its value at a point), is
    entire in x and bounded by exp(Im(x)^2 / (2 l^2)) off the real line, whatever the side. On the
    Bernstein ellipse E_rho of the interval its bound is M = exp(b^2 / (2 l^2)), b = h (rho -
    1 / rho) / 2, and interpolation at n + 1 Chebyshev points errs by at most 4 M rho^-n / (rho - 1)
    (Trefethen, Approximation Theory and Approximation Practice, theorem 8.2); the best rho of a
    few is taken.
    """
    best = 1e300
    for rho in (1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0):
        b = half_width * (rho - 1.0 / rho) / 2.0
        log_bound = math.log(4.0 / (rho - 1.0)) + b * b / (2.0 * length_scale * length_scale)
        n = (log_bound - math.log(error)) / math.log(rho)
        if n < best:
            best = n
    return math.ceil(max(best, 1.0)) + 1


@jit(cache=True, nogil=True)
def _factors_at(
    side_lo: NDArray[np.float64],
    side_hi: NDArray[np.float64],
    used: NDArray[np.int64],
    n_used: int,
    x: NDArray[np.float64],
    length_scale: float,
    point_width: float,
) -> NDArray[np.float64]:  # pragma: no cover - compiled
    """The 1-D SE factor of the sides ``used[:n_used]`` at the coordinates `x`, ndarray of shape (n_used, |x|).

    A side at least ``point_width * l`` wide: ``(G1(hi - x) - G1(lo - x)) / (hi - lo)``, from one
    table of G1 over the sides' distinct ends; a narrower one: its centre's point value.
    """
    scale = 1.0 / (math.sqrt(2.0) * length_scale)
    g1 = length_scale * _SQRT_HALF_PI
    # The sides' distinct ends, and which end each side's lo and hi is: ends[2 t], ends[2 t + 1]
    # are the t-th wide side's.
    ends = np.empty(2 * n_used)
    n_ends = 0
    for u in range(n_used):
        s = used[u]
        if side_hi[s] - side_lo[s] >= point_width * length_scale:
            ends[n_ends] = side_lo[s]
            ends[n_ends + 1] = side_hi[s]
            n_ends += 2
    end_values, end_of = distinct_sorted(ends[:n_ends])
    G = np.empty((end_values.size, x.size))
    for e in range(end_values.size):
        for v in range(x.size):
            G[e, v] = g1 * math.erf((end_values[e] - x[v]) * scale)
    F = np.empty((n_used, x.size))
    wide = 0
    for u in range(n_used):
        s = used[u]
        lo, hi = side_lo[s], side_hi[s]
        w = hi - lo
        if w >= point_width * length_scale:
            a, b = end_of[2 * wide], end_of[2 * wide + 1]
            wide += 1
            for v in range(x.size):
                F[u, v] = (G[b, v] - G[a, v]) / w
        else:
            c = 0.5 * (lo + hi)
            for v in range(x.size):
                t = (c - x[v]) / length_scale
                F[u, v] = math.exp(-0.5 * t * t)
    return F


@jit(cache=True, nogil=True)
def _interpolation_matrix(
    lo: float, hi: float, n_nodes: int, x: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - compiled
    """Chebyshev points of the second kind on [lo, hi], ndarray of shape (n,), and the barycentric
    Lagrange basis at `x`, ndarray of shape (n, |x|): ``f(x) ~ f(nodes) @ B``."""
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    nodes = np.empty(n_nodes)
    weights = np.empty(n_nodes)
    for m in range(n_nodes):
        nodes[m] = centre + half * math.cos(math.pi * m / (n_nodes - 1))
        weights[m] = -1.0 if m % 2 else 1.0
    weights[0] *= 0.5
    weights[n_nodes - 1] *= 0.5
    B = np.empty((n_nodes, x.size))
    for v in range(x.size):
        total = 0.0
        exact = -1
        for m in range(n_nodes):
            d = x[v] - nodes[m]
            if d == 0.0:
                exact = m
                break
            B[m, v] = weights[m] / d
            total += B[m, v]
        if exact >= 0:
            for m in range(n_nodes):
                B[m, v] = 1.0 if m == exact else 0.0
        else:
            for m in range(n_nodes):
                B[m, v] /= total
    return nodes, B


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

    On an axis where the block's queries have many distinct coordinates (scattered points), each
    side's factor is evaluated at a few Chebyshev points across the block and interpolated
    (:func:`chebyshev_nodes_needed`, to :data:`INTERPOLATION_ERROR`), a matrix product in place
    of an erf per end and query; where they repeat (a grid's rows and columns) it is evaluated at
    each distinct coordinate.
    """
    J, Q, d = near.size, queries.size, points.shape[1]
    K = np.full((J, Q), variance)
    sides = np.empty(J, dtype=np.int64)
    coords = np.empty(Q)
    for k in range(d):
        for i in range(Q):
            coords[i] = points[queries[i], k]
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
        values, where = distinct_sorted(coords)
        n_nodes = chebyshev_nodes_needed(0.5 * (values[-1] - values[0]), length_scale, INTERPOLATION_ERROR)
        # The factors in the queries' order (a few sides), so each row of K is a product of two
        # contiguous rows instead of |J| gathers per query. Interpolation where it evaluates far
        # fewer coordinates.
        if n_nodes <= MAX_NODES and 2 * n_nodes < values.size:
            nodes, B = _interpolation_matrix(values[0], values[-1], n_nodes, coords)
            Fq = np.dot(_factors_at(side_lo, side_hi, used, n_used, nodes, length_scale, point_width), B)
        else:
            F = _factors_at(side_lo, side_hi, used, n_used, values, length_scale, point_width)
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
