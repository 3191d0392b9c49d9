"""The map as the robot drives: scans go in one at a time, the map can be read at any moment.

:class:`StreamingGPOM` keeps a :class:`~gpomap.tiles.TiledGPOM` current at a bounded cost per scan.
Each scan is *absorbed* at once (its points filed under their blocks and its rays counted: a few
milliseconds, whatever the size of the map), so the fine ray counts, which carry the detail of the
map where the robot has data, are always up to date. The GP under them is *refreshed* when the map
is read, or when asked: the blocks absorbed since the last refresh get their cell trees rebuilt and
the tiles whose cells changed are refitted, optionally at most ``max_refits`` tiles per refresh
(oldest first), so a reader never waits for more than that many tile fits.

Hyperparameters are learnt once, on the first ``warmup_scans`` scans, or given;
:meth:`StreamingGPOM.relearn` learns them again on every scan so far. The ray-count calibration
is learnt with them and refitted on every scan so far each time the scans have doubled since it
was last fitted (a few warm-up scans calibrate the counts poorly; its points are capped, so each
refit costs about the same and the refits stay a bounded share of the work). After
:meth:`StreamingGPOM.finish` the map equals the batch map of the same scans with the same
hyperparameters (the tests check it to 1e-9).

The class knows nothing of any middleware: ``gpomap stream`` replays logs through it, and the
ROS node is a thin adapter that feeds it scans and publishes its grids.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from gpomap.clouds import CloudScan
from gpomap.errors import NotFittedError
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.lattice import data_extent
from gpomap.scans import Scan, scan_extent

if TYPE_CHECKING:  # the engine is imported when a mapper is made: the CLI's --help stays light
    from gpomap.tiles import TiledGPOM

#: Scans the hyperparameters and the calibration are learnt on before the first map.
DEFAULT_WARMUP_SCANS = 30

#: Tile side of a streaming map, metres: the planar batch map's (``gpomap.tiles.DEFAULT_TILE_SIZE``,
#: not imported here so that the command's ``--help`` needs no SciPy). A refresh refits the tiles
#: round the new scans, and a tile's fit grows with the cube of its cells, so smaller tiles refit
#: faster in all (docs/choices.md, "Streaming maps"); much smaller and the overlap dominates.
DEFAULT_TILE_SIZE = 5.0

#: Change records kept for :meth:`StreamingGPOM.changed_since`; older versions get the whole map.
_CHANGES_KEPT = 10_000

Extent = tuple[float, float, float, float]


def _percentiles(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {"n": 0}
    v = np.asarray(values) * 1e3
    return {
        "n": int(v.size),
        "median_ms": float(np.median(v)),
        "p95_ms": float(np.percentile(v, 95)),
        "max_ms": float(v.max()),
    }


class StreamingGPOM:
    """MSK-GPOM built scan by scan, readable at any time.

    Parameters
    ----------
    warmup_scans : int
        Scans collected before the first fit, which learns the hyperparameters and the ray-count
        calibration (ignored for the hyperparameters when `hyperparameters` is given).
    hyperparameters : dict, optional
        variance, length_scale, noise, alpha and beta to use as they are.
    max_refits : int, optional
        Most tiles refitted by one :meth:`refresh` (and so by one read of the map); the rest
        wait for the next. Default: no limit (every read sees the GP of every scan so far).
    **options
        :class:`~gpomap.tiles.TiledGPOM` options (tile_size, n_workers, ...) and
        map settings (:class:`~gpomap.settings.MapSettings`: kernel, max_cell, evidence_resolution, ...).
        ``n_workers`` defaults to 1: one scan's refits are too small to pay for a process pool;
        ``tile_size`` to :data:`DEFAULT_TILE_SIZE`.

    Attributes
    ----------
    ready_ : bool
        Whether the warm-up is over and the map can be read.
    n_scans_ : int
        Scans added so far.
    model_ : TiledGPOM
        The map being kept (after the warm-up).
    """

    def __init__(
        self,
        warmup_scans: int = DEFAULT_WARMUP_SCANS,
        hyperparameters: dict[str, float] | None = None,
        max_refits: int | None = None,
        **options: Any,
    ) -> None:
        if int(warmup_scans) < 1:
            raise ValueError(f"warmup_scans must be at least 1, got {warmup_scans}")
        if max_refits is not None and int(max_refits) < 1:
            raise ValueError(f"max_refits must be at least 1 (or None for no limit), got {max_refits}")
        self.warmup_scans = int(warmup_scans)
        self.hyperparameters = None if hyperparameters is None else dict(hyperparameters)
        self.max_refits = None if max_refits is None else int(max_refits)
        from gpomap.tiles import TiledGPOM

        self.options = {"n_workers": 1, "tile_size": DEFAULT_TILE_SIZE, **options}
        TiledGPOM(**self.options)  # checks the options now, not at the end of the warm-up
        self._buffer: list[Scan | CloudScan] = []
        self.model_: TiledGPOM | None = None
        self.n_scans_ = 0
        self._version = 0
        self._changes: list[tuple[int, Extent]] = []
        self._add_seconds: list[float] = []
        self._refresh_seconds: list[float] = []
        self._warmup_seconds = 0.0
        self._calibrated_scans = 0

    def __repr__(self) -> str:
        return f"StreamingGPOM(warmup_scans={self.warmup_scans}, max_refits={self.max_refits}, {self.options})"

    # ------------------------------------------------------------------ input
    @property
    def ready_(self) -> bool:
        """Whether the map can be read (the warm-up fit is done)."""
        return self.model_ is not None

    def add_scan(self, scan: Scan | CloudScan) -> None:
        """Add one scan (see :meth:`add_scans`)."""
        self.add_scans([scan])

    def add_scans(self, scans: Sequence[Scan | CloudScan]) -> None:
        """Add scans, in the order the robot took them.

        During the warm-up they are kept until `warmup_scans` have arrived, then the first map
        is fitted on them. After it, each call costs time proportional to the new scans only.

        Parameters
        ----------
        scans : sequence of Scan or CloudScan (one kind throughout)
        """
        scans = list(scans)
        if not scans:
            return
        from gpomap.tiles import TiledGPOM

        t0 = time.perf_counter()
        self.n_scans_ += len(scans)
        if self.model_ is None:
            self._buffer.extend(scans)
            if len(self._buffer) >= self.warmup_scans:
                self.model_ = TiledGPOM(**self.options).fit(self._buffer, self.hyperparameters)
                self._buffer = []
                self._calibrated_scans = self.n_scans_
                self._warmup_seconds = time.perf_counter() - t0
                self._record_change(self._whole_extent())
            return
        self.model_.absorb(scans)
        self._record_change(self._scans_extent(scans))
        self._add_seconds.append((time.perf_counter() - t0) / len(scans))

    def _scans_extent(self, scans: Sequence[Scan | CloudScan]) -> Extent:
        """(xmin, xmax, ymin, ymax) the scans may change: their beams' ends and origins (a cloud's in x, y)."""
        assert self.model_ is not None
        clouds = [c for c in scans if isinstance(c, CloudScan)]
        if not clouds:
            planar = [s for s in scans if isinstance(s, Scan)]
            return scan_extent(planar, include_no_return=True, no_return_cap=self.model_.base.no_return_cap)
        pts = np.concatenate([c.points[c.valid(), :2] for c in clouds] + [np.array([c.origin[:2] for c in clouds])])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])

    # ------------------------------------------------------------------ keeping the GP current
    def _model(self) -> TiledGPOM:
        if self.model_ is None:
            raise NotFittedError(f"the streaming map is still warming up: {len(self._buffer)} of {self.warmup_scans} scans seen")
        return self.model_

    def refresh(self, max_refits: int | None = None) -> list[tuple[int, int]]:
        """Bring the GP up to date with the scans absorbed (at most `max_refits` tile fits).

        Once the scans have doubled since the ray-count calibration was fitted, it is refitted
        on all of them (:meth:`recalibrate`).

        Parameters
        ----------
        max_refits : int, optional
            Default: the `max_refits` the mapper was made with.

        Returns
        -------
        list of (int, int)
            The tiles refitted.
        """
        model = self._model()
        t0 = time.perf_counter()
        refitted = model.refresh(self.max_refits if max_refits is None else max_refits)
        for key in refitted:
            self._record_change(model._blend_region(key))
        if self.n_scans_ >= 2 * self._calibrated_scans:
            self.recalibrate()
        self._refresh_seconds.append(time.perf_counter() - t0)
        return refitted

    def finish(self) -> None:
        """Refit every waiting tile and the ray-count calibration: the batch map of these scans."""
        self._model().refresh(None, exact=True)
        self.recalibrate()

    def recalibrate(self) -> None:
        """Refit the ray-count calibration on every scan so far, against the current GP."""
        model = self._model()
        self._calibrated_scans = self.n_scans_
        if model.evidence_ is not None:
            model.evidence_.recalibrate(model._gp_proba_written)
            self._record_change(self._whole_extent())

    def relearn(self) -> dict[str, float]:
        """Learn the hyperparameters and the calibration again, on every scan so far (a full fit).

        Returns
        -------
        dict
            The new hyperparameters.
        """
        from gpomap.tiles import TiledGPOM

        model = self._model()
        assert model._scans is not None
        self.model_ = TiledGPOM(**self.options).fit(model._scans)
        self._calibrated_scans = self.n_scans_
        self._record_change(self._whole_extent())
        return dict(self.model_.hyperparameters_)

    @property
    def hyperparameters_(self) -> dict[str, float]:
        """The hyperparameters in use."""
        return dict(self._model().hyperparameters_)

    @property
    def pending_tiles_(self) -> int:
        """Blocks and tiles waiting for a refresh (0: the GP has seen every scan)."""
        return self._model().pending_tiles_

    # ------------------------------------------------------------------ change tracking
    def _record_change(self, extent: Extent) -> None:
        self._version += 1
        self._changes.append((self._version, extent))
        if len(self._changes) > _CHANGES_KEPT:
            del self._changes[: len(self._changes) - _CHANGES_KEPT]

    def _whole_extent(self) -> Extent:
        model = self._model()
        assert model._lower is not None and model._upper is not None
        return (float(model._lower[0]), float(model._upper[0]), float(model._lower[1]), float(model._upper[1]))

    @property
    def version_(self) -> int:
        """Counter of changes to the map (scans absorbed, tiles refitted, recalibrations)."""
        return self._version

    def changed_since(self, version: int) -> tuple[int, list[Extent]]:
        """Regions of the map that changed after `version` (a value of :attr:`version_`).

        Parameters
        ----------
        version : int

        Returns
        -------
        version : int
            The current version, to pass next time.
        extents : list of (xmin, xmax, ymin, ymax)
            Regions whose probabilities may have changed; the whole map when `version` is older
            than the changes kept.
        """
        if self._changes and version < self._changes[0][0] - 1:
            return self._version, [self._whole_extent()]
        return self._version, [e for v, e in self._changes if v > version]

    # ------------------------------------------------------------------ reading the map
    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: Literal[False] = False, refresh: bool = True
    ) -> NDArray[np.float64]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: Literal[True], refresh: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    @overload
    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False, refresh: bool = True
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def predict_proba(
        self, points: NDArray[np.float64], return_var: bool = False, refresh: bool = True
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Occupancy probability (and latent variance) at points.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool
        refresh : bool
            Refresh the GP first (at most `max_refits` tiles).

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        model = self._model()
        if refresh:
            self.refresh()
        return model.predict_proba(points, return_var=return_var)

    def predict_ternary(
        self, points: NDArray[np.float64], refresh: bool = True, probability: NDArray[np.float64] | None = None
    ) -> NDArray[np.int8]:
        """Free (0) / unknown (-1) / occupied (1) at points, shape (m,): the written map's call
        (:meth:`gpomap.fitted.FittedMap.predict_ternary`).

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        refresh : bool
            Refresh the GP first (at most `max_refits` tiles).
        probability : ndarray of shape (m,), optional
            :meth:`predict_proba`'s at the same points, when the caller has it already.
        """
        model = self._model()
        if refresh:
            self.refresh()
        return np.asarray(model.predict_ternary(points, probability), dtype=np.int8)

    def default_grid(self, resolution: float | None = None) -> GridSpec:
        """The grid covering every observation, on the ray-count lattice when the resolutions match."""
        model = self._model()
        res = float(model.base.evidence_resolution if resolution is None else resolution)
        xmin, xmax, ymin, ymax = self._whole_extent()
        # Corners on multiples of the resolution: successive maps line up cell for cell, and at
        # the ray counts' resolution the written cells are the counted cells (as a batch map's).
        x0, x1, y0, y1 = data_extent((xmin, ymin), (xmax, ymax), res)
        return GridSpec.from_extent((x0, x1, y0, y1), res, align=True)

    def grid(self, resolution: float | None = None, extent: Extent | None = None, refresh: bool = True) -> OccupancyMap:
        """The map on a grid.

        Parameters
        ----------
        resolution : float, optional
            Cell side, metres; default the ray counts' resolution.
        extent : (xmin, xmax, ymin, ymax), optional
            Default: every observation so far (see :meth:`default_grid`).
        refresh : bool
            Refresh the GP first (at most `max_refits` tiles).

        Returns
        -------
        OccupancyMap
        """
        model = self._model()
        if refresh:
            self.refresh()
        if extent is None:
            spec = self.default_grid(resolution)
            extent = spec.extent
            resolution = spec.resolution
        res = float(model.base.evidence_resolution if resolution is None else resolution)
        om = model.grid(res, extent)
        om.info = {**om.info, "streaming": self.stats()}
        return om

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict[str, Any]:
        """Scans, latency of adding a scan and of a refresh, work waiting."""
        return {
            "n_scans": self.n_scans_,
            "warmup_scans": self.warmup_scans,
            "warmup_seconds": self._warmup_seconds,
            "calibrated_scans": self._calibrated_scans,
            "add_scan": _percentiles(self._add_seconds),
            "refresh": _percentiles(self._refresh_seconds),
            "pending_tiles": self.model_.pending_tiles_ if self.model_ is not None else None,
        }

    def summary(self) -> dict[str, Any]:
        """The model's summary (see :meth:`TiledGPOM.summary`) and the streaming statistics."""
        return {**self._model().summary(), "streaming": self.stats()}
