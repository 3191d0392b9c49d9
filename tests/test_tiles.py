"""TiledGPOM: seamless blending, one-tile equivalence, incremental = batch, executors, failures."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

import gpomap.lapack as lapack
import gpomap.tiles as tiles
import gpomap.tiles.blending as tile_blending
import gpomap.tiles.executors as tile_executors
import gpomap.tiles.fits as tile_fits
import gpomap.tiles.points as tile_points
import gpomap.tiles.store as tile_store
import gpomap.tiles.tiled as tiled_map
from gpomap.errors import GpomapError
from gpomap.gp import SupportGP
from gpomap.observations import Observations
from gpomap.settings import MapSettings
from gpomap.simulate import World, paper_room_scans, simulate_scans
from gpomap.supports import Supports
from gpomap.tiles import TiledGPOM, taper

# Fixed hyperparameters keep the tests fast and the comparisons exact.
OPTS = dict(kernel="se", free_step=0.5, min_cell=0.5, max_cell=3.0, optimise=False, length_scale=1.0, noise=0.1)
MARKER_ENV = "GPOMAP_TEST_DIE_MARKER"
_REAL_FIT = tiles.fit_tile_task


@pytest.fixture(scope="module")
def room():
    return paper_room_scans()


def _corridor_scans():
    # Two long walls along x with a post, crossing the tile border at x = 6.
    world = World(
        segments=[(0.0, 0.0, 12.0, 0.0), (0.0, 3.0, 12.0, 3.0)], obstacles=[[(7.5, 1.2), (8.0, 1.2), (8.0, 1.7), (7.5, 1.7)]]
    )
    xs = np.linspace(0.5, 11.5, 12)
    poses = np.column_stack([xs, np.full_like(xs, 1.5), np.zeros_like(xs)])
    return simulate_scans(world, poses, 72, max_range=8.0, seed=0)


def test_taper_is_partition_of_unity():
    x = np.linspace(-3.0, 13.0, 1601)
    total = sum(taper(x, a, a + 4.0, 1.0) for a in np.arange(-8.0, 16.0, 4.0))
    assert np.allclose(total, 1.0)


def test_a_map_in_one_block_is_one_gp_over_its_cells(room):
    tiled = TiledGPOM(tile_size=50.0, origin=(-1.0, -1.0), n_workers=1, hyper_sample=10**6, **OPTS).fit(room)
    assert len(tiled.tiles_) == 1
    # The reference: the cell tree over all the points and one GP on it, built by hand.
    settings = MapSettings(**OPTS)
    cells = settings.make_cells(settings.make_observations(room))
    lower, upper, labels = tiled.cell_boxes()
    np.testing.assert_array_equal(lower, cells.lower)
    np.testing.assert_array_equal(upper, cells.upper)
    np.testing.assert_array_equal(labels, cells.labels)
    gp = SupportGP(settings.make_kernel(), noise=OPTS["noise"], noise_model=settings.noise_model, optimise=False)
    gp.fit(cells.to_supports(), cells.labels)
    # Fixed hyperparameters; alpha and beta fitted on the same leave-one-out moments.
    hyp = tiled.hyperparameters_
    assert (hyp["length_scale"], hyp["noise"]) == (OPTS["length_scale"], OPTS["noise"])
    assert (hyp["alpha"], hyp["beta"]) == pytest.approx((gp.squash.alpha, gp.squash.beta), rel=1e-9)
    pts = np.random.default_rng(0).uniform([-1.0, -1.0], [21.0, 17.0], (500, 2))
    # The same prediction (local where it pays, as the tile's) as the one GP's.
    mean, var = gp.predict_latent(Supports.from_points(pts))
    mu_t, var_t = tiled.predict(pts, return_var=True)
    np.testing.assert_allclose(mu_t, mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(var_t, var, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tiled.predict_proba_gp(pts), gp.squash(mean, var), rtol=0, atol=1e-10)


def test_a_map_smaller_than_a_tile_is_one_tile_centred_on_it(room):
    points = MapSettings(**OPTS).make_observations(room).points
    lo, hi = points.min(axis=0), points.max(axis=0)
    side = float(np.max(hi - lo)) + 0.5  # one tile holds the whole room
    model = TiledGPOM(tile_size=side, n_workers=1, **OPTS).fit(room)
    x0, y0 = model.origin_
    assert len(model.tiles_) == 1
    # The tile's centre is the data's: the same margin on both sides of each axis.
    np.testing.assert_allclose([x0 + side / 2, y0 + side / 2], (lo + hi) / 2, atol=1e-12)
    assert model.summary()["tile_origin"] == [x0, y0]
    # The same tiles on a grid through the room's middle: four squares, four GPs.
    cut = TiledGPOM(tile_size=side, origin=tuple((lo + hi) / 2), n_workers=1, **OPTS).fit(room)
    assert len(cut.tiles_) == 4
    # Data wider than a tile: the grid is the map frame's.
    wide = TiledGPOM(tile_size=0.75 * side, n_workers=1, **OPTS).fit(room)
    assert wide.origin_ == (0.0, 0.0)


def test_a_map_within_one_block_is_one_cell_tree_whatever_the_tiles(room):
    # A 7 m square of the room's points across the map frame's block border x = 10: wider than 3 m
    # tiles, narrower than a block.
    obs = MapSettings(**OPTS).make_observations(room)
    sel = np.all((obs.points >= [6.5, 4.0]) & (obs.points < [13.5, 11.0]), axis=1)
    part = Observations(obs.points[sel], obs.occupied[sel], obs.scan_index[sel])
    small = TiledGPOM(tile_size=3.0, n_workers=1, **OPTS).fit(part)
    one = TiledGPOM(tile_size=tiles.BLOCK_SIZE, n_workers=1, **OPTS).fit(part)
    assert len(small.tiles_) > 1 and len(one.tiles_) == 1
    # The block is centred on the data, as the one big tile is: the same single cell tree.
    centre = 0.5 * (part.points.min(axis=0) + part.points.max(axis=0))
    np.testing.assert_allclose(np.asarray(small.origin_) + tiles.BLOCK_SIZE / 2, centre, atol=1e-12)
    for a, b in zip(one.cell_boxes(), small.cell_boxes()):
        np.testing.assert_array_equal(a, b)


def _max_jump_ratio(values: np.ndarray, border_step: int, k: int = 5) -> float:
    d = np.abs(np.diff(values))
    neighbours = np.concatenate([d[border_step - k : border_step], d[border_step + 1 : border_step + 1 + k]])
    return float(d[border_step] / (neighbours.max() + 1e-12))


def test_blending_has_no_seam():
    scans = _corridor_scans()
    model = TiledGPOM(tile_size=6.0, overlap=2.5, origin=(0.0, 0.0), n_workers=1, **OPTS).fit(scans)
    assert len(model.tiles_) >= 2
    x = np.linspace(4.0, 8.0, 401) + 0.005  # 1 cm steps; the border x = 6 falls inside one step
    border = int(np.searchsorted(x, 6.0)) - 1
    for y in (0.0, 0.1, 1.5, 2.9):  # on a wall, near it, in the free corridor, near the other wall
        pts = np.column_stack([x, np.full_like(x, y)])
        # The GP layer: the ray counts on top change cell by cell by design, tiles or not.
        p, var = model.predict_proba_gp(pts, return_var=True)
        assert _max_jump_ratio(p, border) < 2.0, y
        assert _max_jump_ratio(var, border) < 2.0, y
    # A hard switch between tiles with a short overlap does jump: the check above sees seams.
    hard = TiledGPOM(tile_size=6.0, overlap=0.5, blend=1e-6, origin=(0.0, 0.0), n_workers=1, **OPTS).fit(
        scans, hyperparameters=model.hyperparameters_
    )
    p_hard = hard.predict_proba_gp(np.column_stack([x, np.full_like(x, 0.1)]))
    assert _max_jump_ratio(p_hard, border) > 5.0


def test_the_hyperparameter_sample_is_anchored_in_a_mixed_block():
    # Cells per block; the upper quartile is 692.5, nearest it the 690-cell block (index 2).
    sizes = [100, 700, 690, 300]
    # That block is an open hall (2 % occupied, under half the map's 20 %): the next nearest, 700.
    assert tiles.hyper_anchor_block(sizes, [0.3, 0.25, 0.02, 0.3], 0.2) == 1
    assert tiles.hyper_anchor_block(sizes, [0.3, 0.25, 0.15, 0.3], 0.2) == 2
    # No block mixed enough: by size alone.
    assert tiles.hyper_anchor_block(sizes, [0.0, 0.0, 0.0, 0.0], 0.2) == 2


def test_tiles_smaller_than_a_block_keep_its_cells_and_hyperparameters(room):
    # The cell trees are grown per block of BLOCK_SIZE whatever the tiles: 4 m tiles give the very
    # cells of 10 m ones and the same learnt hyperparameters.
    opts = {**OPTS, "optimise": True}
    points = MapSettings(**OPTS).make_observations(room)  # labelled points: no variance scale to fit
    big = TiledGPOM(tile_size=tiles.BLOCK_SIZE, origin=(0.0, 0.0), n_workers=1, hyper_sample=200, **opts).fit(points)
    small = TiledGPOM(tile_size=4.0, origin=(0.0, 0.0), n_workers=1, hyper_sample=200, **opts).fit(points)
    assert len(small.tiles_) > len(big.tiles_)
    for a, b in zip(big.cell_boxes(), small.cell_boxes()):
        np.testing.assert_array_equal(a, b)
    for name in tiles.HYPER_NAMES:
        assert small.hyperparameters_[name] == big.hyperparameters_[name], name
    # Both approximate the GP over all those cells as closely: here a tile seeing 10 m round it.
    hyp = big.hyperparameters_
    one = TiledGPOM(tile_size=tiles.BLOCK_SIZE, overlap=10.0, origin=(0.0, 0.0), n_workers=1, **opts).fit(
        room, hyperparameters=hyp
    )
    pts = np.random.default_rng(1).uniform([0.0, 0.0], [20.0, 16.0], (400, 2))
    exact = one.predict(pts)
    error_big = np.mean(np.abs(big.predict(pts) - exact))
    error_small = np.mean(np.abs(small.predict(pts) - exact))
    assert error_small < 1.1 * error_big


def test_update_equals_batch(room):
    a, b = room[:14], room[14:]
    inc = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=1, **OPTS)
    inc.update(a)  # fit
    n_before = len(inc.tiles_)
    inc.update(b)
    assert 0 < len(inc.last_refit_) <= len(inc.tiles_)
    # The tile grid was placed by the first fit (on scans a only); the batch map uses the same one.
    batch = TiledGPOM(tile_size=6.0, overlap=2.5, origin=inc.origin_, n_workers=1, **OPTS)
    batch.fit(room, hyperparameters=inc.hyperparameters_)
    assert sorted(batch.tiles_) == sorted(inc.tiles_)
    extent = (0.0, 20.0, 0.0, 16.0)
    gi, gb = inc.grid(0.25, extent), batch.grid(0.25, extent)
    np.testing.assert_allclose(gi.probability, gb.probability, rtol=0, atol=1e-10)
    np.testing.assert_allclose(gi.variance, gb.variance, rtol=0, atol=1e-10)
    # One more scan touches only the tiles round it.
    inc.update(room[-1:])
    assert len(inc.last_refit_) < len(inc.tiles_)
    assert n_before <= len(inc.tiles_)


def _dying_fit(task):
    """Kill the worker process the first time tile (1, 1) is fitted (marker file records it)."""
    marker = Path(os.environ[MARKER_ENV])
    if tuple(task.key) == (1, 1) and not marker.exists():
        marker.write_text("died")
        os._exit(17)
    return _REAL_FIT(task)


def _always_failing_fit(task):
    if tuple(task.key) == (1, 1):
        raise RuntimeError("disk on fire")
    return _REAL_FIT(task)


@pytest.fixture(scope="module")
def reference(room):
    # One BLAS thread, as each of the 2 pool (and Dask) workers on 2 cores: the same arithmetic,
    # so the maps agree to the last bit. With other thread counts the tiles' GP still agrees to
    # ~1e-14; the ray-evidence calibration and the variance scale fitted on top are converged
    # tightly (an exact gradient, a tight tolerance), so such last bits move them by ~1e-12, not
    # the ~1e-5 of searches that stopped early.
    with threadpool_limits(1):
        model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=1, **OPTS).fit(room)
        return model.hyperparameters_, model.grid(0.25, (0.0, 20.0, 0.0, 16.0))


def _same(grid_a, grid_b):
    np.testing.assert_allclose(grid_a.probability, grid_b.probability, rtol=0, atol=1e-10)
    np.testing.assert_allclose(grid_a.variance, grid_b.variance, rtol=0, atol=1e-10)


@pytest.mark.parametrize("worker_processes", [False, True])
def test_worker_threads_and_processes_match_in_process(room, reference, worker_processes):
    hyp, ref = reference
    model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, worker_processes=worker_processes, **OPTS)
    _same(model.fit(room, hyperparameters=hyp).grid(0.25, (0.0, 20.0, 0.0, 16.0)), ref)
    assert model.summary()["executor"] == ("process pool x2" if worker_processes else "threads x2")


def test_a_prediction_of_few_points_runs_in_process_and_of_many_on_the_threads(room, reference, monkeypatch):
    hyp, _ = reference
    model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, **OPTS).fit(room, hyperparameters=hyp)
    stages = []
    real = TiledGPOM._run_threads

    def recording(self, fn, jobs, bar, what):
        stages.append((what, sum(len(args[1]) for _, args in jobs)))
        return real(self, fn, jobs, bar, what)

    monkeypatch.setattr(TiledGPOM, "_run_threads", recording)
    rng = np.random.default_rng(0)
    # A point in the blend of tiles is predicted by each (up to four): a quarter is surely few.
    few = rng.uniform((0.0, 0.0), (20.0, 16.0), (tiles.SMALL_PREDICTION_POINTS // 4 - 1, 2))
    many = rng.uniform((0.0, 0.0), (20.0, 16.0), (tiles.SMALL_PREDICTION_POINTS, 2))
    p_few = model.predict_proba(few)
    assert stages == []  # not a single stage on the threads
    model.predict_proba(many)
    assert [w for w, _ in stages] == ["tile prediction"] and stages[0][1] >= tiles.SMALL_PREDICTION_POINTS
    # The same numbers on the threads: the few points again, with no stage kept in process.
    monkeypatch.setattr(tile_executors, "SMALL_PREDICTION_POINTS", 0)
    np.testing.assert_allclose(model.predict_proba(few), p_few, rtol=0, atol=1e-12)
    assert len(stages) == 2


def test_pool_workers_inherit_the_tile_states_instead_of_receiving_them(room, reference, monkeypatch):
    # Forked workers read a stage's tasks from the memory they inherit: predicting never pickles
    # a tile's state (its Cholesky factor), only the tiles' answers come back.
    hyp, ref = reference
    model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, worker_processes=True, **OPTS).fit(room, hyperparameters=hyp)

    def no_pickling(self, protocol):
        raise AssertionError("a tile state was pickled")

    monkeypatch.setattr(tiles.TileState, "__reduce_ex__", no_pickling, raising=False)
    _same(model.grid(0.25, (0.0, 20.0, 0.0, 16.0)), ref)
    assert not tile_executors._INHERITED  # the stage's tasks let go


def test_dead_worker_is_retried(room, reference, tmp_path, monkeypatch):
    hyp, ref = reference
    marker = tmp_path / "died"
    monkeypatch.setenv(MARKER_ENV, str(marker))
    monkeypatch.setattr(tile_fits, "fit_tile_task", _dying_fit)
    model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, worker_processes=True, **OPTS).fit(room, hyperparameters=hyp)
    assert marker.exists()  # a worker really died
    assert (1, 1) in model.tiles_
    _same(model.grid(0.25, (0.0, 20.0, 0.0, 16.0)), ref)


@pytest.mark.parametrize("n_workers", [1, 2])
def test_failing_tile_raises_naming_it(room, reference, monkeypatch, n_workers):
    hyp, _ = reference
    monkeypatch.setattr(tile_fits, "fit_tile_task", _always_failing_fit)
    with pytest.raises(GpomapError, match=r"tile \(1, 1\).*disk on fire"):
        TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=n_workers, **OPTS).fit(room, hyperparameters=hyp)


def test_dask_local_cluster_matches_in_process(room, reference, tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    hyp, ref = reference
    marker = tmp_path / "died"
    monkeypatch.setenv(MARKER_ENV, str(marker))  # before the workers start, so they see it
    # Not the default client: gpomap must use the client it is given (or makes) explicitly.
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        ) as cluster,
        distributed.Client(cluster, set_as_default=False) as client,
    ):
        by_address = TiledGPOM(tile_size=6.0, overlap=2.5, scheduler=cluster.scheduler_address, **OPTS)
        _same(by_address.fit(room, hyperparameters=hyp).grid(0.25, (0.0, 20.0, 0.0, 16.0)), ref)
        # A worker dies mid-run: Dask (or our one retry) reruns the tile; nothing goes missing.
        monkeypatch.setattr(tile_fits, "fit_tile_task", _dying_fit)
        model = TiledGPOM(tile_size=6.0, overlap=2.5, scheduler=client, **OPTS).fit(room, hyperparameters=hyp)
        assert marker.exists()
        _same(model.grid(0.25, (0.0, 20.0, 0.0, 16.0)), ref)


@pytest.fixture
def progress_mode(monkeypatch):
    """Set the (process-wide) progress mode for one test, restored afterwards; lines from the first
    step (these stages take a fraction of a second)."""
    from gpomap import progress
    from gpomap.progress import get_progress_mode, set_progress_mode

    monkeypatch.setattr(progress, "LINES_AFTER_SECONDS", 0.0)
    before = get_progress_mode()
    yield set_progress_mode
    set_progress_mode(before)


@pytest.mark.parametrize("n_workers", [1, 2])
def test_progress_of_fit_update_and_grid(room, reference, progress_mode, capsys, n_workers):
    hyp, _ = reference
    progress_mode("lines")
    model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=n_workers, **OPTS).fit(room[:12], hyperparameters=hyp)
    assert re.search(rf"fitting tiles: \d+/{len(model.tiles_)} tiles", capsys.readouterr().err)
    model.update(room[12:24])
    assert len(model.last_refit_) > 1  # one tile would be done at once, with no line before the end
    assert re.search(rf"refitting tiles: \d+/{len(model.last_refit_)} tiles", capsys.readouterr().err)
    model.grid(0.5)
    assert re.search(r"predicting tiles: \d+/\d+ tiles", capsys.readouterr().err)
    progress_mode("quiet")
    model.update(room[24:])
    model.grid(0.5)
    assert len(model.last_refit_) > 1
    assert capsys.readouterr() == ("", "")  # nothing printed at all


def _blas_threads_fit(task):
    """The real fit, with the BLAS thread count of the process it ran in added to the state."""
    from threadpoolctl import threadpool_info

    state = _REAL_FIT(task)
    state.hyperparameters["blas_threads"] = max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
    return state


@pytest.mark.parametrize("worker_processes", [False, True])
def test_pool_workers_share_the_cores_for_blas(room, reference, monkeypatch, worker_processes):
    threadpoolctl = pytest.importorskip("threadpoolctl")
    hyp, _ = reference
    monkeypatch.setattr(tile_fits, "fit_tile_task", _blas_threads_fit)
    opts = {"tile_size": 6.0, "overlap": 2.5, "n_workers": 2, "worker_processes": worker_processes, **OPTS}
    before = threadpoolctl.threadpool_info()
    # As if on 4 or 2 cores with one or two BLAS libraries (both are counted in gpomap.lapack):
    # 2 workers get the cores shared out among them and the libraries. The room's first 6 scans
    # (13 tiles, shared by both workers) are enough: each fit is only asked its threads.
    for cores, libraries, threads in ((4, 1, 2), (4, 2, 1), (2, 1, 1)):
        monkeypatch.setattr(lapack, "available_cores", lambda c=cores: c)
        monkeypatch.setattr(lapack, "blas_libraries", lambda n=libraries: n)
        model = TiledGPOM(**opts).fit(room[:6], hyperparameters=hyp)
        assert len(model.tiles_) > 2
        assert {s.hyperparameters["blas_threads"] for s in model.tiles_.values()} == {threads}
    assert threadpoolctl.threadpool_info() == before  # this process keeps its own


def test_stages_in_this_process_share_the_cores_for_blas(room, reference, monkeypatch):
    # One worker: the tiles are fitted in this process, within the fit's own limit.
    threadpoolctl = pytest.importorskip("threadpoolctl")
    hyp, _ = reference
    monkeypatch.setattr(tile_fits, "fit_tile_task", _blas_threads_fit)
    before = threadpoolctl.threadpool_info()
    # The room's first 3 scans (11 tiles): up to 4 BLAS threads on the 2 cores the tests run on
    # make the whole room's fit 6x slower than the pool's.
    for libraries, threads in ((1, 4), (2, 2)):
        monkeypatch.setattr(lapack, "available_cores", lambda: 4)
        monkeypatch.setattr(lapack, "blas_libraries", lambda n=libraries: n)
        model = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=1, **OPTS).fit(room[:3], hyperparameters=hyp)
        assert len(model.tiles_) > 1
        assert {s.hyperparameters["blas_threads"] for s in model.tiles_.values()} == {threads}
    assert threadpoolctl.threadpool_info() == before


def test_per_tile_hyperparameters_run_and_are_reported(room):
    opts = {**OPTS, "optimise": True, "n_restarts": 0, "hyper_subset": 60, "free_step": 1.0}
    model = TiledGPOM(tile_size=12.0, overlap=2.0, n_workers=2, per_tile_hyperparameters=True, hyper_sample=60, **opts)
    model.fit(room)
    s = model.summary()
    assert s["n_tiles"] == len(model.tiles_) >= 2
    assert set(s["per_tile_hyperparameters"]) == {"variance", "length_scale", "noise", "alpha", "beta"}
    p = model.predict_proba(np.array([[3.0, 3.0], [10.0, 8.0]]))
    assert np.all((p >= 0) & (p <= 1))


@pytest.mark.parametrize("pairs", [1, 7, 1 << 20])
def test_nearest_box_is_the_brute_force_nearest_in_any_chunking(monkeypatch, pairs):
    monkeypatch.setattr(tile_blending, "NEAREST_BOX_PAIRS", pairs)
    rng = np.random.default_rng(3)
    # Unit squares on a lattice with gaps, as a map's tiles are; points inside, between and far out.
    corners = np.array([(x, y) for x in range(0, 10, 2) for y in range(0, 6, 3)], dtype=float)
    boxes = np.column_stack([corners[:, 0], corners[:, 0] + 1, corners[:, 1], corners[:, 1] + 1])
    pts = rng.uniform(-5, 15, size=(300, 2))
    got = tiles.nearest_box(pts, boxes)
    for p, g in zip(pts, got):
        d = [np.hypot(max(b[0] - p[0], 0, p[0] - b[1]), max(b[2] - p[1], 0, p[1] - b[3])) for b in boxes]
        assert d[g] == pytest.approx(min(d), abs=1e-12)
        assert g == int(np.flatnonzero(np.isclose(d, min(d), rtol=0, atol=1e-12))[0])  # the first on ties
    inside = np.array([[0.5, 0.5], [8.2, 3.9]])
    assert tiles.nearest_box(inside, boxes).tolist() == [0, 9]


def test_nearest_box_of_boxes_of_any_size_is_the_brute_force_nearest():
    # Boxes of mixed sizes, overlapping or not, some degenerate; points near and very far: the
    # pruning by squares must keep every box that can be nearest.
    rng = np.random.default_rng(11)
    lo = rng.uniform(-20, 20, size=(40, 2))
    size = rng.choice([0.0, 0.3, 2.0, 7.0], size=(40, 2))
    boxes = np.column_stack([lo[:, 0], lo[:, 0] + size[:, 0], lo[:, 1], lo[:, 1] + size[:, 1]])
    pts = np.concatenate([rng.uniform(-30, 30, size=(2000, 2)), rng.uniform(-1e4, 1e4, size=(200, 2))])
    dx = np.maximum(np.maximum(boxes[None, :, 0] - pts[:, None, 0], pts[:, None, 0] - boxes[None, :, 1]), 0)
    dy = np.maximum(np.maximum(boxes[None, :, 2] - pts[:, None, 1], pts[:, None, 1] - boxes[None, :, 3]), 0)
    assert tiles.nearest_box(pts, boxes).tolist() == np.argmin(dx * dx + dy * dy, axis=1).tolist()
    assert tiles.nearest_box(np.zeros((0, 2)), boxes).shape == (0,)


@pytest.mark.parametrize("spread", [30.0, 1e6], ids=["compact", "sparse-and-wide"])
def test_present_keys_are_the_distinct_keys_of_the_points(spread):
    # Counted over the squares' index box (or sorted, when the box is too wide): the distinct
    # squares holding points, as a sort of every point's key gives them, points on square borders
    # and negative coordinates included.
    rng = np.random.default_rng(4)
    model = TiledGPOM(tile_size=5.0, n_workers=1, **OPTS)
    model.origin_ = (-2.5, 1.0)
    model.tile_size_ = 5.0
    pts = np.vstack([rng.uniform(-spread, spread, (2000, 2)), [[-2.5, 1.0], [2.5, 6.0], [-7.5, -4.0]]])
    for side in (5.0, 10.0):
        expected = np.unique(model._square_keys(pts, side))
        got = model._present_keys(pts, side)
        assert got.dtype == np.int64 and got.tolist() == expected.tolist()
    assert model._present_keys(pts[:0], 5.0).size == 0


def test_points_are_filed_under_their_blocks_in_arrival_order(room):
    # Every point under the block whose square holds it, in the order the points came: what a
    # sort of every point's block key gives, found here by brute force.
    model = TiledGPOM(tile_size=5.0, n_workers=1, **OPTS).fit(room)
    points = np.concatenate([model._block_points[k].arrays()[0] for k in sorted(model._block_points)])
    keys = model._square_keys(points, model.block_size_)
    for k in model._block_points:
        mine = model._block_points[k].arrays()[0]
        assert np.all(model._square_keys(mine, model.block_size_) == k)
    assert len(model._block_points) == np.unique(keys).size >= 2
    obs = model.base.make_observations(room, clearance=False)
    for k, block in model._block_points.items():
        mine = obs.points[model._square_keys(obs.points, model.block_size_) == k]
        np.testing.assert_array_equal(block.arrays()[0], mine)


@pytest.mark.parametrize("dim", [2, 3])
def test_each_tile_sees_the_cells_meeting_its_square_grown_by_its_reach(dim):
    """A tile's cells are those whose boxes meet its x, y square grown by OVERLAP_LENGTH_SCALES
    length scales (brute force over every cell's box), planar squares and voxel columns alike."""
    from tests.world3d import ORIGINS, lidar_clouds

    data = _corridor_scans() if dim == 2 else lidar_clouds(ORIGINS, n_rays=200)
    model = TiledGPOM(tile_size=2.0, n_workers=1, **{**OPTS, "length_scale": 0.5}).fit(data)
    reach = tiles.OVERLAP_LENGTH_SCALES * 0.5
    assert model.overlap_ == pytest.approx(reach)
    lo, hi, _ = model.cell_boxes()
    (ox, oy), side = model.origin_, 2.0
    assert len(model.tiles_) > 1
    for (ix, iy), state in model.tiles_.items():
        x0, y0 = ox + ix * side, oy + iy * side
        meets = (
            (lo[:, 0] <= x0 + side + reach)
            & (hi[:, 0] >= x0 - reach)
            & (lo[:, 1] <= y0 + side + reach)
            & (hi[:, 1] >= y0 - reach)
        )
        want = sorted(map(tuple, np.hstack([lo[meets], hi[meets]]).round(9)))
        got = sorted(map(tuple, np.hstack([state.posterior.inputs.lower, state.posterior.inputs.upper]).round(9)))
        assert got == want


@pytest.mark.parametrize("merged", [False, True])
def test_update_equals_batch_in_3d(monkeypatch, merged):
    """Point clouds added in two batches give the GP map of all of them fitted at once, their
    free samples merged by cube or not; the ray evidence's lattice grows under the second batch
    and its calibration is still fitted."""
    import gpomap.observations as observations
    from tests.world3d import ORIGINS, lidar_clouds

    if merged:
        monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0)

    clouds = lidar_clouds(ORIGINS, n_rays=200)
    opts = {**OPTS, "length_scale": 0.6}
    inc = TiledGPOM(tile_size=2.0, n_workers=1, **opts)
    inc.update(clouds[:2])  # fit
    first_lattice = inc.evidence_.lattice
    inc.update(clouds[2:])
    assert 0 < len(inc.last_refit_) <= len(inc.tiles_)
    batch = TiledGPOM(tile_size=2.0, origin=inc.origin_, n_workers=1, **opts)
    batch.fit(clouds, hyperparameters=inc.hyperparameters_)
    assert sorted(batch.tiles_) == sorted(inc.tiles_)
    for k in batch._blocks:
        np.testing.assert_array_equal(inc._blocks[k].counts, batch._blocks[k].counts)
    heaviest = max(int(block.weighted_arrays()[2].max()) for block in batch._block_points.values())
    assert (heaviest > 1) == merged
    pts = np.random.default_rng(3).uniform([0.0, 0.0, 0.0], [6.0, 4.0, 2.5], (500, 3))
    np.testing.assert_allclose(inc.predict_proba_gp(pts), batch.predict_proba_gp(pts), rtol=0, atol=1e-10)
    # The world's walls lie on voxel borders, so some beams end exactly on one; recounted on the
    # grown lattice they can fall one voxel apart from where they were first counted. The
    # leave-one-scan-out counts stay non-negative and the weights are fitted (the loss was NaN
    # and the weights left at their defaults before).
    assert inc.evidence_.lattice != first_lattice
    report = inc.evidence_.report
    assert np.isfinite(report["log_loss"]) and report["log_loss"] < report["log_loss_default"]


