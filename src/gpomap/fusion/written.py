"""The written grid: the GP sampled coarsely under the counts, and a large planar grid built in bands of rows.

The ray counts give each written cell its detail; the smooth GP under them is sampled every few
cells (:func:`gp_sampling_factor`) and interpolated (:func:`gp_samples`). A planar grid of more
than :data:`~gpomap.resources.WRITTEN_BAND_CELLS` cells is built a band of rows at a time
(:func:`in_bands`), each band waiting in a temporary file until the last is done. The evidence
layer (:meth:`gpomap.fusion.EvidenceLayer.written_grid`) puts the counts on top.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from gpomap.grid import GridSpec, row_bands
from gpomap.lattice import AnyGrid, coarse, grid_centres, grid_dim, interpolate, interpolation_block, make_grid
from gpomap.resources import WRITTEN_BAND_CELLS, SpillFile, release_freed_memory

#: Where ray counts give a written grid its detail, the GP under them is sampled this many times
#: per length scale (at most :data:`MAX_GP_STEP_CELLS` output cells apart) and interpolated
#: bilinearly: a GP varies little within a third of its length scale, and its prediction is the
#: costly part of a fine grid.
GP_SAMPLES_PER_LENGTH_SCALE: int = 3
MAX_GP_STEP_CELLS: int = 4


def gp_sampling_factor(length_scale: float, resolution: float) -> int:
    """Output cells between GP samples of a written grid, from 1 (every cell) to :data:`MAX_GP_STEP_CELLS`."""
    step = length_scale / GP_SAMPLES_PER_LENGTH_SCALE
    return int(min(MAX_GP_STEP_CELLS, max(1, np.floor(step / resolution + 1e-9))))


#: A written map's GP variance is predicted this many GP samples apart and interpolated; its
#: mean at every sample. The variance is what a tile's prediction costs (the whitened
#: cross-covariances, n^2 per point against n for the mean), and it varies over the distance to
#: the data, not over the walls' detail that the mean and the counts carry.
VARIANCE_STEP_SAMPLES: int = 2


def variance_step(length_scale: float, resolution: float) -> float:
    """Metres between a written map's variance samples, whose cells are `resolution` apart."""
    return gp_sampling_factor(length_scale, resolution) * VARIANCE_STEP_SAMPLES * resolution


class BlendedMoments(Protocol):
    """A GP map's calibrated latent moments and their squash (:class:`gpomap.tiles.TiledGPOM`)."""

    def blended_moments(
        self, points: NDArray[np.float64], variance: bool = True
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64], NDArray[np.float64] | None]: ...

    def squash_moments(
        self, num: NDArray[np.float64], den: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...

    def forget_below(self, y: float) -> None: ...


def _variance_apart(moments: BlendedMoments, sampled: AnyGrid) -> tuple[NDArray[np.float64], ...]:
    """The GP's probability, latent variance and probability for unseen space at `sampled`'s
    centres, each (size,), the variances predicted :data:`VARIANCE_STEP_SAMPLES` samples apart."""
    num, _, _, _ = moments.blended_moments(grid_centres(sampled), variance=False)
    apart = coarse(sampled, VARIANCE_STEP_SAMPLES)
    _, den_apart, _, var_apart = moments.blended_moments(grid_centres(apart))
    assert den_apart is not None and var_apart is not None
    den = interpolate(den_apart, apart, sampled).reshape(-1)
    p, p_unseen = moments.squash_moments(num, den)
    return p, interpolate(var_apart, apart, sampled).reshape(-1), p_unseen


def _predict_block(
    predict_gp: Callable[[AnyGrid], tuple[NDArray[np.float64], ...]],
    sampled: AnyGrid,
    block: tuple[slice, ...],
) -> tuple[NDArray[np.float64], ...]:
    """`predict_gp` on `block` of `sampled` only, each result of shape sampled.shape.

    The cells outside the block (the :func:`~gpomap.lattice.coarse` lattice's outer samples,
    which the interpolation reads with weight 0 or not at all; their share is in docs/3d.md)
    take their nearest block cell's values, so that they are finite and the interpolated grid is
    the same as with every sample predicted.

    Parameters
    ----------
    predict_gp : callable
        The block's cells as a grid of their own to arrays of shape (its size,), one value per
        cell in row-major order.
    sampled : GridSpec or VoxelSpec
    block : tuple of slice
        One per array axis (:func:`~gpomap.lattice.interpolation_block`).
    """
    first = [s.start for s in block][::-1]  # array order is coordinate order reversed (x last)
    shape = tuple(s.stop - s.start for s in block)
    inner = make_grid(np.asarray(sampled.origin) + sampled.resolution * np.asarray(first), sampled.resolution, shape[::-1])
    pad = [(s.start, n - s.stop) for s, n in zip(block, sampled.shape, strict=True)]
    return tuple(np.pad(np.asarray(v, dtype=float).reshape(shape), pad, mode="edge").reshape(-1) for v in predict_gp(inner))


#: Points of shape (m, d) to the GP's probability, its latent variance and its probability for
#: unseen space, each (m,).
GPPredict = Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]

