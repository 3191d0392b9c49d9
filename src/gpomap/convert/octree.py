"""From an OctoMap octree to a continuous GP occupancy map: the grid conversion in 3-D.

An octree already says which voxels are free and which occupied; its leaves are cubes of the
tree's resolution or, where pruning merged eight equal children, of a power of two times it. Each
known leaf is split into the resolution-sized voxels it covers (:meth:`Octree.voxel_centres`), and
each voxel becomes one labelled point at its centre, exactly as
:func:`~gpomap.convert.grids.grid_to_observations` makes one point per known pixel; unknown space
gives no point. The cell tree then merges neighbourhoods of same-label voxels into boxes,
:class:`~gpomap.convert.estimator.GridGPOM` widens every box by half a voxel so that it covers its
voxels' cubes (a voxel is a volume observation), the SE GP with the exact box kernel is fitted with
:func:`~gpomap.convert.estimator.model_defaults` (cell sizes and length scale in source voxels),
and the map is sampled on a voxel grid of any resolution.

Size. One GP holds a few thousand cells, and a real octree gives tens or hundreds of thousands
(docs/convert.md, "OctoMap trees, whole"). A region whose
cells one GP holds (at most ``max_cells``) is converted by one GP, trained on the known voxels
inside it grown by a margin of :data:`MARGIN_VOXELS` voxels (so the map at the region's faces sees
the data beyond them). A larger one, up to the whole tree, is converted in tiles
(:class:`~gpomap.convert.octree_tiles.TiledOctreeModel`): the cells and the hyperparameters once,
then square columns fitted, predicted and let go one after another, blended as
:class:`~gpomap.tiles.TiledGPOM` blends its tiles, so memory holds the cells, the output and the
tiles in flight, not every tile's GP.

Agreement is measured as in 2-D: the fraction of the source's known voxels inside the region whose
ternary label the continuous map keeps, per class, and the ROC AUC of the map's probability at
their centres against their labels (on a seeded sample of at most ``max_check`` voxels).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gpomap.config import DEFAULT_MAX_CELLS  # most cells of the one GP of a conversion, as for maps
from gpomap.convert.agreement import label_agreement
from gpomap.convert.estimator import FOOTPRINT_PIXELS, GridGPOM, model_defaults
from gpomap.convert.octree_tiles import TiledOctreeModel
from gpomap.errors import EmptyDataError, GpomapError
from gpomap.io.octomap import Octree, read_octree
from gpomap.lattice import in_box
from gpomap.observations import Observations
from gpomap.resources import peak_rss_mb
from gpomap.voxels import VoxelMap, VoxelSpec

__all__ = [
    "OctreeSource",
    "MARGIN_VOXELS",
    "MAX_CHECK",
    "OctreeConversion",
    "octree_to_observations",
    "region",
    "convert_octree",
]

OctreeSource = Union[Octree, str, "os.PathLike[str]"]

#: The training region reaches this many source voxels past the converted region on every side.
MARGIN_VOXELS = 4
#: Known voxels scored for the agreement, at most (a seeded sample beyond).
MAX_CHECK = 200_000


@dataclass
class OctreeConversion:
    """The continuous map made from an octree, the model behind it, and what was measured.

    Attributes
    ----------
    map : VoxelMap
        Probability and latent variance, ndarrays of shape (nz, ny, nx).
    model : GridGPOM or TiledOctreeModel
        The fitted estimator, one GP or tiles fitted when asked; either answers through its
        fitted map (``model.map_``: ``predict_proba(points)`` anywhere, points of shape (m, 3)).
    report : dict
        ``leaves`` (``n``, ``occupied``, ``free`` of the whole tree), ``voxels`` (known source
        voxels trained on: ``free``, ``occupied``), ``region`` (``lower``, ``upper`` of the
        converted box and of the training box), ``cells`` (``n``, ``occupied``, ``ambiguous``,
        ``min_cell``, ``max_cell``), ``hyperparameters``, ``agreement`` (``ternary``, ``free``,
        ``occupied``, ``auc``, ``n_checked``, ``n_known``), ``grid`` (``origin``, ``resolution``,
        ``shape``) and ``timings`` (seconds: ``read``, ``observations``, ``fit``, ``prediction``,
        ``agreement``, ``total``).
    """

    map: VoxelMap
    model: GridGPOM | TiledOctreeModel
    report: dict[str, Any] = field(default_factory=dict)


def _inside(points: NDArray[np.float64], lower: NDArray[np.float64], upper: NDArray[np.float64]) -> NDArray[np.bool_]:
    return in_box(points, lower, upper)


def octree_to_observations(
    tree: Octree, lower: ArrayLike | None = None, upper: ArrayLike | None = None
) -> tuple[Observations, NDArray[np.float64]]:
    """Known voxels of an octree (inside a box) as labelled points at their centres.

    Parameters
    ----------
    tree : Octree
    lower, upper : array_like of shape (3,), optional
        Keep the voxels whose centre lies in this box (default: all).

    Returns
    -------
    observations : Observations
        ``points`` of shape (n, 3), occupied voxels first, ``occupied`` of shape (n,),
        ``scan_index`` all 0.
    centres : ndarray of shape (n, 3)
        The same points (for callers that score at them).

    Raises
    ------
    EmptyDataError
        No known voxel in the box, or only one class of them.
    """
    occ = tree.voxel_centres(True)
    free = tree.voxel_centres(False)
    if lower is not None and upper is not None:
        lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
        occ, free = occ[_inside(occ, lo, hi)], free[_inside(free, lo, hi)]
    where = "" if lower is None else " in the region"
    if len(occ) == 0 or len(free) == 0:
        raise EmptyDataError(
            f"the octree has {len(occ)} occupied and {len(free)} free voxels{where}: "
            "a GP occupancy map needs both free and occupied ones"
        )
    points = np.concatenate([occ, free])
    occupied = np.concatenate([np.ones(len(occ), dtype=bool), np.zeros(len(free), dtype=bool)])
    obs = Observations(points=points, occupied=occupied, scan_index=np.zeros(len(points), dtype=np.intp))
    return obs, points


def region(tree: Octree, lower: ArrayLike | None, upper: ArrayLike | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The converted box: the tree's extent, with the given corners' finite values in place."""
    lo, hi = tree.extent()
    lo, hi = lo.astype(float).copy(), hi.astype(float).copy()
    for given, out in ((lower, lo), (upper, hi)):
        if given is not None:
            g = np.asarray(given, dtype=float).reshape(3)
            out[np.isfinite(g)] = g[np.isfinite(g)]
    if not (hi > lo).all():
        raise GpomapError(f"the region to convert is empty: x, y, z from {lo.tolist()} to {hi.tolist()}")
    return lo, hi


