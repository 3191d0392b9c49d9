"""The vectorised traversal against an exact one: rational arithmetic, one segment at a time."""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pytest

import gpomap.raycast as raycast
from gpomap.grid import GridSpec
from gpomap.raycast import traverse
from gpomap.voxels import VoxelSpec


def exact_cells(start: np.ndarray, end: np.ndarray, shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Cells (array order, x last) of one segment in cell units, in order: every t where it
    crosses an integer line, exactly; the cell of the midpoint of each interval of positive length
    (a corner crossed drops the side cells); cells outside `shape` left out."""
    a = [Fraction(float(v)) for v in start]
    b = [Fraction(float(v)) for v in end]
    ts = {Fraction(0), Fraction(1)}
    for u0, u1 in zip(a, b, strict=True):
        if u0 != u1:
            lo, hi = min(u0, u1), max(u0, u1)
            for k in range(math.floor(lo) + 1, math.ceil(hi)):
                ts.add((k - u0) / (u1 - u0))
    t = sorted(ts)
    if a == b:
        t = [Fraction(0), Fraction(1)]
    cells = []
    for t0, t1 in itertools.pairwise(t):
        tm = (t0 + t1) / 2
        cell = tuple(math.floor(u0 + tm * (u1 - u0)) for u0, u1 in zip(a, b, strict=True))[::-1]
        if all(0 <= c < n for c, n in zip(cell, shape, strict=True)):
            cells.append(cell)
    return cells


def _segments(dim: int, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # Random ends (some leaving the grid), ends on quarter-cell lattice points (corners, lines,
    # axis-parallel runs: exact ties between axes), and segments of zero length.
    s = rng.uniform(-2, 10, (n, dim))
    e = rng.uniform(-2, 10, (n, dim))
    q = n // 3
    s[:q] = rng.integers(-4, 40, (q, dim)) / 4
    e[:q] = rng.integers(-4, 40, (q, dim)) / 4
    e[q : q + 5] = s[q : q + 5]
    e[q + 5 : q + 15, 0] = s[q + 5 : q + 15, 0]
    return s, e


@pytest.mark.parametrize("dim", [2, 3])
def test_traversal_equals_the_exact_rational_walk(dim: int) -> None:
    shape = (8, 8) if dim == 2 else (6, 8, 8)
    grid = GridSpec((0.0, 0.0), 1.0, (8, 8)) if dim == 2 else VoxelSpec((0.0, 0.0, 0.0), 1.0, (6, 8, 8))
    starts, ends = _segments(dim, 300, seed=dim)
    beam, *idx = traverse(grid, starts, ends)
    assert np.all(np.diff(beam) >= 0)
    for i in range(len(starts)):
        got = list(zip(*(j[beam == i].tolist() for j in idx), strict=True))
        want = exact_cells(starts[i], ends[i], shape)
        assert got == want, (i, starts[i], ends[i])
    assert len(beam) > 1000


def test_traversal_scaled_grid_and_chunks(monkeypatch: pytest.MonkeyPatch) -> None:
    # A grid of 0.1 m cells away from the origin: the same cells as the unit walk of the scaled
    # segment, in one pass and in chunks of a few entries.
    grid = VoxelSpec((-1.0, 2.0, 0.5), 0.1, (30, 40, 40))
    rng = np.random.default_rng(7)
    starts = rng.uniform([-1, 2, 0.5], [3, 6, 3.5], (60, 3))
    ends = rng.uniform([-1.5, 1.5, 0.0], [3.5, 6.5, 4.0], (60, 3))
    whole = traverse(grid, starts, ends)
    o = np.asarray(grid.origin)
    for i in range(len(starts)):
        got = list(zip(*(j[whole[0] == i].tolist() for j in whole[1:]), strict=True))
        assert got == exact_cells((starts[i] - o) / 0.1, (ends[i] - o) / 0.1, grid.shape)
    monkeypatch.setattr(raycast, "ENTRIES_PER_CHUNK", 40)
    for a, b in zip(whole, traverse(grid, starts, ends), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("dim", [2, 3])
def test_segments_far_from_the_grid_are_left_out_and_the_rest_walk_as_before(dim: int) -> None:
    """Most segments pass beside a small grid (a region's among a log's beams): the same cells
    as the exact walk, and the dropped ones are truly dropped (the filter is exercised)."""
    shape = (8, 8) if dim == 2 else (6, 8, 8)
    grid = GridSpec((0.0, 0.0), 1.0, (8, 8)) if dim == 2 else VoxelSpec((0.0, 0.0, 0.0), 1.0, (6, 8, 8))
    rng = np.random.default_rng(11 + dim)
    starts = rng.uniform(-40, 48, (400, dim))
    ends = starts + rng.uniform(-20, 20, (400, dim))
    ends[:20] = starts[:20]  # points, most outside
    ends[20:60, 0] = starts[20:60, 0]  # parallel to an axis
    starts[60:70] = -1.0 + rng.integers(0, 2, (10, dim)) * (np.array(shape[::-1]) + 2.0)  # on the grown box's corners
    ends[60:70] = starts[60:70] + rng.uniform(-1, 1, (10, dim))
    near = raycast._near_box(starts, ends, shape)
    assert 5 < near.sum() < 390
    beam, *idx = traverse(grid, starts, ends)
    for i in range(len(starts)):
        got = list(zip(*(j[beam == i].tolist() for j in idx), strict=True))
        assert got == exact_cells(starts[i], ends[i], shape), (i, starts[i], ends[i])
        assert near[i] or not got
