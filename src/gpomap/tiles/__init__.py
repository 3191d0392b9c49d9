"""Tiled MSK-GPOM: maps larger than one GP can hold, as many small GPs blended without seams.

One dense GP over every cell of a real log does not fit (tens of thousands of cells, O(N^3)
time and O(N^2) memory). :class:`TiledGPOM` cuts the plane into square tiles on a fixed grid
(anchored at the map frame's origin, or one tile centred on the data when they fit in one), and
fits one GP per tile on the cells near it:

1. **Observations once** for the whole log (beams to labelled points).
2. **Cells per block**: the points of each block (a square of :data:`BLOCK_SIZE`, or of the tile
   if larger, on the tile grid's origin) get their own cell tree (:func:`gpomap.cells.build_cells`
   on that block's points), whatever the tile size. A block's cells therefore depend only on the
   points inside it, so new data changes the cells of the blocks it falls in and
   nowhere else; that is what makes ``update`` give exactly the batch answer. The trees are cut
   at block borders, which costs a few extra cells there and nothing else.
3. **Hyperparameters once**: the signal variance, length scale, noise, and the squash's alpha and
   beta are learnt by one :class:`~gpomap.gp.SupportGP` on a compact sample of at most
   `hyper_sample` cells (the cells nearest the centroid of a block at the upper quartile of
   cells per block: a dense but typical patch; in planar maps the search treats it as compact
   groups of :data:`HYPER_GROUP_CELLS`, each its own GP), then every tile uses them as they are.
   With ``per_tile_hyperparameters=True`` each tile learns its own instead.
4. **One GP per tile**, fitted on the cells whose boxes meet the tile grown by `overlap` on each
   side. Tiles are independent tasks run in this process, in a local process pool, or on a Dask
   distributed cluster (:func:`fit_tile_task` and :func:`predict_tile_task` are plain picklable
   functions of arrays and settings).
5. **Blending**: a query point is predicted by every tile whose blend region (the core grown by
   `blend` / 2) holds it, with weights that are products of 1-D smoothstep tapers, zero at the
   edge of the blend region and summing to one (a partition of unity); the calibrated latent
   moments ``alpha m + beta`` and ``alpha^2 v`` are averaged with those weights and then
   squashed, so neither probability nor variance jumps at a tile border.

This is the one engine of every MSK-GPOM map, a room or a building, 2-D or 3-D
(:class:`~gpomap.mapping.AreaGPOM` is its scikit-learn style face). A map whose data fall in one
block is one GP over that block's cells.

The package's rooms, from the ground up (TiledGPOM is put together from the mixins):

- :mod:`~gpomap.tiles.geometry`: the tile and block squares on the grid's origin, their keys, how
  far a tile's GP sees (``TileGrid``).
- :mod:`~gpomap.tiles.tasks`: one tile's fit and prediction as picklable functions of arrays.
- :mod:`~gpomap.tiles.store`: the fitted tiles, their factors in memory within a budget.
- :mod:`~gpomap.tiles.points`: a block's points and cells; a log's points held until filed.
- :mod:`~gpomap.tiles.attributes`: the map's arguments and fitted state, typed once.
- :mod:`~gpomap.tiles.executors`: where a stage's tasks run (this process, threads, a process
  pool, a Dask cluster) and the Dask client's lifetime (``TileExecutors``).
- :mod:`~gpomap.tiles.blocks`: points filed under blocks, their cell trees, a tile's cells (``BlockCells``).
- :mod:`~gpomap.tiles.fits`: the tiles' fits as jobs, and the memory they take (``TileFits``).
- :mod:`~gpomap.tiles.hyperparameters`: given and checked, or learnt once on a sample (``HyperparameterSearch``).
- :mod:`~gpomap.tiles.report`: what a fitted map says of itself (``MapReport``).
- :mod:`~gpomap.tiles.blending`: the tiles' latent moments blended (``TileBlending``).
- :mod:`~gpomap.tiles.prediction`: the tiles' blended GP as a fitted map's field (``TiledField``),
  and the map's :class:`~gpomap.fitted.FittedMap` (``MapPrediction.map_``), which answers.
- :mod:`~gpomap.tiles.updates`: new scans absorbed, changed tiles refitted (``TileUpdates``).
- :mod:`~gpomap.tiles.refit`: the map fitted again on part of its data (``Refit``).
- :mod:`~gpomap.tiles.calibration`: the fit's stages that fit further maps of it: the variance
  scale, the ray evidence and its calibration, the later visit (``CalibrationStages``).
- :mod:`~gpomap.tiles.tiled`: :class:`TiledGPOM`, its arguments and its fit in order.

The classes a map file names (:mod:`gpomap.io.mapfile`: :class:`TiledGPOM`, :class:`TileState`,
the blocks' points and cells) give this package as their module, where they are found by name.
"""

from __future__ import annotations

from gpomap.tiles.blending import NEAREST_BOX_PAIRS, nearest_box, taper
from gpomap.tiles.executors import SMALL_PREDICTION_POINTS
from gpomap.tiles.geometry import (
    BLEND_FRACTION,
    BLOCK_SIZE,
    DEFAULT_TILE_SIZE,
    OVERLAP_LENGTH_SCALES,
    block_side,
    capped_overlap,
    tile_reach,
)
from gpomap.tiles.hyperparameters import (
    DEFAULT_HYPER_SAMPLE,
    HYPER_GROUP_CELLS,
    HYPER_NAMES,
    MIN_SAMPLE_OCCUPIED_SHARE,
    UNSEEN_NAMES,
    given_hyperparameters,
    hyper_anchor_block,
)
from gpomap.tiles.points import _BlockCells, _BlockPoints
from gpomap.tiles.store import TileStore, light_tiles
from gpomap.tiles.tasks import TileCells, TileFitTask, TileSettings, TileState, fit_tile_task, predict_tile_task
from gpomap.tiles.tiled import TiledGPOM

__all__ = [
    "BLEND_FRACTION",
    "BLOCK_SIZE",
    "DEFAULT_HYPER_SAMPLE",
    "DEFAULT_TILE_SIZE",
    "HYPER_GROUP_CELLS",
    "HYPER_NAMES",
    "MIN_SAMPLE_OCCUPIED_SHARE",
    "NEAREST_BOX_PAIRS",
    "OVERLAP_LENGTH_SCALES",
    "SMALL_PREDICTION_POINTS",
    "UNSEEN_NAMES",
    "TileCells",
    "TileFitTask",
    "TileSettings",
    "TileState",
    "TileStore",
    "TiledGPOM",
    "_BlockCells",
    "_BlockPoints",
    "block_side",
    "capped_overlap",
    "fit_tile_task",
    "given_hyperparameters",
    "hyper_anchor_block",
    "light_tiles",
    "nearest_box",
    "predict_tile_task",
    "taper",
    "tile_reach",
]
