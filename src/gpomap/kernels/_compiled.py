"""The tensor-product quadrature kernel's node sums compiled with numba (:mod:`gpomap.kernels.tensor`'s fast path).

:func:`gpomap.kernels.tensor._group_gram` forms a block of node-pair squared distances, turns it
into profile values and reduces it with the rule's weights in a dozen numpy passes over each block
(plus fancy-indexed writes). Here one compiled loop per group pair does the same: per row input
and chunk of column inputs, the per-axis squared differences, their sums over the axes (in the same
order), the profile and its length-scale derivative, and the weighted sums written straight into
``K`` (and its transpose). The numbers are those of the numpy path to round-off (another
summation order; ``tests/test_tensor_compiled.py`` compares the two and both against
:func:`gpomap.kernels.nodes.weighted_gram`, ``tests/test_tensor_kernel.py`` runs on both).

The exponential is evaluated here (:func:`_exp`): numba's ``np.exp`` is glibc's scalar one, and a
loop of ``sqrt`` and ``exp`` with it is slower than numpy's SIMD passes; this branch-free
polynomial vectorises and is within 2 ulp of ``np.exp`` (the tests check it). Below ``EXP_MIN`` it
returns 0 where numpy returns a subnormal (under 3e-308 absolute). Products and sums may be fused
into one multiply-add (rounded once); nothing is reassociated.

``cache=True`` keeps the machine code in ``__pycache__``, so only a process's first call
compiles (what the path saves, and the compile and load times: docs/choices.md, "Measured for
the code"; docs/benchmarks.md, "numba's compile cache").

``AVAILABLE``: numba imports. ``ENABLED``: the tensor kernel takes this path (the environment
variable ``GPOMAP_NUMPY_KERNELS=1`` at import, or setting ``ENABLED = False``, forces numpy).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import compiled_by_default, jit, plain_decorator

_jit: Any = plain_decorator
_intrinsic: Any = plain_decorator
try:
    import numba
    from llvmlite import ir as _ir  # type: ignore[import-untyped]
    from numba.extending import intrinsic

    _jit, _intrinsic, _types = jit, intrinsic, numba.types
    AVAILABLE: bool = True
except ImportError:  # pragma: no cover - numba is a dependency; the numpy path remains the reference
    AVAILABLE = False


#: Whether :mod:`gpomap.kernels.tensor` takes the compiled path (read at each call: tests switch it).
ENABLED: bool = AVAILABLE and compiled_by_default()

#: Profiles compiled here, by :meth:`~gpomap.kernels.point.PointKernel.unit_profile_into`'s owner.
MATERN32: int = 0
SQUARED_EXPONENTIAL: int = 1

#: numba's fast-math flags: only contraction of a * b + c into one fused multiply-add (rounded
#: once, so at least as accurate); no reassociation, no assumptions about NaN or infinity.
_FASTMATH: set[str] = {"contract"}

#: Column inputs per chunk (one row input against them at a time): long enough vector loops, and
#: the chunk's squared differences (d * oa * ob of them per column) stay in L1/L2.
CHUNK_COLUMNS: int = 256

#: Exponents below which exp is taken as 0: e^-708 is about the smallest normal double, so 2^k
#: stays normal (k >= -1022) and needs no subnormal case.
EXP_MIN: float = -708.0

_LOG2E = 1.4426950408889634
# ln 2 in two parts (fdlibm's): k * _LN2_HI is exact for |k| < 2^11, so r = x - k ln 2 is
# accurate to about an ulp.
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
# 1/n! for n = 0..13: Taylor series of e^r on |r| <= ln(2)/2, truncation below 1e-17 relative.
_C = tuple(1.0 / math.factorial(n) for n in range(14))
(_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11, _C12, _C13) = _C


def profile_id(kernel: Any) -> int | None:
    """The compiled profile for `kernel` (:data:`MATERN32`, ...), or None when it has none here.

    A kernel qualifies when it has a unit form and its ``unit_profile_into`` is one of those
    compiled here (a subclass that overrides it does not).
    """
    from gpomap.kernels.point import Matern32, SquaredExponential

    if kernel.unit_scale is None:
        return None
    method = type(kernel).unit_profile_into
    if method is Matern32.unit_profile_into:
        return MATERN32
    if method is SquaredExponential.unit_profile_into:
        return SQUARED_EXPONENTIAL
    return None


@_intrinsic
def _as_float(typingctx: Any, bits: Any) -> Any:  # pragma: no cover - compiled
    """The float64 whose bit pattern is the int64 `bits` (a scalar bit cast)."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.bitcast(args[0], _ir.DoubleType())

    return _types.float64(_types.int64), codegen