def test_merged_3d_points_waiting_in_a_file_map_as_those_held_in_memory(monkeypatch):
    """A voxel map's merged free points keep their weights through the spill file: the same
    cells, counts and map as held in memory, and the cells count the samples, not the points."""
    import gpomap.observations as observations
    from tests.world3d import ORIGINS, lidar_clouds

    monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0)
    clouds = lidar_clouds(ORIGINS, n_rays=300)
    opts = {**OPTS, "length_scale": 0.6}
    held = TiledGPOM(tile_size=2.0, n_workers=1, **opts).fit(clouds)
    monkeypatch.setattr(tiled_map, "POINT_MEMORY", 1)
    spilled = TiledGPOM(tile_size=2.0, n_workers=1, **opts).fit(clouds)
    assert all(isinstance(p, tile_points._SpilledPart) for b in spilled._block_points.values() for p in b._parts)
    assert sorted(spilled._blocks) == sorted(held._blocks)
    for k in held._blocks:
        np.testing.assert_array_equal(spilled._blocks[k].lower, held._blocks[k].lower)
        np.testing.assert_array_equal(spilled._blocks[k].counts, held._blocks[k].counts)
        weights = held._block_points[k].weighted_arrays()[2]
        assert weights is not None and weights.max() > 1
    assert sum(b.counts.sum() for b in held._blocks.values()) > held._n_points
    pts = np.random.default_rng(3).uniform([0.0, 0.0, 0.0], [6.0, 4.0, 2.5], (300, 3))
    np.testing.assert_array_equal(spilled.predict_proba_gp(pts), held.predict_proba_gp(pts))


