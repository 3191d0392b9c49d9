"""The estimator of a grid's conversion: one MSK-GPOM GP over a grid's pixels, its map held to
what each pixel says (:class:`GridGPOM`), and its settings for a grid of a given pixel size
(:func:`model_defaults`).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gpomap.cells import Cells
from gpomap.convert.inputs import CENTRE_NOISE, EDGE_STRIP_PIXELS, grid_cells
from gpomap.convert.pooling import POOLINGS, PixelReading
from gpomap.estimator import DenseField, GPMapEstimator, squash_latent
from gpomap.gp import SupportGP, inverse_diagonal
from gpomap.observations import Observations
from gpomap.settings import MapSettings
from gpomap.supports import Supports

__all__ = [
    "MIN_CELL_PIXELS",
    "MAX_CELL_PIXELS",
    "FOOTPRINT_PIXELS",
    "HELD_SCALE",
    "SHARE_SAMPLES",
    "LENGTH_SCALE_PIXELS",
    "LENGTH_SCALE_BOUNDS_PIXELS",
    "GridGPOM",
    "model_defaults",
]

#: Cell-tree sizes in source pixels (docs/convert.md has the measurements behind them).
MIN_CELL_PIXELS = 1.2
MAX_CELL_PIXELS = 4.0
#: Each cell box is widened by this many source pixels on every side: half a pixel turns the
#: bounding box of the cell's pixel centres into the union of its pixels' footprints.
FOOTPRINT_PIXELS = 0.5
#: What the map keeps of the GP's probability in a pixel the grid holds wholly free (and of its
#: complement in one it holds wholly occupied): nothing there is otherwise, and the GP's order is kept.
HELD_SCALE = 1e-3
#: Samples per pixel side over which a pixel's mean probability is measured (:class:`GridGPOM`).
SHARE_SAMPLES = 8
#: Starting length scale and its search bounds, in source (octree) voxels, where they are learnt.
LENGTH_SCALE_PIXELS = 3.0
LENGTH_SCALE_BOUNDS_PIXELS = (1.0, 50.0)


def _fit_soft_squash(gp: SupportGP, y: NDArray[np.float64], class_weight: str | None) -> None:
    """Refit the fitted `gp`'s squash to soft targets `y` in [-1, 1] (shape (n,)).

    An input whose target is 2 f - 1 counts as occupied with weight f and free with weight
    1 - f in the leave-one-out log predictive probability (a cross-entropy with soft labels);
    with ``"balanced"`` class weights the occupied and the free weights each total half.
    """
    post = gp.posterior_
    d = inverse_diagonal(post.L)
    mu, var = y - post.weights / d, 1.0 / d
    f = 0.5 * (y + 1.0)
    w_occ, w_free = f, 1.0 - f
    if class_weight == "balanced" and w_occ.sum() > 0 and w_free.sum() > 0:
        n = y.size
        w_occ, w_free = w_occ * n / (2.0 * w_occ.sum()), w_free * n / (2.0 * w_free.sum())
    labels = np.concatenate([np.ones(y.size), -np.ones(y.size)])
    weights = np.concatenate([w_occ, w_free])
    keep = weights > 0
    gp.squash.fit(labels[keep], np.concatenate([mu, mu])[keep], np.concatenate([var, var])[keep], weights[keep])


class GridGPOM(MapSettings, GPMapEstimator):
    """One MSK-GPOM GP over a grid's pixels, with cells that know the pixels.

    Maps from scans are local GPs in tiles (:class:`~gpomap.mapping.AreaGPOM`); a converted grid
    is one GP over all its cells (at most ``--max-cells``), predicted on the output grid block by
    block from the cells near each block (:meth:`gpomap.gp.GPPosterior.latent`).

    A grid pixel is an area observation: a free pixel says its whole square is free, an occupied
    one that something within its square is occupied. With ``pixel_pad`` > 0 (half the source
    pixel) and ``wall_reach`` set, the inputs are :func:`grid_cells`: single-pixel cells near
    occupied pixels, merged free cells farther away, free strips along the edges free pixels share
    with occupied ones, and a point at every occupied pixel's centre. With ``wall_reach=None`` the
    project's cell tree runs on the pixel centres and each box is widened by ``pixel_pad`` (the
    union of its pixels' squares with ``cell_box="tight"``); ``pixel_pad=0`` is the plain cell tree.

    Parameters
    ----------
    pixel_pad : float
        Half the source pixel side, metres (0: plain cell tree, no footprints).
    wall_reach : int or None
        See :func:`grid_cells`; None: the cell tree widened by ``pixel_pad``.
    edge_strip : float
        See :func:`grid_cells`.
    centre_noise : float or None
        See :func:`grid_cells`. The weights go through the member counts, so they assume the
        ``"per_count"`` noise model and ``"mean"`` normalisation (the defaults).
    occupied_fraction : float, optional
        See :func:`~gpomap.convert.pooling.read_pixels`.
    pooling : {"auto", "any", "majority", "mean"}
        How the grid was made from a finer one (:func:`~gpomap.convert.pooling.read_pixels`). The map keeps what the
        pooling says of each pixel, measured on :data:`SHARE_SAMPLES` x :data:`SHARE_SAMPLES`
        points in it (:meth:`_share_scales`):

        - a pixel the grid holds wholly free (a 0 of an any- or mean-pooled grid) keeps
          :data:`HELD_SCALE` of the GP's probability, a wholly occupied one (a 1 of a mean-pooled
          grid) as much of its complement;
        - elsewhere the probability is scaled within each pixel so that its mean over the pixel
          is the pixel's share (a mean-pooled value) or within the pooling's bounds (at least
          half for a 1 of a majority-pooled grid, at most half for a 0);
        - the occupied region (p > 0.5) is the GP's (where its probability passes 0.5), except
          where that covers less of a pixel than the bounds allow (a mean-pooled value, all of a
          majority-pooled 1, some of a pixel holding anything; :attr:`~gpomap.convert.pooling.PixelReading.region_lower`)
          or more: there it is the part of the pixel where the GP's probability is highest, as
          much as the bound allows. A point the scaling would put on the other side of 0.5 is
          held beside it.

        So the map's occupied region, pooled again the way the grid was made, gives back the
        grid (to a sample's area).
    pooling_factor : int, optional
        Fine pixels per side of a pixel of the grid, when it was pooled from a finer one
        (:func:`~gpomap.convert.pooling.read_pixels`); None: not known.
    **options
        :class:`~gpomap.settings.MapSettings` arguments (``min_cell`` is used only by the cell tree).
    """

    method_name = "msk-gpom"
    # MSK-GPOM's search, as the maps from scans run it (see SupportGP's objective_per_input).
    objective_per_input = True

    def __init__(
        self,
        pixel_pad: float = 0.0,
        wall_reach: int | None = None,
        edge_strip: float = EDGE_STRIP_PIXELS,
        centre_noise: float | None = CENTRE_NOISE,
        occupied_fraction: float | None = None,
        pooling: str = "auto",
        pooling_factor: int | None = None,
        **options: Any,
    ) -> None:
        super().__init__(**options)
        if pooling not in POOLINGS:
            raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
        self.pixel_pad = float(pixel_pad)
        self.wall_reach = wall_reach
        self.edge_strip = edge_strip
        self.centre_noise = centre_noise
        self.occupied_fraction = None if occupied_fraction is None else float(occupied_fraction)
        self.pooling = pooling
        self.pooling_factor = None if pooling_factor is None else int(pooling_factor)

    def __repr__(self) -> str:
        return f"GridGPOM(pixel_pad={self.pixel_pad}, wall_reach={self.wall_reach}, {MapSettings.__repr__(self)})"

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name (the map settings and the grid ones)."""
        names = ("pixel_pad", "wall_reach", "edge_strip", "centre_noise", "occupied_fraction", "pooling", "pooling_factor")
        own = {n: getattr(self, n) for n in names}
        return {**own, **MapSettings.get_params(self)}

    def fit(self, data: Observations) -> GridGPOM:
        """Fit the GP on the pixels' labelled points (:func:`~gpomap.convert.grids.grid_to_observations`).

        Parameters
        ----------
        data : Observations
            One point per known pixel, at its centre.

        Returns
        -------
        self
        """
        timings: dict[str, float] = {}
        t = time.perf_counter()
        obs = self.make_observations(data)
        cells = self.make_cells(obs)
        timings["cells"] = time.perf_counter() - t
        gp = self._make_gp(self.make_kernel())
        y = cells.labels
        self._fit_gp(gp, cells.to_supports(), y)
        if not np.all(np.abs(y) == 1.0):
            t = time.perf_counter()
            _fit_soft_squash(gp, y, self.class_weight)
            timings["soft_squash"] = time.perf_counter() - t
        timings.update(gp.timings_)
        self.observations_: Observations = obs
        self.cells_: Cells = cells
        self.gp_ = gp
        self.timings_ = timings
        self.extent_points_ = obs.points
        self.path_ = None
        # Pixels are not rays: no held-out stretches (the variance scale stays 1), no ray counts.
        self.extrapolation_: dict[str, Any] = {"kappa": 1.0, "reason": "labelled points given, not scans"}
        self.evidence_ = None
        self.reading_: PixelReading | None = getattr(cells, "reading", None)
        self.share_scale_: NDArray[np.float64] | None = None
        self.share_threshold_: NDArray[np.float64] | None = None
        self.pixel_variance_: float | None = None
        if self.reading_ is not None:
            t = time.perf_counter()
            self.pixel_variance_ = self._pixel_variance(cells, self.reading_.pixel)
            self.share_scale_, self.share_threshold_ = self._share_scales(self.reading_)
            timings["shares"] = time.perf_counter() - t
        return self

    def _pixel_variance(self, cells: Cells, pixel: float) -> float:
        """The median latent variance at the centres of the one-pixel cells of `cells`."""
        side = cells.upper - cells.lower
        single = np.all(np.abs(side - pixel) <= 1e-6 * pixel, axis=1)
        centres = 0.5 * (cells.lower[single] + cells.upper[single])
        if centres.shape[0] == 0:
            return 0.0
        # A sample is enough for a median.
        step = max(1, centres.shape[0] // 2000)
        _, var = self.predict(centres[::step], return_var=True)
        return float(np.median(var))

    def _pixel_proba(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
        """The probability at `points` (m, 2) before it is held to the pixels, the latent
        variance and the known pixel of each point (-1 outside them), each of shape (m,).

        Within a known pixel the latent mean is squashed at the variance of a one-pixel input
        (:attr:`pixel_variance_`): the free blocks merged far from walls save inputs, they are not
        weaker evidence, and the variance they leave inside would rank open space above the free
        pixels beside walls. Outside, at the GP's own variance.
        """
        mean, var = self.predict(points, return_var=True)
        reading, v_px = getattr(self, "reading_", None), getattr(self, "pixel_variance_", None)
        if reading is None or v_px is None:
            return squash_latent(self.gp_.squash, mean, var).probability, var, np.full(mean.shape, -1, dtype=np.intp)
        k = reading.locate(points)
        return squash_latent(self.gp_.squash, mean, np.where(k >= 0, v_px, var)).probability, var, k

    def _share_scales(self, reading: PixelReading) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The factor on the GP's probability and the occupied threshold in each known pixel, each
        of shape (m,) (see the class docstring).

        The factor is 1 where the GP's mean probability over the pixel is within the pixel's
        bounds, else the factor s that brings the mean of min(s p, 1) to the nearer bound. The
        threshold is 0.5 where the share of the pixel with p > 0.5 is within the bounds, else the
        probability that cuts the pixel's samples at the nearer bound.
        """
        lo, hi = reading.lower, reading.upper
        scale, threshold = np.ones(lo.size), np.full(lo.size, 0.5)
        some = reading.value > 0.0
        bounded = ((lo > 0.0) | (hi < 1.0) | some) & (hi > 0.0) & (lo < 1.0)
        some_grid = np.zeros(reading.index.shape, dtype=bool)
        ij = reading.ij
        some_grid[ij[:, 1], ij[:, 0]] = reading.value > 0.0
        if some_grid.any() and self.wall_reach is not None:
            # A pixel far from everything occupied holds the prior's free mean, far below any bound.
            near = ndimage.distance_transform_cdt(~some_grid, metric="chessboard") <= self.wall_reach
            bounded &= near[ij[:, 1], ij[:, 0]] | (lo > 0.0)
        idx = np.flatnonzero(bounded)
        if idx.size == 0:
            return scale, threshold
        n = SHARE_SAMPLES
        offsets = ((np.arange(n) + 0.5) / n - 0.5) * reading.pixel
        ox, oy = np.meshgrid(offsets, offsets)
        centres = reading.origin + ij[idx] * reading.pixel
        samples = (centres[:, None, :] + np.column_stack([ox.ravel(), oy.ravel()])[None, :, :]).reshape(-1, 2)
        p = self._pixel_proba(samples)[0].reshape(idx.size, n * n)
        mean = p.mean(axis=1)
        low, high = mean < lo[idx], mean > hi[idx]
        s = np.ones(idx.size)
        s[high] = hi[idx][high] / mean[high]
        if low.any():
            # mean(min(s p, 1)) grows with s: bisection on log s, every low pixel at once.
            pl, target = p[low], lo[idx][low]
            a, b = np.zeros(pl.shape[0]), np.full(pl.shape[0], math.log(1e12))
            for _ in range(60):
                mid = 0.5 * (a + b)
                below = np.minimum(pl * np.exp(mid)[:, None], 1.0).mean(axis=1) < target
                a, b = np.where(below, mid, a), np.where(below, b, mid)
            s[low] = np.exp(b)
        scale[idx] = s
        # The occupied region: the samples above 0.5, unless they fill less of the pixel than the
        # region's lower bound or more than the share's upper one; then the samples ranked
        # highest, as many as the bound allows.
        ranked = -np.sort(-p, axis=1)
        m = n * n
        area = (p > 0.5).mean(axis=1)
        t = np.full(idx.size, 0.5)
        # A pixel holding anything holds some of the occupied region.
        need = np.maximum(np.ceil(reading.region_lower[idx] * m - 1e-9).astype(np.intp), some[idx].astype(np.intp))
        few = area < need / m
        # Just below the need-th highest sample: it and those above it are in.
        t[few] = np.nextafter(ranked[few, need[few] - 1], -np.inf)
        allow = np.floor(hi[idx] * m + 1e-9).astype(np.intp)
        many = area > hi[idx]
        t[many] = ranked[many, np.minimum(allow[many], m - 1)]
        threshold[idx] = t
        return scale, threshold

    def _field(self) -> HeldField:
        """The GP held to the pixels: every answer of the fitted map (``map_``) is held."""
        return HeldField(self)

    def _held(self, p: NDArray[np.float64], k: NDArray[np.intp]) -> NDArray[np.float64]:
        """Probabilities `p` (shape (m,)) in known pixels `k` (shape (m,), -1: none) held to the pixels.

        In a pixel the grid holds wholly free, :data:`HELD_SCALE` p; wholly occupied,
        1 - :data:`HELD_SCALE` (1 - p); elsewhere min(s p, 1) with the pixel's share scale s,
        held beside 0.5 on the side of the pixel's occupied threshold t (p > t: occupied; both
        from :meth:`_share_scales`) where it would cross it. Outside the known pixels, p.
        """
        reading, scale = getattr(self, "reading_", None), getattr(self, "share_scale_", None)
        threshold = getattr(self, "share_threshold_", None)
        if reading is None or scale is None or threshold is None:
            return p
        inside = k >= 0
        kk, pi = k[inside], p[inside]
        q = np.minimum(pi * scale[kk], 1.0)
        # The occupied region is where p passes the pixel's threshold: a point the scaling puts
        # on the other side of 0.5 stays beside it.
        occupied = pi > threshold[kk]
        up, down = occupied & (q <= 0.5), ~occupied & (q > 0.5)
        q[up] = 0.5 + HELD_SCALE * np.maximum(q[up], 1e-12)
        q[down] = 0.5 - HELD_SCALE * np.maximum(1.0 - q[down], 1e-12)
        free, full = reading.upper[kk] == 0.0, reading.lower[kk] == 1.0
        q[free] = HELD_SCALE * pi[free]
        q[full] = 1.0 - HELD_SCALE * (1.0 - pi[full])
        out = p.copy()
        out[inside] = q
        return out

    @property
    def n_inputs_(self) -> int:
        """Number of GP inputs (cells)."""
        self._check_fitted()
        return len(self.cells_)

    def _queries(self, points: NDArray[np.float64]) -> Supports:
        return Supports.from_points(points)

    def _summary_extra(self) -> dict[str, Any]:
        return {"area": self.area_method, "n_cells": len(self.cells_), "n_ambiguous_cells": int(self.cells_.ambiguous.sum())}

    def make_cells(self, obs: Observations) -> Cells:
        """The GP inputs over the pixel centres `obs` (see the class docstring)."""
        if self.pixel_pad > 0 and self.wall_reach is not None:
            frac = getattr(obs, "fraction", None)
            # A grid read by its thresholds is an occupancy grid: its occupied cells are where
            # beams ended, anywhere in them.
            pooling = "any" if self.pooling == "auto" and getattr(obs, "values", "fraction") == "ternary" else self.pooling
            return grid_cells(
                obs.points,
                obs.occupied if frac is None else frac,
                2.0 * self.pixel_pad,
                self.cell_sides(2)[1],
                self.wall_reach,
                self.edge_strip,
                self.centre_noise,
                self.occupied_fraction,
                pooling,
                self.pooling_factor,
            )
        cells = MapSettings.make_cells(self, obs)
        if self.pixel_pad > 0:
            cells = replace(cells, lower=cells.lower - self.pixel_pad, upper=cells.upper + self.pixel_pad)
        return cells


def model_defaults(resolution: float) -> dict[str, Any]:
    """Map settings for a grid of pixel side `resolution` (see the module docstring).

    Parameters
    ----------
    resolution : float
        Source pixel side, metres.

    Returns
    -------
    dict
        Constructor arguments of :class:`GridGPOM` (``convert_grid`` adds
        ``pixel_pad`` = :data:`FOOTPRINT_PIXELS` pixels for :class:`GridGPOM`).
    """
    r = float(resolution)
    return {
        "kernel": "se",
        "cell_box": "tight",
        "min_cell": MIN_CELL_PIXELS * r,
        "max_cell": MAX_CELL_PIXELS * r,
        "length_scale": LENGTH_SCALE_PIXELS * r,
        "length_scale_bounds": (LENGTH_SCALE_BOUNDS_PIXELS[0] * r, LENGTH_SCALE_BOUNDS_PIXELS[1] * r),
        "n_restarts": 0,
    }


class HeldField(DenseField):
    """The conversion's GP as its fitted map asks it (:class:`~gpomap.fitted.LatentField`): its
    probability in each known pixel squashed at a pixel's variance and held to what the pixel's
    value says (:meth:`GridGPOM._pixel_proba`, :meth:`GridGPOM._held`); elsewhere the GP's own.

    Parameters
    ----------
    model : GridGPOM
        A fitted conversion.
    """

    def __init__(self, model: GridGPOM) -> None:
        super().__init__(model.gp_, model._queries, model.extent_points_.shape[1], model.chunk_size)
        self._model = model

    def gp_probabilities(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The held probability, the latent variance, and the held probability again (a grid has
        no unseen space apart), each (m,)."""
        p, var, k = self._model._pixel_proba(points)
        p = self._model._held(p, k)
        return p, var, p
