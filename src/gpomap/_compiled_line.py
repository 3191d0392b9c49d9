"""GPOMIK's line kernel compiled with numba (:class:`gpomap.baselines.gpomik.CompiledLineKernel`'s fast path).

:class:`gpomap.kernels.line.LineKernel` builds a Gram matrix over beams from blocks of numpy
passes: for Matern 3/2 every node pair's squared distance, profile and derivative as (block, block)
arrays, reduced per input with ``np.add.reduceat``; for the squared exponential every (node,
segment) entry of every pair of inputs, gathered by fancy indexing, evaluated in closed form and
reduced with ``np.bincount``. On the paper's two rooms these passes cost more per evaluation of
the hyperparameter objective than its Cholesky factorisation and inverse (docs/choices.md,
"Measured for the code"). Here one compiled loop per row input does the same sums with no
temporaries beyond a row of nodes:

- **Matern 3/2**: per row input and each of its nodes, one vectorised pass over the nodes of the
  columns from that input on, accumulating the profile and its length-scale derivative per node;
  then the per-node sums are reduced with the column inputs' weights. Pairs (i, j >= i) only, the
  lower triangle mirrored, so K is exactly symmetric.
- **squared exponential**: per pair of inputs, the closed form for parallel proper segments, else
  Gauss-Legendre along the shorter one (the same symmetric rule, on the same lengths) against the
  closed-form segment-point integral along the other: the reference's sums term by term.

The values are the numpy path's to round-off (another summation order, a polynomial exponential
within 2 ulp of ``np.exp`` for Matern 3/2); ``tests/test_baselines_compiled.py`` compares the two.
``LineKernel`` stays the tests' reference.

``ENABLED``: :class:`~gpomap.baselines.gpomik.CompiledLineKernel` takes this path (read at each
call; :func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit
from gpomap.kernels._compiled import MATERN32, _unit, _value

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether the compiled line kernel is used (read at each call).
ENABLED: bool = compiled_by_default()

#: As :mod:`gpomap.kernels._compiled`: only a * b + c contracted into one multiply-add.
_FASTMATH: set[str] = {"contract"}

#: One input set for :func:`se_gram`: starts, ends, lengths, nodes, node weights, node offsets.
SegmentArrays = tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]
]

_SQRT_HALF_PI = math.sqrt(math.pi / 2.0)
_SQRT2 = math.sqrt(2.0)


# ------------------------------------------------------------------------ Matern 3/2: node sums


@jit(cache=True, fastmath=_FASTMATH, nogil=True)
def _node_sums_symmetric(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    w: NDArray[np.float64],
    offsets: NDArray[np.intp],
    owner: NDArray[np.intp],
    scale2: float,
    variance: float,
    gradient: bool,
    K: NDArray[np.float64],
    dL: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled (the numpy path is the tests' reference)
    """K[i, j] = variance sum_p sum_q w_p w_q k(x_p, x_q) over the nodes of inputs i and j, j >= i, mirrored.

    `scale2` is the unit scale squared (3 / l^2 for Matern 3/2); `dL` gets d/dlog l with `gradient`.
    """
    n = offsets.size - 1
    P = x.size
    acc = np.empty(P)
    gacc = np.empty(P)
    for i in range(n):
        first = offsets[i]
        # Views from this input's first node on, indexed from 0: loops whose indices are known
        # not to be negative (no wraparound test) vectorise.
        xs, ys, a, ga = x[first:], y[first:], acc[first:], gacc[first:]
        a[:] = 0.0
        ga[:] = 0.0
        for p in range(first, offsets[i + 1]):
            xp, yp, wp = x[p], y[p], w[p]
            if gradient:
                for t in range(xs.size):
                    dx = xp - xs[t]
                    dy = yp - ys[t]
                    v, g = _unit((dx * dx + dy * dy) * scale2, MATERN32)
                    a[t] += wp * v
                    ga[t] += wp * g
            else:
                for t in range(xs.size):
                    dx = xp - xs[t]
                    dy = yp - ys[t]
                    a[t] += wp * _value((dx * dx + dy * dy) * scale2, MATERN32)
        # Reduce the per-node sums by the column inputs' weights (columns j >= i).
        for j in range(i, n):
            K[i, j] = 0.0
            if gradient:
                dL[i, j] = 0.0
        for q in range(first, P):
            j = owner[q]
            K[i, j] += w[q] * acc[q]
            if gradient:
                dL[i, j] += w[q] * gacc[q]
        for j in range(i, n):
            K[i, j] *= variance
            K[j, i] = K[i, j]
            if gradient:
                dL[i, j] *= variance
                dL[j, i] = dL[i, j]


@jit(cache=True, fastmath=_FASTMATH, nogil=True)
def _node_sums_cross(
    xa: NDArray[np.float64],
    ya: NDArray[np.float64],
    wa: NDArray[np.float64],
    owner_a: NDArray[np.intp],
    xb: NDArray[np.float64],
    yb: NDArray[np.float64],
    wb: NDArray[np.float64],
    offsets_b: NDArray[np.intp],
    scale2: float,
    variance: float,
    Kt: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """Kt[j, i] = variance sum_p sum_q w_p w_q k(a_p, b_q): the cross Gram, column input by column input, transposed."""
    m = offsets_b.size - 1
    Pa = xa.size
    acc = np.empty(Pa)
    for j in range(m):
        acc[:] = 0.0
        for q in range(offsets_b[j], offsets_b[j + 1]):
            xq, yq, wq = xb[q], yb[q], wb[q]
            for p in range(Pa):
                dx = xa[p] - xq
                dy = ya[p] - yq
                acc[p] += wq * _value((dx * dx + dy * dy) * scale2, MATERN32)
        row = Kt[j]
        row[:] = 0.0
        for p in range(Pa):
            row[owner_a[p]] += wa[p] * acc[p]
        for i in range(row.size):
            row[i] *= variance


def _owners(offsets: NDArray[np.intp]) -> NDArray[np.intp]:
    """The input of each node, ndarray of int, shape (offsets[-1],)."""
    return np.repeat(np.arange(offsets.size - 1, dtype=np.intp), np.diff(offsets))


def matern32_gram(
    nodes: NDArray[np.float64],
    weights: NDArray[np.float64],
    offsets: NDArray[np.intp],
    variance: float,
    length_scale: float,
    gradient: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The Matern 3/2 kernel averaged over each pair of inputs' weighted nodes, and its d/dlog l.

    Parameters
    ----------
    nodes : ndarray of shape (P, 2)
    weights : ndarray of shape (P,)
    offsets : ndarray of int, shape (n + 1,)
        Input i's nodes are ``nodes[offsets[i]:offsets[i + 1]]``.
    variance, length_scale : float
    gradient : bool

    Returns
    -------
    K : ndarray of shape (n, n)
        Exactly symmetric.
    dL : ndarray of shape (n, n) or None
        d K / d log(length_scale), with `gradient`.
    """
    offsets = np.ascontiguousarray(offsets, dtype=np.intp)
    n = offsets.size - 1
    K = np.empty((n, n))
    dL = np.empty((n, n)) if gradient else np.empty((0, 0))
    _node_sums_symmetric(
        np.ascontiguousarray(nodes[:, 0], dtype=np.float64),
        np.ascontiguousarray(nodes[:, 1], dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64),
        offsets,
        _owners(offsets),
        3.0 / (length_scale * length_scale),
        float(variance),
        bool(gradient),
        K,
        dL,
    )
    return K, (dL if gradient else None)


