"""Points filed under blocks: the squares holding them (the compiled pass against the numpy
expression), the block each is filed under (found by hand), and what a fit takes from the blocks
instead of the scans (held-in squares, a kept block's clearance)."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap import _compiled_squares
from gpomap.tiles import TiledGPOM

pytestmark = pytest.mark.skipif(not _compiled_squares.AVAILABLE, reason="numba is not installed")


def _numpy_indices(points: np.ndarray, origin: tuple[float, float], side: float) -> np.ndarray:
    return np.floor((points[:, :2] - np.asarray(origin)) / side).astype(np.int64)


@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_squares_are_the_numpy_expressions_on_borders_and_far_away(dim):
    rng = np.random.default_rng(3)
    side, origin = 5.0, (-12.5, 7.3)
    # Points spread wide, points exactly on square borders and a hair either side of them.
    spread = rng.uniform(-500.0, 500.0, size=(20_000, dim))
    borders = np.stack(np.meshgrid(np.arange(-6, 7) * side + origin[0], np.arange(-6, 7) * side + origin[1]), -1).reshape(-1, 2)
    hair = np.concatenate([borders, np.nextafter(borders, -np.inf), np.nextafter(borders, np.inf)])
    hair = np.column_stack([hair, np.zeros((hair.shape[0], dim - 2))])
    points = np.concatenate([spread, hair])
    got = _compiled_squares.square_indices(points, origin, side)
    assert got.dtype == np.int64 and got.shape == (points.shape[0], 2)
    np.testing.assert_array_equal(got, _numpy_indices(points, origin, side))
    # A strided view (a column slice of a wider array) reads the same points.
    wide = np.column_stack([points, points])
    np.testing.assert_array_equal(_compiled_squares.square_indices(wide[:, dim:], origin, side), got)


@pytest.mark.parametrize("compiled", [True, False])
def test_points_are_filed_under_the_block_that_holds_them(compiled, monkeypatch):
    monkeypatch.setattr(_compiled_squares, "ENABLED", compiled)
    rng = np.random.default_rng(5)
    model = TiledGPOM(tile_size=5.0, origin=(0.0, 0.0), n_workers=1)
    model._start_blocks(2)
    model.origin_ = (0.0, 0.0)
    points = rng.uniform(-23.0, 31.0, size=(5_000, 2))
    occupied = rng.random(5_000) < 0.1
    touched = model._add_points(points, occupied)
    side = model.block_size_
    # Each point's block by hand: the square of the block's side from the origin holding it.
    ix, iy = (np.floor(points[:, k] / side).astype(int) for k in (0, 1))
    want: dict[tuple[int, int], list[int]] = {}
    for i, key in enumerate(zip(ix.tolist(), iy.tolist(), strict=True)):
        want.setdefault(key, []).append(i)
    assert len(touched) == len(want) == len(model._block_points)
    for key, block in model._block_points.items():
        square = tuple(int(v) for v in np.column_stack(model._decode(np.array([key])))[0])
        filed, labels = block.arrays()
        # In observation order within the block, labels with their points.
        np.testing.assert_array_equal(filed, points[want[square]])
        np.testing.assert_array_equal(labels, occupied[want[square]])


def test_a_held_in_square_cut_from_the_blocks_is_the_one_made_from_the_scans():
    # The variance scale's held-in points taken from the blocks the map filed (FiledPoints):
    # the points region_observations cuts from every point at once, each block's in the log's
    # order, and a held-in GP fitted on them answers as on those made again from the scans.
    import gpomap.extrapolation as ex
    from gpomap.heldout import FOLD_STARTS, holdout_stretches
    from gpomap.mapping import AreaGPOM
    from gpomap.observations import ScanPoints
    from gpomap.simulate import paper_room, simulate_scans
    from gpomap.tiles.points import FiledPoints

    world, poses = paper_room()
    scans = simulate_scans(world, poses, 90, max_range=3.0, seed=0)
    settings = AreaGPOM().base
    whole = settings.make_observations(scans, clearance=False)
    made = ScanPoints(scans, settings.free_step, settings.hit_margin, settings.no_return_cap)
    centre = np.median(whole.points[whole.occupied], axis=0)  # a block corner among the walls
    origin = (float(centre[0]), float(centre[1]))
    model = TiledGPOM(tile_size=5.0, origin=origin, n_workers=1)
    model._start_blocks(2)
    model.origin_ = origin
    model._add_points(whole.points, whole.occupied, scans=whole.scan_index)
    filed = model._filed_points(made)
    assert isinstance(filed, FiledPoints) and len(model._block_points) >= 4
    clearance = settings.clearance(2)
    lo, hi = centre - 2.5, centre + 3.0  # a square across the four blocks' corner

    def by_block(points: np.ndarray) -> np.ndarray:
        ij = np.floor((points - centre) / model.block_size_).astype(int)
        return np.argsort(ij[:, 0] * 1000 + ij[:, 1], kind="stable")

    hyperparameters = {"variance": 1.0, "length_scale": 0.5, "noise": 0.1, "alpha": 1.0, "beta": 0.0, "variance_scale": 1.0}
    asked = np.random.default_rng(0).uniform(lo, hi, size=(200, 2))
    for first in FOLD_STARTS:
        kept = holdout_stretches(len(scans), first)[0]
        got = ex._kept_region(filed, kept, lo, hi, clearance)
        want = ex.region_observations(whole, kept, lo, hi, clearance)
        assert want.n_free > 0 and want.n_occupied > 0
        assert len(np.unique(np.floor((want.points - centre) / model.block_size_), axis=0)) == 4
        for a in ("points", "occupied", "scan_index"):
            np.testing.assert_array_equal(getattr(got, a)[by_block(got.points)], getattr(want, a)[by_block(want.points)])
        assert ex._observes_both(filed, len(scans), lo, hi)(kept) == ex._observes_both(made, len(scans), lo, hi)(kept)
        fits = [
            TiledGPOM(tile_size=5.0, origin=origin, n_workers=1, ray_evidence=False).fit(obs, hyperparameters=hyperparameters)
            for obs in (got, want)
        ]
        means = [f.predict(asked, return_var=True) for f in fits]
        for a, b in zip(means[0], means[1], strict=True):
            np.testing.assert_array_equal(a, b)
    # A block whose points came without their scans: the points are made again from the scans.
    model._block_points[next(iter(model._block_points))]._runs = None
    assert model._filed_points(made) is made


@pytest.mark.parametrize("same_clearance", [True, False])
def test_a_kept_block_finds_free_points_near_kept_hits_as_a_block_of_its_own_would(same_clearance):
    # The block of a map of some scans takes which free points are near a hit from the fitted
    # map's block (near a hit there, asked again about the kept hits alone): the answer of the
    # clearance over the kept points, some near dropped hits only among them.
    from gpomap.observations import free_near_hits
    from gpomap.tiles.points import _BlockPoints, _KeptBlock, scan_runs

    rng = np.random.default_rng(4)
    scans = np.sort(rng.integers(0, 12, 4000))
    points = rng.uniform(0.0, 3.0, size=(4000, 2))
    occupied = rng.random(4000) < 0.05
    block = _BlockPoints(points, occupied, scan_runs(scans))
    block.free_near_hits(0.1)
    dropped = np.array([2, 5, 6])
    kept = ~np.isin(scans, dropped)
    own = _KeptBlock(block, dropped, 0.1 if same_clearance else 0.2)
    got = own.free_near_hits(0.1)
    want = free_near_hits(points[kept], occupied[kept], 0.1)
    np.testing.assert_array_equal(got, want)
    # Some free points were near a hit of the dropped scans only.
    assert np.count_nonzero(block._near[kept] & ~want) > 0 and want.any()
