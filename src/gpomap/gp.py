"""Gaussian process regression over multi-support inputs, with two ways to learn hyperparameters.

The model is zero-mean GP regression on +-1 targets (Rasmussen & Williams, algorithm 2.1) over
:class:`~gpomap.supports.Supports`, with noise variance ``noise * noise_scale_i`` per input.
Hyperparameters live in log space and are found with L-BFGS-B from a few seeded starts, with
analytic gradients, by one of two objectives:

- ``"lml"``: the log marginal likelihood (R&W eq. 5.8, gradient eq. 5.9); the probit squash is
  then fitted to the leave-one-out moments afterwards.
- ``"loo"``: the leave-one-out probit predictive probability (probabilistic least-squares
  classification, R&W sections 5.4.2 and 6.5), fitted jointly with the squash's alpha and beta.
  The signal variance is held fixed: scaling signal and noise together leaves the LOO means
  unchanged and alpha absorbs the scale, so it is not identifiable there.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import itertools
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple, overload

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import LinAlgError, cholesky, solve_triangular
from scipy.optimize import minimize

from gpomap import _compiled_local, lapack
from gpomap.errors import NotFittedError, NumericalError
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.closed_form import POINT_WIDTH, BoxPointFactors
from gpomap.kernels.tensor import TensorDistances
from gpomap.lattice import column_bounds, stable_order
from gpomap.squash import CLASS_WEIGHTS, SQUASH_BOUNDS, ProbitSquash, class_weights, loo_probit, probit_gradient_in_shift
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


def robust_cholesky(K: NDArray[np.float64], max_tries: int = 6) -> tuple[NDArray[np.float64], float]:
    """Lower Cholesky factor of `K`, adding diagonal jitter only if plain factorisation fails.

    Parameters
    ----------
    K : ndarray of shape (n, n)
        Symmetric covariance matrix.
    max_tries : int
        Jitter grows tenfold per try, from 1e-10 times the mean diagonal.

    Returns
    -------
    L : ndarray of shape (n, n)
    jitter : float
        What was added to the diagonal (0 when none was needed).

    Raises
    ------
    NumericalError
        When no jitter in range makes `K` positive definite.
    """
    try:
        return cholesky(K, lower=True, check_finite=False), 0.0
    except LinAlgError:
        pass
    if not np.all(np.isfinite(K)):
        raise NumericalError("covariance matrix has NaN or inf entries; check the inputs and hyperparameters")
    scale = float(np.mean(np.diag(K)))
    jitter = 1e-10 * scale
    for _ in range(max_tries):
        try:
            return cholesky(K + jitter * np.eye(K.shape[0]), lower=True, check_finite=False), jitter
        except LinAlgError:
            jitter *= 10.0
    raise NumericalError(
        f"covariance matrix is not positive definite even with jitter {jitter / 10:.3g}; "
        "raise the noise lower bound, or remove duplicate inputs with conflicting labels"
    )


def cholesky_in_place(K: NDArray[np.float64], clean: bool = True) -> NDArray[np.float64] | None:
    """Lower Cholesky factor of a symmetric C-ordered `K`, computed in `K`'s own memory; None if not positive definite.

    An exactly symmetric C-ordered matrix read in Fortran order is itself, so LAPACK factorises
    it where it lies: no Fortran-ordered copy (a tile's 1,500-cell covariance is 18 MB, fresh
    pages each time), the same numbers as :func:`robust_cholesky`'s first try. `K` is
    overwritten either way; on None the caller forms it again for :func:`robust_cholesky`.

    Parameters
    ----------
    K : ndarray of shape (n, n)
    clean : bool
        Zero the strict upper triangle; False leaves K's entries there (for callers that read
        the lower triangle only, such as LAPACK's and cho_solve's with ``lower=True``).

    Returns
    -------
    ndarray of shape (n, n), Fortran-ordered (``K.T``'s memory), or None
    """
    if not K.flags.c_contiguous:
        K = np.ascontiguousarray(K)
    L = K.T
    if lapack.potrf(L) != 0:
        return None
    if clean:
        _clear_strict_upper(L)
    return L


def _clear_strict_upper(L: NDArray[np.float64]) -> None:
    """Zero the strict upper triangle of the Fortran-ordered square `L` in place (its C-ordered
    transpose's strict lower one, by row blocks of :data:`FILL_BLOCK`)."""
    C = L.T
    n = C.shape[0]
    for i0 in range(0, n, FILL_BLOCK):
        i1 = min(n, i0 + FILL_BLOCK)
        C[i0:i1, :i0] = 0.0
        block = C[i0:i1, i0:i1]
        block[...] = np.triu(block)


def cholesky_solve(L: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """(L L^T)^-1 y from a lower Cholesky factor (its lower triangle read), ndarray of `y`'s shape (n,) or (n, k)."""
    x = np.array(y, dtype=float, order="F")
    info = lapack.potrs(np.asfortranarray(L), x)
    if info != 0:
        raise NumericalError(f"solve from the Cholesky factor failed (LAPACK info {info})")
    return x


def noisy_cholesky(
    K: NDArray[np.float64], noise: NDArray[np.float64], form_again: Callable[[], NDArray[np.float64]], clean: bool = True
) -> tuple[NDArray[np.float64], float]:
    """Lower Cholesky factor of K + diag(noise), in `K`'s own memory where it succeeds, and the jitter it took.

    The factorisation of every fit (:meth:`SupportGP.fit`, a tile's): :func:`cholesky_in_place`
    first (no copy of an n x n matrix); where K + noise is not positive definite as it stands,
    `form_again` gives K afresh (the first try overwrote it) for :func:`robust_cholesky`'s jitter.

    Parameters
    ----------
    K : ndarray of shape (n, n)
        Noise-free covariance, symmetric and C-ordered; overwritten.
    noise : ndarray of shape (n,)
    form_again : callable
        K as it was.
    clean : bool
        As :func:`cholesky_in_place`'s (the jitter's factor is always clean).

    Returns
    -------
    L : ndarray of shape (n, n)
    jitter : float
    """
    K[np.diag_indices_from(K)] += noise
    L = cholesky_in_place(K, clean)
    if L is not None:
        return L, 0.0
    K = form_again()
    K[np.diag_indices_from(K)] += noise
    return robust_cholesky(K)


def cholesky_inverse(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """(L L^T)^-1 from a lower Cholesky factor, ndarray of shape (n, n): :func:`_inverse_in_place` on a copy."""
    return _inverse_in_place(np.array(L, dtype=float, order="F"))


def _triangular_inverse(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """L^-1 in a Fortran-ordered copy of the lower factor `L`, ndarray of shape (n, n); the strict
    upper triangle is `L`'s own (LAPACK leaves it as it finds it)."""
    L_inv = np.array(L, dtype=float, order="F")
    info = lapack.trtri(L_inv)
    if info != 0:
        raise NumericalError(f"triangular inverse of the Cholesky factor failed (LAPACK info {info})")
    return L_inv


def inverse_diagonal(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """diag((L L^T)^-1) from a lower Cholesky factor, ndarray of shape (n,).

    The squared column norms of L^-1: one triangular inverse, half the work of the full inverse.
    """
    L_inv = _triangular_inverse(L)
    return np.einsum("ij,ij->j", L_inv, L_inv)


#: Rows per block when :func:`_fill_lower` mirrors a triangle: blocks this size transpose in
#: cache, faster than ``np.tril(inv) + np.tril(inv, -1).T`` (docs/choices.md, "Measured for the code").
FILL_BLOCK: int = 128


def _fill_lower(S: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mirror the upper triangle of the C-ordered square `S` into its lower one, in place; returns `S`."""
    n = S.shape[0]
    for i0 in range(0, n, FILL_BLOCK):
        i1 = min(n, i0 + FILL_BLOCK)
        S[i1:, i0:i1] = S[i0:i1, i1:].T
        block = S[i0:i1, i0:i1]
        block[...] = np.triu(block) + np.triu(block, 1).T
    return S


def _inverse_in_place(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """(L L^T)^-1 in `L`'s memory from a Fortran-ordered lower factor, full and C-ordered (n, n).

    dpotri fills the lower triangle only (the C-ordered transpose's upper one), which is then
    mirrored in cache-sized blocks: the same numbers as ``np.tril(inv) + np.tril(inv, -1).T`` at
    a third of the time.
    """
    if not L.flags.f_contiguous:  # a factor from robust_cholesky's jitter may not be
        L = np.asfortranarray(L)
    info = lapack.potri(L)
    if info != 0:
        raise NumericalError(f"inverse from the Cholesky factor failed (LAPACK info {info})")
    # Fortran lower triangle = C upper triangle of the transposed view.
    return _fill_lower(L.T)


def _trace_product_upper(G: NDArray[np.float64], M_upper: NDArray[np.float64]) -> float:
    """tr(G M) = sum_ij G_ij M_ij for symmetric G and M, from M's upper triangle (zeros below).

    Parameters
    ----------
    G : ndarray of shape (n, n), symmetric, C-ordered
    M_upper : ndarray of shape (n, n), C-ordered
        M on and above the diagonal, zero below.
    """
    return float(2.0 * np.vdot(G, M_upper) - np.diagonal(G) @ np.diagonal(M_upper))


def _weighted_outer_upper(C: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """C diag(w) C for a symmetric C, on and above the diagonal (zeros below), ndarray of shape (n, n).

    Two symmetric rank-k updates (``dsyrk``, half the work of a general product): the columns with
    positive weights scaled by sqrt(w), less those with negative ones by sqrt(-w).

    Parameters
    ----------
    C : ndarray of shape (n, n), symmetric, C-ordered
    w : ndarray of shape (n,)
    """
    n = C.shape[0]
    root = np.sqrt(np.abs(w))
    out = np.zeros((n, n), order="F")
    for sign, cols in ((1.0, np.flatnonzero(w > 0)), (-1.0, np.flatnonzero(w < 0))):
        if cols.size == 0:
            continue
        # Rows of the symmetric C are its columns; the transpose of the scaled rows is a
        # Fortran-ordered (n, k) matrix, which BLAS takes without a copy. The second update adds
        # onto the first.
        lapack.syrk(sign, (C[cols] * root[cols, None]).T, 1.0, out)
    # Fortran lower triangle = C upper triangle of the transposed view.
    return out.T


#: Local prediction treats covariances below this fraction of the signal variance as zero. The
#: latent mean then moves by at most LOCAL_TOL * variance * sum(|weights|) of the cells left out.
#: Tight enough that probabilities barely move against the dense prediction, loose enough that
#: most SE tiles predict locally (docs/choices.md, "Local prediction leaves out covariances").
LOCAL_TOL = 1e-6

#: The variance's reduction k_J^T (K^-1)_JJ k_J takes only the inputs whose covariance with the
#: block reaches this fraction of the signal variance (a subset of the mean's). An input left out
#: changes the reduction by its covariance with the query times its weight in the query's kriging
#: predictor (K^-1 k)_i, and both decay with distance, so the error is second order and a looser
#: tolerance than the mean's costs little. The product over |J|^2 inputs per query is most of the
#: local prediction's work, so fewer inputs pay (docs/choices.md, "Local prediction leaves out
#: covariances", the variance's own tolerance).
LOCAL_VARIANCE_TOL = 1e-4

#: Side of the local-prediction blocks, in cutoff distances r. A block's inputs lie within r of
#: it (a rounded square of area s^2 + 4 s r + pi r^2), and each query costs about their number
#: squared, so smaller blocks gather fewer inputs per query, down to where the per-block
#: overhead and the short matrix products take over.
LOCAL_BLOCK_SIDE: float = 0.25

#: Taking a block's (K^-1)_JJ costs about what this many of its queries' products with it do
#: (a gather of |J|^2 entries against |J|^2 fused multiply-adds per query; docs/choices.md,
#: "Measured for the code").
LOCAL_GATHER_QUERIES: int = 64

#: Local prediction is taken where its work (:func:`local_blocks`' estimate, plus n^3 for K^-1)
#: is at most this share of the dense n^2 m: half with numpy's block loop, whose products are the
#: dense path's own; twice with the compiled walk (:mod:`gpomap._compiled_local`), whose kernel
#: costs a small part of the dense path's numpy one (an erf per side end and point), so it wins
#: even on tiles whose every cell is within reach of every block (docs/choices.md, "Local
#: prediction leaves out covariances", the compiled walk).
LOCAL_WORK_SHARE: float = 0.5
COMPILED_LOCAL_WORK_SHARE: float = 2.0

#: Block-cell pairs tested at once when :func:`local_blocks` looks for each block's inputs.
_PAIRS_AT_ONCE: int = 1 << 15


class LocalBlock(NamedTuple):
    """A spatial block of queries and the training inputs near it (:func:`local_blocks`)."""

    #: Indices of the block's queries, ndarray of int, shape (q,).
    queries: NDArray[np.intp]
    #: Indices of the inputs within the radius, ndarray of int, shape (J,); those within the
    #: inner radius first.
    inputs: NDArray[np.intp]
    #: How many of `inputs` lie within the inner radius (the variance's).
    n_inner: int


@dataclass(frozen=True)
class LocalBlocks:
    """Every block of a local prediction, packed: block b's queries are
    ``query_index[query_start[b]:query_start[b + 1]]``, its inputs likewise, the first
    ``n_inner[b]`` of them within the inner radius. Iterating gives each :class:`LocalBlock`."""

    #: ndarray of int64, shape (m,): the queries, block after block.
    query_index: NDArray[np.int64]
    #: ndarray of int64, shape (blocks + 1,).
    query_start: NDArray[np.int64]
    #: ndarray of int64, shape (sum of |J|,): the inputs, block after block, inner ones first.
    input_index: NDArray[np.int64]
    #: ndarray of int64, shape (blocks + 1,).
    input_start: NDArray[np.int64]
    #: ndarray of int64, shape (blocks,).
    n_inner: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.n_inner.size)

    def __iter__(self) -> Iterator[LocalBlock]:
        qs, js = self.query_start, self.input_start
        for b in range(len(self)):
            yield LocalBlock(self.query_index[qs[b] : qs[b + 1]], self.input_index[js[b] : js[b + 1]], int(self.n_inner[b]))


def local_blocks(
    queries: Supports,
    train: Supports,
    radius: float,
    chunk_size: int,
    axes: int | None = None,
    side: float = LOCAL_BLOCK_SIDE,
    euclidean: bool = True,
    inner_radius: float | None = None,
) -> tuple[LocalBlocks, float]:
    """The queries in spatial blocks, each with the training inputs that come within `radius` of it.

    Queries are binned by centre on a grid of side ``LOCAL_BLOCK_SIDE * radius`` (bins of more
    than `chunk_size` queries are split); a block's inputs are those whose box is nearer than
    `radius` (Euclidean) to the bounding box of its queries. For an isotropic point kernel that
    decreases with distance and is below the tolerance beyond `radius`, a mean-normalised area
    kernel between two boxes is an average of point-kernel values (a Gauss-Legendre rule's
    weights are positive), none larger than at the boxes' nearest points, so every input left out
    covaries with every query of the block by less than the tolerance.

    Parameters
    ----------
    queries : Supports
        m query inputs.
    train : Supports
        n training inputs.
    radius : float
        Distance beyond which the point kernel is negligible.
    chunk_size : int
        Most queries per block.
    axes : int, optional
        Bin on the first `axes` coordinates only (3-D tile columns: x, y); default all.
    side : float
        Bin side, in units of `radius`.
    euclidean : bool
        Keep the inputs nearer than `radius` to a block; False: those whose box meets the block
        grown by `radius` along every axis (a superset: the corners too).
    inner_radius : float, optional
        A second, smaller distance (the variance's, :data:`LOCAL_VARIANCE_TOL`): each block's
        inputs within it come first; default `radius` (all of them).

    Returns
    -------
    blocks : LocalBlocks
        Query indices, training indices and how many of those are within `inner_radius`, per
        block; every query is in exactly one block.
    work : float
        Sum over blocks of ``|J_inner|^2 (|q| + LOCAL_GATHER_QUERIES)``: about the work of the
        local prediction's variance, in the units of the dense ``n^2 m``.
    """
    m = len(queries)
    if m == 0:
        empty = np.zeros(0, dtype=np.int64)
        return LocalBlocks(empty, np.zeros(1, dtype=np.int64), empty, np.zeros(1, dtype=np.int64), empty), 0.0
    centres = queries.centres
    a = centres.shape[1] if axes is None else axes
    low, _ = column_bounds(centres[:, :a])
    bins = np.floor((centres[:, :a] - low) / (side * radius)).astype(np.int64)
    # One integer per bin, the last axis fastest, sorted stably, and cut where it changes.
    key = np.zeros(m, dtype=np.int64)
    for k in range(a):
        key *= int(bins[:, k].max()) + 1
        key += bins[:, k]
    order = stable_order(key)
    sorted_key = key[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_key[1:] != sorted_key[:-1]]))
    ends = np.append(starts[1:], m)
    # Bins of more than chunk_size queries in pieces of at most that many.
    pieces = [np.arange(s, e, chunk_size) for s, e in zip(starts, ends)]
    cuts = np.concatenate(pieces) if pieces else starts
    lo_b = np.minimum.reduceat(queries.lower[order], cuts, axis=0)
    hi_b = np.maximum.reduceat(queries.upper[order], cuts, axis=0)
    n = len(train)
    inner = radius if inner_radius is None else min(inner_radius, radius)
    limit, inner_limit = (radius * radius, inner * inner) if euclidean else (radius, inner)
    rows: list[NDArray[np.intp]] = []
    cols: list[NDArray[np.intp]] = []
    outer: list[NDArray[np.bool_]] = []
    step = max(1, _PAIRS_AT_ONCE // max(n, 1))
    for b0 in range(0, cuts.size, step):
        b1 = min(cuts.size, b0 + step)
        # Squared distance between each block's box and each input's box, axis by axis.
        d2 = np.zeros((b1 - b0, n))
        for k in range(train.dim):
            gap = np.maximum(train.lower[None, :, k] - hi_b[b0:b1, k, None], lo_b[b0:b1, k, None] - train.upper[None, :, k])
            np.maximum(gap, 0.0, out=gap)
            if euclidean:
                gap *= gap
                d2 += gap
            else:
                np.maximum(d2, gap, out=d2)
        r, c = np.nonzero(d2 < limit)  # by block, then input
        rows.append(r + b0)
        cols.append(c)
        outer.append(d2[r, c] >= inner_limit)
    row, is_outer = np.concatenate(rows), np.concatenate(outer)
    # Each block's inner inputs first, each part in input order (a stable sort on small integers).
    order_in = np.argsort(2 * row + is_outer, kind="stable")
    counts = np.bincount(row, minlength=cuts.size)
    n_inner = counts - np.bincount(row, weights=is_outer, minlength=cuts.size).astype(np.int64)
    query_start = np.append(cuts, m).astype(np.int64)
    blocks = LocalBlocks(
        query_index=order.astype(np.int64),
        query_start=query_start,
        input_index=np.concatenate(cols)[order_in].astype(np.int64),
        input_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        n_inner=n_inner.astype(np.int64),
    )
    work = float(np.sum(n_inner.astype(np.float64) ** 2 * (np.diff(query_start) + LOCAL_GATHER_QUERIES)))
    return blocks, work


#: Dimensions whose predictions whiten the cross-covariances with an explicit L^-1 (a matrix
#: product) instead of a triangular solve per chunk: the product is faster, the variances equal
#: to round-off (docs/3d.md, "one dense GP"); planar maps take it too (the written grid's
#: tiles predict many more points than they have cells).
WHITEN_BY_PRODUCT_DIMS: tuple[int, ...] = (2, 3)


def triangular_inverse_for(L: NDArray[np.float64], n_queries: int, dim: int) -> NDArray[np.float64] | None:
    """L^-1 (lower, ndarray of shape (n, n)) when whitening `n_queries` queries by a product pays, else None.

    Only for dimensions in :data:`WHITEN_BY_PRODUCT_DIMS`, and only when the queries are at least
    as many as the inputs: inverting costs about n^3 / 3, the product saves part of n^2 per query.
    """
    n = L.shape[0]
    if dim not in WHITEN_BY_PRODUCT_DIMS or n_queries < n or n == 0:
        return None
    return np.tril(_triangular_inverse(L))


#: Row blocks of :func:`lower_product`: each block's product skips the zeros right of its
#: diagonal block, (1 + 1 / 8) / 2 of the full product's work (timings: docs/3d.md, "one dense GP"
#: and docs/choices.md, "Measured for the code").
LOWER_PRODUCT_BLOCKS: int = 8


def lower_product(L_inv: NDArray[np.float64], K: NDArray[np.float64]) -> NDArray[np.float64]:
    """``L_inv @ K`` for a lower-triangular `L_inv` of shape (n, n) and `K` of shape (n, c), by row blocks."""
    n = L_inv.shape[0]
    out = np.empty((n, K.shape[1]))
    edges = np.linspace(0, n, min(LOWER_PRODUCT_BLOCKS, max(n, 1)) + 1).round().astype(int)
    for a, b in itertools.pairwise(edges):
        if b > a:
            np.matmul(L_inv[a:b, :b], K[:b], out=out[a:b])
    return out


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


#: Most queries per kernel evaluation of a local block for the quadrature and summed kernels,
#: whose time per query grows past a few hundred (see :meth:`GPPosterior.latent`); the exact SE
#: kernel's tabled factors take a block in one piece.
LOCAL_KERNEL_POINTS: int = 256

#: Queries per local block aimed at, and the bounds of the block side (in cutoff distances r):
#: where queries are sparse the kernel call's fixed cost dominates, so sparse blocks grow.
LOCAL_BLOCK_QUERIES: int = 256
LOCAL_SIDE_RANGE: tuple[float, float] = (0.25, 1.0)

#: Query coordinates the local blocks bin on, per dimension (None: all). 3-D tiles are columns
#: and bin in x, y: several times faster than binning in z too (docs/choices.md, "Measured for
#: the code").
LOCAL_AXES: dict[int, int | None] = {2: None, 3: 2}


@dataclass
class GPPosterior:
    """A fitted GP: what predicting from it takes, and its prediction, dense or local.

    What :meth:`SupportGP.fit` and a tile's fit (:func:`gpomap.tiles.fit_tile_task`) return, and
    what pool and Dask workers send back: picklable, its cache of K^-1 left out.

    Attributes
    ----------
    inputs : Supports
        The n training inputs (or any inputs `kernel` takes, such as GPOMIK's segments).
    L : ndarray of shape (n, n)
        Lower Cholesky factor of K + noise (+ jitter).
    weights : ndarray of shape (n,)
        (K + noise)^-1 y.
    kernel : AreaKernel
        The kernel, with the hyperparameters the factor was formed with (for GPOMIK's segments,
        its line kernel).
    squash : ProbitSquash
        Latent moments to probabilities.
    jitter : float
        What was added to the diagonal for the factorisation to succeed (0 when nothing was).
    precision : ndarray of shape (n, n) or None
        (K + noise)^-1, formed by the first local prediction and kept for the next ones; a
        cache, left out of comparisons and pickles (a worker forms its own).
    """

    inputs: Supports
    L: NDArray[np.float64]
    weights: NDArray[np.float64]
    kernel: AreaKernel
    squash: ProbitSquash
    jitter: float = 0.0
    precision: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)

    def __getstate__(self) -> dict[str, object]:
        # The cache would double what is shipped to a worker.
        return {**self.__dict__, "precision": None}

    @property
    def n_inputs(self) -> int:
        """Number of training inputs."""
        return int(self.weights.size)

    def latent(
        self, queries: Supports, variance: bool = True, local: bool = True, chunk_size: int = 4096
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Latent mean and (with `variance`) variance at the queries, each ndarray of shape (m,).

        Parameters
        ----------
        queries : Supports
            m query inputs (points are boxes of zero width).
        variance : bool
            Also the variance (the costly part); False gives None.
        local : bool
            Where the kernel falls below ``LOCAL_TOL`` of its variance within a small part of the
            inputs, predict block by block from the inputs near each block of queries (see
            :meth:`local_blocks`): equal to the dense prediction to that tolerance, and taken only
            where it saves at least half of the dense work. False: always dense (the reference).
        chunk_size : int
            Queries per block, bounding memory at ``n * chunk_size``.
        """
        if local:
            blocks = self.local_blocks(queries, chunk_size)
            if blocks is not None:
                return self._latent_local(queries, blocks, variance)
        return self._latent_dense(queries, variance, chunk_size)

    def local_blocks(self, queries: Supports, chunk_size: int) -> LocalBlocks | None:
        """Spatial blocks of queries with the inputs near each (:func:`local_blocks`), or None
        where the dense prediction is taken.

        A block's inputs are those within r of it, r the distance beyond which the point kernel
        is below ``LOCAL_TOL`` of its variance: every input left out covaries with every query
        of the block by less than that. Those within the distance of ``LOCAL_VARIANCE_TOL`` come
        first and make the variance. None for kernels without such a bound (member sums, the
        "sum" normalisation, other inputs than boxes) and where the blocks' work is more than
        ``LOCAL_WORK_SHARE`` of the dense one (``COMPILED_LOCAL_WORK_SHARE`` where the compiled
        walk takes them). The decision counts forming K^-1 (n^3) even when it is cached, so an
        answer never depends on what was predicted before.
        """
        kern, X = self.kernel, self.inputs
        if not (isinstance(kern, AreaKernel) and isinstance(X, Supports) and isinstance(queries, Supports)):
            return None
        if kern.method == "summed" or kern.normalisation != "mean" or len(queries) == 0:
            return None
        n, m = len(X), len(queries)
        share = COMPILED_LOCAL_WORK_SHARE if self._walks_compiled(queries) else LOCAL_WORK_SHARE
        if n**3 > share * n * n * m:
            return None  # dense whatever the blocks' work (below): not worth finding them
        r = kern.base.cutoff(LOCAL_TOL)
        axes = LOCAL_AXES.get(X.dim)
        # Blocks of about LOCAL_BLOCK_QUERIES queries where they are sparse (each kernel call and
        # gather of (K^-1)_JJ costs as much as a few dozen queries), else small, so their inputs
        # stay few: the side from the queries' mean density over their bounding box, within bounds.
        low, high = column_bounds(queries.centres[:, :axes])
        lo_side, hi_side = LOCAL_SIDE_RANGE
        extent = np.maximum(high - low, lo_side * r)
        side = (LOCAL_BLOCK_QUERIES * float(np.prod(extent)) / m) ** (1.0 / extent.size) / r
        blocks, work = local_blocks(
            queries,
            X,
            r,
            chunk_size,
            axes=axes,
            side=min(max(side, lo_side), hi_side),
            inner_radius=kern.base.cutoff(LOCAL_VARIANCE_TOL),
        )
        if work + n**3 > share * n * n * m:
            return None
        return blocks

    def _walks_compiled(self, queries: Supports) -> bool:
        """Whether local prediction at `queries` takes the compiled walk: the exact (SE) kernel at points."""
        kern = self.kernel
        return (
            _compiled_local.ENABLED
            and isinstance(kern, AreaKernel)
            and kern.method == "exact"
            and kern.normalisation == "mean"
            and bool(np.array_equal(queries.lower, queries.upper))
        )

    def _latent_local(
        self, queries: Supports, blocks: LocalBlocks, variance: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Mean k_J^T w_J and (with `variance`) variance k** - k_I^T (K^-1)_II k_I, block by block
        (J a block's inputs, I its inner ones).

        The exact SE kernel at points takes one compiled call over every block
        (:func:`gpomap._compiled_local.point_block_moments`) where numba is enabled; the loop
        below is the reference it is tested against, and the path of every other kernel.
        """
        kern, X = self.kernel, self.inputs
        mean = np.zeros(len(queries))
        var = kern.diag(queries) if variance else None  # the prior where no input is near
        if variance and self.precision is None:
            self.precision = cholesky_inverse(self.L)
        points = bool(np.array_equal(queries.lower, queries.upper))
        # Work common to every block done once (the exact kernel's tables of factors).
        cross = kern.point_blocks(X, queries.lower) if points else None
        if isinstance(cross, BoxPointFactors) and _compiled_local.ENABLED:
            reduction = np.zeros(len(queries))
            side_lo, side_hi, side_of = cross.packed_sides()
            _compiled_local.point_block_moments(
                self.precision if self.precision is not None else np.empty((0, 0)),
                self.weights,
                side_lo,
                side_hi,
                side_of,
                np.ascontiguousarray(queries.lower, dtype=np.float64),
                blocks.query_index,
                blocks.query_start,
                blocks.input_index,
                blocks.input_start,
                blocks.n_inner,
                float(cross.length_scale),
                float(cross.variance),
                POINT_WIDTH,
                var is not None,
                mean,
                reduction,
            )
            if var is not None:
                var = np.maximum(var - reduction, 0.0)
            return mean, var
        for q, near, n_inner in blocks:
            if near.size == 0:
                continue
            K_II = None
            if var is not None:
                K_inv = self.precision
                assert K_inv is not None  # formed above
                inner = near[:n_inner]
                # One gather of the |I|^2 entries (rows then columns would copy |I| whole rows first).
                K_II = np.take(K_inv, inner[:, None] * K_inv.shape[1] + inner[None, :])
            w_J = self.weights[near]
            step = q.size if kern.method == "exact" else LOCAL_KERNEL_POINTS
            for s in range(0, q.size, step):
                qs = q[s : s + step]
                # (|J|, |qs|)
                Ks = cross.block(near, qs) if cross is not None else kern(X.subset(near), queries.subset(qs))
                mean[qs] = w_J @ Ks
                if var is not None and K_II is not None:
                    K_I = Ks[:n_inner]
                    reduction = np.einsum("ij,ij->j", K_I, K_II @ K_I)
                    var[qs] = np.maximum(var[qs] - reduction, 0.0)
        return mean, var

    def _latent_dense(
        self, queries: Supports, variance: bool, chunk_size: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Mean and variance from every input, in chunks of queries."""
        m = len(queries)
        mean = np.empty(m)
        var = np.empty(m) if variance else None
        # Whitening by a product where it pays (see triangular_inverse_for).
        L_inv = triangular_inverse_for(self.L, m, getattr(self.inputs, "dim", 2)) if variance else None
        for s in range(0, m, chunk_size):
            part = queries.subset(slice(s, min(m, s + chunk_size)))
            Ks = self.kernel(self.inputs, part)  # (n, c)
            mean[s : s + len(part)] = Ks.T @ self.weights
            if var is not None:
                v = solve_triangular(self.L, Ks, lower=True, check_finite=False) if L_inv is None else lower_product(L_inv, Ks)
                var[s : s + len(part)] = np.maximum(self.kernel.diag(part) - np.einsum("ij,ij->j", v, v), 0.0)
        return mean, var


@dataclass
class FitReport:
    """What hyperparameter learning did: the objective, its value, and the time and evaluations spent."""

    objective: str
    value: float
    n_evaluations: int
    seconds: float
    restarts: list[float] = field(default_factory=list)
    groups: int = 1


class SupportGP:
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
        noise: float = 0.1,
        noise_bounds: tuple[float, float] = (1e-4, 10.0),
        noise_model: str = "constant",
        objective: str = "loo",
        optimise: bool = True,
        n_restarts: int = 1,
        seed: int = 0,
        max_iter: int = 100,
        hyper_subset: int | None = 300,
        prior_std: float | None = 1.0,
        class_weight: str | None = "balanced",
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

    # ----------------------------------------------------------------- objectives
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
        self, X: Supports, return_var: bool = True, chunk_size: int = 4096, local: bool = True
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

    def predict_proba(self, X: Supports, chunk_size: int = 4096) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability and latent variance at new inputs, each ndarray of shape (m,)."""
        mean, var = self.predict_latent(X, True, chunk_size)
        assert var is not None  # asked for with return_var=True
        return self.squash(mean, var), var
