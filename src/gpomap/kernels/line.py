"""Integral ("line") kernels over beams as line segments, and points (GPOMIK).

O'Callaghan & Ramos (AAAI 2011) treat a laser beam as a line segment of free space and integrate
a point kernel ``k`` along it (the paper's eqs. 5-6). With a segment parameterised by arc length,
``x(u) = s + u d`` for ``u`` in ``[0, L]`` and ``|d| = 1``:

    K(A, B) = (1 / (L_A L_B)) int_0^{L_A} int_0^{L_B} k(x_A(u), x_B(v)) dv du     ("mean")
    K(A, B) = int int k(x_A(u), x_B(v)) dv du = L_A L_B times the above           ("sum")

A point is a segment of zero length; with "mean" it is the limit L -> 0 (the point kernel itself),
with "sum" its weight is 1 (not 0), which is eqs. 5-6 exactly: points are not integrated.

Squared exponential
    *Segment-point* is closed form. Project the point p onto the segment's line: ``t = (p - s).d``
    along it, ``h^2 = |p - s|^2 - t^2`` across. Then ``|x(u) - p|^2 = (u - t)^2 + h^2`` and

        int_0^L exp(-|x(u) - p|^2 / (2 l^2)) du
            = exp(-h^2 / (2 l^2)) l sqrt(pi/2) [erf((L - t) / (sqrt 2 l)) - erf(-t / (sqrt 2 l))].

    *Parallel segments* (including a segment against itself and collinear ones) are closed form
    as well: the perpendicular offset gives a Gaussian factor and the 1-D interval-interval
    double integral is the G2 formula of :mod:`gpomap.kernels.closed_form`.
    *Skew segments* have no closed form in elementary functions: the double integral is a
    bivariate normal probability over a parallelogram (Owen's T function territory). We take a
    fixed Gauss-Legendre rule along the *shorter* segment and the closed-form segment-point
    integral along the longer one. Choosing the side by a rule symmetric in (A, B) (shorter
    length, ties broken by coordinates) keeps K exactly symmetric; the hybrid is not exactly a
    Gram matrix of one feature map, so K is PSD only up to the quadrature error.

Matern 3/2 (or any point kernel)
    Gauss-Legendre along both segments: each segment becomes weighted nodes and K is the weighted
    sum of the point kernel over node pairs, so K is exactly PSD (a Gram matrix of the nodes).
    The integrand has a kink where segments cross (all beams of one scan meet at the sensor),
    so the rule converges more slowly there than for smooth integrands.

Rules are composite: a segment is cut into ``ceil(L / max_panel)`` panels of `order` nodes each
(one panel with ``max_panel=None``). Panels are fixed in metres, not in length scales, so the
nodes never move with the hyperparameters and the analytic gradient is the exact gradient of
the approximation. Gradients with respect to ``theta = [log variance, log length_scale]`` are
analytic everywhere: the GL parts differentiate the point kernel or the closed form at the nodes.
The inputs and their nodes (:class:`Segments`, :func:`segment_nodes`) are
:mod:`gpomap.kernels.segments`'; this module holds the closed forms and :class:`LineKernel`.
"""

from __future__ import annotations

import copy
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray
from scipy.special import erf

from gpomap.config import MapConfig
from gpomap.kernels.nodes import NodeSet, weighted_gram, weighted_self
from gpomap.kernels.point import PointKernel, SquaredExponential, make_point_kernel
from gpomap.kernels.segments import Segments, as_segments, concatenate_segments, segment_nodes

# The inputs (gpomap.kernels.segments) are named from here too, where they were first.
__all__ = [
    "NORMALISATIONS",
    "PARALLEL_SIN",
    "POINT_LENGTH",
    "LineKernel",
    "Segments",
    "as_segments",
    "concatenate_segments",
    "se_parallel_pairs",
    "se_point_segment",
    "segment_nodes",
]

NORMALISATIONS = ("mean", "sum")

_SQRT_HALF_PI = np.sqrt(np.pi / 2.0)
_SQRT2 = np.sqrt(2.0)

#: A segment shorter than this fraction of the length scale is evaluated as its midpoint in the
#: closed forms: the error is about (L / l)^2 / 24 (< 1e-7), while the erf difference divided by
#: L would lose digits to cancellation.
POINT_LENGTH = 1e-3

#: Two segments count as parallel (closed form) when the sine of the angle between them is below this.
PARALLEL_SIN = 1e-10