@_jit(cache=True, fastmath=_FASTMATH, inline="always")
def _exp(x: float) -> float:  # pragma: no cover - compiled
    """e^x for x <= 0 to about an ulp, 0 below EXP_MIN: branch-free, so loops of it vectorise.

    x = k ln 2 + r with |r| <= ln(2)/2 (Cody-Waite), e^r by its Taylor polynomial, 2^k from its
    bit pattern.
    """
    y = max(x, EXP_MIN)
    k = np.floor(y * _LOG2E + 0.5)
    r = (y - k * _LN2_HI) - k * _LN2_LO
    # Estrin's scheme: the same polynomial in 4 dependent steps instead of Horner's 13, so that
    # consecutive vectors overlap (Horner's latency chain is slower in the kernel).
    r2 = r * r
    r4 = r2 * r2
    s0 = (_C0 + _C1 * r) + (_C2 + _C3 * r) * r2
    s1 = (_C4 + _C5 * r) + (_C6 + _C7 * r) * r2
    s2 = (_C8 + _C9 * r) + (_C10 + _C11 * r) * r2
    s3 = _C12 + _C13 * r
    p = (s0 + s1 * r4) + (s2 + s3 * r4) * (r4 * r4)
    e = p * _as_float((np.int64(k) + 1023) << 52)
    return 0.0 if x < EXP_MIN else e


@_jit(cache=True, fastmath=_FASTMATH)
def exp_into(x: NDArray[np.float64], out: NDArray[np.float64]) -> None:  # pragma: no cover - compiled
    """``out = exp(x)`` by :func:`_exp` (x <= 0); for the tests.

    Parameters
    ----------
    x, out : ndarray of shape (L,)
    """
    for t in range(x.size):
        out[t] = _exp(x[t])


@_jit(cache=True, fastmath=_FASTMATH, inline="always")
def _unit(u2: float, profile: int) -> tuple[float, float]:  # pragma: no cover - compiled
    """The unit profile at `u2` and its d/dlog l, as :mod:`~gpomap.kernels.point` has them.

    Matern 3/2: (1 + u) e^-u and u^2 e^-u with u = sqrt(u2); squared exponential: e^(-u2/2)
    and u2 e^(-u2/2).
    """
    if profile == MATERN32:
        u = np.sqrt(u2)
        e = _exp(-u)
        return (u + 1.0) * e, e * u2
    e = _exp(u2 * -0.5)
    return e, e * u2


@_jit(cache=True, fastmath=_FASTMATH, inline="always")
def _value(u2: float, profile: int) -> float:  # pragma: no cover - compiled
    """The unit profile at `u2` alone (:func:`_unit` without the derivative, for a Gram without gradient)."""
    if profile == MATERN32:
        u = np.sqrt(u2)
        return (u + 1.0) * _exp(-u)
    return _exp(u2 * -0.5)


def group_gram(
    ca: NDArray[np.float64],
    cb: NDArray[np.float64],
    w: NDArray[np.float64],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    K: NDArray[np.float64],
    dL: NDArray[np.float64],
    gradient: bool,
    symmetric: bool,
    mirror: bool,
    profile: int,
) -> None:
    """The averaged kernel between two groups of inputs, written at ``K[rows, cols]`` (:func:`~gpomap.kernels.tensor._group_gram`).

    Parameters
    ----------
    ca : ndarray of shape (d, oa, n)
        ``ca[k, p, i]``: the p-th node coordinate of row input i along axis k, in units of the
        kernel's scale (:attr:`gpomap.kernels.tensor.TensorRule.coords`).
    cb : ndarray of shape (d, ob, m)
        The same for the column inputs.
    w : ndarray of shape (oa ** d * ob ** d,)
        The node pairs' weights (times the variance), a's node index major, each node's axis
        indices in row-major order.
    rows : ndarray of int of shape (n,)
    cols : ndarray of int of shape (m,)
        Where the inputs' rows and columns go in `K`.
    K : ndarray of shape (N, M)
        Receives the values.
    dL : ndarray of shape (N, M)
        Receives d/dlog l with `gradient` (any array otherwise).
    gradient : bool
    symmetric : bool
        `ca` is `cb`: pair (i, j) computed for j >= i only, (j, i) written with it.
    mirror : bool
        Also write the transpose at ``K[cols, rows]``.
    profile : int
        :data:`MATERN32` or :data:`SQUARED_EXPONENTIAL`.
    """
    # One compiled function per dimension: a first run compiles the loops of its own alone.
    gram = _plane_gram if ca.shape[0] == 2 else _space_gram
    gram(ca, cb, w, rows, cols, K, dL, gradient, symmetric, mirror, profile)


