"""Memory estimates and limits, checked before any expensive work starts.

A map request that cannot fit in memory should be refused in a second, with the numbers and the
options that change them, not after a long fit and a ``MemoryError``. The command line (and any
caller) estimates what a run needs from cheap facts known up front — the grid's extent and
resolution, the number of cells per GP — and compares it with a limit, by default half of the
machine's physical memory (:data:`DEFAULT_MEMORY_FRACTION`).

The estimates are deliberately simple upper-bound-ish sums of the large arrays (every constant
below says what it counts). They decide between "fine" and "hopeless", so a factor of two does
not matter; orders of magnitude do: a log with one pose at 1e9 m asks for a grid of 1e16 cells.
"""

from __future__ import annotations

import ctypes
import functools
import math
import os
import sys
import tempfile
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig
from gpomap.errors import GpomapError

__all__ = [
    "BYTES_PER_BAND_CELL",
    "BYTES_PER_FIGURE_CELL",
    "BYTES_PER_MAP_CELL",
    "BYTES_PER_SAMPLE",
    "DEFAULT_MEMORY_FRACTION",
    "FIGURE_CELLS",
    "figure_step",
    "FIT_MATRICES",
    "MemoryLimitError",
    "check_memory",
    "memory_limit",
    "peak_rss_mb",
    "release_freed_memory",
    "TRIM_FREE_BYTES",
    "rss_mb",
    "SpillFile",
    "POINT_MEMORY",
    "TILE_MEMORY",
    "default_memory_limit",
    "fit_memory",
    "format_bytes",
    "grid_memory",
    "grid_shape",
    "largest_tile_cells",
    "points_extent",
    "prediction_chunk_memory",
    "total_memory",
    "BYTES_PER_VOXEL",
    "voxel_grid_memory",
    "WRITTEN_BAND_CELLS",
    "voxel_shape",
]

#: Fraction of the physical memory a run may plan to use by default (``--memory-limit``).
DEFAULT_MEMORY_FRACTION = 0.5

#: Bytes of labelled points (coordinates and labels) a fit keeps in memory: a log with more
#: files them under their blocks in a temporary file (:class:`SpillFile`), each block's read back
#: while its cells are built (a building's log gives tens of millions, a gigabyte).
POINT_MEMORY: int = 256 * 2**20

#: Bytes of fitted tiles' Cholesky factors (with the inverses prediction forms from them) a map
#: keeps in memory; the least recently used beyond it wait in a temporary file
#: (:class:`SpillFile`, :class:`gpomap.tiles.TileStore`), so a building's thousands of tiles
#: cost the memory of the tiles in use, not of the building. A band of a building's written map
#: needs a few hundred tiles' variances, predicted a batch within this at a time.
TILE_MEMORY: int = 128 * 2**20

#: A planar written map is built in bands of rows of at most about this many cells
#: (:meth:`gpomap.fusion.EvidenceLayer.written_grid`): its temporaries (GP samples, counts,
#: distances to hits, :data:`BYTES_PER_BAND_CELL`) then follow the band, not the map: a campus
#: map at 0.05 m has tens of millions of cells (docs/choices.md, "The written map in bands").
WRITTEN_BAND_CELLS: int = 2**20

#: A map's figure draws at most this many cells a side: every k-th row and column of a larger
#: map (:func:`gpomap.plot.plot_map`). A panel is about 600 pixels wide (4 inches at 150 dpi)
#: and nearest-neighbour drawing shows one cell a pixel anyway, while matplotlib draws from float
#: copies of the whole array (docs/choices.md, "Measured for the code").
FIGURE_CELLS: int = 2048

#: Bytes per cell of a written map: probability and variance (float64, 8 + 8), the ternary map
#: and the PGM image (1 + 1), their copies while the NPZ is compressed (8 + 8), and the ray
#: counts of a grid off the counted lattice (an ``--extent``), counted whole (4 x 4).
BYTES_PER_MAP_CELL = 8 + 8 + 1 + 1 + 8 + 8 + 4 * 4

#: Bytes per cell of one band of a written map while it is built (GP samples, ray counts, distances
#: to hits and their interpolations; :data:`WRITTEN_BAND_CELLS` cells a band), measured over a
#: campus map built whole, its 16 bytes a cell of probability and variance among them
#: (docs/choices.md, "The written map in bands").
BYTES_PER_BAND_CELL = 150


