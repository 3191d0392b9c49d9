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
    f = (_g2(b - c, l) - _g2(a - c, l) - _g2(b - d, l) + _g2(a - d, l)) / area
    df = None
    if eval_gradient:
        df = l * (_dg2_dl(b - c, l) - _dg2_dl(a - c, l) - _dg2_dl(b - d, l) + _dg2_dl(a - d, l)) / area
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
