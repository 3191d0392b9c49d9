"""From an occupancy grid to a continuous GP occupancy map.

A grid (a ROS map_server map, or an :class:`~gpomap.grid.OccupancyMap` such as one read from an
``.npz``) already says which pixels are free and which occupied. Each known pixel becomes one
labelled point at its centre; unknown pixels are not evidence and give no point. The cell tree then
merges neighbourhoods of same-label pixels into larger cells, each covering its pixels' squares,
the MSK-GPOM model is fitted on those cells, and the continuous map is sampled back onto a grid at
any resolution.

    >>> result = convert_grid("map.yaml", resolution=0.01)      # doctest: +SKIP
    >>> write_rosmap(result.map, "map_fine.yaml")               # doctest: +SKIP

Output grid geometry
--------------------
By default the output covers the source's extent with the source's origin convention (origin = the
lower-left corner of the lower-left cell). The origin is always kept, so the output sits exactly on
the source in ROS tools. When the new resolution divides the source's width and height (0.05 m
written at 0.01 m, 0.025 m or 0.1 m, 0.2 m for a 384-pixel map, ...) the outer edges coincide too.
Otherwise the grid gets as many whole cells as are needed to cover the source, so its top and right
edges lie up to one output cell beyond the source's (they are never cropped short of it).

Defaults (measured with benchmarks/convert_maps.py; see docs/convert.md)
-------------------------------------------------------------------------
- cells cover their pixels' full footprints (:class:`GridGPOM`: the tree's "tight" box of pixel
  centres widened by half a source pixel): a pixel is an area observation, not a point at its
  centre. Converting the Stage arena plan down-sampled to 0.05 m back to 0.01 m, footprints and
  ``max_cell`` = 4 pixels give ROC AUC 0.9922 against the fine plan (centre boxes and 8 pixels:
  0.9775; bilinear up-sampling 0.9885, nearest 0.9770) and occupied IoU (p > 0.5) 0.345 (0.257;
  bilinear 0.379). On the TurtleBot3 map (384 x 384 pixels of 0.05 m, 8,734 known) 99.0 % of
  known pixels keep their label (98.7 % before), free 99.7 % (99.0 %), occupied 92.2 % (96.0 %:
  alpha settles at 6.4 instead of the cap of 30, so a few wall pixels fall to p 0.5-0.66);
- ``max_cell`` = 4 pixels: with footprints the learnt length scale is 1-3 pixels, and free cells
  of 8 x 8 pixels (much larger than it) constrain only their average: the map rang inside them
  (bands of p > 0.5 parallel to walls, arena IoU 0.319). 2 pixels: IoU 0.365, AUC 0.9885, at 2.5x
  the cells and twice the time;
- ``min_cell`` = 1.2 pixels: a single pixel stops splitting, so a mixed 2 x 2 block is the smallest
  ambiguous cell;
- squared-exponential kernel with the exact closed-form area kernel (measured earlier with centre
  boxes on TurtleBot3: 98.4 % of known pixels in 1 s of fitting, against 98.2 % in 22 s for
  Matern 3/2 with quadrature);
- length scale started at 3 pixels and bounded to 1..50 pixels. A lower bound of 2 pixels was no
  better: arena 0.1 m AUC 0.9781 / IoU 0.177 against 0.9759 / 0.190; 0.05 m with 8-pixel cells
  0.9780 / 0.257 against 0.9900 / 0.319. The default ``objective="loo"``; no restarts.

Occupied-class IoU at p > 0.5 stays below interpolation's: with labels +-1, a zero prior mean and
beta held at 0, p > 0.5 exactly where the latent mean is positive, whatever alpha; between an
occupied pixel and its free neighbour the mean crosses 0 near their shared edge, so the p > 0.5 band
is about one coarse pixel wide, as interpolation's, while a thin wall is narrower. (The ternary
"occupied", p > 0.66, is narrower: arena IoU 0.412.) Free supports along each wall pixel's edges
moved the crossing inside the pixel but made the SE map ring in the larger free cells (IoU 0.265).
At 0.1 m -> 0.01 m (10 x 10 fine pixels per coarse one) the map is below bilinear in AUC too
(0.9759 against 0.9817).

Known weakness: on a perfectly separable grid (a clean synthetic map) the leave-one-out objective
has no finite optimum (alpha and beta can grow without bound), and where the optimiser stops
decides whether a wall 1, 2 or 4 pixels thick comes out occupied or "unknown" (p ~ 0.5). Real maps
(TurtleBot3: alpha ~ 6.4) are not separable and do not show it.

Second weakness, measured on the TurtleBot3 map (benchmarks/convert_maps.py): where an occupied
wall borders unknown space (the outside of a map's outer walls), nothing free counters it and the
wall bleeds outwards: 99.3 % of unknown pixels 1-2 pixels from known ones and 98.9 % of those 3-10
pixels away come out occupied, 15 % of those 11-20 pixels away (mean p 0.57). Farther the map is
the prior (variance 1, p = 0.5, labelled unknown).

Any of these can be overridden through ``**model_options`` (the :class:`GridGPOM` constructor
arguments: those of :class:`~gpomap.mapping.AreaGPOM` and ``pixel_pad``; ``pixel_pad=0`` gives the
centre boxes of before). ``free_step``, ``hit_margin`` and ``no_return_cap`` concern laser beams and
have no effect here.
"""

