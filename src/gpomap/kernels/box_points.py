"""The exact SE area kernel between boxes and points: each box averaged against each point.

A prediction asks every cell of a tile against every query point; the kernel is a product over
axes of 1-D factors (:func:`side_point_factors`), each the SE kernel averaged over a side,
``(G1(hi - x) - G1(lo - x)) / (hi - lo)`` with G1 as in :mod:`gpomap.kernels.closed_form`.
:class:`BoxPointFactors` tables those factors once per axis and gives any block of the matrix.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpomap.kernels.closed_form import POINT_WIDTH, _g1, distinct_intervals


def se_box_point_average(
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    points: NDArray[np.float64],
    variance: float,
    length_scale: float,
) -> NDArray[np.float64]:
    """The SE kernel averaged over each box against each point: :func:`se_box_average` of boxes and points, faster.

    The same numbers, bit for bit: a box side [c, d] against a coordinate x takes
    ``(G1(d - x) - G1(c - x)) / (d - c)`` as :func:`se_box_average` does, but per axis G1 is
    tabled once over the distinct ends of the boxes' sides against the distinct coordinates of
    the points (cells from the tree share their sides, grid points their rows and columns), the
    1-D factors are formed once per distinct side, and each box then takes its row of every
    axis's factor table: erf runs ``ends x coordinates`` times per axis instead of
    ``2 x boxes x points``. Sides narrower than ``POINT_WIDTH`` length scales take the point
    formula, as there.

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
        The boxes.
    points : ndarray of shape (m, d)
    variance, length_scale : float

    Returns
    -------
    K : ndarray of shape (n, m)
    """
    n, d = lower.shape
    m = points.shape[0]
    K: NDArray[np.float64] | None = None
    for k in range(d):
        # (u, m) factors of the distinct sides, then each box's row of them.
        a, b, side = distinct_intervals(lower[:, k], upper[:, k])
        f = side_point_factors(a, b, points[:, k], length_scale)
        if K is None:
            K = np.take(f, side, axis=0)
        else:
            K *= np.take(f, side, axis=0)
    if K is None:
        K = np.ones((n, m))
    # variance * (f_0 * f_1 * ...), in se_box_average's order (a unit variance changes nothing).
    if variance != 1.0:
        K *= variance
    return K


def side_point_factors(
    lo: NDArray[np.float64], hi: NDArray[np.float64], x: NDArray[np.float64], l: float, repeated: bool = True
) -> NDArray[np.float64]:
    """The 1-D SE factor of each side [lo_i, hi_i] against each coordinate x_j: its average over the side.

    ``(G1(hi - x) - G1(lo - x)) / (hi - lo)``, from one table of G1 over the sides' distinct ends
    and the distinct coordinates; sides narrower than ``POINT_WIDTH * l`` take the point value
    ``exp(-(c - x)^2 / (2 l^2))`` at their centre c. The same numbers as :func:`interval_average`
    of the sides against zero-width intervals at x.

    Parameters
    ----------
    lo, hi : ndarray of shape (u,)
    x : ndarray of shape (m,)
    l : float
        Length scale.
    repeated : bool
        Whether x may repeat values worth tabling once (False: the caller knows it does not,
        and the sort that finds them is skipped).

    Returns
    -------
    F : ndarray of shape (u, m)
    """
    values, inverse = _distinct_coordinates(x) if repeated else (x, None)
    w = hi - lo
    is_point = w < POINT_WIDTH * l
    if not is_point.any():
        # Intervals only (cells of the tree): no masks, the differences formed in place.
        ends, where = np.unique(np.concatenate([lo, hi]), return_inverse=True)
        where = where.reshape(-1)
        g1 = _g1(ends[:, None] - values[None, :], l)
        F = np.take(g1, where[lo.size :], axis=0)
        F -= np.take(g1, where[: lo.size], axis=0)
        F /= w[:, None]
        return F if inverse is None else F[:, inverse]
    F = np.empty((lo.size, values.size))
    ii = np.flatnonzero(~is_point)
    if ii.size:
        ends, where = np.unique(np.concatenate([lo[ii], hi[ii]]), return_inverse=True)
        where = where.reshape(-1)
        # G1 of every (end - x): the very differences, so the very values, _block takes.
        g1 = _g1(ends[:, None] - values[None, :], l)
        F[ii] = (g1[where[ii.size :]] - g1[where[: ii.size]]) / w[ii, None]
    ip = np.flatnonzero(is_point)
    if ip.size:
        u = 0.5 * (lo[ip] + hi[ip])[:, None] - values[None, :]
        F[ip] = np.exp(-0.5 * (u / l) ** 2)
    return F if inverse is None else F[:, inverse]


#: Most entries of one axis's table of factors between a box set's distinct sides and a point
#: set's distinct coordinates that :class:`BoxPointFactors` forms up front (memory bound).
MAX_FACTOR_TABLE: int = 4_000_000


#: One axis of :class:`BoxPointFactors`: distinct sides lo and hi, each box's side, the table of
#: factors against the distinct coordinates and each point's coordinate among them (or None), and
#: whether the points repeat coordinates.
_AxisFactors = tuple[
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.intp],
    tuple[NDArray[np.float64], NDArray[np.intp]] | None,
    bool,
]


class BoxPointFactors:
    """The SE kernel between one set of boxes and one set of points, evaluated block by block.

    What :func:`se_box_point_average` gives for ``lower[rows]``, ``upper[rows]`` and
    ``points[cols]``, the same numbers bit for bit, with the work that does not depend on the
    block done once: each axis's distinct box sides are found once, and on an axis where the
    points repeat their coordinates (grid rows and columns) the factor of every distinct side
    against every distinct coordinate is tabled once, so a block is gathers and products only.
    On other axes (scattered points) a block tables its own sides against its own points.

    Parameters
    ----------
    lower, upper : ndarray of shape (n, d)
        The boxes.
    points : ndarray of shape (m, d)
    variance, length_scale : float
    """

    def __init__(
        self,
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
        points: NDArray[np.float64],
        variance: float,
        length_scale: float,
    ) -> None:
        self.points = points
        self.variance = variance
        self.length_scale = length_scale
        self.n = lower.shape[0]
        #: Per axis: its distinct sides (lo, hi) and each box's side among them.
        self.sides: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]] = [
            distinct_intervals(lower[:, k], upper[:, k]) for k in range(lower.shape[1])
        ]
        self._axes: list[_AxisFactors] | None = None

    @property
    def axes(self) -> list[_AxisFactors]:
        """Per axis: distinct sides (lo, hi), each box's side, either (table, coordinate index of
        each point) or None (tabled per block), and whether the points repeat coordinates.

        Formed on first use: the compiled local prediction (:mod:`gpomap._compiled_local`) takes
        only :meth:`packed_sides`.
        """
        if self._axes is None:
            self._axes = []
            for k, (a, b, side) in enumerate(self.sides):
                values, inverse = _distinct_coordinates(self.points[:, k])
                table = None
                if inverse is not None and a.size * values.size <= MAX_FACTOR_TABLE:
                    table = (side_point_factors(a, b, values, self.length_scale), inverse)
                self._axes.append((a, b, side, table, inverse is not None))
        return self._axes

    def packed_sides(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """Every axis's distinct sides one axis after another, and each box's side on each axis among them.

        Returns
        -------
        side_lo, side_hi : ndarray of shape (s,)
        side_of : ndarray of int, shape (n, d)
            Box i's side on axis k is ``side_lo[side_of[i, k]]``, ``side_hi[side_of[i, k]]``.
        """
        side_of = np.empty((self.n, len(self.sides)), dtype=np.int64)
        offset = 0
        for k, (a, _, side) in enumerate(self.sides):
            side_of[:, k] = side + offset
            offset += a.size
        lo = np.concatenate([a for a, _, _ in self.sides]) if self.sides else np.empty(0)
        hi = np.concatenate([b for _, b, _ in self.sides]) if self.sides else np.empty(0)
        return lo, hi, side_of

    def block(self, rows: NDArray[np.intp], cols: NDArray[np.intp]) -> NDArray[np.float64]:
        """K[rows][:, cols], ndarray of shape (len(rows), len(cols)).

        Parameters
        ----------
        rows : ndarray of int, shape (r,)
            Boxes.
        cols : ndarray of int, shape (c,)
            Points.
        """
        K: NDArray[np.float64] | None = None
        for k, (a, b, side, table, repeated) in enumerate(self.axes):
            s = side[rows]
            if table is not None:
                f, inverse = table
                # Rows first (few distinct sides), then the block's columns.
                f = np.take(np.take(f, s, axis=0), inverse[cols], axis=1)
            else:
                # The block's distinct sides (sorted, as np.unique gives them) by marks: no sort.
                mark = np.zeros(a.size, dtype=bool)
                mark[s] = True
                used = np.flatnonzero(mark)
                f = side_point_factors(a[used], b[used], self.points[cols, k], self.length_scale, repeated)
                f = np.take(f, (np.cumsum(mark) - 1)[s], axis=0)
            if K is None:
                K = f
            else:
                K *= f
        if K is None:
            K = np.ones((rows.size, cols.size))
        if self.variance != 1.0:
            K *= self.variance
        return K


def _distinct_coordinates(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.intp] | None]:
    """The distinct values of x and where each input is among them, or x itself and None when few repeat.

    Parameters
    ----------
    x : ndarray of shape (m,)

    Returns
    -------
    values : ndarray of shape (u,)
    inverse : ndarray of int, shape (m,), or None
        ``values[inverse]`` is x; None when `values` is x (gathering would cost more than it saves).
    """
    values, inverse = np.unique(x, return_inverse=True)
    if values.size > 0.5 * x.size:
        return x, None
    return values, inverse.reshape(-1)
