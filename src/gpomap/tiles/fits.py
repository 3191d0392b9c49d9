"""The tiles' fits as jobs, and the memory they will take.

Each tile's cells are gathered into a task (:class:`~gpomap.tiles.tasks.TileFitTask`), the tasks
run where the map runs its tasks, and the fitted tiles go into its tile store. Before any costly
stage, a fit whose largest tile's GP, times the GPs fitted at once, would not fit in the memory
allowed is refused.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields

import numpy as np

from gpomap.tiles.blocks import BlockCells
from gpomap.tiles.executors import TileExecutors
from gpomap.tiles.geometry import tile_reach
from gpomap.tiles.tasks import TileCells, TileFitTask, TileSettings, fit_tile_task


class TileFits(BlockCells, TileExecutors):
    """Fits a map's tiles (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    def _settings(self) -> TileSettings:
        b = self.base
        # Every field but these two is the map setting of the same name.
        same = {f.name: getattr(b, f.name) for f in fields(TileSettings) if f.name not in ("area", "per_tile")}
        return TileSettings(area=b.area_method, per_tile=self.per_tile_hyperparameters, **same)

    def _fit_jobs(
        self, tiles: Sequence[tuple[int, int]], reuse: bool = False
    ) -> tuple[list[tuple[tuple[int, int], tuple[TileFitTask]]], dict[tuple[int, int], TileCells]]:
        settings = self._settings()
        jobs, gathered = [], {}
        for t in tiles:
            g = self._gather(t)
            if g is None:
                continue
            gathered[t] = g
            previous = self.tiles_[t] if reuse and t in self.tiles_ else None
            jobs.append((t, (TileFitTask(t, g, settings, self.hyperparameters_, previous),)))
        return jobs, gathered

    def _fit_tiles(self, jobs: list[tuple[tuple[int, int], tuple[TileFitTask]]], desc: str) -> None:
        """Fit the tiles of `jobs` (:func:`~gpomap.tiles.tasks.fit_tile_task`) into the tile store; `desc` names the stage in progress."""
        self._run(fit_tile_task, jobs, "tile fit", desc, into=self.tiles_)

    def _fit_waiting(self, keys: list[tuple[int, int]]) -> None:
        """Fit the tiles of `keys` that wait to be asked (a map fitted with ``_tiles_when_asked``)."""
        if keys:
            self._fit_tiles([(k, self._waiting.pop(k)) for k in keys], "fitting tiles")

    def check_fit_memory(self, length_scale: float) -> int:
        """Refuse tile fits whose largest GP, times the GPs fitted at once, needs more than `memory_limit`.

        Called by :meth:`fit` once the cells are built, before the hyperparameters are learnt:
        a tile's GP is taken to reach past its square by the overlap of `length_scale` (the
        learnt one is not known yet; the overlap is at most a block either way).

        Parameters
        ----------
        length_scale : float
            The length scale the overlap is taken from, metres.

        Returns
        -------
        int
            The largest tile's cells (an estimate: cells are counted by centre).

        Raises
        ------
        MemoryLimitError
            The estimate exceeds the limit.
        """
        from gpomap.resources import check_memory, fit_memory, largest_tile_cells, memory_limit

        overlap = tile_reach(self.tile_size_, length_scale, self.overlap)
        blocks = list(self._blocks.values())
        centres = np.concatenate([0.5 * (b.lower + b.upper)[:, :2] for b in blocks]) if blocks else np.zeros((0, 2))
        per_tile = largest_tile_cells(centres, self.tile_size_, overlap, self.origin_)
        n_at_once = 1 if self.scheduler is not None else self.n_workers_
        limit, source = memory_limit(self.memory_limit)
        check_memory(
            fit_memory(per_tile, n_at_once),
            limit,
            f"fitting {n_at_once} GP(s) of {per_tile} cells at once (the largest of the tiles of {self.tile_size_:g} m)",
            "use a larger --min-cell (min_cell), a smaller --tile-size (tile_size), fewer --workers (n_workers), "
            "or a larger --memory-limit GB (memory_limit) if the machine has the memory",
            source,
        )
        return per_tile