def matern32_cross(
    nodes_a: NDArray[np.float64],
    weights_a: NDArray[np.float64],
    offsets_a: NDArray[np.intp],
    nodes_b: NDArray[np.float64],
    weights_b: NDArray[np.float64],
    offsets_b: NDArray[np.intp],
    variance: float,
    length_scale: float,
) -> NDArray[np.float64]:
    """The Matern 3/2 kernel averaged over the nodes of each input of A against each of B, ndarray of shape (n, m).

    Parameters as :func:`matern32_gram`, for two node sets (n and m inputs).
    """
    offsets_a = np.ascontiguousarray(offsets_a, dtype=np.intp)
    offsets_b = np.ascontiguousarray(offsets_b, dtype=np.intp)
    Kt = np.empty((offsets_b.size - 1, offsets_a.size - 1))
    _node_sums_cross(
        np.ascontiguousarray(nodes_a[:, 0], dtype=np.float64),
        np.ascontiguousarray(nodes_a[:, 1], dtype=np.float64),
        np.ascontiguousarray(weights_a, dtype=np.float64),
        _owners(offsets_a),
        np.ascontiguousarray(nodes_b[:, 0], dtype=np.float64),
        np.ascontiguousarray(nodes_b[:, 1], dtype=np.float64),
        np.ascontiguousarray(weights_b, dtype=np.float64),
        offsets_b,
        3.0 / (length_scale * length_scale),
        float(variance),
        Kt,
    )
    return np.ascontiguousarray(Kt.T)


