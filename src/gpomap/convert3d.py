"""From an OctoMap octree to a continuous GP occupancy map: :mod:`gpomap.convert` in 3-D.

An octree already says which voxels are free and which occupied; its leaves are cubes of the
tree's resolution or, where pruning merged eight equal children, of a power of two times it. Each
known leaf is split into the resolution-sized voxels it covers (:meth:`Octree.voxel_centres`), and
each voxel becomes one labelled point at its centre, exactly as :func:`gpomap.convert.grid_to_observations`
makes one point per known pixel; unknown space gives no point. The cell tree then merges
neighbourhoods of same-label voxels into boxes, :class:`gpomap.convert.GridGPOM` widens every box by
half a voxel so that it covers its voxels' cubes (a voxel is a volume observation), the SE GP with
the exact box kernel is fitted with :func:`gpomap.convert.model_defaults` (cell sizes and length
scale in source voxels), and the map is sampled on a voxel grid of any resolution.

Size. One GP holds a few thousand cells, and a real octree gives far more: ``geb079.bt`` (428,144
leaves, 1.14 million known voxels of 0.08 m) makes about 197,000 cells at these settings. A
conversion therefore covers a region (``lower``, ``upper``: a part of the tree), trained on the
known voxels inside it grown by a margin of :data:`MARGIN_VOXELS` voxels (so the map at the
region's faces sees the data beyond them), and is refused with the numbers when the region holds
more than ``max_cells`` cells.

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
from gpomap.convert import FOOTPRINT_PIXELS, GridGPOM, _agreement, model_defaults
from gpomap.errors import EmptyDataError, GpomapError
from gpomap.io.octomap import Octree, read_octree
from gpomap.lattice import in_box
from gpomap.observations import Observations
from gpomap.voxels import VoxelMap, VoxelSpec

__all__ = ["OctreeConversion", "octree_to_observations", "convert_octree", "region", "MARGIN_VOXELS", "DEFAULT_MAX_CELLS"]

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
    model : GridGPOM
        The fitted estimator (``predict_proba(points)`` anywhere, points of shape (m, 3)).
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
    model: GridGPOM
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
        Refuse a region whose cell tree holds more cells than this (None: no limit).
    max_check : int
        Known voxels scored for the agreement, at most.
    seed : int
        Seed of that sample.
    before_fit : callable, optional
        Called with the number of cells once the cell tree is built, before the fit (a memory
        check may raise there).
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
        An empty region, or more cells than `max_cells`.
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
    model = GridGPOM(**options)
    cells = model.make_cells(obs)
    t_obs = time.perf_counter() - t
    if max_cells is not None and len(cells) > max_cells:
        raise GpomapError(
            f"{len(cells)} cells from {len(obs.points)} known voxels in x {lo[0]:.4g}..{hi[0]:.4g}, y {lo[1]:.4g}..{hi[1]:.4g}, "
            f"z {lo[2]:.4g}..{hi[2]:.4g} m (and {margin:g} m around) are more than one GP holds ({max_cells}); "
            "convert a smaller region (--extent, --z-range)"
        )
    if before_fit is not None:
        before_fit(len(cells))
    t = time.perf_counter()
    model.fit(obs)
    t_fit = time.perf_counter() - t

    out = resolution if resolution is not None else res
    t = time.perf_counter()
    voxel_map = model.grid(out, tuple(float(v) for pair in zip(lo, hi) for v in pair))
    t_pred = time.perf_counter() - t

    t = time.perf_counter()
    check = _inside(obs.points, lo, hi)
    idx = np.flatnonzero(check)
    if idx.size > max_check:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_check, replace=False))
    agreement: dict[str, Any] = {"n_known": int(check.sum()), "n_checked": int(idx.size)}
    occupied = obs.occupied[idx]
    if occupied.any() and not occupied.all():
        agreement.update(_agreement(model.predict_proba(obs.points[idx]), occupied, model.thresholds_))
    t_agree = time.perf_counter() - t

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
            "n": len(model.cells_),
            "occupied": int(model.cells_.occupied.sum()),
            "ambiguous": int(model.cells_.ambiguous.sum()),
            "min_cell": float(model.min_cell),
            "max_cell": float(model.max_cell),
        },
        "hyperparameters": dict(model.hyperparameters_),
        "agreement": agreement,
        "grid": {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape},
        "timings": {
            "read": t_read,
            "observations": t_obs,
            "fit": t_fit,
            "prediction": t_pred,
            "agreement": t_agree,
            "total": time.perf_counter() - t_start,
        },
    }
    voxel_map.info = {
        **voxel_map.info,
        "source": "octree conversion",
        "conversion": {k: report[k] for k in report if k != "timings"},
    }
    return OctreeConversion(map=voxel_map, model=model, report=report)
