"""Points filed under their blocks, each block's cell tree, and the cells a tile's GP sees.

A block's cells depend only on the points inside it, so new data rebuild the trees of the blocks
they fall in and nowhere else: that is what makes an update give the batch answer.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.cells import build_cells
from gpomap.lattice import column_bounds
from gpomap.observations import Observations
from gpomap.resources import SpillFile
from gpomap.supports import Supports
from gpomap.tiles.geometry import _KEY_CHUNK, DEFAULT_TILE_SIZE, TileGrid, _box_offset
from gpomap.tiles.points import (
    KeptPoints,
    Part,
    _BlockCells,
    _BlockPoints,
    _HeldParts,
    _KeptBlock,
    _SpilledPart,
    part_rows,
    scan_runs,
)
from gpomap.tiles.tasks import TileCells


class BlockCells(TileGrid):
    """A map's points by block and the cells grown from them (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    def _build_block(self, key: int) -> _BlockCells:
        b = self.base
        points, occupied, weights = self._kept_arrays(key)
        c = build_cells(points, occupied, *b.cell_sides(points.shape[1]), b.cell_box, weights)
        summed = b.area_method == "summed"
        return _BlockCells(
            lower=c.lower,
            upper=c.upper,
            counts=c.counts.astype(float),
            occupied=c.occupied,
            n_ambiguous=int(c.ambiguous.sum()),
            member_points=c.points[c.member_order] if summed else None,
            member_offsets=c.member_offsets if summed else None,
        )

    def _kept_arrays(self, key: int) -> Part:
        """A block's points (shape (n, d)), labels (n,) and weights (n,; None: one each) without
        the free ones near its hits (the points its cells grow from); their bounds noted in
        :attr:`_kept_bounds`."""
        block = self._block_points[key]
        points, occupied, weights = block.weighted_arrays()
        keep = ~block.free_near_hits(self._clearance, (points, occupied))
        # Rebound, so that a spilled block's points read back are let go before the tree's copies.
        points, occupied, weights = part_rows((points, occupied, weights), keep)
        if self._kept_bounds is None:  # a map read from its file keeps none
            self._kept_bounds = {}
        self._kept_bounds[key] = column_bounds(points)
        return points, occupied, weights

    def _add_points(
        self,
        points: NDArray[np.float64],
        occupied: NDArray[np.bool_],
        spill: SpillFile | None = None,
        scans: NDArray[np.integer[Any]] | None = None,
        weights: NDArray[np.int32] | None = None,
    ) -> set[int]:
        """File points under their blocks (in observation order within each) and note their tiles; returns the blocks touched.

        With `spill`, each block's new points wait in that file (:class:`_SpilledPart`) instead of
        in memory. With `scans` (each point's scan, shape (n,), non-decreasing), each block keeps
        its new points' runs (:func:`~gpomap.tiles.points.scan_runs`). With `weights` (shape (n,)),
        how many samples each point stands for."""
        for block in self._block_points.values():
            block.made()  # a map read from its file: its own points first, then those added
        # Keys per chunk of points, blocks then numbered 0..b-1 in key order: a whole log's int64
        # keys and their sorted copy would be hundreds of megabytes.
        chunks = range(0, points.shape[0], _KEY_CHUNK)
        found = [np.zeros(0, dtype=np.int64)]
        for s in chunks:
            part = points[s : s + _KEY_CHUNK]
            self._tiles_with_points.update(self._present_keys(part, self.tile_size_).tolist())
            found.append(self._present_keys(part, self.block_size_))
        block_keys = np.unique(np.concatenate(found))
        if block_keys.size == 1:
            # One block (a room's depth frames, a small log): every point in order, unsorted, and
            # copied only to be held (the caller's arrays are theirs).
            held = (points, occupied, weights)
            if spill is None:
                held = (points.copy(), occupied.copy(), None if weights is None else weights.copy())
            self._file_block(int(block_keys[0]), *held, spill, scans)
            self._count_points(points, occupied, weights)
            return {int(block_keys[0])}
        ids = np.empty(points.shape[0], dtype=np.int16 if block_keys.size <= np.iinfo(np.int16).max else np.int32)
        # Each block's id looked up in a table over the blocks' index box (a search per point
        # where that box is too large for a table).
        table = None
        if block_keys.size:
            bxy = np.column_stack(self._decode(block_keys))
            b_lo, b_hi = column_bounds(bxy)
            b_span = b_hi - b_lo + 1
            if int(b_span[0]) * int(b_span[1]) <= _KEY_CHUNK:
                table = np.zeros(int(b_span.prod()), dtype=ids.dtype)
                table[_box_offset(bxy, b_lo, b_span)] = np.arange(block_keys.size)
        for s in chunks:
            part = points[s : s + _KEY_CHUNK]
            if table is None:
                ids[s : s + _KEY_CHUNK] = np.searchsorted(block_keys, self._block_keys(part))
            else:
                ids[s : s + _KEY_CHUNK] = table[_box_offset(self._square_indices(part, self.block_size_), b_lo, b_span)]
        # Stable (a radix sort for 16-bit ids): keeps observation order per block.
        order = np.argsort(ids, kind="stable")
        cuts = np.cumsum(np.bincount(ids, minlength=block_keys.size))[:-1]
        del ids
        touched = set()
        for k, grp in zip(block_keys.tolist(), np.split(order, cuts)):
            if grp.size == 0:
                continue
            self._file_block(k, *part_rows((points, occupied, weights), grp), spill, None if scans is None else scans[grp])
            touched.add(k)
        self._count_points(points, occupied, weights)
        return touched

    def _file_block(
        self,
        key: int,
        points: NDArray[np.float64],
        occupied: NDArray[np.bool_],
        weights: NDArray[np.int32] | None,
        spill: SpillFile | None,
        scans: NDArray[np.integer[Any]] | None,
    ) -> None:
        """Append a block's new points (shape (n, d), labels (n,), weights (n,) or None, in
        observation order) to it, in `spill` when given, with their scans' runs when `scans`
        (shape (n,)) is."""
        filed: Any = _SpilledPart.put(spill, points, occupied, weights) if spill is not None else points
        labels, held_weights = (None, None) if spill is not None else (occupied, weights)
        runs = None if scans is None else scan_runs(scans)
        if key in self._block_points:
            self._block_points[key].append(filed, labels, runs, held_weights)
        else:
            self._block_points[key] = _BlockPoints(filed, labels, runs, held_weights)

    def _count_points(
        self, points: NDArray[np.float64], occupied: NDArray[np.bool_], weights: NDArray[np.int32] | None = None
    ) -> None:
        """Add points filed (shape (n, d), labels (n,), weights (n,) or None) to the map's extent and counts."""
        if points.shape[0]:
            lo, hi = column_bounds(points)
            self._lower = lo if self._lower is None else np.minimum(self._lower, lo)
            self._upper = hi if self._upper is None else np.maximum(self._upper, hi)
        self._n_points += int(points.shape[0])
        self._n_occupied_points += int(occupied.sum())
        free = ~occupied
        self._n_free_samples += int(np.count_nonzero(free)) if weights is None else int(weights[free].sum(dtype=np.int64))

    def _file_part(self, part: Observations, spill: SpillFile | None, with_scans: bool) -> None:
        """File a part's points under their blocks (:meth:`_add_points`), in `spill` when given;
        `with_scans`, with their scans' runs (points made from scans: a map of some of the scans
        reuses them)."""
        if part.occupied.size:
            scans = np.asarray(part.scan_index) if with_scans else None
            points, occupied = np.asarray(part.points, dtype=float), np.asarray(part.occupied, dtype=bool)
            self._add_points(points, occupied, spill, scans, part.weight)

    def _file_kept(self, kept: KeptPoints) -> tuple[int, int, int, NDArray[np.float64] | None, NDArray[np.float64] | None]:
        """Take a fitted map's blocks without the scans it leaves out (:class:`~gpomap.tiles.points.KeptPoints`)
        as this map's, fitted on the others with the fitted map's origin: the points, blocks and
        tiles that making the points again from those scans would file. Returns the free and
        occupied points, one past the last scan with a point, and the points' bounds."""
        if self.origin is None:
            raise ValueError("a map of another map's points takes its origin")
        self._start_blocks(kept.dim)
        self.origin_ = (float(self.origin[0]), float(self.origin[1]))
        last = -1
        for key, block in kept.blocks.items():
            own = _KeptBlock(block, kept.dropped, kept.clearance)
            points, occupied, weights = own.weighted_arrays()
            if occupied.size == 0:
                continue
            self._block_points[key] = own
            self._tiles_with_points.update(self._present_keys(points, self.tile_size_).tolist())
            self._count_points(points, occupied, weights)
            last = max(last, own.last_scan())
        n_scans = int(np.searchsorted(kept.kept, last)) + 1 if last >= 0 else 0
        n_occupied = self._n_occupied_points
        return self._n_points - n_occupied, n_occupied, n_scans, self._lower, self._upper

    def _start_blocks(self, dim: int) -> None:
        """No points filed yet, for data of `dim` dimensions: the tile side set, the origin not."""
        self._block_points = {}
        self._blocks = {}
        self._tiles_with_points = set()
        self._lower = None
        self._upper = None
        self._kept_bounds = {}
        self._n_points = self._n_occupied_points = self._n_free_samples = 0
        self._dim = dim
        self.tile_size_ = self.tile_size if self.tile_size is not None else DEFAULT_TILE_SIZE[dim]

    def _build_blocks(self, keys: Sequence[int] | None = None) -> None:
        """(Re)build the cell trees of the given blocks (all when None)."""
        if keys is None:
            self._blocks = {}
            self._kept_bounds = {}
            keys = list(self._block_points)
        for k in keys:
            self._blocks[int(k)] = self._build_block(int(k))

    def _blocks_seen_by(self, tile: tuple[int, int]) -> list[int]:
        """Keys of the blocks whose squares meet the tile's grown square (those it gathers cells from)."""
        return [self._encode(*b) for b in self._meeting(*self._grown(self._core(tile)), self.block_size_)]

    def _tiles_seeing(self, block: int) -> list[tuple[int, int]]:
        """The tiles holding points whose grown squares meet the block's square."""
        lo, hi = self._grown(self._square(self._decode(block), self.block_size_))
        return [t for t in self._meeting(lo, hi, self.tile_size_) if self._encode(*t) in self._tiles_with_points]

    def _gather(self, tile: tuple[int, int]) -> TileCells | None:
        """The cells meeting the tile's grown square, in canonical (block key, tree) order."""
        (gx0, gy0), (gx1, gy1) = self._grown(self._core(tile))
        parts = []
        for key in self._blocks_seen_by(tile):
            bc = self._blocks.get(key)
            if bc is None:
                continue
            keep = (bc.lower[:, 0] <= gx1) & (bc.upper[:, 0] >= gx0) & (bc.lower[:, 1] <= gy1) & (bc.upper[:, 1] >= gy0)
            if keep.any():
                parts.append((key, bc, np.flatnonzero(keep)))
        if not parts:
            return None
        parts.sort(key=lambda p: p[0])
        out = TileCells(
            lower=np.concatenate([bc.lower[k] for _, bc, k in parts]),
            upper=np.concatenate([bc.upper[k] for _, bc, k in parts]),
            counts=np.concatenate([bc.counts[k] for _, bc, k in parts]),
            labels=np.concatenate([np.where(bc.occupied[k], 1.0, -1.0) for _, bc, k in parts]),
        )
        if self.base.area_method == "summed":
            sup = [Supports(bc.lower, bc.upper, bc.counts, bc.member_points, bc.member_offsets).subset(k) for _, bc, k in parts]
            from gpomap.supports import concatenate

            s = concatenate(sup)
            out.member_points, out.member_offsets = s.member_points, s.member_offsets
        return out

    def _all_cells(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], list[int]]:
        keys = sorted(self._blocks)
        lo = np.concatenate([self._blocks[k].lower for k in keys])
        hi = np.concatenate([self._blocks[k].upper for k in keys])
        cnt = np.concatenate([self._blocks[k].counts for k in keys])
        lab = np.concatenate([np.where(self._blocks[k].occupied, 1.0, -1.0) for k in keys])
        return lo, hi, cnt, lab, keys