@_jit(cache=True, fastmath=_FASTMATH, inline="always")
def _squared_differences(
    ca: NDArray[np.float64], cb: NDArray[np.float64], i: int, j0: int, nj: int, diff: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    """``diff[k, p, q, jj]``: the squared difference along axis k of row input i's node p and
    column input j0 + jj's node q; every inner loop runs over the chunk's columns, contiguous, and vectorises."""
    d, oa, _ = ca.shape
    ob = cb.shape[1]
    for k in range(d):
        for p in range(oa):
            x = ca[k, p, i]
            for q in range(ob):
                for jj in range(nj):
                    t = x - cb[k, q, j0 + jj]
                    diff[k, p, q, jj] = t * t


@_jit(cache=True, fastmath=_FASTMATH, inline="always")
def _store(
    K: NDArray[np.float64],
    dL: NDArray[np.float64],
    ri: int,
    cols: NDArray[np.intp],
    j0: int,
    nj: int,
    acc: NDArray[np.float64],
    gacc: NDArray[np.float64],
    gradient: bool,
    mirror: bool,
) -> None:  # pragma: no cover - compiled
    """One row input's sums against a chunk of columns, written at ``K[ri, cols]`` (and mirrored)."""
    for jj in range(nj):
        cj = cols[j0 + jj]
        K[ri, cj] = acc[jj]
        if mirror:
            K[cj, ri] = acc[jj]
        if gradient:
            dL[ri, cj] = gacc[jj]
            if mirror:
                dL[cj, ri] = gacc[jj]


# nogil: a Dask worker runs its tasks (tiles) in threads by default; numpy's passes released the GIL too.
@_jit(cache=True, fastmath=_FASTMATH, nogil=True)
def _plane_gram(
    ca: NDArray[np.float64],
    cb: NDArray[np.float64],
    w: NDArray[np.float64],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    K: NDArray[np.float64],
    dL: NDArray[np.float64],
    gradient: bool,
    symmetric: bool,
    mirror: bool,
    profile: int,
) -> None:  # pragma: no cover - compiled
    """:func:`group_gram` of planar inputs (d = 2)."""
    d, oa, n = ca.shape
    ob, m = cb.shape[1], cb.shape[2]
    pb = ob**d
    diff = np.empty((d, oa, ob, CHUNK_COLUMNS))
    acc = np.empty(CHUNK_COLUMNS)
    gacc = np.empty(CHUNK_COLUMNS)
    for i in range(n):
        ri = rows[i]
        for j0 in range(i if symmetric else 0, m, CHUNK_COLUMNS):
            nj = min(m, j0 + CHUNK_COLUMNS) - j0
            _squared_differences(ca, cb, i, j0, nj, diff)
            acc[:nj] = 0.0
            gacc[:nj] = 0.0
            # Node pairs in the weights' order; the squared distance summed over the axes in
            # order, from the first (as tensor._squared_distances).
            for p0 in range(oa):
                for p1 in range(oa):
                    for q0 in range(ob):
                        for q1 in range(ob):
                            wp = w[(p0 * oa + p1) * pb + q0 * ob + q1]
                            if gradient:
                                for jj in range(nj):
                                    v, g = _unit(diff[0, p0, q0, jj] + diff[1, p1, q1, jj], profile)
                                    acc[jj] += wp * v
                                    gacc[jj] += wp * g
                            else:
                                for jj in range(nj):
                                    acc[jj] += wp * _value(diff[0, p0, q0, jj] + diff[1, p1, q1, jj], profile)
            _store(K, dL, ri, cols, j0, nj, acc, gacc, gradient, mirror)


@_jit(cache=True, fastmath=_FASTMATH, nogil=True)
def _space_gram(
    ca: NDArray[np.float64],
    cb: NDArray[np.float64],
    w: NDArray[np.float64],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    K: NDArray[np.float64],
    dL: NDArray[np.float64],
    gradient: bool,
    symmetric: bool,
    mirror: bool,
    profile: int,
) -> None:  # pragma: no cover - compiled
    """:func:`group_gram` of inputs in space (d = 3, :data:`gpomap.kernels.area.TENSOR_DIMS`)."""
    d, oa, n = ca.shape
    ob, m = cb.shape[1], cb.shape[2]
    pb = ob**d
    diff = np.empty((d, oa, ob, CHUNK_COLUMNS))
    acc = np.empty(CHUNK_COLUMNS)
    gacc = np.empty(CHUNK_COLUMNS)
    for i in range(n):
        ri = rows[i]
        for j0 in range(i if symmetric else 0, m, CHUNK_COLUMNS):
            nj = min(m, j0 + CHUNK_COLUMNS) - j0
            _squared_differences(ca, cb, i, j0, nj, diff)
            acc[:nj] = 0.0
            gacc[:nj] = 0.0
            for p0 in range(oa):
                for p1 in range(oa):
                    for p2 in range(oa):
                        for q0 in range(ob):
                            for q1 in range(ob):
                                for q2 in range(ob):
                                    wp = w[((p0 * oa + p1) * oa + p2) * pb + (q0 * ob + q1) * ob + q2]
                                    if gradient:
                                        for jj in range(nj):
                                            s = (diff[0, p0, q0, jj] + diff[1, p1, q1, jj]) + diff[2, p2, q2, jj]
                                            v, g = _unit(s, profile)
                                            acc[jj] += wp * v
                                            gacc[jj] += wp * g
                                    else:
                                        for jj in range(nj):
                                            s = (diff[0, p0, q0, jj] + diff[1, p1, q1, jj]) + diff[2, p2, q2, jj]
                                            acc[jj] += wp * _value(s, profile)
            _store(K, dL, ri, cols, j0, nj, acc, gacc, gradient, mirror)