# ------------------------------------------------------------- squared exponential: closed forms


@jit(cache=True, nogil=True, inline="always")
def _g1(u: float, l: float) -> float:  # pragma: no cover - compiled
    """Antiderivative of exp(-u^2 / (2 l^2)) (:func:`gpomap.kernels.line._g1`)."""
    return l * _SQRT_HALF_PI * math.erf(u / (_SQRT2 * l))


@jit(cache=True, nogil=True, inline="always")
def _dg1(u: float, l: float) -> float:  # pragma: no cover - compiled
    """l d(_g1)/dl (:func:`gpomap.kernels.line._dg1_dlogl`)."""
    return _g1(u, l) - u * math.exp(-0.5 * (u / l) ** 2)


@jit(cache=True, nogil=True, inline="always")
def _g2(u: float, l: float) -> float:  # pragma: no cover - compiled
    """Second antiderivative of exp(-u^2 / (2 l^2)) (:func:`gpomap.kernels.line._g2`)."""
    return l * _SQRT_HALF_PI * u * math.erf(u / (_SQRT2 * l)) + l * l * math.expm1(-0.5 * (u / l) ** 2)


@jit(cache=True, nogil=True, inline="always")
def _dg2(u: float, l: float) -> float:  # pragma: no cover - compiled
    """l d(_g2)/dl (:func:`gpomap.kernels.line._dg2_dlogl`)."""
    return l * _SQRT_HALF_PI * u * math.erf(u / (_SQRT2 * l)) + 2.0 * l * l * math.expm1(-0.5 * (u / l) ** 2)


@jit(cache=True, nogil=True)
def _point_segment(
    px: float, py: float, sx: float, sy: float, ex: float, ey: float, L: float, short: float, l: float
) -> tuple[float, float]:  # pragma: no cover - compiled
    """The unit SE averaged along segment s -> e (length L) against a point, and d/dlog l
    (:func:`gpomap.kernels.line.se_point_segment` for one pair; a segment shorter than `short`
    acts as its midpoint)."""
    is_short = short > L
    Ls = 1.0 if is_short else L
    dx = (ex - sx) / Ls
    dy = (ey - sy) / Ls
    if is_short:
        ox, oy = 0.5 * (sx + ex), 0.5 * (sy + ey)
    else:
        ox, oy = sx, sy
    rx = px - ox
    ry = py - oy
    t = rx * dx + ry * dy
    if is_short:
        h2 = rx * rx + ry * ry
    else:
        c = rx * dy - ry * dx
        h2 = c * c
    q = h2 / (l * l)
    gauss = math.exp(-0.5 * q)
    if is_short:
        return gauss, gauss * q
    hi, lo = L - t, -t
    # _g1 once per end, shared with _dg1 (= _g1 - u exp(-u^2 / 2 l^2)): the same numbers, half the erfs.
    g_hi, g_lo = _g1(hi, l), _g1(lo, l)
    inner = (g_hi - g_lo) / Ls
    dinner = ((g_hi - hi * math.exp(-0.5 * (hi / l) ** 2)) - (g_lo - lo * math.exp(-0.5 * (lo / l) ** 2))) / Ls
    return gauss * inner, gauss * (q * inner + dinner)