# ---------------------------------------------------------------- SE closed forms


def _g1(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    """Antiderivative of exp(-u^2 / (2 l^2)): l sqrt(pi/2) erf(u / (sqrt 2 l))."""
    return l * _SQRT_HALF_PI * erf(u / (_SQRT2 * l))


def _dg1_dlogl(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    """l * d(_g1)/dl."""
    return _g1(u, l) - u * np.exp(-0.5 * (u / l) ** 2)


def _g2(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    """Second antiderivative of exp(-u^2 / (2 l^2)) with G2(0) = G2'(0) = 0."""
    return l * _SQRT_HALF_PI * u * erf(u / (_SQRT2 * l)) + l * l * np.expm1(-0.5 * (u / l) ** 2)


def _dg2_dlogl(u: NDArray[np.float64], l: float) -> NDArray[np.float64]:
    """l * d(_g2)/dl."""
    return l * _SQRT_HALF_PI * u * erf(u / (_SQRT2 * l)) + 2.0 * l * l * np.expm1(-0.5 * (u / l) ** 2)


def se_point_segment(
    points: NDArray[np.float64],
    starts: NDArray[np.float64],
    ends: NDArray[np.float64],
    length_scale: float,
    eval_gradient: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Unit-variance SE kernel averaged along segments, against points, pair by pair (closed form).

    Parameters
    ----------
    points : ndarray of shape (k, 2)
    starts, ends : ndarray of shape (k, 2)
        Segment i is ``starts[i] -> ends[i]``, paired with ``points[i]``; a segment shorter than
        ``POINT_LENGTH * l`` (a point included) acts as its midpoint. Any shapes that broadcast
        to (..., 2) work; outer products come from ``points[:, None]`` against ``starts[None]``.
    length_scale : float
    eval_gradient : bool
        Also return the derivative with respect to log length scale.

    Returns
    -------
    F : ndarray of shape (k,)
        ``(1 / L) int_0^L exp(-|x(u) - p|^2 / (2 l^2)) du``.
    dF : ndarray of shape (k,) or None
        dF / dlog(l).
    """
    l = float(length_scale)
    vec = ends - starts
    L = np.hypot(vec[..., 0], vec[..., 1])
    short = POINT_LENGTH * l > L
    Ls = np.where(short, 1.0, L)
    dx, dy = vec[..., 0] / Ls, vec[..., 1] / Ls
    # Short segments: measure from the midpoint, with zero length, so the formula below becomes
    # the point kernel without a 0 / 0.
    origin = np.where(short[..., None], 0.5 * (starts + ends), starts)
    rx = points[..., 0] - origin[..., 0]
    ry = points[..., 1] - origin[..., 1]
    t = rx * dx + ry * dy  # along the segment
    h2 = np.where(short, rx * rx + ry * ry, (rx * dy - ry * dx) ** 2)  # across it, squared
    q = h2 / (l * l)
    gauss = np.exp(-0.5 * q)
    hi, lo = L - t, -t
    with np.errstate(invalid="ignore", divide="ignore"):
        inner = np.where(short, 1.0, (_g1(hi, l) - _g1(lo, l)) / Ls)
    F = gauss * inner
    if not eval_gradient:
        return F, None
    dinner = np.where(short, 0.0, (_dg1_dlogl(hi, l) - _dg1_dlogl(lo, l)) / Ls)
    return F, gauss * (q * inner + dinner)


def _interval_pairs(
    a0: NDArray[np.float64],
    a1: NDArray[np.float64],
    b0: NDArray[np.float64],
    b1: NDArray[np.float64],
    l: float,
    eval_gradient: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Elementwise mean of exp(-(s - t)^2 / (2 l^2)) over s in [a0, a1], t in [b0, b1].

    All arrays of one shape, ``a1 >= a0`` and ``b1 >= b0``; returns (F, dF / dlog l or None).
    """
    wa, wb = a1 - a0, b1 - b0
    pa, pb = wa < POINT_LENGTH * l, wb < POINT_LENGTH * l
    F = np.empty(a0.shape)
    dF = np.empty(a0.shape) if eval_gradient else None
    both = ~pa & ~pb
    if both.any():
        a, b, c, d = a0[both], a1[both], b0[both], b1[both]
        area = (b - a) * (d - c)
        F[both] = (_g2(b - c, l) - _g2(a - c, l) - _g2(b - d, l) + _g2(a - d, l)) / area
        if dF is not None:
            dF[both] = (_dg2_dlogl(b - c, l) - _dg2_dlogl(a - c, l) - _dg2_dlogl(b - d, l) + _dg2_dlogl(a - d, l)) / area
    one = pa ^ pb
    if one.any():
        # A point x against an interval [c, d]; which side is the point does not matter.
        apt = pa[one]
        x = np.where(apt, 0.5 * (a0[one] + a1[one]), 0.5 * (b0[one] + b1[one]))
        c = np.where(apt, b0[one], a0[one])
        d = np.where(apt, b1[one], a1[one])
        F[one] = (_g1(d - x, l) - _g1(c - x, l)) / (d - c)
        if dF is not None:
            dF[one] = (_dg1_dlogl(d - x, l) - _dg1_dlogl(c - x, l)) / (d - c)
    none = pa & pb
    if none.any():
        q = ((0.5 * (a0[none] + a1[none] - b0[none] - b1[none])) / l) ** 2
        F[none] = np.exp(-0.5 * q)
        if dF is not None:
            dF[none] = F[none] * q
    return F, dF


def se_parallel_pairs(
    sa: NDArray[np.float64],
    ea: NDArray[np.float64],
    sb: NDArray[np.float64],
    eb: NDArray[np.float64],
    length_scale: float,
    eval_gradient: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Unit-variance SE kernel averaged over pairs of parallel segments (closed form).

    Parameters
    ----------
    sa, ea, sb, eb : ndarray of shape (k, 2)
        Pair i is segment ``sa[i] -> ea[i]`` against ``sb[i] -> eb[i]``; the first of each pair
        must have positive length and the second must be parallel to it (either direction).
    length_scale : float
    eval_gradient : bool

    Returns
    -------
    F : ndarray of shape (k,)
    dF : ndarray of shape (k,) or None
        dF / dlog(l).
    """
    l = float(length_scale)
    va = ea - sa
    La = np.hypot(va[:, 0], va[:, 1])
    d = va / La[:, None]
    # Coordinates along and across the first segment's line, origin at its start.
    rs, re = sb - sa, eb - sa
    ts = rs[:, 0] * d[:, 0] + rs[:, 1] * d[:, 1]
    te = re[:, 0] * d[:, 0] + re[:, 1] * d[:, 1]
    # Offset across: use the midpoint of B (both ends agree for exactly parallel segments).
    rm = 0.5 * (rs + re)
    h = rm[:, 0] * d[:, 1] - rm[:, 1] * d[:, 0]
    q = (h / l) ** 2
    gauss = np.exp(-0.5 * q)
    inner, dinner = _interval_pairs(np.zeros_like(La), La, np.minimum(ts, te), np.maximum(ts, te), l, eval_gradient)
    F = gauss * inner
    return F, (gauss * (q * inner + dinner) if dinner is not None else None)  # dinner: with eval_gradient


def _lex_less_equal(A: Segments, B: Segments, ia: NDArray[np.intp], ib: NDArray[np.intp]) -> NDArray[np.bool_]:
    """For pairs (A[ia], B[ib]): A's segment is shorter, or equally long and not greater in
    its coordinates. A rule symmetric in the pair, so K(A, B) = K(B, A)^T exactly."""
    ka = np.column_stack([A.lengths[ia], A.starts[ia], A.ends[ia]])
    kb = np.column_stack([B.lengths[ib], B.starts[ib], B.ends[ib]])
    result = np.ones(ia.size, dtype=bool)
    undecided = np.ones(ia.size, dtype=bool)
    for c in range(ka.shape[1]):
        lt, gt = ka[:, c] < kb[:, c], ka[:, c] > kb[:, c]
        result[undecided & gt] = False
        undecided &= ~(lt | gt)
    return result


class LineKernel:
    """A point kernel integrated along line segments (GPOMIK's integral kernel).

    Follows the protocol of :class:`gpomap.kernels.area.AreaKernel`, so
    :class:`gpomap.gp.SupportGP` uses it unchanged with :class:`Segments` inputs.

    Parameters
    ----------
    base : PointKernel or str
        The point kernel ("se", "matern32" or an instance).
    normalisation : {"mean", "sum"}
        Average along the segments, or integrate (the average times both lengths; a point
        weighs 1). See the module docstring.
    order : int
        Gauss-Legendre nodes per panel.
    max_panel : float, optional
        Longest quadrature panel, in the units of the inputs (see :func:`segment_nodes`);
        None: one panel per segment.
    max_block : int
        Most kernel entries (node-by-input pairs) evaluated at once; bounds memory.
    """

    def __init__(
        self,
        base: PointKernel | str = "se",
        normalisation: str = MapConfig.normalisation,
        order: int = 4,
        max_panel: float | None = 1.0,
        max_block: int = 2_000_000,
    ) -> None:
        self.base = make_point_kernel(base)
        if normalisation not in NORMALISATIONS:
            raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}")
        if int(order) < 1:
            raise ValueError(f"quadrature order must be at least 1, got {order}")
        self.normalisation = normalisation
        self.order = int(order)
        self.max_panel = None if max_panel is None else float(max_panel)
        self.max_block = int(max_block)

    def __repr__(self) -> str:
        return f"LineKernel({self.base!r}, normalisation={self.normalisation!r}, order={self.order}, max_panel={self.max_panel})"

    @property
    def closed_form(self) -> bool:
        """Whether segment-point terms are closed form (squared exponential base)."""
        return isinstance(self.base, SquaredExponential)

    @property
    def theta(self) -> NDArray[np.float64]:
        """Log hyperparameters of the base kernel, ndarray of shape (2,)."""
        return self.base.theta

    @theta.setter
    def theta(self, value: NDArray[np.float64]) -> None:
        self.base.theta = value

    @property
    def bounds(self) -> NDArray[np.float64]:
        """Log bounds, ndarray of shape (2, 2)."""
        return self.base.bounds

    def clone_with_theta(self, theta: NDArray[np.float64]) -> LineKernel:
        """A copy with hyperparameters `theta`."""
        k = copy.copy(self)
        k.base = self.base.clone_with_theta(theta)
        return k

    def nodes(self, X: Segments) -> NodeSet:
        """The quadrature nodes of `X` under this kernel's rule."""
        return segment_nodes(X, self.order, self.max_panel)

    def _weights(self, X: Segments) -> NDArray[np.float64]:
        # "sum": the integral is the mean times the length; a point is not integrated (weight 1).
        L = X.lengths
        return np.where(X.is_point, 1.0, L)

    @overload
    def __call__(self, A: Segments, B: Segments | None = None, eval_gradient: Literal[False] = False) -> NDArray[np.float64]: ...

    @overload
    def __call__(
        self, A: Segments, B: Segments | None = None, *, eval_gradient: Literal[True]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def __call__(
        self, A: Segments, B: Segments | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def __call__(
        self, A: Segments, B: Segments | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Covariances between two sets of segments (or points).

        Parameters
        ----------
        A : Segments
            n inputs (an (n, 2) array or point Supports are taken as points).
        B : Segments, optional
            m inputs; defaults to `A`.
        eval_gradient : bool
            Also return dK/dtheta.

        Returns
        -------
        K : ndarray of shape (n, m)
        dK : ndarray of shape (n, m, 2), only with `eval_gradient`
        """
        same = B is None
        A = as_segments(A)
        B = A if same else as_segments(B)
        if self.closed_form:
            K, dK = self._se(A, B, eval_gradient, same)
        else:
            na = self.nodes(A)
            nb = na if same else self.nodes(B)
            K, dK = weighted_gram(self.base, na, nb, eval_gradient, self.max_block)
            if same:
                # Symmetric by construction; remove the rounding asymmetry.
                K = 0.5 * (K + K.T)
                if dK is not None:
                    dK = 0.5 * (dK + dK.transpose(1, 0, 2))
        if self.normalisation == "sum":
            scale = np.outer(self._weights(A), self._weights(B))
            K = K * scale
            if dK is not None:
                dK = dK * scale[:, :, None]
        if not eval_gradient:
            return K
        assert dK is not None  # returned with eval_gradient
        return K, dK

    def _se(
        self, A: Segments, B: Segments, eval_gradient: bool, same: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """SE: closed form for point and parallel pairs, GL along the shorter segment otherwise."""
        var, l = self.base.variance, self.base.length_scale
        n, m = len(A), len(B)
        F = np.zeros((n, m))
        dF = np.zeros((n, m)) if eval_gradient else None
        na = self.nodes(A)
        nb = na if same else self.nodes(B)
        size_a, size_b = np.diff(na.offsets), np.diff(nb.offsets)
        # Rows per chunk so that the node-by-segment entries of a chunk stay near max_block.
        per_pair = float(min(size_a.mean(), size_b.mean())) + 1.0
        rows = max(1, int(self.max_block // max(1.0, m * per_pair)))
        for start in range(0, n, rows):
            stop = min(n, start + rows)
            grid_a, grid_b = np.meshgrid(np.arange(start, stop), np.arange(m), indexing="ij")
            ia, jb = grid_a.ravel(), grid_b.ravel()
            if same:
                # Upper triangle only; the lower one is its mirror.
                keep = jb >= ia
                ia, jb = ia[keep], jb[keep]
            along_a = _lex_less_equal(A, B, ia, jb)
            f = np.empty(ia.size)
            df = np.empty(ia.size) if eval_gradient else None
            for mask, nodes, sizes, node_of, seg_of, segs in (
                (along_a, na, size_a, ia, jb, B),
                (~along_a, nb, size_b, jb, ia, A),
            ):
                sel = np.flatnonzero(mask)
                if sel.size == 0:
                    continue
                # Every (node of the shorter input, longer segment) entry of the selected pairs.
                cnt = sizes[node_of[sel]]
                pair = np.repeat(np.arange(sel.size), cnt)
                first = np.repeat(nodes.offsets[node_of[sel]] - (np.cumsum(cnt) - cnt), cnt)
                node = first + np.arange(pair.size)
                seg = seg_of[sel][pair]
                g, dg = se_point_segment(nodes.nodes[node], segs.starts[seg], segs.ends[seg], l, eval_gradient)
                w = nodes.weights[node]
                f[sel] = np.bincount(pair, weights=g * w, minlength=sel.size)
                if df is not None:
                    assert dg is not None  # returned when eval_gradient is set
                    df[sel] = np.bincount(pair, weights=dg * w, minlength=sel.size)
            F[ia, jb] = f
            if dF is not None:
                dF[ia, jb] = df
            # Parallel pairs of proper segments: exact closed form (the diagonal among them).
            ra, cb = self._parallel_pairs(A.subset(slice(start, stop)), B, l)
            ra = ra + start
            if same:
                keep = cb >= ra
                ra, cb = ra[keep], cb[keep]
            if ra.size:
                g, dg = se_parallel_pairs(A.starts[ra], A.ends[ra], B.starts[cb], B.ends[cb], l, eval_gradient)
                F[ra, cb] = g
                if dF is not None:
                    dF[ra, cb] = dg
        if same:
            iu = np.triu_indices(n, 1)
            F[iu[1], iu[0]] = F[iu]
            if dF is not None:
                dF[iu[1], iu[0]] = dF[iu]
        K = var * F
        if dF is None:
            return K, None
        return K, np.stack([K, var * dF], axis=-1)

    def _parallel_pairs(self, A: Segments, B: Segments, l: float) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Index pairs (i, j) where A[i] and B[j] are both proper segments and parallel."""
        short = POINT_LENGTH * l
        ia = np.flatnonzero(A.lengths >= short)
        jb = np.flatnonzero(B.lengths >= short)
        if ia.size == 0 or jb.size == 0:
            return np.zeros(0, np.intp), np.zeros(0, np.intp)
        da = (A.ends - A.starts)[ia] / A.lengths[ia, None]
        db = (B.ends - B.starts)[jb] / B.lengths[jb, None]
        sin = np.abs(da[:, None, 0] * db[None, :, 1] - da[:, None, 1] * db[None, :, 0])
        r, c = np.nonzero(sin < PARALLEL_SIN)
        return ia[r], jb[c]

    def diag(self, A: Segments) -> NDArray[np.float64]:
        """k(a, a) for each input, ndarray of shape (n,)."""
        A = as_segments(A)
        if self.closed_form:
            l = self.base.length_scale
            L = A.lengths
            # A segment against itself: the interval formula 2 G2(L) / L^2 (1 for a point).
            with np.errstate(divide="ignore", invalid="ignore"):
                f = np.where(POINT_LENGTH * l > L, 1.0, 2.0 * _g2(L, l) / np.where(L > 0, L, 1.0) ** 2)
            d = self.base.variance * f
        else:
            d = weighted_self(self.base, self.nodes(A), self.max_block)
        if self.normalisation == "sum":
            d = d * self._weights(A) ** 2
        return d