def test_square_keys_decode_to_their_indices_for_arrays_and_scalars():
    rng = np.random.default_rng(4)
    ix, iy = rng.integers(-5000, 5000, 200), rng.integers(-5000, 5000, 200)
    keys = TiledGPOM._encode(ix, iy)
    dx, dy = TiledGPOM._decode(keys)
    np.testing.assert_array_equal(dx, ix)
    np.testing.assert_array_equal(dy, iy)
    assert [TiledGPOM._decode(int(k)) for k in keys[:20]] == list(zip(ix[:20].tolist(), iy[:20].tolist(), strict=True))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"noise": None}, r"missing \['noise'\]"),
        ({"length_scale": 0.0}, "length_scale must be positive, got 0.0"),
        ({"alpha": float("nan")}, "alpha must be positive, got nan"),
        ({"beta": float("inf")}, "beta must be finite, got inf"),
        ({"variance_scale": "wide"}, "variance_scale must be a number, got 'wide'"),
    ],
)
def test_bad_given_hyperparameters_are_named_before_any_work(room, monkeypatch, change, message):
    good = {"variance": 1.0, "length_scale": 1.0, "noise": 0.1, "alpha": 2.0, "beta": 0.0, "variance_scale": 3.0}
    given = {**good, **change}
    given = {k: v for k, v in given.items() if v is not None}

    def no_work(*args, **kwargs):
        raise AssertionError("observations made before the hyperparameters were checked")

    monkeypatch.setattr(MapSettings, "make_observations", no_work)
    with pytest.raises(ValueError, match=message):
        TiledGPOM(n_workers=1, **OPTS).fit(room, hyperparameters=given)


