"""The attributes of a tiled map, typed once for the parts of :class:`~gpomap.tiles.TiledGPOM`.

Each part of the class (a mixin of this package) reads some of them and sets others. The map file
(:mod:`gpomap.io.mapfile`) saves them by these names: a name changed here is a new file format.
"""

from __future__ import annotations

from collections.abc import MutableMapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.counted_cells import CountsNear
from gpomap.fusion import EvidenceCalibration, EvidenceLayer
from gpomap.settings import MapSettings
from gpomap.tiles.points import KeptPoints, _BlockCells, _BlockPoints
from gpomap.tiles.tasks import TileFitTask, TileState


class TiledAttributes:
    """The arguments and fitted state of a :class:`~gpomap.tiles.TiledGPOM`, declared only (the
    instance sets them): a part of the class that reads one need not be the part that sets it."""

    # The arguments (TiledGPOM.__init__), and the map's settings.
    tile_size: float | None
    overlap: float | None
    blend: float | None
    origin: tuple[float, float] | None
    n_workers: int | None
    scheduler: Any
    hyper_sample: int | None
    per_tile_hyperparameters: bool
    blas_threads: int | None
    worker_processes: bool
    scheduler_timeout: float
    memory_limit: float | None
    base: MapSettings
    options: dict[str, Any]
    #: The distributed.Client of the stage running, if any.
    _client: Any

    # Set by fit: the grids, and the observation points per block, their cell trees and extent.
    _dim: int
    tile_size_: float
    origin_: tuple[float, float]
    overlap_: float
    blend_: float
    _clearance: float
    _block_points: dict[int, _BlockPoints]
    _blocks: dict[int, _BlockCells]
    _tiles_with_points: set[int]
    _lower: NDArray[np.float64] | None
    _upper: NDArray[np.float64] | None
    #: Each built block's points' bounds once the clearance is applied (not saved: made again on asking).
    _kept_bounds: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] | None
    _n_points: int
    _n_occupied_points: int
    #: The free samples the free points stand for (more than the points where a scan's were merged by cube).
    _n_free_samples: int
    _n_scans: int
    _n_invalid: int
    _n_no_return: int
    path_: NDArray[np.float64] | None
    _scans: list[Any] | None

    # The fit's results: hyperparameters, calibrations, tiles, ray evidence.
    hyperparameters_: dict[str, float]
    hyper_source_: dict[str, Any]
    extrapolation_: dict[str, Any]
    revisit_: dict[str, Any]
    tiles_: MutableMapping[tuple[int, int], TileState]
    #: Each tile's cells' digest when it was fitted (an update refits a tile only when it changes).
    _signatures: dict[tuple[int, int], tuple[bytes, ...]]
    evidence_: EvidenceLayer | None
    timings_: dict[str, float]

    # Updates: blocks absorbed and not yet rebuilt, tiles waiting for a refit (oldest first), tiles
    # last fitted reusing covariances, and the tiles the last fit or refresh fitted.
    _dirty: set[int]
    _stale: dict[tuple[int, int], None]
    _reused: set[tuple[int, int]]
    last_refit_: list[tuple[int, int]]

    #: Fit each tile when a prediction first needs it (set on a map asked at a few points only).
    _tiles_when_asked: bool = False
    #: The ray counts' calibration to take instead of fitting one (set on a map of part of a log).
    _given_calibration: EvidenceCalibration | None = None
    #: The only points the map will be asked about, shape (m, d): its ray counts are taken at their
    #: cells alone (set, with a given calibration, on a map asked at a few points).
    _asked_at: NDArray[np.float64] | None = None
    #: Another map's points, which this map of some of its scans takes as its own instead of
    #: making them again (set, with given hyperparameters and origin, on a map of part of a log).
    _kept_points: KeptPoints | None = None
    #: Another map's counts round the asked points and the scans it has besides this map's: the
    #: ray counts are taken as its less theirs (set, with `_asked_at`, on a map of part of a log).
    _counted_without: tuple[CountsNear, list[Any]] | None = None
    #: The tasks of the tiles that wait to be asked, by tile (a map fitted with ``_tiles_when_asked``).
    _waiting: dict[tuple[int, int], tuple[TileFitTask]]
