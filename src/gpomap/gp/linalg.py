"""The dense linear algebra of a GP: Cholesky factors, their solves and inverses, whitening products.

A factor that fails is retried with jitter (:func:`robust_cholesky`, :func:`noisy_cholesky`);
inverses and their diagonals are formed in place, a block at a time, through LAPACK without the
GIL (:mod:`gpomap.lapack`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import LinAlgError, cholesky

from gpomap import lapack
from gpomap.errors import NumericalError


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
