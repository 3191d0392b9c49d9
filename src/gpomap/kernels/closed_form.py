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

from gpomap.kernels import _compiled_box

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


def _block(
    a_lo: NDArray[np.float64],
    a_hi: NDArray[np.float64],
    a_point: bool,
    b_lo: NDArray[np.float64],
    b_hi: NDArray[np.float64],
    b_point: bool,
    l: float,
    eval_gradient: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
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


def interval_gram(
    lo: NDArray[np.float64], hi: NDArray[np.float64], l: float, eval_gradient: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """:func:`interval_average` of one set of intervals against itself, symmetrised.

    The same numbers as ``interval_average(lo, hi, lo, hi, ...)`` and its mean with its
    transpose, for less work: the point-interval block is computed once for both sides, and
    the interval-interval block takes its four corner terms from one table of G2 over the
    differences of the intervals' distinct ends (the very differences the corners take, so the
    very values), a quarter of the erf evaluations.

    Parameters
    ----------
    lo, hi : ndarray of shape (u,)
    l : float
        Length scale.
    eval_gradient : bool
        Also return the derivative with respect to log l.

    Returns
    -------
    F : ndarray of shape (u, u)
    dF : ndarray of shape (u, u) or None
    """
    u = lo.size
    is_point = hi - lo < POINT_WIDTH * l
    ip, ii = np.flatnonzero(is_point), np.flatnonzero(~is_point)
    F = np.empty((u, u))
    dF = np.empty_like(F) if eval_gradient else None
    blocks = []
    if ip.size:
        blocks.append((ip, ip, _block(lo[ip], hi[ip], True, lo[ip], hi[ip], True, l, eval_gradient)))
    if ii.size:
        blocks.append((ii, ii, _interval_self_block(lo[ii], hi[ii], l, eval_gradient)))
    if ip.size and ii.size:
        f, df = _block(lo[ip], hi[ip], True, lo[ii], hi[ii], False, l, eval_gradient)
        # The point-interval formula is the same whichever side is the point.
        blocks.append((ip, ii, (f, df)))
        blocks.append((ii, ip, (f.T, None if df is None else df.T)))
    for rows, cols, (f, df) in blocks:
        F[np.ix_(rows, cols)] = f
        if dF is not None:
            dF[np.ix_(rows, cols)] = df
    return 0.5 * (F + F.T), (None if dF is None else 0.5 * (dF + dF.T))


def _interval_self_block(
    a: NDArray[np.float64], b: NDArray[np.float64], l: float, eval_gradient: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The interval-interval block of `_block` for intervals [a, b] against themselves, from a table over their ends."""
    ends, where = np.unique(np.concatenate([a, b]), return_inverse=True)
    ia, ib = where[: a.size], where[a.size :]
    diff = ends[:, None] - ends[None, :]  # the corners' differences, each once
    e = erf(diff / (np.sqrt(2.0) * l))
    m = np.expm1(-0.5 * (diff / l) ** 2)
    # Corners b - c, a - c, b - d, a - d with [c, d] = [a_j, b_j], as _block takes them.
    corners = ((ib, ia), (ia, ia), (ib, ib), (ia, ib))
    area = (b - a)[:, None] * (b - a)[None, :]
    g2 = l * SQRT_HALF_PI * diff * e + l * l * m
    t = [g2[r][:, c] for r, c in corners]
    f = (t[0] - t[1] - t[2] + t[3]) / area
    df = None
    if eval_gradient:
        dg2 = SQRT_HALF_PI * diff * e + 2.0 * l * m
        t = [dg2[r][:, c] for r, c in corners]
        df = l * (t[0] - t[1] - t[2] + t[3]) / area
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
        a_lo, a_hi, ia = distinct_intervals(a_lower[:, k], a_upper[:, k])
        b_lo, b_hi, ib = distinct_intervals(b_lower[:, k], b_upper[:, k])
        f, df = interval_average(a_lo, a_hi, b_lo, b_hi, length_scale, eval_gradient)
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


def distinct_intervals(
    lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """The distinct intervals [lo_i, hi_i], sorted by (lo, hi), and which one each input is.

    What ``np.unique`` of the stacked ends with ``axis=0`` gives, by one lexsort (much faster on a
    few hundred cells: ``unique`` with an axis sorts a structured view).

    Parameters
    ----------
    lo, hi : ndarray of shape (n,)

    Returns
    -------
    lo, hi : ndarray of shape (u,)
        The distinct intervals.
    inverse : ndarray of int, shape (n,)
        Input i is interval ``inverse[i]``.
    """
    order = np.lexsort((hi, lo))
    a, b = lo[order], hi[order]
    first = np.empty(a.size, dtype=bool)
    first[:1] = True
    first[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    inverse = np.empty(a.size, dtype=np.intp)
    inverse[order] = np.cumsum(first) - 1
    return a[first], b[first], inverse


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
    if _compiled_box.ENABLED and lower.size:
        # One compiled pass (the numpy path below stays the reference).
        K, dK = _compiled_box.box_gram(
            np.ascontiguousarray(lower, dtype=float),
            np.ascontiguousarray(upper, dtype=float),
            float(variance),
            float(length_scale),
            eval_gradient,
            POINT_WIDTH,
        )
        return K, (dK if eval_gradient else None)
    n, d = lower.shape
    tables: list[NDArray[np.float64]] = []
    dtables: list[NDArray[np.float64]] = []
    index: list[NDArray[np.intp]] = []
    for k in range(d):
        # Far fewer distinct intervals than inputs per dimension (see se_box_average).
        lo, hi, inverse = distinct_intervals(lower[:, k], upper[:, k])
        f, df = interval_gram(lo, hi, length_scale, eval_gradient)
        scale = variance if k == 0 else 1.0
        tables.append(scale * f)
        if df is not None:
            dtables.append(scale * df)
        index.append(inverse)

    def gather(table: NDArray[np.float64], k: int, rows: slice) -> NDArray[np.float64]:
        # Rows of the small table, then columns: much faster than np.ix_ (the result comes out
        # in Fortran order).
        return table[index[k][rows]][:, index[k]]

    def rows_of(rows: slice) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """K[rows] and dK[rows], products formed in the gathered arrays (no further copies)."""
        factors = [gather(t, k, rows) for k, t in enumerate(tables)]
        dl = None
        if eval_gradient:
            # Product rule over dimensions, without dividing by factors that may underflow to zero.
            for k in range(d):
                term = gather(dtables[k], k, rows)
                for j in range(d):
                    if j != k:
                        term *= factors[j]
                if dl is None:
                    dl = term
                else:
                    dl += term
        K = factors[0]
        for f in factors[1:]:
            K *= f
        return K, dl

    rows = max(1, max_block // max(n, 1))
    if rows >= n:
        K, dl = rows_of(slice(0, n))
        # Exactly symmetric, so the transpose is the same matrix, and C-ordered.
        return K.T, (None if dl is None else dl.T)
    K = np.empty((n, n))
    dK = np.empty((n, n)) if eval_gradient else None
    for s in range(0, n, rows):
        k_rows, dl_rows = rows_of(slice(s, min(n, s + rows)))
        K[s : s + rows] = k_rows
        if dK is not None:
            dK[s : s + rows] = dl_rows
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
    # For an interval against itself the four G2 terms reduce to 2 G2(w) / w^2; a point's is 1
    # (formed only where the sides are wide: a prediction's points have none).
    f = np.ones_like(w)
    wide = w >= POINT_WIDTH * l
    if wide.any():
        f[wide] = 2.0 * _g2(w[wide], l) / w[wide] ** 2
    return variance * np.prod(f, axis=1)