from __future__ import annotations

import inspect
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Union

import numpy as np
from numpy.typing import NDArray

from gpomap.cells import Cells
from gpomap.errors import EmptyDataError, InputFormatError
from gpomap.grid import FREE, OCCUPIED, UNKNOWN, GridSpec, OccupancyMap, ternary
from gpomap.io.npz import load_map
from gpomap.io.rosmap import RosMap, read_rosmap
from gpomap.kernels.point import make_point_kernel
from gpomap.mapping import AreaGPOM
from gpomap.metrics import roc_auc
from gpomap.observations import Observations

__all__ = ["ConversionResult", "GridGPOM", "grid_to_observations", "convert_grid", "output_grid", "load_grid", "model_defaults"]

GridSource = Union[RosMap, OccupancyMap, str, "os.PathLike[str]"]

#: Cell-tree sizes in source pixels (see the module docstring for the measurements behind them).
MIN_CELL_PIXELS = 1.2
MAX_CELL_PIXELS = 4.0
#: Each cell box is widened by this many source pixels on every side: half a pixel turns the
#: bounding box of the cell's pixel centres into the union of its pixels' footprints.
FOOTPRINT_PIXELS = 0.5
#: Starting length scale and its search bounds, in source pixels.
LENGTH_SCALE_PIXELS = 3.0
LENGTH_SCALE_BOUNDS_PIXELS = (1.0, 50.0)

# Beyond this many length scales from every cell the kernel is below ~1e-13 and the prediction is
# the prior's: predicting there is skipped (the large unknown margins of most saved maps).
_NEGLIGIBLE_LENGTH_SCALES = {"se": 8.0, "matern32": 20.0}
# Tolerance for "the resolution divides the extent": relative to one output cell.
_DIVIDES_TOLERANCE = 1e-6


@dataclass
class ConversionResult:
    """The continuous map made from a grid, the model behind it, and what the conversion measured.

    Attributes
    ----------
    map : OccupancyMap
        Probability and latent variance on the output grid, ndarrays of shape (ny, nx).
    model : AreaGPOM
        The fitted estimator; ask it anywhere with ``predict_proba(points)``.
    report : dict
        ``pixels`` (``free``, ``occupied``, ``unknown`` counts of the source), ``cells`` (``n``,
        ``occupied``, ``ambiguous``, ``min_cell``, ``max_cell``), ``hyperparameters``, ``timings``
        (seconds: ``read``, ``observations``, ``fit`` with its stages, ``prediction``,
        ``agreement``, ``total``), ``agreement`` (``ternary``: fraction of known source pixels
        whose ternary label in the continuous map equals theirs; ``free`` and ``occupied``: the
        same per class; ``auc``: ROC AUC of the probability at known pixel centres against their
        labels) and ``grid`` (``source`` and ``output`` origin, resolution, shape, extent, and
        ``edges_coincide``).
    """

    map: OccupancyMap
    model: AreaGPOM
    report: dict[str, Any] = field(default_factory=dict)


def load_grid(source: GridSource) -> RosMap | OccupancyMap:
    """Read a grid from a ROS map YAML or a gpomap ``.npz``; pass maps already read through.

    Parameters
    ----------
    source : RosMap, OccupancyMap, or path to a ``.yaml`` / ``.yml`` or ``.npz`` file

    Returns
    -------
    RosMap or OccupancyMap

    Raises
    ------
    InputFormatError
        Unknown suffix, or whatever the reader rejects (for example a rotated map origin).
    """
    if isinstance(source, (RosMap, OccupancyMap)):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        suffix = path.suffix.lower()
        if suffix in (".yaml", ".yml"):
            return read_rosmap(path)
        if suffix == ".npz":
            return load_map(path)
        raise InputFormatError(
            "cannot tell the grid format from the file name: expected a ROS map YAML (.yaml, .yml) or a gpomap map (.npz)",
            path=str(path),
        )
    raise TypeError(f"source must be a RosMap, an OccupancyMap or a path, got {type(source).__name__}")


