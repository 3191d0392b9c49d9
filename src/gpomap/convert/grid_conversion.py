"""A grid turned into a continuous map: the converter for a grid (:func:`converter_for`), its fit
and the map sampled on an output grid (:func:`convert_grid`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.convert.agreement import label_agreement
from gpomap.convert.estimator import FOOTPRINT_PIXELS, GridGPOM, model_defaults
from gpomap.convert.grids import GridSource, grid_fractions, grid_to_observations, load_grid, output_grid
from gpomap.convert.inputs import WALL_REACH_PIXELS
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.kernels.point import make_point_kernel

__all__ = ["GRID_LENGTH_SCALE_PIXELS", "ConversionResult", "converter_for", "convert_grid"]

#: Length scale of a converted grid, in source pixels, not learnt: the maps with a learnt one
#: scored lower on most pooled plans (docs/convert.md).
GRID_LENGTH_SCALE_PIXELS = 1.0


# Beyond this many length scales from every cell the kernel is below ~1e-13 and the prediction is
# the prior's: predicting there is skipped (the large unknown margins of most saved maps).
_NEGLIGIBLE_LENGTH_SCALES = {"se": 8.0, "matern32": 20.0}


@dataclass
class ConversionResult:
    """The continuous map made from a grid, the model behind it, and what the conversion measured.

    Attributes
    ----------
    map : OccupancyMap
        Probability and latent variance on the output grid, ndarrays of shape (ny, nx).
    model : GridGPOM
        The fitted estimator; ask it anywhere with ``predict_proba(points)``.
    report : dict
        ``pixels`` (``free``, ``occupied``, ``unknown`` counts of the source), ``cells`` (``n``,
        ``occupied``, ``ambiguous``, ``min_cell``, ``max_cell``), ``pooling`` (how the pixels were
        read, :func:`~gpomap.convert.pooling.read_pixels`), ``hyperparameters``, ``timings``
        (seconds: ``read``, ``observations``, ``fit`` with its stages, ``prediction``,
        ``agreement``, ``total``), ``agreement`` (``ternary``: fraction of known source pixels
        whose ternary label in the continuous map equals theirs; ``free`` and ``occupied``: the
        same per class; ``auc``: ROC AUC of the probability at known pixel centres against their
        labels) and ``grid`` (``source`` and ``output`` origin, resolution, shape, extent, and
        ``edges_coincide``).
    """

    map: OccupancyMap
    model: GridGPOM
    report: dict[str, Any] = field(default_factory=dict)


def _predict_on(
    model: GridGPOM, spec: GridSpec, support_box: tuple[NDArray[np.float64], NDArray[np.float64]]
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
        # The local prediction's blocks of the exact SE kernel table its factors once per grid
        # row and column (gpomap.kernels.box_points.BoxPointFactors).
        xx, yy = np.meshgrid(xs[ix], ys[iy])
        p, v = model.predict_proba(np.column_stack([xx.ravel(), yy.ravel()]), return_var=True)
        prob[np.ix_(iy, ix)] = p.reshape(iy.size, ix.size)
        var[np.ix_(iy, ix)] = v.reshape(iy.size, ix.size)
    return prob, var


def _grid_dict(spec: GridSpec) -> dict[str, Any]:
    return {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape, "extent": spec.extent}


def converter_for(resolution: float, **model_options: Any) -> GridGPOM:
    """The unfitted :class:`GridGPOM` that :func:`convert_grid` fits on a grid of pixel side `resolution`.

    Its :meth:`GridGPOM.make_cells` gives the GP inputs, so their number (what a fit's memory
    grows with) can be known before fitting.

    Parameters
    ----------
    resolution : float
        Source pixel side, metres.
    **model_options
        Override :func:`model_defaults`, the pixel footprint and wall-aware inputs, and the
        fixed length scale (:data:`GRID_LENGTH_SCALE_PIXELS`; ``optimise=True`` learns it).
    """
    options = model_defaults(resolution)
    options["pixel_pad"] = FOOTPRINT_PIXELS * resolution
    options["wall_reach"] = WALL_REACH_PIXELS
    # The length scale is the pixel's and the noise the map settings' own: only the squash is
    # fitted (GRID_LENGTH_SCALE_PIXELS).
    options["length_scale"] = GRID_LENGTH_SCALE_PIXELS * resolution
    options["optimise"] = False
    options.update(model_options)
    return GridGPOM(**options)


def convert_grid(
    source: GridSource,
    resolution: float | None = None,
    extent: tuple[float, float, float, float] | None = None,
    values: str = "auto",
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
        :class:`GridGPOM` arguments (those of :class:`~gpomap.settings.MapSettings`, and
        ``pixel_pad``, default half a source pixel; ``pooling``, how the grid was made from a
        finer one, default inferred), overriding :func:`model_defaults` (which are relative to
        the source's pixel size).

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
    obs = grid_to_observations(grid_map, values)
    t_obs = time.perf_counter() - t
    src = grid_map.grid

    model = converter_for(src.resolution, **model_options)
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
    # Wholly free or occupied pixels are scored (a partly occupied one has no single label);
    # on the source grid itself they are in the observations' row-major order.
    assert obs.fraction is not None
    hard = (obs.fraction == 0.0) | (obs.fraction == 1.0)
    p_known = prob[np.isfinite(grid_fractions(grid_map, values))] if spec == src else model.predict_proba(obs.points)
    agreement = label_agreement(p_known[hard], obs.fraction[hard] == 1.0, model.thresholds_)
    t_agree = time.perf_counter() - t

    cells = model.cells_
    tol = 1e-6 * spec.resolution
    edges = all(math.isclose(a, b, rel_tol=0.0, abs_tol=tol) for a, b in zip(spec.extent, src.extent))
    report: dict[str, Any] = {
        "pixels": {
            "free": int((obs.fraction == 0.0).sum()),
            "occupied": int((obs.fraction == 1.0).sum()),
            "partial": int((~hard).sum()),
            "unknown": int(src.shape[0] * src.shape[1] - obs.points.shape[0]),
        },
        "cells": {
            "n": len(cells),
            "occupied": int(cells.occupied.sum()),
            "ambiguous": int(cells.ambiguous.sum()),
            "min_cell": model.cell_sides(2)[0],
            "max_cell": model.cell_sides(2)[1],
        },
        "pooling": model.reading_.pooling if model.reading_ is not None else None,
        "pooling_factor": model.pooling_factor,
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
    info["conversion"] = {k: report[k] for k in ("pixels", "cells", "pooling", "pooling_factor", "agreement", "grid")}
    occupancy_map = OccupancyMap(spec, prob, variance=var, thresholds=model.thresholds_, info=info)
    return ConversionResult(map=occupancy_map, model=model, report=report)