class PointFiling:
    """A log's points, a part at a time as they are made, filed under a map's blocks
    (:meth:`BlockCells._add_points`) as soon as the grid of blocks is settled
    (:meth:`~gpomap.tiles.geometry.TileGrid._settled_origin`), held in `held` until then.

    Past `held`'s budget the blocks keep their points in its spill file, those filed in memory
    before included; so a large log's points are written once, under their blocks. With
    `settled`, the blocks' grid is known already (a map read from its file, its points made
    again): every part is filed as it comes.
    """

    def __init__(self, blocks: BlockCells, held: _HeldParts, settled: bool = False) -> None:
        self.blocks, self.held = blocks, held
        self.filing = settled
        self._started = False

    def __call__(self, part: Observations) -> None:
        """Take the next part."""
        held, blocks = self.held, self.blocks
        crossed = held.count(part)
        if self.filing:
            if crossed:
                assert held.blocks_file is not None
                for block in blocks._block_points.values():
                    block.spill(held.blocks_file)
            blocks._file_part(part, held.blocks_file, held.with_scans)
            return
        held.hold(part)
        if part.occupied.size == 0:
            return
        if not self._started:
            blocks._start_blocks(held.dim)
            self._started = True
        origin = blocks._settled_origin(held.lower, held.upper)
        if origin is not None:
            blocks.origin_, self.filing = origin, True
            for p in held.take():
                blocks._file_part(p, held.blocks_file, held.with_scans)

    def finish(self, lower: NDArray[np.float64] | None, upper: NDArray[np.float64] | None) -> None:
        """After the last part: file what still waits, on the origin of every point's bounds
        `lower`..`upper` (shape (d,) each; None without points)."""
        if self.filing:
            return
        blocks = self.blocks
        blocks._start_blocks(self.held.dim)
        blocks.origin_ = blocks.origin if blocks.origin is not None else blocks._default_origin(lower, upper)
        for p in self.held.take():
            blocks._file_part(p, self.held.blocks_file, self.held.with_scans)
