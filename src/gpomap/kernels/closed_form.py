"""Exact squared-exponential kernels averaged over axis-aligned boxes, in closed form.

The squared exponential is separable, so its average over a pair of boxes is a product of 1-D
averages over intervals. With ``f(u) = exp(-u^2 / (2 l^2))`` and

    G1(u) = l sqrt(pi/2) erf(u / (sqrt(2) l))                       (G1' = f)
    G2(u) = l sqrt(pi/2) u erf(u / (sqrt(2) l)) + l^2 (f(u) - 1)    (G2'' = f, G2(0) = G2'(0) = 0)

the interval-interval integral of f(s - t) over s in [a, b], t in [c, d] is
``G2(b - c) - G2(a - c) - G2(b - d) + G2(a - d)``, and the point-interval integral of f(x - t)
over t in [c, d] is ``G1(d - x) - G1(c - x)``. Dividing by the interval lengths gives averages.
Zero-width intervals (points) take the point formula, so points and boxes mix freely.

Derivatives with respect to l are closed form too: dG2/dl = sqrt(pi/2) u erf(.) + 2 l (f - 1), and
dG1/dl = sqrt(pi/2) erf(.) - u f / l.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import erf

SQRT_HALF_PI = np.sqrt(np.pi / 2.0)

#: An interval narrower than this fraction of the length scale is treated as a point: the error
#: of that is about (w / l)^2 / 24 (< 1e-7), while the interval formula would lose digits to
#: cancellation.
POINT_WIDTH = 1e-3


def _g2(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    return l * SQRT_HALF_PI * u * erf(u / (np.sqrt(2.0) * l)) + l * l * np.expm1(-0.5 * (u / l) ** 2)


def _dg2_dl(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    return SQRT_HALF_PI * u * erf(u / (np.sqrt(2.0) * l)) + 2.0 * l * np.expm1(-0.5 * (u / l) ** 2)


def _g1(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    return l * SQRT_HALF_PI * erf(u / (np.sqrt(2.0) * l))


def _dg1_dl(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    return SQRT_HALF_PI * erf(u / (np.sqrt(2.0) * l)) - u * np.exp(-0.5 * (u / l) ** 2) / l


def interval_average(
    a_lo: NDArray[np.float64],
    a_hi: NDArray[np.float64],
    b_lo: NDArray[np.float64],
    b_hi: NDArray[np.float64],
    l: float,
    eval_gradient: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Average of exp(-(s - t)^2 / (2 l^2)) over s in [a_lo, a_hi] and t in [b_lo, b_hi].

    Parameters
    ----------
    a_lo, a_hi : ndarray of shape (n,)
        First set of intervals (equal ends for a point).
    b_lo, b_hi : ndarray of shape (m,)
        Second set of intervals.
    l : float
        Length scale.
    eval_gradient : bool
        Also return the derivative with respect to log l.

    Returns
    -------
    F : ndarray of shape (n, m)
    dF : ndarray of shape (n, m) or None
        dF / dlog(l).
    """
    wa = a_hi - a_lo
    wb = b_hi - b_lo
    pa = wa < POINT_WIDTH * l
    pb = wb < POINT_WIDTH * l
    F = np.empty((a_lo.size, b_lo.size))
    dF = np.empty_like(F) if eval_gradient else None
    for amask, apt in ((pa, True), (~pa, False)):
        ia = np.flatnonzero(amask)
        if ia.size == 0:
            continue
        for bmask, bpt in ((pb, True), (~pb, False)):
            ib = np.flatnonzero(bmask)
            if ib.size == 0:
                continue
            f, df = _block(a_lo[ia], a_hi[ia], apt, b_lo[ib], b_hi[ib], bpt, l, eval_gradient)
            F[np.ix_(ia, ib)] = f
            if dF is not None:
                dF[np.ix_(ia, ib)] = df
    return F, dF


def _block(a_lo, a_hi, a_point, b_lo, b_hi, b_point, l, eval_gradient):
    """One block of `interval_average` where each side is all points or all intervals."""
    if a_point and b_point:
        u = 0.5 * (a_lo + a_hi)[:, None] - 0.5 * (b_lo + b_hi)[None, :]
        f = np.exp(-0.5 * (u / l) ** 2)
        return f, (f * (u / l) ** 2 if eval_gradient else None)
    if a_point or b_point:
        # Point x against interval [c, d]; the average is symmetric in which side is the point.
        if a_point:
            x = 0.5 * (a_lo + a_hi)[:, None]
            c, d = b_lo[None, :], b_hi[None, :]
        else:
            x = 0.5 * (b_lo + b_hi)[None, :]
            c, d = a_lo[:, None], a_hi[:, None]
        w = d - c
        f = (_g1(d - x, l) - _g1(c - x, l)) / w
        df = l * (_dg1_dl(d - x, l) - _dg1_dl(c - x, l)) / w if eval_gradient else None
        return f, df
    a, b = a_lo[:, None], a_hi[:, None]
    c, d = b_lo[None, :], b_hi[None, :]
    area = (b - a) * (d - c)
    # The four corner terms take their erf and exp once each, for the value and the derivative.
    g2 = []
    dg2 = []
    for u in (b - c, a - c, b - d, a - d):
        e = erf(u / (np.sqrt(2.0) * l))
        m = np.expm1(-0.5 * (u / l) ** 2)
        g2.append(l * SQRT_HALF_PI * u * e + l * l * m)
        if eval_gradient:
            dg2.append(SQRT_HALF_PI * u * e + 2.0 * l * m)
    f = (g2[0] - g2[1] - g2[2] + g2[3]) / area
    df = l * (dg2[0] - dg2[1] - dg2[2] + dg2[3]) / area if eval_gradient else None
    return f, df