def _labels(grid_map: RosMap | OccupancyMap) -> NDArray[np.int8]:
    """FREE / OCCUPIED / UNKNOWN per source pixel, ndarray of int8, shape (ny, nx)."""
    # RosMap.ternary keeps map_server's own reading (thresholds, modes, transparency);
    # OccupancyMap.ternary applies the map's thresholds, NaN probabilities being unknown.
    return np.asarray(grid_map.ternary, dtype=np.int8)


def grid_to_observations(grid_map: RosMap | OccupancyMap) -> Observations:
    """Known pixels of a grid as labelled points at their centres.

    Parameters
    ----------
    grid_map : RosMap or OccupancyMap
        Row 0 at the lowest y. Free and occupied pixels are evidence; unknown pixels are not and
        give no point.

    Returns
    -------
    Observations
        ``points`` of shape (n_known, 2) in row-major pixel order, ``occupied`` of shape
        (n_known,), ``scan_index`` all 0 (a grid has no scans).

    Raises
    ------
    EmptyDataError
        No known pixel, or only one class of them (a GP occupancy map needs free and occupied
        evidence).
    """
    labels = _labels(grid_map)
    n_free = int((labels == FREE).sum())
    n_occ = int((labels == OCCUPIED).sum())
    n_unknown = int(labels.size - n_free - n_occ)
    shape = f"{labels.shape[0]} x {labels.shape[1]}"
    if n_free + n_occ == 0:
        raise EmptyDataError(f"the {shape} grid has no known pixels (all {n_unknown} unknown): nothing to convert")
    if n_free == 0 or n_occ == 0:
        only = "free" if n_occ == 0 else "occupied"
        raise EmptyDataError(
            f"the {shape} grid has only {only} known pixels ({n_free} free, {n_occ} occupied, {n_unknown} unknown): "
            "a GP occupancy map needs both free and occupied pixels"
        )
    known = labels != UNKNOWN
    rows, cols = np.nonzero(known)
    g = grid_map.grid
    points = np.column_stack([g.x_centres()[cols], g.y_centres()[rows]])
    occupied = labels[rows, cols] == OCCUPIED
    return Observations(points=points, occupied=occupied, scan_index=np.zeros(points.shape[0], dtype=np.intp))


def _cells_along(length: float, resolution: float) -> tuple[int, bool]:
    """Whole cells of side `resolution` covering `length`, and whether they fit it exactly."""
    ratio = length / resolution
    nearest = round(ratio)
    if nearest >= 1 and abs(ratio - nearest) <= _DIVIDES_TOLERANCE * max(1.0, ratio):
        return int(nearest), True
    return max(1, math.ceil(ratio)), False


def output_grid(
    source: GridSpec, resolution: float | None = None, extent: tuple[float, float, float, float] | None = None
) -> GridSpec:
    """The grid a converted map is written on.

    Parameters
    ----------
    source : GridSpec
        The source grid.
    resolution : float, optional
        Output cell side, metres; default the source's.
    extent : (xmin, xmax, ymin, ymax), optional
        Region to cover; default the source's extent.

    Returns
    -------
    GridSpec
        Origin = ``(xmin, ymin)`` of the extent (the source's origin by default). When `resolution`
        divides the extent's width / height (to a relative 1e-6 of a cell, which forgives float
        noise such as 19.2 / 0.01), the grid ends exactly on its right / top edge; otherwise it has
        one more cell there, ending less than one cell beyond the edge.
    """
    res = source.resolution if resolution is None else float(resolution)
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number, got {resolution}")
    xmin, xmax, ymin, ymax = source.extent if extent is None else (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"extent must have xmin < xmax and ymin < ymax, got {extent}")
    nx, _ = _cells_along(xmax - xmin, res)
    ny, _ = _cells_along(ymax - ymin, res)
    return GridSpec((xmin, ymin), res, (ny, nx))