@jit(cache=True, nogil=True)
def _parallel(
    sax: float,
    say: float,
    eax: float,
    eay: float,
    sbx: float,
    sby: float,
    ebx: float,
    eby: float,
    short: float,
    l: float,
) -> tuple[float, float]:  # pragma: no cover - compiled
    """The unit SE averaged over two parallel segments, A of positive length, and d/dlog l
    (:func:`gpomap.kernels.line.se_parallel_pairs` for one pair)."""
    vx, vy = eax - sax, eay - say
    La = math.hypot(vx, vy)
    dx, dy = vx / La, vy / La
    rsx, rsy = sbx - sax, sby - say
    rex, rey = ebx - sax, eby - say
    ts = rsx * dx + rsy * dy
    te = rex * dx + rey * dy
    mx, my = 0.5 * (rsx + rex), 0.5 * (rsy + rey)
    h = mx * dy - my * dx
    q = (h / l) ** 2
    gauss = math.exp(-0.5 * q)
    # The interval pair (0, La) against (c, d) (gpomap.kernels.line._interval_pairs).
    a0, a1 = 0.0, La
    b0, b1 = min(ts, te), max(ts, te)
    pa = a1 - a0 < short
    pb = b1 - b0 < short
    if not pa and not pb:
        area = (a1 - a0) * (b1 - b0)
        inner = (_g2(a1 - b0, l) - _g2(a0 - b0, l) - _g2(a1 - b1, l) + _g2(a0 - b1, l)) / area
        dinner = (_dg2(a1 - b0, l) - _dg2(a0 - b0, l) - _dg2(a1 - b1, l) + _dg2(a0 - b1, l)) / area
    elif pa != pb:
        if pa:
            x, c, d = 0.5 * (a0 + a1), b0, b1
        else:
            x, c, d = 0.5 * (b0 + b1), a0, a1
        inner = (_g1(d - x, l) - _g1(c - x, l)) / (d - c)
        dinner = (_dg1(d - x, l) - _dg1(c - x, l)) / (d - c)
    else:
        r = (0.5 * (a0 + a1 - b0 - b1)) / l
        rr = r * r
        inner = math.exp(-0.5 * rr)
        dinner = inner * rr
    return gauss * inner, gauss * (q * inner + dinner)


