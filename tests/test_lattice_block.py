"""The block of a coarse lattice that interpolation reads, and the written voxel grid that predicts only it."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap import lattice
from gpomap.clouds import CloudScan
from gpomap.fusion import EvidenceLayer
from gpomap.grid import GridSpec
from gpomap.voxels import VoxelSpec


@pytest.mark.parametrize("dim", [2, 3])
def test_values_outside_the_block_do_not_change_the_interpolation(dim: int) -> None:
    rng = np.random.default_rng(dim)
    # Extents that are and are not whole multiples of the coarse step (a target centre on the
    # last source centre reads its upper neighbour with weight 0).
    for shape in ((12, 17, 9)[:dim], (13, 16, 8)[:dim]):
        fine = GridSpec((-1.0, 2.0), 0.05, shape) if dim == 2 else VoxelSpec((-1.0, 2.0, 0.3), 0.05, shape)  # type: ignore[arg-type]
        for factor in (1, 2, 3, 4):
            big = lattice.coarse(fine, factor)
            block = lattice.interpolation_block(big, fine)
            values = rng.uniform(size=big.shape)
            want = lattice.interpolate(values, big, fine)
            other = rng.uniform(-1e6, 1e6, size=big.shape)
            other[block] = values[block]
            np.testing.assert_array_equal(lattice.interpolate(other, big, fine), want)
            if factor > 1:
                assert np.prod([b.stop - b.start for b in block]) < values.size
            # And the block is the least: its first and last cells along each axis are read.
            for axis in range(dim):
                for edge in (block[axis].start, block[axis].stop - 1):
                    changed = values.copy()
                    index = [slice(None)] * dim
                    index[axis] = slice(edge, edge + 1)
                    changed[tuple(index)] += 1.0
                    assert not np.array_equal(lattice.interpolate(changed, big, fine), want)


def test_written_voxel_grid_predicts_the_gp_only_where_it_is_read() -> None:
    rng = np.random.default_rng(0)
    o = np.array([0.5, 0.5, 0.5])
    ends = o + rng.normal(0.0, 0.6, (200, 3))
    scans = [
        CloudScan(o, ends, hit=np.ones(len(ends), bool), max_range=3.0),
        CloudScan(o + 0.1, ends, hit=np.ones(len(ends), bool)),
    ]

    def p_gp(points: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.sin(3 * points[:, 0]) - points[:, 1] * points[:, 2]))

    asked: list[int] = []

    def gp(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        asked.append(len(points))
        p = p_gp(points)
        return p, 0.3 * p + points[:, 2], 0.5 + 0.2 * (p - 0.5)

    layer = EvidenceLayer(scans, 0.1, p_gp)
    grid = VoxelSpec.from_extent(ends.min(axis=0), ends.max(axis=0), 0.1)
    length_scale = 1.2  # 4 cells between GP samples
    got = layer.written_grid(grid, length_scale, gp)
    # Truth: every sample of the coarse lattice predicted, interpolated and fused.
    sampled = lattice.coarse(grid, 4)
    p, var, p_unseen = gp(lattice.grid_centres(sampled))
    want_p = layer.grid_proba(grid, lattice.interpolate(p, sampled, grid), lattice.interpolate(p_unseen, sampled, grid))
    np.testing.assert_array_equal(got[0], want_p)
    np.testing.assert_array_equal(got[1], lattice.interpolate(var, sampled, grid))
    block = lattice.interpolation_block(sampled, grid)
    assert asked[0] == np.prod([s.stop - s.start for s in block]) < asked[1] == np.prod(sampled.shape)


def test_written_voxel_grid_takes_the_variance_two_samples_apart() -> None:
    """With the GP's moments, a voxel map's GP samples take the mean at every sample that is read
    and the variance two samples apart, interpolated trilinearly (checked against scipy's
    interpolator and a squash worked out here)."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.special import ndtr

    from gpomap.fusion import VARIANCE_STEP_SAMPLES

    rng = np.random.default_rng(1)
    o = np.array([0.5, 0.5, 0.5])
    ends = o + rng.normal(0.0, 0.6, (200, 3))
    scans = [CloudScan(o, ends, hit=np.ones(len(ends), bool), max_range=3.0)]

    def mean(points: np.ndarray) -> np.ndarray:
        return np.sin(3 * points[:, 0]) + points[:, 1] * points[:, 2]

    def latent_variance(points: np.ndarray) -> np.ndarray:
        return 0.2 + 0.5 * np.cos(points[:, 0]) ** 2 + 0.3 * points[:, 2] ** 2

    asked = {"mean": 0, "variance": 0}

    class Moments:
        def blended_moments(self, points: np.ndarray, variance: bool = True) -> tuple:
            asked["variance" if variance else "mean"] += len(points)
            v = latent_variance(points) if variance else None
            return 2.0 * mean(points), None if v is None else 4.0 * v, mean(points), v

        def squash_moments(self, num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return ndtr(num / np.sqrt(1.0 + den)), ndtr(num / np.sqrt(1.0 + 3.0 * den))

        def forget_below(self, y: float) -> None:
            pass

    def never(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise AssertionError("the moments answer a grid")

    layer = EvidenceLayer(scans, 0.1, lambda p: 1.0 / (1.0 + np.exp(-mean(p))))
    grid = VoxelSpec.from_extent(ends.min(axis=0), ends.max(axis=0), 0.1)
    got = layer.written_grid(grid, 1.2, never, Moments())  # 4 cells between GP samples
    # Truth: at the samples interpolation reads, the mean there and the variance interpolated
    # from a lattice twice as coarse; the others take the nearest read sample's values.
    sampled = lattice.coarse(grid, 4)
    block = lattice.interpolation_block(sampled, grid)
    centres = lattice.grid_centres(sampled).reshape(*sampled.shape, 3)[block]
    read = centres.reshape(-1, 3)
    step = sampled.resolution * VARIANCE_STEP_SAMPLES
    axes = [np.arange(read[:, k].min() - step, read[:, k].max() + 1.5 * step, step) for k in range(3)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    den = RegularGridInterpolator(axes, 4.0 * latent_variance(nodes).reshape([a.size for a in axes]))(read)
    var = RegularGridInterpolator(axes, latent_variance(nodes).reshape([a.size for a in axes]))(read)
    p, p_unseen = Moments().squash_moments(2.0 * mean(read), den)
    pad = [(b.start, n - b.stop) for b, n in zip(block, sampled.shape, strict=True)]
    spread = [np.pad(v.reshape(centres.shape[:3]), pad, mode="edge") for v in (p, var, p_unseen)]
    want_p = layer.grid_proba(grid, lattice.interpolate(spread[0], sampled, grid), lattice.interpolate(spread[2], sampled, grid))
    np.testing.assert_allclose(got[0], want_p, atol=1e-12)
    np.testing.assert_allclose(got[1], lattice.interpolate(spread[1], sampled, grid), atol=1e-12)
    assert asked["mean"] == len(read) > 2 * asked["variance"] > 0
    assert np.ptp(den) > 0


def test_column_bounds_are_the_least_and_greatest_of_each_column():
    rng = np.random.default_rng(2)
    for a in (rng.normal(size=(1000, 2)), rng.integers(-50, 50, size=(777, 3)), rng.normal(size=(1, 1))):
        lo, hi = lattice.column_bounds(a)
        assert lo.dtype == a.dtype and hi.dtype == a.dtype
        np.testing.assert_array_equal(lo, np.min(a, axis=0))
        np.testing.assert_array_equal(hi, np.max(a, axis=0))
    with pytest.raises(ValueError):
        lattice.column_bounds(np.zeros((0, 2)))


@pytest.mark.parametrize("compiled", [True, False])
def test_column_bounds_of_many_points_on_either_path(monkeypatch, compiled):
    # Enough planar and 3-D points for the compiled pass, a NaN among them (propagated, as
    # numpy's minimum does), a strided view and integers (numpy's path): numpy's bounds exactly.
    from gpomap import _compiled_bounds

    monkeypatch.setattr(_compiled_bounds, "ENABLED", compiled)
    rng = np.random.default_rng(6)
    many = _compiled_bounds.MIN_ROWS * 3
    with_nan = rng.normal(size=(many, 3))
    with_nan[many // 2, 1] = np.nan
    wide = rng.normal(size=(many, 4))
    for a in (rng.normal(size=(many, 2)), rng.uniform(-1e6, 1e6, size=(many, 3)), with_nan, wide[:, 1:], wide[:, :2].astype(int)):
        lo, hi = lattice.column_bounds(a)
        np.testing.assert_array_equal(lo, np.min(a, axis=0))
        np.testing.assert_array_equal(hi, np.max(a, axis=0))
    if compiled:
        assert _compiled_bounds.bounds(with_nan) is None and _compiled_bounds.bounds(wide[:, 1:]) is None
        assert _compiled_bounds.bounds(np.ones((many, 2))) is not None


def test_rows_selects_what_indexing_selects():
    # Masks and indices (repeated, negative, unordered, none), on points of two and three
    # columns, a single column's array and an integer array: the rows numpy's indexing gives.
    rng = np.random.default_rng(4)
    for a in (rng.normal(size=(1000, 2)), rng.integers(-50, 50, size=(777, 3)), rng.normal(size=500)):
        n = a.shape[0]
        for which in (
            rng.random(n) < 0.3,
            np.zeros(n, dtype=bool),
            rng.integers(-n, n, size=300),
            rng.permutation(n),
            np.zeros(0, dtype=np.intp),
        ):
            got = lattice.rows(a, which)
            np.testing.assert_array_equal(got, a[which])
            assert got.dtype == a.dtype and got.shape == a[which].shape
    # Runs of rows, copied as slices: a run, the whole array, a run of one row short of the
    # end, and near-runs (a gap, a repeat, the right span but out of order, past the end).
    a = rng.normal(size=(5000, 3))
    run = lattice.RUN_ROWS
    gap = np.arange(10, 10 + run + 1)
    gap[5] = gap[4]
    swapped = np.arange(run + 1)
    swapped[[3, 4]] = swapped[[4, 3]]
    for which in (np.arange(100, 100 + run), np.arange(5000), np.arange(5000 - run - 1, 4999), gap, swapped):
        got = lattice.rows(a, which)
        np.testing.assert_array_equal(got, a[which])
        got[0] = np.nan  # a copy: the points are untouched
        assert np.all(np.isfinite(a))
    with pytest.raises(IndexError):
        lattice.rows(a, np.arange(5000 - run + 1, 5001))
    # A mask of another length is refused, as indexing refuses it (np.compress would cut it short).
    with pytest.raises(IndexError):
        lattice.rows(np.zeros((5, 2)), np.ones(4, dtype=bool))
    with pytest.raises(IndexError):
        lattice.rows(np.zeros((5, 2)), np.array([5]))


def test_in_box_is_the_closed_box_test_of_every_axis_it_gives():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-2.0, 3.0, size=(5000, 3))
    pts[:50, 0] = 1.0  # on a face: inside (the box is closed)
    pts[50:60, 1] = np.nan  # NaN: outside
    lo, hi = np.array([-1.0, 0.0, 0.5]), np.array([1.0, 2.0, 2.5])
    with np.errstate(invalid="ignore"):
        expected = np.all((pts >= lo) & (pts <= hi), axis=1)
    np.testing.assert_array_equal(lattice.in_box(pts, lo, hi), expected)
    assert expected[:50].any() and not expected[50:60].any()
    # A square bounds 3-D points as a column: their heights are not looked at.
    np.testing.assert_array_equal(
        lattice.in_box(pts, lo[:2], hi[:2]), np.all((pts[:, :2] >= lo[:2]) & (pts[:, :2] <= hi[:2]), axis=1)
    )


@pytest.mark.parametrize("pad", [0, 2])
def test_box_index_is_the_row_major_index_of_the_floored_offsets(pad):
    rng = np.random.default_rng(7)
    pts = rng.uniform(-3.0, 5.0, (500, 3))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    shape = lattice.box_shape(lo, hi, 2.5, pad)
    assert shape == tuple(int(np.floor((h - l) * 2.5)) + 1 + 2 * pad for l, h in zip(lo, hi, strict=True))
    boxes = np.minimum(np.floor((pts - lo) * 2.5).astype(np.int64) + pad, np.array(shape) - 1 - pad)
    want = np.ravel_multi_index(tuple(boxes.T), shape)
    np.testing.assert_array_equal(lattice.box_index(pts, lo, 2.5, shape, pad), want)


@pytest.mark.parametrize("high", [40, 2**15 - 1, 10**6])
def test_stable_order_is_a_stable_argsort(high):
    # Many ties (a stable sort keeps their order), -1 among the keys, and keys that do or do not
    # fit 16 bits: the same order as numpy's stable argsort of int64.
    keys = np.random.default_rng(3).integers(-1, high, 5000)
    np.testing.assert_array_equal(lattice.stable_order(keys), np.argsort(keys, kind="stable"))
    assert lattice.stable_order(np.zeros(0, dtype=np.int64)).size == 0


def test_row_sums_are_numpys_sums_of_each_row_to_the_bit():
    # Columns of very different sizes, where the order of the additions shows in the last bit.
    rng = np.random.default_rng(8)
    for d in (1, 2, 3):
        v = rng.normal(size=(20000, d)) ** 2 * 10.0 ** rng.integers(-8, 8, size=(20000, d))
        np.testing.assert_array_equal(lattice.row_sums(v), v.sum(axis=1))
