"""How a grid was made from a finer one (its pooling), and what each pixel then says about the
fine occupancy within it.

A value between 0 and 1 is a pixel's occupied share, whatever the pooling. A grid of 0s and 1s says
less, and what it says depends on how it was made: a pixel occupied if any of its fine pixels is
(``"any"``), if more than half is (``"majority"``), or holding the occupied share (``"mean"``).
:func:`read_pixels` reads each pixel so (:class:`PixelReading`: the share the GP is given, and the
bounds the map is held to); :func:`infer_pooling` tells the pooling from the grid itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

__all__ = [
    "POOLINGS",
    "OCCUPIED_FRACTION",
    "MAJORITY_NEIGHBOUR_SHARE",
    "MAJORITY_REACH",
    "BROKEN_SHARE",
    "PixelReading",
    "infer_pooling",
    "read_pixels",
    "pixel_lattice",
]

#: What an occupied pixel of a grid of 0s and 1s is taken to hold: any-pixel pooling marks pixels
#: a thin wall grazes, majority pooling pixels more than half filled (docs/convert.md).
OCCUPIED_FRACTION = 0.7
#: What a free pixel of a majority-pooled grid within :data:`MAJORITY_REACH` pixels (chessboard)
#: of an occupied one is taken to hold: up to half of it may be a wall that continues from its
#: neighbour, and such walls vanish from the grid (docs/convert.md).
MAJORITY_NEIGHBOUR_SHARE = 0.2
MAJORITY_REACH = 1
#: A grid of 0s and 1s more than this share of whose occupied pixels end a wall or touch another
#: only at a corner is read as majority-pooled (:func:`infer_pooling`).
BROKEN_SHARE = 0.1
#: How a grid of 0s and 1s was made from a finer one (:func:`read_pixels`); "auto": see
#: :func:`infer_pooling`.
POOLINGS = ("auto", "any", "majority", "mean")


@dataclass(frozen=True)
class PixelReading:
    """What each known pixel of a grid says about the fine occupancy within it (:func:`read_pixels`).

    Attributes
    ----------
    origin : ndarray of shape (2,)
        Centre of the lattice's pixel (column 0, row 0), metres.
    pixel : float
        Pixel side, metres.
    index : ndarray of int, shape (ny, nx)
        The observation (known pixel) at each lattice pixel, -1 where the grid has none.
    pooling : str
        How the grid was read: ``"any"``, ``"majority"`` or ``"mean"``.
    value : ndarray of shape (m,)
        Each known pixel's occupied fraction as the grid gives it (:func:`~gpomap.convert.grids.grid_fractions`).
    share : ndarray of shape (m,)
        The occupied share the GP is given for each pixel (its input's target is 2 share - 1);
        NaN: the pixel is not evidence (known, but its value bounds its share too loosely).
    lower, upper : ndarray of shape (m,)
        Bounds on each pixel's occupied share that the pooling rule implies; the map's mean
        probability over the pixel is kept within them (:class:`~gpomap.convert.estimator.GridGPOM`),
        and its occupied region covers at least :attr:`region_lower` of the pixel and at most
        `upper`.
    """

    origin: NDArray[np.float64]
    pixel: float
    index: NDArray[np.intp]
    pooling: str
    value: NDArray[np.float64]
    share: NDArray[np.float64]
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]

    @property
    def region_lower(self) -> NDArray[np.float64]:
        """The least share of each pixel the map's occupied region (p > 0.5) covers, shape (m,).

        :attr:`lower`, but all of a majority-pooled 1: more than half of such a pixel is occupied,
        so a part of it is more likely occupied than not, and which of its parts make up the
        free rest the grid does not say (docs/convert.md).
        """
        if self.pooling != "majority":
            return self.lower
        return np.where(self.value == 1.0, 1.0, self.lower)

    @property
    def ij(self) -> NDArray[np.intp]:
        """(column, row) of every known pixel on the lattice, ndarray of shape (m, 2)."""
        rows, cols = np.nonzero(self.index >= 0)
        out = np.empty((self.value.size, 2), dtype=np.intp)
        out[self.index[rows, cols]] = np.column_stack([cols, rows])
        return out

    def locate(self, points: NDArray[np.float64]) -> NDArray[np.intp]:
        """The known pixel holding each of `points` (shape (n, 2)), -1 outside them; shape (n,)."""
        f = np.floor((np.asarray(points, dtype=float) - self.origin) / self.pixel + 0.5)
        ny, nx = self.index.shape
        inside = (f[:, 0] >= 0) & (f[:, 0] < nx) & (f[:, 1] >= 0) & (f[:, 1] < ny)
        out = np.full(f.shape[0], -1, dtype=np.intp)
        c, r = f[inside, 0].astype(np.intp), f[inside, 1].astype(np.intp)
        out[inside] = self.index[r, c]
        return out


def pixel_lattice(points: NDArray[np.float64], pixel: float) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp]]:
    """The pixel lattice of known pixel centres.

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        Known pixel centres.
    pixel : float
        Pixel side, metres.

    Returns
    -------
    origin : ndarray of shape (2,)
        The centre of the lattice's pixel (column 0, row 0).
    ij : ndarray of int, shape (m, 2)
        Each point's (column, row).
    index : ndarray of int, shape (ny, nx)
        The point at every lattice pixel, -1 where none.

    Raises
    ------
    ValueError
        The points are not the centres of a grid of `pixel` m pixels.
    """
    origin = points.min(axis=0)
    f = (points - origin) / pixel
    ij = np.rint(f).astype(np.intp)  # (column, row)
    if np.abs(f - ij).max() > 1e-3:
        raise ValueError(f"the points are not the centres of a grid of {pixel} m pixels")
    nx, ny = ij.max(axis=0) + 1
    index = np.full((ny, nx), -1, dtype=np.intp)
    index[ij[:, 1], ij[:, 0]] = np.arange(points.shape[0])
    return origin, ij, index


def infer_pooling(values: NDArray[np.float64]) -> str:
    """The pooling ``"auto"`` reads a grid by, from its values (ndarray of shape (ny, nx), NaN unknown).

    A grid with values between 0 and 1 holds occupied shares: ``"mean"``. A grid of 0s and 1s is
    read as ``"any"`` (an occupancy grid marks the cell a beam ended in, wherever in it), unless
    its walls are broken: more than :data:`BROKEN_SHARE` of its occupied pixels end a wall (at
    most one occupied pixel among their eight neighbours) or touch an occupied pixel only at a
    corner. Any-pixel pooling keeps a wall's pixels edge to edge; majority pooling drops the
    stretches of a thin wall that fill less than half of a pixel, and what is left are ends and
    diagonal steps (docs/convert.md).
    """
    v = np.asarray(values, dtype=float)
    if np.any((v > 0.0) & (v < 1.0)):
        return "mean"
    occ = v == 1.0
    if not occ.any():
        return "any"
    padded = np.pad(occ, 1)
    ny, nx = occ.shape

    def shifted(dy: int, dx: int) -> NDArray[np.bool_]:
        return padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]

    neighbours = sum(shifted(dy, dx).astype(int) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
    corner_only = np.zeros_like(occ)
    for dy, dx in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        corner_only |= shifted(dy, dx) & ~shifted(dy, 0) & ~shifted(0, dx)
    broken = occ & ((neighbours <= 1) | corner_only)
    return "majority" if broken.sum() > BROKEN_SHARE * occ.sum() else "any"


def read_pixels(
    points: NDArray[np.float64],
    value: NDArray[np.float64],
    pixel: float,
    pooling: str = "auto",
    occupied_fraction: float | None = None,
) -> PixelReading:
    """What each known pixel says about its fine occupancy, given how the grid was made.

    A pixel value between 0 and 1 is its occupied share, whatever the pooling. A grid of 0s and 1s
    says less, and what it says depends on how it was made from a finer one:

    - ``"any"`` (a pixel occupied if any of its fine pixels is; an occupancy grid marking the cell
      a beam ended in): a 0 is wholly free; a 1 holds something, anywhere from a sliver to all of
      it: its share is taken as `occupied_fraction` (default :data:`OCCUPIED_FRACTION`), bounded
      only by (0, 1].
    - ``"majority"`` (occupied if more than half is): a 1 holds more than half (taken as
      `occupied_fraction`, default :data:`OCCUPIED_FRACTION`, bounded to [0.5, 1]); a 0 at most
      half. Walls thinner than half a pixel vanish from such a grid between the pixels where they
      cross or thicken, so a 0 within :data:`MAJORITY_REACH` pixels (chessboard) of a 1 is taken
      as :data:`MAJORITY_NEIGHBOUR_SHARE` occupied (the walls ending at the 1 continue into some of
      its neighbours); farther 0s are free. Every 0 is bounded to [0, 0.5].
    - ``"mean"`` (the occupied share as the value): every value is exact, bounds included.

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        Known pixel centres on a lattice of pitch `pixel`.
    value : ndarray of shape (m,)
        Each pixel's occupied fraction in [0, 1] (:func:`~gpomap.convert.grids.grid_fractions`).
    pixel : float
        Pixel side, metres.
    pooling : {"auto", "any", "majority", "mean"}
        ``"auto"``: :func:`infer_pooling` on the grid's values.
    occupied_fraction : float, optional
        The share taken for a 1 of an any- or majority-pooled grid, in (0, 1].

    Returns
    -------
    PixelReading
    """
    if pooling not in POOLINGS:
        raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
    if occupied_fraction is not None and not 0.0 < occupied_fraction <= 1.0:
        raise ValueError(f"occupied_fraction must be in (0, 1], got {occupied_fraction}")
    pts = np.asarray(points, dtype=float)
    v = np.asarray(value, dtype=float)
    origin, ij, index = pixel_lattice(pts, pixel)
    if pooling == "auto":
        grid = np.full(index.shape, np.nan)
        grid[ij[:, 1], ij[:, 0]] = v
        read = infer_pooling(grid)
    else:
        read = pooling
    share, lower, upper = v.copy(), v.copy(), v.copy()  # mean pooling, and any value between 0 and 1
    ones, zeros = v == 1.0, v == 0.0
    if read == "any":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.0
    elif read == "majority":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.5
        upper[zeros] = 0.5
        ones_grid = np.zeros(index.shape, dtype=bool)
        ones_grid[ij[ones, 1], ij[ones, 0]] = True
        near = ndimage.binary_dilation(ones_grid, structure=np.ones((3, 3), dtype=bool), iterations=MAJORITY_REACH)
        share[zeros & near[ij[:, 1], ij[:, 0]]] = MAJORITY_NEIGHBOUR_SHARE
    return PixelReading(origin, float(pixel), index, read, v, share, lower, upper)
