"""The compiled ray walks (gpomap._compiled_raycast, the fused counts of gpomap._compiled_counts)
against the numpy paths they replace, array for array, to the bit."""

from __future__ import annotations

import numpy as np
import pytest

import gpomap.evidence as evidence
import gpomap.raycast as raycast
from gpomap import _compiled_counts, _compiled_raycast
from gpomap.clouds import CloudScan
from gpomap.evidence import RayEvidence, lattice_grid
from gpomap.grid import GridSpec
from gpomap.observations import ray_free_points
from gpomap.voxels import VoxelSpec

pytestmark = pytest.mark.skipif(not _compiled_raycast.AVAILABLE, reason="numba is not installed")


def _segments(dim: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random segments, some from one sensor, some on grid lines and corners, some of zero length, some off the grid."""
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-1, 1, dim)
    starts = np.vstack([np.broadcast_to(origin, (n, dim)), np.round(rng.uniform(-3, 4, (n, dim)) / 0.1) * 0.1])
    ends = np.vstack([origin + rng.normal(0, 3, (n, dim)), np.round(rng.uniform(-3, 4, (n, dim)) / 0.1) * 0.1])
    ends[n : n + n // 8] = starts[n : n + n // 8]  # zero length
    ends[n + n // 8 : n + n // 4] = starts[n + n // 8 : n + n // 4] + 0.3  # through corners
    ends[n + n // 4 : n + n // 4 + 20, 0] = starts[n + n // 4 : n + n // 4 + 20, 0]  # along a grid plane
    starts[-10:] += 50.0  # far off the grid
    return starts, ends


def _grid(dim: int) -> GridSpec | VoxelSpec:
    if dim == 2:
        return lattice_grid((-2.5, 3.5, -2.0, 3.0), 0.1)
    return VoxelSpec.from_extent(np.array([-2.5, -2.0, -1.0]), np.array([3.5, 3.0, 2.0]), 0.1)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("chunk", [1 << 17, 64])
def test_compiled_traverse_equals_numpys(dim: int, chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # Small chunks put segments at other places within their chunks: the merge key changes with it.
    monkeypatch.setattr(raycast, "ENTRIES_PER_CHUNK", chunk)
    grid = _grid(dim)
    starts, ends = _segments(dim, 3000, seed=dim)
    got = {}
    for compiled in (False, True):
        monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
        got[compiled] = raycast.traverse(grid, starts, ends)
    assert got[False][0].size > 10_000
    for a, b in zip(got[False], got[True], strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_seen_equals_numpys(dim: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", 5000)  # many batches
    starts, ends = _segments(dim, 100, seed=10 + dim)
    rng = np.random.default_rng(dim)
    ev = RayEvidence(starts, ends, rng.uniform(size=len(starts)) < 0.7, np.repeat(np.arange(10), len(starts) // 10))
    grid = _grid(dim)
    got = {}
    for compiled in (False, True):
        monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
        got[compiled] = ev.seen(grid)
    assert 0 < got[True].sum() < got[True].size
    np.testing.assert_array_equal(got[False], got[True])


@pytest.mark.parametrize("budget", [1 << 22, 3000])
@pytest.mark.parametrize("resolution", [0.1, 0.05])
def test_walked_counts_equal_numpys(budget: int, resolution: float, monkeypatch: pytest.MonkeyPatch) -> None:
    # Clouds whose rays end near one another (near misses) and some no-returns; whole batches and
    # small ones, big chunks and small ones: the walked counts are the listed entries' counts.
    monkeypatch.setattr(evidence, "_ENTRIES_PER_BATCH", budget)
    monkeypatch.setattr(raycast, "ENTRIES_PER_CHUNK", 256 if budget < 10_000 else 1 << 17)
    rng = np.random.default_rng(5)
    clouds = []
    for _ in range(6):
        o = rng.uniform([0.5, 0.5, 0.2], [2.0, 2.0, 0.8])
        ends = np.vstack([o + rng.normal(0, 1.0, (300, 3)), rng.uniform([0, 0, 0], [3, 3, 1.5], (300, 3))])
        clouds.append(CloudScan(o, ends, hit=np.linalg.norm(ends - o, axis=1) < 1.6, max_range=1.6))
    ev = RayEvidence.from_scans(clouds)
    grid = lattice_grid(ev.extent(), resolution, margin=resolution)
    got, kept = {}, {}
    for compiled in (False, True):
        monkeypatch.setattr(_compiled_counts, "ENABLED", compiled)
        monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
        ev.forget()
        got[compiled] = ev.counts(grid, keep=np.array([0, 2, 5]))
        kept[compiled] = dict(ev._kept)
    assert got[True].hits.sum() > 0 and 0 < got[True].near.sum() < got[True].misses.sum()
    for a, b in zip(got[False], got[True], strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    # The kept scans' own updates (what a leave-one-scan-out calibration reads) alike.
    assert sorted(k for _, k in kept[True]) == sorted(k for _, k in kept[False]) == [0, 2, 5]
    for key, arrays in kept[False].items():
        assert arrays[0].size > 0
        for a, b in zip(arrays, kept[True][key], strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_free_samples_equal_numpys(dim: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(7)
    n = 2000
    directions = rng.normal(size=(n, dim))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    lengths = rng.uniform(0, 5, n)
    lengths[:50] = 0.2 * rng.integers(0, 10, 50)  # samples landing on the limit
    for origins in (np.broadcast_to(rng.normal(size=dim), (n, dim)), rng.normal(size=(n, dim))):
        got = {}
        for compiled in (False, True):
            monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
            got[compiled] = ray_free_points(origins, directions, lengths, 0.2)
        assert got[True][0].shape[0] > n
        for a, b in zip(got[False], got[True], strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


def test_compiled_voxel_index_equals_numpys(monkeypatch: pytest.MonkeyPatch) -> None:
    # Inside, outside, on voxel faces and corners, non-finite.
    spec = VoxelSpec.from_extent(np.array([-3.0, -2.5, -1.0]), np.array([4.0, 5.0, 3.0]), 0.1)
    rng = np.random.default_rng(11)
    p = rng.uniform(-5, 6, (20_000, 3))
    p[:5] = np.nan
    p[5:10, 1] = np.inf
    p[10:20, 2] = -np.inf
    p[20:200] = np.round(p[20:200] / 0.1) * 0.1
    p[200:210] = spec.lower
    p[210:220] = spec.upper
    got = {}
    for compiled in (False, True):
        monkeypatch.setattr(_compiled_raycast, "ENABLED", compiled)
        got[compiled] = spec.index_of(p)
    assert 0 < got[True][3].sum() < p.shape[0]
    for a, b in zip(got[False], got[True], strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_the_walks_compile_for_c_ordered_writeable_arrays_only() -> None:
    # Every path into the walks, with F-ordered beams and read-only origins as callers hand them:
    # numba compiles a kernel again for each new argument type, the walks it calls with it (seconds
    # of a first run each).
    from numba import types

    # All inside the grid (none left out, which would copy them), in F order.
    rng = np.random.default_rng(3)
    starts, ends = (np.asfortranarray(rng.uniform([-2.0, -1.5], [3.0, 2.5], (390, 2))) for _ in range(2))
    grid = _grid(2)
    ev = RayEvidence(starts, ends, np.ones(len(starts), bool), np.repeat(np.arange(10), 39))
    ev.seen(grid)
    ev.counts(grid, keep=np.array([1]))
    ev.counts(grid, out=evidence.RayCounts(*(np.zeros(grid.shape, np.float32) for _ in evidence.RayCounts._fields)))
    raycast.traverse(grid, starts, ends)
    origins = np.zeros((5, 2))
    origins.flags.writeable = False
    _compiled_raycast.free_samples(origins, np.tile([1.0, 0.0], (5, 1)), np.full(5, 3), 0.1)
    kernels = (
        _compiled_raycast._mark_cells,
        _compiled_raycast._traverse,
        _compiled_raycast._samples,
        _compiled_counts._count_beams,
    )
    for kernel in kernels:
        assert kernel.signatures, kernel
        for signature in kernel.signatures:
            arrays = [t for t in signature if isinstance(t, types.Array)]
            assert all(t.layout == "C" and t.mutable for t in arrays), (kernel, signature)
    # Counts tallied in one type, with a lattice given or not: one compile of the tally.
    assert {str(sig[15].dtype) for sig in _compiled_counts._count_beams.signatures} == {"float32"}