def _state(key, n, rng, order="F"):
    """A tile state whose factor is a random lower-triangular n x n matrix (a -0.0 on its diagonal's left)."""
    L = np.tril(rng.normal(size=(n, n)))
    if n > 1:
        L[1, 0] = -0.0
    L = np.asfortranarray(L) if order == "F" else np.ascontiguousarray(L)
    lower = rng.normal(size=(n, 2))
    X = Supports(lower, lower + 0.5, np.ones(n))
    from gpomap.gp import GPPosterior
    from gpomap.squash import ProbitSquash

    post = GPPosterior(X, L, rng.normal(size=n), MapSettings(**OPTS).make_kernel(), ProbitSquash(1.0, 0.0))
    return tiles.TileState(key, post, {"noise": 0.1}, 0.5)


def test_a_tile_store_gives_back_every_factor_to_the_bit_whatever_waits_in_its_file():
    rng = np.random.default_rng(3)
    states = {(i, -i): _state((i, -i), 20 + 3 * i, rng, "F" if i % 2 else "C") for i in range(12)}
    # Room for about two factors: the rest go to the file, least recently used first.
    store = tiles.TileStore(budget=2 * 2 * 8 * 40 * 40, tiles=states)
    assert store.spilled_bytes > 0 and len(store.resident()) < len(states)
    assert sorted(store) == sorted(states) and len(store) == 12 and (3, -3) in store
    for key, state in states.items():
        got = store[key]
        L = state.posterior.L
        assert got.posterior.L.tobytes(order="A") == L.tobytes(order="A")
        assert got.posterior.L.flags.f_contiguous == L.flags.f_contiguous
        assert np.signbit(got.posterior.L[1, 0])  # the -0.0 below the diagonal kept
        assert got.posterior.weights is state.posterior.weights and got.hyperparameters == state.hyperparameters
        assert store.light(key).posterior.L.size == 0 and store.light(key).n_cells == state.n_cells
    # A factor with something above its diagonal is kept whole.
    full = _state((99, 0), 30, rng)
    full.posterior.L[0, 5] = 2.5
    store[(99, 0)] = full
    for key in list(states)[:6]:
        store[key]
    assert store[(99, 0)].posterior.L.tobytes() == full.posterior.L.tobytes()
    # Replaced and deleted tiles free their segments, which a factor of the same size takes again.
    size = store.spilled_bytes
    for key in list(states)[:6]:
        store[key] = states[key]
        store[key]
    for key in list(states)[6:]:
        store[key]
    assert store.spilled_bytes == size
    del store[(0, 0)]
    assert (0, 0) not in store and len(store) == 12
    # A peek reads a tile back without keeping it.
    resident = [s.key for s in store.resident()]
    waiting = next(k for k in states if k not in resident and k in store)
    assert store.peek(waiting).posterior.L.tobytes() == states[waiting].posterior.L.tobytes()
    assert [s.key for s in store.resident()] == resident
    store.shrink()  # every factor to the file, and read back the same
    assert store.resident() == []
    assert all(store[k].posterior.L.tobytes() == states[k].posterior.L.tobytes() for k in resident if k in states)


