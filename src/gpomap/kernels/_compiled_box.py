"""The exact SE area kernel's Gram matrix compiled with numba (:func:`gpomap.kernels.closed_form.se_box_gram`'s fast path).

:func:`~gpomap.kernels.closed_form.se_box_gram` finds each axis's distinct intervals, tables the
1-D kernel between them from one table of G2 over their distinct ends, and gathers the tables into
the n x n Gram matrix (and its length-scale derivative) in about forty numpy passes. A map's
hyperparameter search evaluates it on 200-cell groups sixty times, and every tile fit once, so on
small maps it is a good part of the fit. Here one compiled call does the
same: the distinct intervals and ends by stable sorts, the G2 table, the 1-D tables and the
products, written straight into K. The numbers are the numpy path's to round-off (the 1-D tables
are formed once per pair and mirrored instead of averaged with their transpose, and libm's erf
stands for scipy's); ``tests/test_kernels.py`` compares the two, and both with the box average.

What it saves per call and per paper-benchmark fit: docs/choices.md, "Measured for the code".

Sides narrower than :data:`~gpomap.kernels.closed_form.POINT_WIDTH` of the length scale take
the point formulas, as in the numpy path (a cell of the tree over hits on one line is a point
across it).

``ENABLED``: :func:`~gpomap.kernels.closed_form.se_box_gram` takes this path (read at each call;
:func:`gpomap.compiled.compiled_by_default` at import, tests switch it).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpomap.compiled import NUMBA_AVAILABLE, compiled_by_default, jit

#: Whether numba imports here.
AVAILABLE: bool = NUMBA_AVAILABLE

#: Whether :func:`gpomap.kernels.closed_form.se_box_gram` takes the compiled path (read at each call).
ENABLED: bool = compiled_by_default()

_SQRT_HALF_PI = math.sqrt(math.pi / 2.0)


@jit(cache=True, nogil=True)
def distinct_sorted(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.intp]]:  # pragma: no cover - compiled
    """The distinct values of x, sorted, and where each element of x is among them (``values[where] == x``)."""
    order = np.argsort(x, kind="mergesort")
    values = np.empty(x.size)
    where = np.empty(x.size, dtype=np.intp)
    u = 0
    for t in range(x.size):
        v = x[order[t]]
        if u == 0 or v != values[u - 1]:
            values[u] = v
            u += 1
        where[order[t]] = u - 1
    return values[:u], where


@jit(cache=True, nogil=True)
def _axis_tables(
    lo: NDArray[np.float64], hi: NDArray[np.float64], l: float, eval_gradient: bool, point_width: float
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - compiled
    """One axis: each box's distinct interval, and the 1-D kernel (and d / dlog l) between the distinct intervals.

    Intervals narrower than ``point_width * l`` are points, as in the numpy path.

    Returns
    -------
    inverse : ndarray of int, shape (n,)
    F, dF : ndarray of shape (u, u)
        dF is empty (0, 0) without `eval_gradient`.
    """
    n = lo.size
    # The distinct intervals, sorted by (lo, hi): stable sorts by hi, then by lo.
    by_hi = np.argsort(hi, kind="mergesort")
    order = by_hi[np.argsort(lo[by_hi], kind="mergesort")]
    inverse = np.empty(n, dtype=np.intp)
    a = np.empty(n)
    b = np.empty(n)
    u = 0
    for t in range(n):
        i = order[t]
        if u == 0 or lo[i] != a[u - 1] or hi[i] != b[u - 1]:
            a[u] = lo[i]
            b[u] = hi[i]
            u += 1
        inverse[i] = u - 1
    # Their distinct ends, and which end each interval's lo and hi is.
    both = np.empty(2 * u)
    both[:u] = a[:u]
    both[u:] = b[:u]
    ends, where = distinct_sorted(both)
    e = ends.size
    # G2 (and its derivative in l) of every difference of ends: the very differences the
    # corners take. G2 is even, so each pair once.
    g2 = np.empty((e, e))
    dg2 = np.empty((e, e)) if eval_gradient else np.empty((0, 0))
    scale = 1.0 / (math.sqrt(2.0) * l)
    for r in range(e):
        for c in range(r, e):
            x = ends[r] - ends[c]
            q = x / l
            erf = math.erf(x * scale)
            m = math.expm1(-0.5 * q * q)
            g2[r, c] = g2[c, r] = l * _SQRT_HALF_PI * x * erf + l * l * m
            if eval_gradient:
                dg2[r, c] = dg2[c, r] = _SQRT_HALF_PI * x * erf + 2.0 * l * m
    F = np.empty((u, u))
    dF = np.empty((u, u)) if eval_gradient else np.empty((0, 0))
    for i in range(u):
        ia, ib = where[i], where[u + i]
        wi = b[i] - a[i]
        point_i = wi < point_width * l
        for j in range(i, u):
            ja, jb = where[j], where[u + j]
            wj = b[j] - a[j]
            point_j = wj < point_width * l
            if not point_i and not point_j:
                # Corners b - c, a - c, b - d, a - d of intervals [a, b] and [c, d].
                area = wi * wj
                f = (g2[ib, ja] - g2[ia, ja] - g2[ib, jb] + g2[ia, jb]) / area
                df = l * (dg2[ib, ja] - dg2[ia, ja] - dg2[ib, jb] + dg2[ia, jb]) / area if eval_gradient else 0.0
            elif point_i and point_j:
                x = 0.5 * (a[i] + b[i]) - 0.5 * (a[j] + b[j])
                q = x / l
                f = math.exp(-0.5 * q * q)
                df = f * q * q
            else:
                # A point x against an interval [c, d], whichever side the point is.
                if point_i:
                    x, c, d, w = 0.5 * (a[i] + b[i]), a[j], b[j], wj
                else:
                    x, c, d, w = 0.5 * (a[j] + b[j]), a[i], b[i], wi
                ed, ec = math.erf((d - x) * scale), math.erf((c - x) * scale)
                f = l * _SQRT_HALF_PI * (ed - ec) / w
                df = 0.0
                if eval_gradient:
                    qd, qc = (d - x) / l, (c - x) / l
                    dd = _SQRT_HALF_PI * ed - (d - x) * math.exp(-0.5 * qd * qd) / l
                    dc = _SQRT_HALF_PI * ec - (c - x) * math.exp(-0.5 * qc * qc) / l
                    df = l * (dd - dc) / w
            F[i, j] = F[j, i] = f
            if eval_gradient:
                dF[i, j] = dF[j, i] = df
    return inverse, F, dF


@jit(cache=True, nogil=True)
def box_gram(
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    variance: float,
    l: float,
    eval_gradient: bool,
    point_width: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - compiled
    """The exact SE Gram matrix of boxes (points are boxes of zero width), and (with `eval_gradient`) dK / dlog l.

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
    variance, l : float
    point_width : float
        Sides narrower than this fraction of `l` are points
        (:data:`gpomap.kernels.closed_form.POINT_WIDTH`).

    Returns
    -------
    K : ndarray of shape (n, n)
        Exactly symmetric.
    dK : ndarray of shape (n, n), or (0, 0) without `eval_gradient`
    """
    n, d = lower.shape
    inverses = np.empty((d, n), dtype=np.intp)
    parts = []
    size = 0
    for k in range(d):
        inv, F, dF = _axis_tables(
            np.ascontiguousarray(lower[:, k]), np.ascontiguousarray(upper[:, k]), l, eval_gradient, point_width
        )
        inverses[k] = inv
        parts.append((F, dF))
        size = max(size, F.shape[0])
    # The axes' tables in one array (padded), the variance folded into the first as numpy does.
    T = np.zeros((d, size, size))
    dT = np.zeros((d, size, size)) if eval_gradient else np.zeros((0, 0, 0))
    for k in range(d):
        F, dF = parts[k]
        u = F.shape[0]
        s = variance if k == 0 else 1.0
        T[k, :u, :u] = s * F
        if eval_gradient:
            dT[k, :u, :u] = s * dF
    K = np.empty((n, n))
    dK = np.empty((n, n)) if eval_gradient else np.empty((0, 0))
    if d == 2:
        x, y = inverses[0], inverses[1]
        for i in range(n):
            xi, yi = x[i], y[i]
            for j in range(i, n):
                fx, fy = T[0, xi, x[j]], T[1, yi, y[j]]
                K[i, j] = K[j, i] = fx * fy
                if eval_gradient:
                    dK[i, j] = dK[j, i] = dT[0, xi, x[j]] * fy + dT[1, yi, y[j]] * fx
        return K, dK
    f = np.empty(d)
    for i in range(n):
        for j in range(i, n):
            prod = 1.0
            for k in range(d):
                f[k] = T[k, inverses[k, i], inverses[k, j]]
                prod *= f[k]
            K[i, j] = K[j, i] = prod
            if eval_gradient:
                # Product rule over the axes, without dividing by factors that may be zero.
                total = 0.0
                for k in range(d):
                    term = dT[k, inverses[k, i], inverses[k, j]]
                    for m in range(d):
                        if m != k:
                            term *= f[m]
                    total += term
                dK[i, j] = dK[j, i] = total
    return K, dK