class GridGPOM(AreaGPOM):
    """:class:`~gpomap.mapping.AreaGPOM` whose cells cover their pixels' full footprints.

    A grid pixel is an area observation: a free pixel says its whole square is free, an occupied
    one that something within its square is occupied. The cell tree runs on pixel centres as for
    any labelled points; each cell's box is then widened by `pixel_pad` metres on every side, so
    a cell of pixels covers those pixels' squares (with ``cell_box="tight"``) rather than the
    bounding box of their centres (a single pixel would be a point, a run of pixels a segment).

    Parameters
    ----------
    pixel_pad : float
        Widening of every cell box, metres (half the source pixel for footprints; 0: the plain
        :class:`~gpomap.mapping.AreaGPOM`).
    **options
        :class:`~gpomap.mapping.AreaGPOM` arguments.
    """

    def __init__(self, pixel_pad: float = 0.0, **options: Any) -> None:
        super().__init__(**options)
        self.pixel_pad = float(pixel_pad)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name (AreaGPOM's and ``pixel_pad``)."""
        names = [n for n in inspect.signature(AreaGPOM.__init__).parameters if n != "self"]
        return {"pixel_pad": self.pixel_pad, **{n: getattr(self, n) for n in names}}

    def make_cells(self, obs: Observations) -> Cells:
        """The cell tree over the pixel centres, each box widened to its pixels' full squares."""
        cells = super().make_cells(obs)
        if self.pixel_pad > 0:
            cells = replace(cells, lower=cells.lower - self.pixel_pad, upper=cells.upper + self.pixel_pad)
        return cells


def model_defaults(resolution: float) -> dict[str, Any]:
    """AreaGPOM settings for a grid of pixel side `resolution` (see the module docstring).

    Parameters
    ----------
    resolution : float
        Source pixel side, metres.

    Returns
    -------
    dict
        Constructor arguments of :class:`~gpomap.mapping.AreaGPOM` (``convert_grid`` adds
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


def _predict_on(
    model: AreaGPOM, spec: GridSpec, support_box: tuple[NDArray[np.float64], NDArray[np.float64]]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Probability and latent variance at every cell centre of `spec`, each of shape (ny, nx).

    Rows and columns farther than the kernel's negligible distance from `support_box` (lower,
    upper corners of shape (2,) round every GP input) get the prior's prediction, computed once.
    """
    name = make_point_kernel(model.kernel).name
    reach = _NEGLIGIBLE_LENGTH_SCALES.get(name, math.inf) * model.hyperparameters_["length_scale"]
    lo, hi = support_box[0] - reach, support_box[1] + reach
    xs, ys = spec.x_centres(), spec.y_centres()
    near_x = (xs >= lo[0]) & (xs <= hi[0])
    near_y = (ys >= lo[1]) & (ys <= hi[1])
    prob = np.empty(spec.shape)
    var = np.empty(spec.shape)
    if not (near_x.all() and near_y.all()):
        # One point well outside the reach stands for all of them: there the mean is 0 and the
        # variance the prior's, whatever the data. (reach is finite here: an infinite one keeps
        # every row and column.)
        far = np.array([[hi[0] + reach + 1.0, hi[1] + reach + 1.0]])
        p_far, v_far = model.predict_proba(far, return_var=True)
        prob[:] = p_far[0]
        var[:] = v_far[0]
    ix, iy = np.flatnonzero(near_x), np.flatnonzero(near_y)
    if ix.size and iy.size:
        xx, yy = np.meshgrid(xs[ix], ys[iy])
        p, v = model.predict_proba(np.column_stack([xx.ravel(), yy.ravel()]), return_var=True)
        prob[np.ix_(iy, ix)] = p.reshape(iy.size, ix.size)
        var[np.ix_(iy, ix)] = v.reshape(iy.size, ix.size)
    return prob, var


def _grid_dict(spec: GridSpec) -> dict[str, Any]:
    return {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape, "extent": spec.extent}


def convert_grid(
    source: GridSource,
    resolution: float | None = None,
    extent: tuple[float, float, float, float] | None = None,
    **model_options: Any,
) -> ConversionResult:
    """Turn an occupancy grid into a continuous GP occupancy map, sampled on a grid.

    Parameters
    ----------
    source : RosMap, OccupancyMap, or path to a ROS map ``.yaml`` or gpomap ``.npz``
        The grid; its free and occupied pixels are the training data (:func:`grid_to_observations`).
    resolution : float, optional
        Output cell side, metres; default the source's.
    extent : (xmin, xmax, ymin, ymax), optional
        Output region; default the source's extent, with its origin. See :func:`output_grid` for
        when the outer edges coincide with the source's.
    **model_options
        :class:`GridGPOM` arguments (those of :class:`~gpomap.mapping.AreaGPOM`, and
        ``pixel_pad``, default half a source pixel), overriding :func:`model_defaults` (which are
        relative to the source's pixel size).

    Returns
    -------
    ConversionResult
        ``map`` (probability and variance of shape (ny, nx) on the output grid, the model's
        thresholds), ``model`` and ``report``.

    Raises
    ------
    EmptyDataError
        The source has no known pixels, or only free or only occupied ones.
    InputFormatError
        The source file cannot be read (missing, malformed, rotated origin, ...).
    """
    t_start = time.perf_counter()
    grid_map = load_grid(source)
    t_read = time.perf_counter() - t_start

    t = time.perf_counter()
    obs = grid_to_observations(grid_map)
    t_obs = time.perf_counter() - t
    src = grid_map.grid
    labels = _labels(grid_map)

    options = model_defaults(src.resolution)
    options["pixel_pad"] = FOOTPRINT_PIXELS * src.resolution
    options.update(model_options)
    model = GridGPOM(**options)
    t = time.perf_counter()
    model.fit(obs)
    t_fit = time.perf_counter() - t
    fit_stages = dict(model.timings_)

    spec = output_grid(src, resolution, extent)
    t = time.perf_counter()
    # Every cell box lies within the known pixel centres' bounding box ("node" and "tight" alike),
    # widened by the footprint padding.
    pad = model.pixel_pad
    support_box = (obs.points.min(axis=0) - pad, obs.points.max(axis=0) + pad)
    prob, var = _predict_on(model, spec, support_box)
    t_pred = time.perf_counter() - t

    t = time.perf_counter()
    # On the source grid itself the known pixels are in the observations' row-major order.
    p_known = prob[labels != UNKNOWN] if spec == src else model.predict_proba(obs.points)
    agreement = _agreement(p_known, obs.occupied, model.thresholds)
    t_agree = time.perf_counter() - t

    cells = model.cells_
    tol = 1e-6 * spec.resolution
    edges = all(math.isclose(a, b, rel_tol=0.0, abs_tol=tol) for a, b in zip(spec.extent, src.extent))
    report: dict[str, Any] = {
        "pixels": {"free": obs.n_free, "occupied": obs.n_occupied, "unknown": int(labels.size - obs.points.shape[0])},
        "cells": {
            "n": len(cells),
            "occupied": int(cells.occupied.sum()),
            "ambiguous": int(cells.ambiguous.sum()),
            "min_cell": float(model.min_cell),
            "max_cell": float(model.max_cell),
        },
        "hyperparameters": dict(model.hyperparameters_),
        "agreement": agreement,
        "grid": {
            "source": _grid_dict(src),
            "output": _grid_dict(spec),
            "edges_coincide": edges,
        },
    }
    report["timings"] = {
        "read": t_read,
        "observations": t_obs,
        "fit": t_fit,
        "fit_stages": fit_stages,
        "prediction": t_pred,
        "agreement": t_agree,
        "total": time.perf_counter() - t_start,
    }
    info = dict(model.summary())
    info["source"] = "grid conversion"
    info["conversion"] = {k: report[k] for k in ("pixels", "cells", "agreement", "grid")}
    occupancy_map = OccupancyMap(spec, prob, variance=var, thresholds=model.thresholds, info=info)
    return ConversionResult(map=occupancy_map, model=model, report=report)


def _agreement(
    probability: NDArray[np.float64], occupied: NDArray[np.bool_], thresholds: tuple[float, float]
) -> dict[str, float]:
    """How well probabilities at known pixels reproduce their labels.

    Parameters
    ----------
    probability : ndarray of shape (n,)
    occupied : ndarray of bool, shape (n,)
        Known labels (both classes present).
    thresholds : (float, float)
        Ternary thresholds; a pixel agrees when its ternary label equals its known label (an
        "unknown" answer never agrees).

    Returns
    -------
    dict
        ``ternary``, ``free``, ``occupied`` (fractions) and ``auc``.
    """
    lab = ternary(probability, thresholds)
    truth = np.where(occupied, OCCUPIED, FREE)
    match = lab == truth
    return {
        "ternary": float(match.mean()),
        "free": float(match[~occupied].mean()),
        "occupied": float(match[occupied].mean()),
        "auc": float(roc_auc(occupied, probability)),
    }