#: One band of a written grid, from its first and past-last rows and the band's grid, to its
#: probability, latent variance and the cells beams saw through (or None).
BandBlock = Callable[[int, int, GridSpec], tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]]


def gp_samples(
    grid: AnyGrid, factor: int, predict_gp: GPPredict, moments: BlendedMoments | None
) -> tuple[AnyGrid, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The GP under a written grid, sampled every `factor` cells.

    Parameters
    ----------
    grid : GridSpec or VoxelSpec
    factor : int
        Cells of `grid` between samples (:func:`gp_sampling_factor`).
    predict_gp : callable
        Points of shape (m, d) to the GP's probability, its latent variance and its probability
        for unseen space, each (m,).
    moments : BlendedMoments, optional
        The same GP's moments: the grid then takes the variance :data:`VARIANCE_STEP_SAMPLES`
        samples apart.

    Returns
    -------
    sampled : GridSpec or VoxelSpec
        The samples' lattice (:func:`~gpomap.lattice.coarse`), to interpolate from onto `grid`.
    p, variance, p_unseen : ndarray of shape (sampled size,)
        The GP's probability, latent variance and probability for unseen space at the samples.
    """
    sampled = coarse(grid, factor)
    block = interpolation_block(sampled, grid)
    if grid_dim(grid) == 3 and all(s.stop > s.start for s in block):
        by_grid: Callable[[AnyGrid], tuple[NDArray[np.float64], ...]]
        if moments is None:
            # The block's centres as the whole lattice has them, to the bit.
            d, centres = grid_dim(grid), grid_centres(sampled)
            by_grid = lambda inner: predict_gp(centres.reshape(*sampled.shape, d)[block].reshape(-1, d))  # noqa: E731
        else:
            by_grid = lambda inner: _variance_apart(moments, inner)  # noqa: E731
        p, var, p_unseen = _predict_block(by_grid, sampled, block)
    elif moments is not None and grid_dim(grid) == 2:
        p, var, p_unseen = _variance_apart(moments, sampled)
    else:
        # Every sample, the planar margins too: the tiles' local prediction bins the queries
        # it is given, so another set of queries moves the values by round-off (and a plane's
        # margins are a few rows of hundreds).
        p, var, p_unseen = predict_gp(grid_centres(sampled))
    return sampled, p, var, p_unseen


def band_rows(grid: GridSpec, factor: int) -> int:
    """Rows of one band of a planar written grid whose GP is sampled every `factor` cells: at most
    :data:`~gpomap.resources.WRITTEN_BAND_CELLS` cells, a whole number of variance samples
    (:data:`VARIANCE_STEP_SAMPLES`), at least one."""
    unit = factor * VARIANCE_STEP_SAMPLES
    return max(unit, WRITTEN_BAND_CELLS // grid.shape[1] // unit * unit)


def in_bands(
    grid: GridSpec,
    factor: int,
    block: BandBlock,
    moments: BlendedMoments | None,
    seen: bool,
    finished: Callable[[], None],
) -> SpilledGrid:
    """A planar written grid built in bands of :func:`band_rows` rows, each waiting in a
    temporary file until read (:meth:`SpilledGrid.read`).

    Parameters
    ----------
    grid : GridSpec
    factor : int
        Cells of `grid` between GP samples (:func:`gp_sampling_factor`).
    block : callable
        One band (its first and past-last rows, its grid) to its probability and latent
        variance, each of the band's shape, and the cells beams saw through (or None).
    moments : BlendedMoments, optional
        The GP's moments, told to forget the tiles each band has passed.
    seen : bool
        Whether the grid keeps the cells beams saw through.
    finished : callable
        Called once the last band is built, before the bands are read back: drops what the bands
        shared, so it and the whole grid are never in memory together.

    Returns
    -------
    SpilledGrid
        Its :meth:`~SpilledGrid.read` gives the probability and variance, each of shape
        grid.shape, and the cells beams saw through (None unless `seen`).
    """
    unit = factor * VARIANCE_STEP_SAMPLES
    # Each band's rows wait in a temporary file until the last band is done, so the whole
    # grid (16 bytes a cell) and one band's temporaries are never in memory together
    # (docs/choices.md, "Measured for the code").
    done = SpillFile()
    bands: list[tuple[int, int, tuple[int, int], tuple[int, int], tuple[int, int] | None]] = []
    for start, stop, band in row_bands(grid, band_rows(grid, factor)):
        p, var, seen_band = block(start, stop, band)
        rows_of = (stop - start, *grid.shape[1:])
        kept = done.put(np.broadcast_to(np.asarray(seen_band, dtype=bool), rows_of)) if seen and seen_band is not None else None
        cells = (np.broadcast_to(np.asarray(a, dtype=np.float64), rows_of) for a in (p, var))
        bands.append((start, stop, done.put(next(cells)), done.put(next(cells)), kept))
        del p, var, seen_band
        if moments is not None:
            # The next band's GP samples, and its variance's, reach at most 4.5 samples below its rows.
            moments.forget_below(grid.origin[1] + (stop - 3 * unit) * grid.resolution)
        release_freed_memory()  # the band's tiles' inverses, freed among what the map keeps
    if moments is not None:
        moments.forget_below(np.inf)
    finished()
    release_freed_memory()
    return SpilledGrid(grid.shape, seen, done, bands)


def read_grid(
    made: SpilledGrid | tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
    """A written grid's arrays (:meth:`gpomap.fusion.EvidenceLayer.written_bands`): its bands
    read back when it was made in bands, else as they are."""
    return made.read() if isinstance(made, SpilledGrid) else made


class SpilledGrid:
    """A written grid whose bands wait in a temporary file (:func:`in_bands`), read back whole
    when asked: whatever made them (a building's map, gigabytes) can be let go first.

    Parameters
    ----------
    shape : tuple of int
        The grid's.
    seen : bool
        Whether the bands kept the cells beams saw through.
    done : SpillFile
        Where the bands wait.
    bands : list
        Each band's first and past-last rows and its arrays' places in `done`.
    """

    def __init__(
        self,
        shape: tuple[int, ...],
        seen: bool,
        done: SpillFile,
        bands: list[tuple[int, int, tuple[int, int], tuple[int, int], tuple[int, int] | None]],
    ) -> None:
        self.shape, self.seen, self._done, self._bands = shape, seen, done, bands

    def read(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_] | None]:
        """Probability, latent variance (float64) and the cells beams saw through (or None), each
        of the grid's shape; the file is then closed (a grid is read once)."""
        probability, variance = np.empty(self.shape), np.empty(self.shape)
        seen_through = np.zeros(self.shape, dtype=bool) if self.seen else None
        for start, stop, p_at, var_at, seen_at in self._bands:
            self._done.read_into(p_at, probability[start:stop])
            self._done.read_into(var_at, variance[start:stop])
            if seen_through is not None and seen_at is not None:
                self._done.read_into(seen_at, seen_through[start:stop])
        self._done.close()
        return probability, variance, seen_through