def se_box_average(
    a_lower: NDArray[np.float64],
    a_upper: NDArray[np.float64],
    b_lower: NDArray[np.float64],
    b_upper: NDArray[np.float64],
    variance: float,
    length_scale: float,
    eval_gradient: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Squared-exponential kernel averaged over pairs of boxes (points are zero-width boxes).

    Parameters
    ----------
    a_lower, a_upper : ndarray of shape (n, d)
    b_lower, b_upper : ndarray of shape (m, d)
    variance, length_scale : float
    eval_gradient : bool
        Also return the gradient with respect to (log variance, log length scale).

    Returns
    -------
    K : ndarray of shape (n, m)
    dK : ndarray of shape (n, m, 2) or None
    """
    d = a_lower.shape[1]
    factors = []
    dfactors: list[NDArray[np.float64]] = []
    for k in range(d):
        # Cells from the tree share their sides and grid points share their coordinates, so
        # each dimension has far fewer distinct intervals than inputs: evaluate the erf terms
        # once per distinct pair and gather.
        ua, ia = np.unique(np.column_stack([a_lower[:, k], a_upper[:, k]]), axis=0, return_inverse=True)
        ub, ib = np.unique(np.column_stack([b_lower[:, k], b_upper[:, k]]), axis=0, return_inverse=True)
        f, df = interval_average(ua[:, 0], ua[:, 1], ub[:, 0], ub[:, 1], length_scale, eval_gradient)
        ia, ib = ia.reshape(-1), ib.reshape(-1)
        factors.append(f[np.ix_(ia, ib)])
        if df is not None:
            dfactors.append(df[np.ix_(ia, ib)])
    K = variance * np.prod(factors, axis=0) if d > 1 else variance * factors[0]
    if not eval_gradient:
        return K, None
    # Product rule over dimensions, without dividing by factors that may underflow to zero.
    dl = np.zeros_like(K)
    for k in range(d):
        term = dfactors[k].copy()
        for j in range(d):
            if j != k:
                term *= factors[j]
        dl += term
    return K, np.stack([K, variance * dl], axis=-1)


def se_box_gram(
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    variance: float,
    length_scale: float,
    eval_gradient: bool = False,
    max_block: int = 4_000_000,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The SE kernel averaged over every pair of boxes of one set: the Gram matrix, exactly symmetric.

    The same numbers as :func:`se_box_average` of the set against itself, symmetrised (to
    round-off): each dimension's table over its distinct intervals is symmetrised before it is
    gathered, so the n x n results need no transposed pass, and the variance is folded into the
    first table. Only the derivative with respect to log length scale is returned; the one with
    respect to log variance is `K` itself.

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
    variance, length_scale : float
    eval_gradient : bool
        Also return dK / dlog(length_scale).
    max_block : int
        Most entries gathered at once per array (rows are taken in blocks); bounds memory.

    Returns
    -------
    K : ndarray of shape (n, n)
    dK_dlog_length_scale : ndarray of shape (n, n) or None
    """
    n, d = lower.shape
    tables: list[NDArray[np.float64]] = []
    dtables: list[NDArray[np.float64]] = []
    index: list[NDArray[np.intp]] = []
    for k in range(d):
        # Far fewer distinct intervals than inputs per dimension (see se_box_average).
        u, inv = np.unique(np.column_stack([lower[:, k], upper[:, k]]), axis=0, return_inverse=True)
        f, df = interval_average(u[:, 0], u[:, 1], u[:, 0], u[:, 1], length_scale, eval_gradient)
        scale = variance if k == 0 else 1.0
        tables.append(scale * 0.5 * (f + f.T))
        if df is not None:
            dtables.append(scale * 0.5 * (df + df.T))
        index.append(inv.reshape(-1))
    K = np.empty((n, n))
    dK = np.empty((n, n)) if eval_gradient else None
    rows = max(1, max_block // max(n, 1))
    for s in range(0, n, rows):
        e = min(n, s + rows)
        # Two-step gathers (rows of the small table, then columns): much faster than np.ix_.
        factors = [t[i[s:e]][:, i] for t, i in zip(tables, index, strict=True)]
        if dK is not None:
            # Product rule over dimensions, without dividing by factors that may underflow to zero.
            dl = dK[s:e]
            for k in range(d):
                term = dtables[k][index[k][s:e]][:, index[k]]
                for j in range(d):
                    if j != k:
                        term *= factors[j]
                if k == 0:
                    dl[...] = term
                else:
                    dl += term
        block = K[s:e]
        block[...] = factors[0]
        for f in factors[1:]:
            block *= f
    return K, dK


def se_box_self_average(
    lower: NDArray[np.float64], upper: NDArray[np.float64], variance: float, length_scale: float
) -> NDArray[np.float64]:
    """The SE kernel averaged over each box against itself, ndarray of shape (n,).

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
    """
    l = length_scale
    w = upper - lower
    # For an interval against itself the four G2 terms reduce to 2 G2(w) / w^2.
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(w < POINT_WIDTH * l, 1.0, 2.0 * _g2(w, l) / np.where(w > 0, w, 1.0) ** 2)
    return variance * np.prod(f, axis=1)
