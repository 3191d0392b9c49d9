"""A map's fitted tiles by key (:class:`TileStore`): their Cholesky factors in memory within a budget, the rest in a temporary file."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Mapping, MutableMapping
from dataclasses import replace
from typing import Any

import numpy as np

from gpomap.resources import TILE_MEMORY, SpillFile, release_freed_memory
from gpomap.tiles.tasks import TileState

#: A factor's place in a state that waits in a :class:`TileStore`'s file.
_NO_FACTOR = np.zeros((0, 0))


class TileStore(MutableMapping[tuple[int, int], TileState]):
    """A map's fitted tiles by key, their Cholesky factors in memory within a budget.

    A building holds thousands of tiles, each with an n x n factor (a megabyte at 380 cells),
    and uses a few hundred at a time: the rows of a written map's band, the tiles round a
    calibration's points. The factors of the tiles read or stored last are kept while they and
    the inverses prediction forms beside them (counted as much again) fit in `budget` bytes; the
    least recently used beyond it wait in a temporary file (:class:`~gpomap.resources.SpillFile`:
    their lower triangle, the rest being zero as factors are, else the whole matrix) and are
    read back when asked, the same numbers to the bit and in the same memory order. Everything
    else of a state (cells, weights, hyperparameters, a few kilobytes) stays in memory:
    :meth:`light` gives it without its factor.

    Reading a tile moves it to the front; the states handed out stay valid whatever is evicted
    after. Safe to use from several threads.

    Parameters
    ----------
    budget : int, optional
        Bytes of factors (twice each factor's size) kept in memory; the last tile stored or read
        is kept whatever its size. Default :data:`gpomap.resources.TILE_MEMORY`.
    tiles : mapping, optional
        States to store first.
    """

    def __init__(self, budget: int | None = None, tiles: Mapping[tuple[int, int], TileState] | None = None) -> None:
        self.budget = int(TILE_MEMORY if budget is None else budget)
        self._light: dict[tuple[int, int], TileState] = {}
        self._resident: OrderedDict[tuple[int, int], TileState] = OrderedDict()
        # Where each factor waiting in the file is: (segment, rows, "C" or "F", lower triangle only).
        self._spilled: dict[tuple[int, int], tuple[tuple[int, int], int, str, bool]] = {}
        self._bytes = 0
        self._peeks = 0
        self._file: SpillFile | None = None
        self._lock = threading.RLock()
        if tiles is not None:
            self.update(tiles)

    @staticmethod
    def _cost(state: TileState) -> int:
        # The factor and the K^-1 a prediction forms beside it (as large).
        return 2 * int(state.posterior.L.nbytes)

    @staticmethod
    def _spillable(L: Any) -> bool:
        return isinstance(L, np.ndarray) and L.ndim == 2 and L.shape[0] == L.shape[1] and L.dtype == np.float64

    def __setitem__(self, key: tuple[int, int], state: TileState) -> None:
        with self._lock:
            self._forget(key)
            if not self._spillable(state.posterior.L):
                self._light[key] = state  # nothing to spill: kept whole
                return
            light = replace(state.posterior, L=_NO_FACTOR, precision=None)
            self._light[key] = TileState(state.key, light, state.hyperparameters, state.seconds)
            self._resident[key] = state
            self._bytes += self._cost(state)
            self._evict()

    def _forget(self, key: tuple[int, int]) -> None:
        state = self._resident.pop(key, None)
        if state is not None:
            self._bytes -= self._cost(state)
        spilled = self._spilled.pop(key, None)
        if spilled is not None and self._file is not None:
            self._file.free(spilled[0])
        self._light.pop(key, None)

    def __delitem__(self, key: tuple[int, int]) -> None:
        with self._lock:
            if key not in self._light:
                raise KeyError(key)
            self._forget(key)

    def __getitem__(self, key: tuple[int, int]) -> TileState:
        with self._lock:
            state = self._resident.get(key)
            if state is not None:
                self._resident.move_to_end(key)
                return state
            if key not in self._spilled:
                return self._light[key]  # kept whole
            state = self._read(key)
            self._resident[key] = state
            self._bytes += self._cost(state)
            self._evict()
            return state

    def peek(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s whole state, as reading it gives, but not kept in memory after (nor moved
        to the front): for a pass over every tile, such as the map file's."""
        with self._lock:
            state = self._resident.get(key)
            if state is not None:
                return state
            if key not in self._spilled:
                return self._light[key]
            self._peeks += 1
            if self._peeks % 256 == 0:
                release_freed_memory()  # the factors read and let go, scattered in the heap
            return self._read(key)

    def _read(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s state with its factor read back from the file."""
        assert self._file is not None
        light = self._light[key]
        where, n, order, lower = self._spilled[key]
        if lower:
            L = np.zeros((n, n), order="F" if order == "F" else "C")
            L[np.tri(n, dtype=bool)] = self._file.get(where, np.float64, (n * (n + 1) // 2,))
        else:
            L = self._file.get(where, np.float64, (n, n))
            if order == "F":
                L = np.asfortranarray(L)
        return TileState(light.key, replace(light.posterior, L=L), light.hyperparameters, light.seconds)

    def _evict(self, budget: int | None = None, keep: int = 1) -> None:
        """Send the least recently used factors to the file until the rest fit in the budget
        (or `budget`), keeping at least `keep`."""
        budget = self.budget if budget is None else budget
        while self._bytes > budget and len(self._resident) > keep:
            key, state = self._resident.popitem(last=False)
            self._bytes -= self._cost(state)
            if key in self._spilled:
                continue  # its factor is in the file already (factors never change)
            L = state.posterior.L
            order = "F" if L.flags.f_contiguous and not L.flags.c_contiguous else "C"
            below = np.tri(L.shape[0], dtype=bool)
            # Bit by bit, so a -0.0 above the diagonal is kept too.
            lower = not np.ascontiguousarray(L).view(np.uint64)[~below].any()
            if self._file is None:
                self._file = SpillFile()
            where = self._file.put(L[below] if lower else np.ascontiguousarray(L))
            self._spilled[key] = (where, int(L.shape[0]), order, lower)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        return iter(list(self._light))

    def __len__(self) -> int:
        return len(self._light)

    def __contains__(self, key: object) -> bool:
        return key in self._light

    def shrink(self) -> None:
        """Send every factor in memory to the file, as if the budget were nothing (a map done
        predicting for now: the files of its written grid come next)."""
        with self._lock:
            self._evict(budget=0, keep=0)

    def light(self, key: tuple[int, int]) -> TileState:
        """Tile `key`'s state without its factor (an empty ``posterior.L``): cells, weights,
        hyperparameters, fit time; never read from the file."""
        return self._light[key]

    def light_states(self) -> list[TileState]:
        """Every tile's :meth:`light` state, in key order of storing."""
        with self._lock:
            return list(self._light.values())

    def resident(self) -> list[TileState]:
        """The states whose factors are in memory now."""
        with self._lock:
            return list(self._resident.values())

    @property
    def spilled_bytes(self) -> int:
        """Bytes of the temporary file (0 while every factor is in memory)."""
        return 0 if self._file is None else self._file.size

    def __reduce__(self) -> tuple[Any, ...]:
        # Pickled whole: a plain dict's worth of states.
        return (TileStore, (self.budget, dict(self.items())))


def light_tiles(tiles: Mapping[tuple[int, int], TileState]) -> Iterable[TileState]:
    """The states of `tiles` as far as their cells, weights and hyperparameters go, without
    reading factors back (:meth:`TileStore.light_states`; a plain dict's own values)."""
    return tiles.light_states() if isinstance(tiles, TileStore) else tiles.values()