def test_a_map_whose_tiles_wait_in_a_file_is_the_map_kept_in_memory(room, reference, monkeypatch, tmp_path):
    from gpomap.io.mapfile import load_fitted_map, save_fitted_map

    hyp, _ = reference
    whole = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, **OPTS).fit(room, hyperparameters=hyp)
    monkeypatch.setattr(tile_store, "TILE_MEMORY", 1)  # one factor in memory at a time
    spilled = TiledGPOM(tile_size=6.0, overlap=2.5, n_workers=2, **OPTS).fit(room, hyperparameters=hyp)
    assert spilled.tiles_.spilled_bytes > 0 and len(spilled.tiles_.resident()) == 1
    a, b = whole.grid(0.25, (0.0, 20.0, 0.0, 16.0)), spilled.grid(0.25, (0.0, 20.0, 0.0, 16.0))
    np.testing.assert_array_equal(a.probability, b.probability)
    np.testing.assert_array_equal(a.variance, b.variance)
    pts = np.random.default_rng(1).uniform((-2.0, -2.0), (22.0, 18.0), (3000, 2))
    for x, y in zip(whole.predict_proba(pts, return_var=True), spilled.predict_proba(pts, return_var=True), strict=True):
        np.testing.assert_array_equal(x, y)
    # Updated, and saved and loaded: the same as the map kept in memory.
    whole.update(room[:5])
    spilled.update(room[:5])
    np.testing.assert_array_equal(whole.predict_proba(pts), spilled.predict_proba(pts))
    loaded = load_fitted_map(save_fitted_map(spilled, tmp_path / "map.gpom"))
    np.testing.assert_array_equal(loaded.predict_proba(pts), whole.predict_proba(pts))
    assert spilled.summary()["cells_per_tile"] == whole.summary()["cells_per_tile"]


