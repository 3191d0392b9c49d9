"""How a grid was made from a finer one (its pooling), and what each pixel then says about the
fine occupancy within it.

A value between 0 and 1 is a pixel's occupied share, whatever the pooling. A grid of 0s and 1s says
less, and what it says depends on how it was made: a pixel occupied if any of its fine pixels is
(``"any"``), if more than half is (``"majority"``), or holding the occupied share (``"mean"``).
:func:`read_pixels` reads each pixel so (:class:`PixelReading`: the share the GP is given, and the
bounds the map is held to); :func:`infer_pooling` tells the pooling from the grid itself.
"""

from __future__ import annotations

import math
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
    "boundary_wall_thickness",
    "occluded_share",
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


def _unknown_beside(grid: NDArray[np.float64]) -> tuple[NDArray[np.float64], list[NDArray[np.float64]]]:
    """`grid` (shape (ny, nx), NaN unknown) padded with one ring of unknown pixels, and each
    pixel's four edge neighbours in it (left, right, below, above), each of shape (ny, nx)."""
    pad = np.pad(np.asarray(grid, dtype=float), 1, constant_values=np.nan)
    return pad, [pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]]


def boundary_wall_thickness(grid: NDArray[np.float64], factor: int) -> float:
    """The thickness, in fine pixels, of the walls of an any-pooled grid between free and unknown space.

    A sensor sees a wall's front and nothing behind it, so a wall between free and unknown pixels
    (the grid's outside being unknown too) is, across it, free fine pixels, the wall's t fine
    pixels, then unseen ones. Pooled at `factor` fine pixels a side, its front lands on each of
    the `factor` fine pixels of a coarse one alike, and it is one coarse pixel thick when its t
    fine pixels fit in the rest: a share (factor - t + 1) / factor of such walls. So
    t = 1 + factor (1 - p1), p1 the share of the grid's runs of occupied pixels along a row or
    column from an unknown pixel to a free one that are one pixel long.

    Parameters
    ----------
    grid : ndarray of shape (ny, nx)
        An any-pooled grid of 0s and 1s, NaN unknown.
    factor : int
        Fine pixels per side of the grid's pixel.

    Returns
    -------
    float
        t, at least 1; 1 (a wall is at least a fine pixel) where the grid has no such run.
    """
    pad, _ = _unknown_beside(grid)
    n_runs, n_single = 0, 0
    for g in (pad, pad.T):
        # Rows laid end to end, each closed by its unknown padding.
        flat = g.ravel()
        one = flat == 1.0
        edges = np.diff(one.astype(np.int8))
        starts, ends = np.flatnonzero(edges == 1) + 1, np.flatnonzero(edges == -1)  # the padding closes every run
        before, after = flat[starts - 1], flat[ends + 1]
        crossing = (np.isnan(before) & (after == 0.0)) | ((before == 0.0) & np.isnan(after))
        n_runs += int(crossing.sum())
        n_single += int((crossing & (ends == starts)).sum())
    if n_runs == 0:
        return 1.0
    return 1.0 + factor * (1.0 - n_single / n_runs)


def occluded_share(thickness: float, factor: int) -> float:
    """The occupied share of the known part of an any-pooled 1 that holds a wall's front, its back
    facing unseen space.

    Across it lie j free fine pixels, the wall's `thickness` t, then unseen ones (not part of what
    the pixel says): its known part is t / (j + t) occupied, j = 0, 1, ... as long as the wall
    fits (j + t <= `factor`), each alike (:func:`boundary_wall_thickness`); 1 for a wall as thick
    as the pixel.
    """
    if thickness >= factor:
        return 1.0
    j = np.arange(math.floor(factor - thickness + 1e-9) + 1)
    return float(np.mean(thickness / (j + thickness)))


def read_pixels(
    points: NDArray[np.float64],
    value: NDArray[np.float64],
    pixel: float,
    pooling: str = "auto",
    occupied_fraction: float | None = None,
    pooling_factor: int | None = None,
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

    Told the `pooling_factor` of an any-pooled grid, its 1s beside unknown space (an unknown
    pixel, or the grid's outside, at an edge) are read as walls a sensor saw the front of, their
    backs facing unseen space: with no free side, the wall came in from an occupied neighbour and
    all of the pixel's known part is occupied (share 1); with one, its known part is a free strip,
    then the wall, and its share is :func:`occluded_share` of the walls' thickness
    (:func:`boundary_wall_thickness`).

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
    pooling_factor : int, optional
        Fine pixels per side of a pixel of the grid, when it was pooled from a finer one; None:
        not known (every 1 of an any-pooled grid is then taken as `occupied_fraction`).

    Returns
    -------
    PixelReading
    """
    if pooling not in POOLINGS:
        raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
    if occupied_fraction is not None and not 0.0 < occupied_fraction <= 1.0:
        raise ValueError(f"occupied_fraction must be in (0, 1], got {occupied_fraction}")
    if pooling_factor is not None and pooling_factor < 1:
        raise ValueError(f"pooling_factor must be a whole number of fine pixels, at least 1, got {pooling_factor}")
    pts = np.asarray(points, dtype=float)
    v = np.asarray(value, dtype=float)
    origin, ij, index = pixel_lattice(pts, pixel)
    grid = np.full(index.shape, np.nan)
    grid[ij[:, 1], ij[:, 0]] = v
    read = infer_pooling(grid) if pooling == "auto" else pooling
    share, lower, upper = v.copy(), v.copy(), v.copy()  # mean pooling, and any value between 0 and 1
    ones, zeros = v == 1.0, v == 0.0
    if read == "any":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.0
        if pooling_factor is not None:
            _, sides = _unknown_beside(grid)
            unknown = np.any([np.isnan(n) for n in sides], axis=0)[ij[:, 1], ij[:, 0]]
            free_side = np.any([n == 0.0 for n in sides], axis=0)[ij[:, 1], ij[:, 0]]
            share[ones & unknown & ~free_side] = 1.0
            front = occluded_share(boundary_wall_thickness(grid, pooling_factor), pooling_factor)
            share[ones & unknown & free_side] = front
    elif read == "majority":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.5
        upper[zeros] = 0.5
        ones_grid = np.zeros(index.shape, dtype=bool)
        ones_grid[ij[ones, 1], ij[ones, 0]] = True
        near = ndimage.binary_dilation(ones_grid, structure=np.ones((3, 3), dtype=bool), iterations=MAJORITY_REACH)
        share[zeros & near[ij[:, 1], ij[:, 0]]] = MAJORITY_NEIGHBOUR_SHARE
    return PixelReading(origin, float(pixel), index, read, v, share, lower, upper)