def figure_step(shape: tuple[int, int]) -> int:
    """Every how many rows and columns a map of `shape` (ny, nx) is drawn: at most
    :data:`FIGURE_CELLS` cells a side."""
    return -(-max(int(v) for v in shape) // FIGURE_CELLS)


#: Bytes per cell drawn in the map's figure (at most :data:`FIGURE_CELLS` a side):
#: three panels, each normalised to float64 and coloured before resampling (3 x 24).
BYTES_PER_FIGURE_CELL = 3 * 24

#: Bytes per prediction sample of a supersampled grid (``supersample`` K > 1 gives K x K per map
#: cell, predicted at once): its coordinates (2 x 8), latent mean and variance (8 + 8) and
#: probability (8).
BYTES_PER_SAMPLE = 2 * 8 + 8 + 8 + 8

#: Bytes per voxel of a written 3-D map: probability and variance (8 + 8), the ternary layer (1),
#: their copies while the NPZ is compressed (8 + 8), the voxel centres (3 x 8) and the meshgrid
#: they are built from (3 x 8) when the octree and the 3-D view are made, the padded copy marching
#: cubes meshes (8), and the ray counts and interpolated GP of the written grid (8 + 8 + 8).
BYTES_PER_VOXEL = 8 + 8 + 1 + 8 + 8 + 3 * 8 + 3 * 8 + 8 + 8 + 8 + 8

#: Dense n x n float64 matrices alive at once while one GP over n cells is fitted: the Gram
#: matrix, its Cholesky factor, the inverse the squash fit and leave-one-out moments use, and one
#: work array.
FIT_MATRICES = 4

#: Cross-covariance arrays of one prediction chunk (queries x cells): the kernel block, the
#: triangular solve and one work array.
PREDICTION_MATRICES = 3


class MemoryLimitError(GpomapError, MemoryError):
    """A run would need more memory than it is allowed (see :func:`check_memory`)."""


def total_memory() -> int | None:
    """Physical memory of this machine in bytes, or None when it cannot be told.

    Reads ``MemTotal`` from ``/proc/meminfo`` (Linux), else ``SC_PHYS_PAGES * SC_PAGE_SIZE``.
    """
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    return int(pages) * int(size) if pages > 0 and size > 0 else None


def rss_mb() -> float | None:
    """This process's resident memory now, MiB (None where the system does not say: not Linux)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def peak_rss_mb() -> dict[str, float]:
    """Peak resident memory so far, MiB: ``"self"``, this process; ``"children"``, its largest reaped child.

    NaN where the system keeps no such record (Windows). The record is ``getrusage``'s
    ``ru_maxrss``: KiB on Linux, bytes on macOS.
    """
    try:
        import resource  # POSIX only
    except ImportError:
        return {"self": math.nan, "children": math.nan}
    per_mib = 2**20 if sys.platform == "darwin" else 2**10
    return {
        "self": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / per_mib,
        "children": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / per_mib,
    }


def release_freed_memory() -> bool:
    """Hand the memory this process has freed back to the system, when it holds at least
    :data:`TRIM_FREE_BYTES` of it; whether the system was asked.

    glibc's allocator raises its mmap threshold each time a large block is freed, so the arrays of
    one stage that come after (tens of MB each) are carved from the heap, and freed they stay in
    it: gigabytes on a campus log (docs/choices.md, "The map's probabilities for a later
    visit"). ``malloc_trim`` returns them. A no-op (False) where the C library has no such call
    (macOS, Windows, musl); where it cannot say how much is free (glibc before 2.33), it is
    always asked.
    """
    trim = _malloc_trim()
    if trim is None:
        return False
    free = _heap_free_bytes()
    if free is not None and free < TRIM_FREE_BYTES:
        return False
    trim(0)
    return True


#: :func:`release_freed_memory` asks the system only when the allocator holds at least this
#: many bytes free. Pages handed back are faulted in again when the next stage allocates: on a
#: log of a few thousand scans, which frees a hundred MB or two between stages, trimming cost
#: more system time than it saved memory (docs/benchmarks.md, "Trimming the heap").
TRIM_FREE_BYTES: int = 256 * 2**20


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2`` (every field a ``size_t``; ``fordblks``: bytes in free chunks)."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")
    ]


def _heap_free_bytes() -> int | None:
    """Bytes the allocator holds in free chunks, every arena (glibc's ``mallinfo2``); None where unknown."""
    info = _mallinfo2()
    return None if info is None else int(info().fordblks)


@functools.cache
def _libc() -> Any:
    """glibc, or None where it is not there."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


@functools.cache
def _malloc_trim() -> Any:
    """glibc's ``malloc_trim``, or None where it is not there."""
    return getattr(_libc(), "malloc_trim", None)


@functools.cache
def _mallinfo2() -> Any:
    """glibc's ``mallinfo2`` (2.33 and later), returning :class:`_MallInfo2`; None where it is not there."""
    info = getattr(_libc(), "mallinfo2", None)
    if info is not None:
        info.restype = _MallInfo2
    return info


class SpillFile:
    """An unnamed temporary file that arrays are written to and read back from, exactly.

    What a map holds but does not use all at once (the Cholesky factors of tiles not being
    predicted) waits here instead of in memory. The file lives in :func:`tempfile.gettempdir`
    (``TMPDIR``) and disappears with this object or the process. A segment freed (:meth:`free`)
    is reused by the next array of the same size (a refitted tile is often as large as before).
    Safe to use from several threads.
    """

    def __init__(self) -> None:
        self._file: Any = None
        self._end = 0
        self._free: dict[int, list[int]] = {}
        self._lock = threading.Lock()

    @property
    def size(self) -> int:
        """Bytes the file holds, freed segments included."""
        return self._end

    def put(self, array: NDArray[Any]) -> tuple[int, int]:
        """Write `array`'s bytes (C order); returns their (offset, length) for :meth:`get`."""
        data = memoryview(np.ascontiguousarray(array).view(np.uint8).reshape(-1).data)
        n = len(data)
        with self._lock:
            if self._file is None:
                self._file = tempfile.TemporaryFile(prefix="gpomap-spill-")  # noqa: SIM115 (lives with the object)
            reuse = self._free.get(n)
            if reuse:
                offset = reuse.pop()
            else:
                offset, self._end = self._end, self._end + n
        fd = self._file.fileno()
        done = 0
        while done < n:
            done += os.pwrite(fd, data[done:], offset + done)
        return offset, n

    def get(self, where: tuple[int, int], dtype: Any, shape: tuple[int, ...]) -> NDArray[Any]:
        """The array written at `where` (:meth:`put`'s answer), of `dtype` and `shape` (C order)."""
        out = np.empty(where[1], dtype=np.uint8)
        self.read_into(where, out)
        return out.view(dtype).reshape(shape)

    def read_into(self, where: tuple[int, int], out: NDArray[Any]) -> None:
        """Read the array written at `where` into `out` (C-contiguous, as many bytes), in place."""
        offset, n = where
        if n == 0 and out.nbytes == 0:
            return
        if not out.flags.c_contiguous or out.nbytes != n:
            raise ValueError(f"reading {n} bytes into a C-contiguous array of as many, got {out.nbytes} bytes")
        view = memoryview(out.reshape(-1).view(np.uint8).data)
        fd = self._file.fileno()
        done = 0
        while done < n:
            got = os.preadv(fd, [view[done:]], offset + done)
            if got <= 0:
                raise OSError(f"the spill file ended {n - done} bytes short of an array")
            done += got

    def free(self, where: tuple[int, int]) -> None:
        """Let the segment at `where` be written over by a later array of its size."""
        with self._lock:
            self._free.setdefault(where[1], []).append(where[0])

    def close(self) -> None:
        """Delete the file now (it goes with the object otherwise)."""
        with self._lock:
            if self._file is not None:
                self._file.close()
            self._file, self._end, self._free = None, 0, {}


def default_memory_limit(fraction: float = DEFAULT_MEMORY_FRACTION) -> int | None:
    """`fraction` of :func:`total_memory` in bytes (None when the machine's memory is unknown)."""
    total = total_memory()
    return None if total is None else int(fraction * total)


def format_bytes(n: float) -> str:
    """`n` bytes as a short decimal figure: ``"1.5 GB"``, ``"320 MB"``, ``"200 kB"``, ``"8.0e+07 GB"``."""
    gb = n / 1e9
    if gb >= 1e5:
        return f"{gb:.1e} GB"
    if gb >= 1:
        return f"{gb:.1f} GB"
    if n >= 1e6:
        return f"{n / 1e6:.0f} MB"
    return f"{n / 1e3:.0f} kB"


def grid_shape(extent: Sequence[float], resolution: float) -> tuple[int, int]:
    """(ny, nx) of the grid :meth:`gpomap.grid.GridSpec.from_extent` would build, without building it.

    Parameters
    ----------
    extent : (xmin, xmax, ymin, ymax)
        Metres; must be finite.
    resolution : float
        Cell side, metres; must be finite and positive.

    Returns
    -------
    (int, int)
        Rows and columns (Python ints: no overflow however absurd the extent).
    """
    xmin, xmax, ymin, ymax = (float(v) for v in extent)
    if not all(math.isfinite(v) for v in (xmin, xmax, ymin, ymax)):
        raise ValueError(f"extent must be finite, got {tuple(extent)}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"grid resolution must be a positive number, got {resolution}")
    # The same rounding as GridSpec.from_extent: a whole number of cells does not gain one.
    nx = max(1, math.ceil((xmax - xmin) / resolution - 1e-9))
    ny = max(1, math.ceil((ymax - ymin) / resolution - 1e-9))
    return ny, nx


def prediction_chunk_memory(n_cells: int, chunk_size: int = MapConfig.chunk_size) -> int:
    """Bytes of one prediction chunk's cross-covariance arrays: ``chunk_size x n_cells`` float64 each."""
    return PREDICTION_MATRICES * int(chunk_size) * int(n_cells) * 8


def grid_memory(shape: tuple[int, int], supersample: int = 1, n_cells: int = 0, chunk_size: int = MapConfig.chunk_size) -> int:
    """Bytes needed to predict and write a map on a grid of `shape`.

    Parameters
    ----------
    shape : (int, int)
        (ny, nx) of the written grid.
    supersample : int
        Samples per cell side (K x K predictions per cell).
    n_cells : int
        Cells of the largest GP the prediction solves against (0 leaves the chunk term out).
    chunk_size : int
        Query points per prediction chunk.

    Returns
    -------
    int
        ``ny * nx * BYTES_PER_MAP_CELL``, one band's cells times :data:`BYTES_PER_BAND_CELL`,
        the figure's cells times :data:`BYTES_PER_FIGURE_CELL`, with K > 1 ``ny * nx * K^2 *
        BYTES_PER_SAMPLE``, and one chunk's arrays.
    """
    ny, nx = (int(v) for v in shape)
    k = int(supersample)
    cells = ny * nx
    # A band holds WRITTEN_BAND_CELLS cells, or 8 rows of a wider map: its rows are a whole
    # number of the GP's variance samples, two samples of at most four cells (gpomap.fusion).
    band = min(cells, max(WRITTEN_BAND_CELLS, 8 * nx))
    step = figure_step((ny, nx))
    drawn = -(-ny // step) * -(-nx // step)
    samples = cells * k * k * BYTES_PER_SAMPLE if k > 1 else 0
    return (
        cells * BYTES_PER_MAP_CELL
        + band * BYTES_PER_BAND_CELL
        + drawn * BYTES_PER_FIGURE_CELL
        + samples
        + prediction_chunk_memory(n_cells, chunk_size)
    )


def voxel_shape(
    lower: Sequence[float] | NDArray[np.float64], upper: Sequence[float] | NDArray[np.float64], resolution: float
) -> tuple[int, int, int]:
    """(nz, ny, nx) of the grid :meth:`gpomap.voxels.VoxelSpec.from_extent` would build, without building it.

    Parameters
    ----------
    lower, upper : sequence of float, length 3
        Corners (x, y, z), metres; must be finite.
    resolution : float
        Voxel side, metres.

    Returns
    -------
    (int, int, int)
        Python ints (no overflow however absurd the extent); the origin is aligned to a multiple of
        `resolution` as ``from_extent`` aligns it.
    """
    lo = [float(v) for v in lower]
    hi = [float(v) for v in upper]
    if not all(math.isfinite(v) for v in lo + hi):
        raise ValueError(f"voxel extent must be finite, got {lo} .. {hi}")
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"voxel resolution must be a positive number, got {resolution}")
    n = [max(1, math.ceil((h - math.floor(a / resolution + 1e-9) * resolution) / resolution - 1e-9)) for a, h in zip(lo, hi)]
    return n[2], n[1], n[0]


def voxel_grid_memory(shape: tuple[int, int, int], n_cells: int = 0, chunk_size: int = MapConfig.chunk_size) -> int:
    """Bytes needed to predict and write a voxel map of `shape` (nz, ny, nx).

    ``nz * ny * nx * BYTES_PER_VOXEL`` plus one prediction chunk against `n_cells` cells.
    """
    nz, ny, nx = (int(v) for v in shape)
    return nz * ny * nx * BYTES_PER_VOXEL + prediction_chunk_memory(n_cells, chunk_size)


def fit_memory(n_cells: int, n_at_once: int = 1) -> int:
    """Bytes of the dense matrices of `n_at_once` GPs of `n_cells` cells fitted at the same time.

    ``n_at_once * FIT_MATRICES * n_cells^2 * 8``: one GP for a single-GP map, one per worker
    process for tiles (each holding at most the largest tile's cells).
    """
    n = int(n_cells)
    return int(n_at_once) * FIT_MATRICES * n * n * 8


def points_extent(points: NDArray[np.float64]) -> tuple[float, float, float, float]:
    """Bounding box (xmin, xmax, ymin, ymax) of (m, 2) points: a map's default extent."""
    p = np.asarray(points, dtype=float)
    lo, hi = p.min(axis=0), p.max(axis=0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def largest_tile_cells(
    centres: NDArray[np.float64], tile_size: float, overlap: float, origin: tuple[float, float] = (0.0, 0.0)
) -> int:
    """Most cells any one tile's GP sees: cells whose centre lies in a tile grown by `overlap`.

    Parameters
    ----------
    centres : ndarray of shape (n, 2)
        Cell centres.
    tile_size : float
        Tile side, metres.
    overlap : float
        How far past its square a tile's GP reaches, metres.
    origin : (float, float)
        Corner of tile (0, 0).

    Returns
    -------
    int
        An estimate (cells are counted by centre); 0 for no cells.
    """
    c = np.asarray(centres, dtype=float).reshape(-1, 2)
    if c.shape[0] == 0:
        return 0
    reach = float(overlap)
    # Every tile whose grown square holds a centre: the tiles of the centre shifted by -reach..+reach.
    rel = (c - np.asarray(origin, dtype=float)) / tile_size
    lo = np.floor(rel - reach / tile_size).astype(np.int64)
    hi = np.floor(rel + reach / tile_size).astype(np.int64)
    counts: dict[tuple[int, int], int] = {}
    # Each centre touches at most span x span tiles.
    span = int((hi - lo).max()) + 1
    for dx in range(span):
        for dy in range(span):
            tx, ty = lo[:, 0] + dx, lo[:, 1] + dy
            ok = (tx <= hi[:, 0]) & (ty <= hi[:, 1])
            keys, n = np.unique(np.column_stack([tx[ok], ty[ok]]), axis=0, return_counts=True)
            for key, m in zip(map(tuple, keys), n):
                counts[key] = counts.get(key, 0) + int(m)
    return max(counts.values()) if counts else 0


def check_memory(need: int, limit: int | None, what: str, advice: str, limit_source: str = "--memory-limit") -> None:
    """Refuse a run that would need more than `limit` bytes.

    Parameters
    ----------
    need : int
        Estimated bytes.
    limit : int or None
        Allowed bytes; None checks nothing (the machine's memory is unknown and no limit given).
    what : str
        What needs the memory, with its numbers ("a 1000 x 1e10 grid at --resolution 0.1 m ...").
    advice : str
        The options that would bring it down.
    limit_source : str
        How the limit was chosen (see :func:`memory_limit`).

    Raises
    ------
    MemoryLimitError
        When `need` exceeds `limit`.
    """
    if limit is not None and need > limit:
        raise MemoryLimitError(
            f"{what} would need about {format_bytes(need)} of memory, more than the limit of {format_bytes(limit)}"
            f" ({limit_source}); {advice}"
        )


def memory_limit(limit_gb: float | None = None) -> tuple[int | None, str]:
    """The limit in bytes for ``--memory-limit GB`` (None: the default fraction), and how it was chosen."""
    if limit_gb is not None:
        return int(limit_gb * 1e9), f"--memory-limit {limit_gb:g}"
    total = total_memory()
    if total is None:
        return None, "no limit (this machine's memory is unknown)"
    return int(DEFAULT_MEMORY_FRACTION * total), f"{DEFAULT_MEMORY_FRACTION:g} of this machine's {format_bytes(total)}"