def _recording(add_points, filed):
    """TiledGPOM._add_points, noting whether each call files in a spill file."""

    def add(self, points, occupied, spill=None, scans=None, weights=None):
        filed.append(spill is not None)
        return add_points(self, points, occupied, spill, scans, weights)

    return add


@pytest.mark.parametrize("budget", [1, 100_000])
def test_a_log_whose_points_wait_in_a_file_maps_as_one_held_in_memory(monkeypatch, budget):
    # Points made a part at a time (a few scans each) and filed under their blocks in a temporary
    # file: the same cells, variance scale and map as the whole log's points held in memory. With
    # the larger budget the first parts are filed in memory (the log is wider than a block from
    # its first part) and go to the file when a later part passes the budget.
    import gpomap.observations as observations

    world = World(outlines=[[(0.0, 0.0), (24.0, 0.0), (24.0, 14.0), (0.0, 14.0)]], segments=[(12.0, 0.0, 12.0, 9.0)])
    xs = np.linspace(2.0, 22.0, 50)
    poses = np.column_stack([xs, 11.0 + np.sin(xs), 0.3 * np.cos(xs)])
    scans = simulate_scans(world, poses, 60, max_range=12.0, noise_std=0.01, seed=1)
    opts = dict(kernel="se", free_step=0.4, min_cell=0.5, max_cell=2.0, n_workers=1, calibration_scans=5)
    held = TiledGPOM(**opts).fit(scans)
    monkeypatch.setattr(tiled_map, "POINT_MEMORY", budget)
    monkeypatch.setattr(observations, "PART_POINTS", 2000)
    filed = []
    monkeypatch.setattr(TiledGPOM, "_add_points", _recording(TiledGPOM._add_points, filed))
    spilled = TiledGPOM(**opts).fit(scans)
    # Filed part by part as the points came: in memory before the budget was passed, not after.
    assert len(filed) > 3 and filed[0] is (budget == 1)
    assert all(filed[filed.index(True) :]) and not any(filed[: filed.index(True)])
    assert all(isinstance(p, tile_points._SpilledPart) for b in spilled._block_points.values() for p in b._parts)
    assert spilled.extrapolation_ == held.extrapolation_ and spilled.hyperparameters_ == held.hyperparameters_
    for k in held._blocks:
        np.testing.assert_array_equal(spilled._blocks[k].lower, held._blocks[k].lower)
        np.testing.assert_array_equal(spilled._blocks[k].counts, held._blocks[k].counts)
    a, b = held.grid(0.2), spilled.grid(0.2)
    np.testing.assert_array_equal(a.probability, b.probability)
    np.testing.assert_array_equal(a.variance, b.variance)
    # An update appends points in memory to the blocks' parts in the file: the same again.
    more = simulate_scans(world, poses[::-7] + np.array([0.0, -4.0, 1.0]), 60, max_range=12.0, seed=2)
    held.update(more)
    spilled.update(more)
    np.testing.assert_array_equal(held.grid(0.2).probability, spilled.grid(0.2).probability)