def convert_octree(
    source: OctreeSource,
    resolution: float | None = None,
    lower: ArrayLike | None = None,
    upper: ArrayLike | None = None,
    max_cells: int | None = DEFAULT_MAX_CELLS,
    max_check: int = MAX_CHECK,
    seed: int = 0,
    before_fit: Callable[[int], None] | None = None,
    tile_size: float | None = None,
    hyperparameters: dict[str, float] | None = None,
    n_workers: int = 1,
    **model_options: Any,
) -> OctreeConversion:
    """Turn an OctoMap octree (or a region of it) into a continuous GP map, sampled on voxels.

    Parameters
    ----------
    source : Octree, or path to a ``.bt`` / ``.ot`` file
    resolution : float, optional
        Output voxel side, metres; default the tree's.
    lower, upper : array_like of shape (3,), optional
        Corners (x, y, z) of the region to convert (default the tree's extent; a non-finite value
        keeps the tree's bound on that axis).
    max_cells : int or None
        Most cells of one GP: a region with more is converted in tiles (:class:`TiledOctreeModel`)
        whose GPs each hold at most this many. None: one GP whatever the size.
    max_check : int
        Known voxels scored for the agreement, at most.
    seed : int
        Seed of that sample.
    before_fit : callable, optional
        Called with the most cells one GP will hold (the region's, or the largest tile's) before
        any GP is fitted (a memory check may raise there).
    tile_size : float, optional
        Convert in tiles of this side (metres) whatever the region's size; default only when the
        cells are more than `max_cells`, of the side :class:`TiledOctreeModel` chooses.
    hyperparameters : dict, optional
        variance, length_scale, noise, alpha and beta, used as they are by a tiled conversion (a
        single GP takes its starting values from `model_options`).
    n_workers : int
        Tiles in flight at once (threads).
    **model_options
        :class:`~gpomap.convert.GridGPOM` arguments overriding :func:`gpomap.convert.model_defaults`.

    Returns
    -------
    OctreeConversion

    Raises
    ------
    EmptyDataError
        No known voxels (or one class only) in the training region.
    GpomapError
        An empty region, or a column too dense for `max_cells` even in the smallest tiles.
    InputFormatError
        The file cannot be read (see :func:`gpomap.io.octomap.read_octree`).
    """
    t_start = time.perf_counter()
    tree = source if isinstance(source, Octree) else read_octree(source)
    t_read = time.perf_counter() - t_start
    res = tree.resolution
    lo, hi = region(tree, lower, upper)
    margin = MARGIN_VOXELS * res
    t = time.perf_counter()
    obs, _ = octree_to_observations(tree, lo - margin, hi + margin)
    options = model_defaults(res)
    options["pixel_pad"] = FOOTPRINT_PIXELS * res
    options.update(model_options)
    settings = GridGPOM(**options)
    cells = settings.make_cells(obs)
    t_obs = time.perf_counter() - t
    tiled = tile_size is not None or (max_cells is not None and len(cells) > max_cells)
    out = resolution if resolution is not None else res
    extent = tuple(float(v) for pair in zip(lo, hi) for v in pair)
    check = _inside(obs.points, lo, hi)
    idx = np.flatnonzero(check)
    if idx.size > max_check:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_check, replace=False))
    model: GridGPOM | TiledOctreeModel
    if tiled:
        limit = DEFAULT_MAX_CELLS if max_cells is None else max_cells
        model = TiledOctreeModel(settings, tile_size=tile_size, max_cells=limit, n_workers=n_workers)
        t = time.perf_counter()
        model.fit(obs, hyperparameters)
        t_fit = time.perf_counter() - t
        if before_fit is not None:
            before_fit(model.largest_tile_cells_)
        t = time.perf_counter()
        voxel_map, p_check = model.map_.voxels_and_points(out, extent, obs.points[idx])
        t_pred = time.perf_counter() - t
        t_agree = 0.0  # scored in the same pass over the tiles
    else:
        if before_fit is not None:
            before_fit(len(cells))
        model = settings
        t = time.perf_counter()
        model.fit(obs)
        t_fit = time.perf_counter() - t
        t = time.perf_counter()
        voxel_map = model.grid(out, extent)
        t_pred = time.perf_counter() - t
        t = time.perf_counter()
        p_check = model.predict_proba(obs.points[idx]) if idx.size else np.zeros(0)
        t_agree = time.perf_counter() - t

    agreement: dict[str, Any] = {"n_known": int(check.sum()), "n_checked": int(idx.size)}
    occupied = obs.occupied[idx]
    if occupied.any() and not occupied.all():
        agreement.update(label_agreement(p_check, occupied, model.thresholds_))

    spec: VoxelSpec = voxel_map.spec
    report: dict[str, Any] = {
        "leaves": {"n": tree.n_leaves, "occupied": int(tree.occupied.sum()), "free": int((~tree.occupied).sum())},
        "voxels": {"free": obs.n_free, "occupied": obs.n_occupied, "resolution": res},
        "region": {
            "lower": lo.tolist(),
            "upper": hi.tolist(),
            "train_lower": (lo - margin).tolist(),
            "train_upper": (hi + margin).tolist(),
        },
        "cells": {
            "n": len(cells),
            "occupied": int(cells.occupied.sum()),
            "ambiguous": int(cells.ambiguous.sum()),
            "min_cell": settings.cell_sides(3)[0],
            "max_cell": settings.cell_sides(3)[1],
        },
        "hyperparameters": dict(model.hyperparameters_),
        "agreement": agreement,
        "grid": {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape},
    }
    if isinstance(model, TiledOctreeModel):
        report["tiles"] = {
            "tile_size": model.tile_size_,
            "overlap": model.overlap_,
            "blend": model.blend_,
            "largest_tile_cells": model.largest_tile_cells_,
            **model.last_prediction_,
        }
    report["timings"] = {
        "read": t_read,
        "observations": t_obs,
        "fit": t_fit,
        "prediction": t_pred,
        "agreement": t_agree,
        "total": time.perf_counter() - t_start,
    }
    report["peak_memory_mb"] = peak_rss_mb()
    voxel_map.info = {
        **voxel_map.info,
        "source": "octree conversion",
        "conversion": {k: report[k] for k in report if k not in ("timings", "peak_memory_mb")},
    }
    return OctreeConversion(map=voxel_map, model=model, report=report)