@jit(cache=True, nogil=True)
def _se_pairs(
    sa: NDArray[np.float64],
    ea: NDArray[np.float64],
    La: NDArray[np.float64],
    nodes_a: NDArray[np.float64],
    wa: NDArray[np.float64],
    off_a: NDArray[np.intp],
    sb: NDArray[np.float64],
    eb: NDArray[np.float64],
    Lb: NDArray[np.float64],
    nodes_b: NDArray[np.float64],
    wb: NDArray[np.float64],
    off_b: NDArray[np.intp],
    l: float,
    short: float,
    parallel_sin: float,
    symmetric: bool,
    gradient: bool,
    F: NDArray[np.float64],
    dF: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """F[i, j]: the unit SE averaged over input i of A and j of B (j >= i and mirrored when `symmetric`), dF its d/dlog l.

    Per pair as :meth:`gpomap.kernels.line.LineKernel._se`: parallel proper segments in closed
    form; otherwise the nodes of the shorter (by length, then start and end coordinates: a rule
    symmetric in the pair) against the closed-form integral along the other.
    """
    n, m = La.size, Lb.size
    for i in range(n):
        proper_a = La[i] >= short
        if proper_a:
            dax = (ea[i, 0] - sa[i, 0]) / La[i]
            day = (ea[i, 1] - sa[i, 1]) / La[i]
        else:
            dax = day = 0.0
        for j in range(i if symmetric else 0, m):
            if proper_a and Lb[j] >= short:
                dbx = (eb[j, 0] - sb[j, 0]) / Lb[j]
                dby = (eb[j, 1] - sb[j, 1]) / Lb[j]
                if abs(dax * dby - day * dbx) < parallel_sin:
                    f, g = _parallel(sa[i, 0], sa[i, 1], ea[i, 0], ea[i, 1], sb[j, 0], sb[j, 1], eb[j, 0], eb[j, 1], short, l)
                    F[i, j] = f
                    if gradient:
                        dF[i, j] = g
                    continue
            # The lexicographic rule of gpomap.kernels.line._lex_less_equal: A's side when A is not greater.
            along_a = True
            ka = (La[i], sa[i, 0], sa[i, 1], ea[i, 0], ea[i, 1])
            kb = (Lb[j], sb[j, 0], sb[j, 1], eb[j, 0], eb[j, 1])
            for c in range(5):
                if ka[c] < kb[c]:
                    break
                if ka[c] > kb[c]:
                    along_a = False
                    break
            f = 0.0
            g = 0.0
            if along_a:
                for p in range(off_a[i], off_a[i + 1]):
                    v, dv = _point_segment(nodes_a[p, 0], nodes_a[p, 1], sb[j, 0], sb[j, 1], eb[j, 0], eb[j, 1], Lb[j], short, l)
                    f += v * wa[p]
                    g += dv * wa[p]
            else:
                for q in range(off_b[j], off_b[j + 1]):
                    v, dv = _point_segment(nodes_b[q, 0], nodes_b[q, 1], sa[i, 0], sa[i, 1], ea[i, 0], ea[i, 1], La[i], short, l)
                    f += v * wb[q]
                    g += dv * wb[q]
            F[i, j] = f
            if gradient:
                dF[i, j] = g
    if symmetric:
        for i in range(n):
            for j in range(i + 1, n):
                F[j, i] = F[i, j]
                if gradient:
                    dF[j, i] = dF[i, j]


def se_gram(
    a: SegmentArrays,
    b: SegmentArrays | None,
    length_scale: float,
    point_length: float,
    parallel_sin: float,
    gradient: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The unit-variance SE kernel averaged over pairs of segments (or points), and its d/dlog l.

    Parameters
    ----------
    a, b : tuple
        Each input set as (starts (n, 2), ends (n, 2), lengths (n,), nodes (P, 2), node weights
        (P,), node offsets (n + 1,)): :class:`~gpomap.kernels.line.Segments`' end points and
        lengths and the :func:`~gpomap.kernels.line.segment_nodes` of the kernel's rule. `b` None:
        `a` against itself (pairs j >= i computed, the rest mirrored: exactly symmetric).
    length_scale : float
    point_length : float
        Segments shorter than this fraction of the length scale act as their midpoint
        (:data:`gpomap.kernels.line.POINT_LENGTH`).
    parallel_sin : float
        Proper segments whose directions' sine is below this are parallel (closed form).
    gradient : bool

    Returns
    -------
    F : ndarray of shape (n, m)
    dF : ndarray of shape (n, m) or None
        dF / dlog(length_scale), with `gradient`.
    """
    symmetric = b is None
    A = tuple(np.ascontiguousarray(v) for v in a)
    B = A if b is None else tuple(np.ascontiguousarray(v) for v in b)
    n, m = A[2].size, B[2].size
    F = np.empty((n, m))
    dF = np.empty((n, m)) if gradient else np.empty((0, 0))
    l = float(length_scale)
    _se_pairs(*A, *B, l, point_length * l, parallel_sin, symmetric, bool(gradient), F, dF)
    return F, (dF if gradient else None)
