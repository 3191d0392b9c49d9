"""StreamingGPOM and what it rests on: ray counts added scan by scan, tile refits that reuse covariances."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import gpomap.tiles as tiles
from gpomap.errors import NotFittedError
from gpomap.evidence import next_to_hits
from gpomap.fusion import EvidenceLayer, surface_misses
from gpomap.grid import GridSpec
from gpomap.scans import Scan
from gpomap.simulate import paper_room_scans
from gpomap.streaming import StreamingGPOM
from gpomap.tiles import TiledGPOM

# Small tiles over the paper's room: several tiles, fast fits; the kernel and cells are the defaults'.
OPTS = dict(tile_size=6.0, overlap=2.5, free_step=0.5, max_cell=1.0, optimise=False, length_scale=1.0, noise=0.1)


@pytest.fixture(scope="module")
def room():
    # The room moved off the 5 cm lattice: its walls on exact multiples of the cell side would
    # put beam ends on cell borders, which lattices of other origins may round either way.
    return [Scan(s.pose + np.array([0.0123, 0.0177, 0.0]), s.angles, s.ranges, s.max_range) for s in paper_room_scans()]


def _half(points):
    return np.full(len(points), 0.5)


def test_ray_counts_added_scan_by_scan_equal_counting_them_at_once(room):
    batch = EvidenceLayer(room, 0.05, _half)
    inc = EvidenceLayer(room[:2], 0.05, _half)
    for s in room[2:]:
        inc.add_scans([s])
    assert inc.lattice is not None and batch.lattice is not None
    assert inc.lattice.shape != batch.lattice.shape  # it grew, with its own margin
    inc.calibration = batch.calibration
    rng = np.random.default_rng(1)
    x0, x1, y0, y1 = batch.lattice.extent
    pts = np.column_stack([rng.uniform(x0 - 1, x1 + 1, 50_000), rng.uniform(y0 - 1, y1 + 1, 50_000)])
    for a, b in zip(batch.counts_at(pts), inc.counts_at(pts)):
        np.testing.assert_array_equal(a, b)
    assert batch.counts_at(pts)[0].sum() > 100
    # A grid off the lattice is counted from the beams themselves: the same either way.
    off = GridSpec((x0 + 0.013, y0 + 0.021), 0.05, (120, 150))
    for a, b in zip(batch.grid_counts(off), inc.grid_counts(off)):
        np.testing.assert_array_equal(a, b)
    # A grid on the lattice reads the running counts: the same as traversing its own cells.
    on = GridSpec((x0 + 0.5, y0 + 0.25), 0.05, (120, 150))
    hits, misses, near, _ = inc.evidence.counts(on)
    np.testing.assert_array_equal(inc.grid_counts(on)[0], inc.calibration.hits(hits, near))
    # Its surface misses are found from the hits of the cells round it as well (a grid one cell wider).
    wider = GridSpec((on.origin[0] - 0.05, on.origin[1] - 0.05), 0.05, (122, 152))
    surface = surface_misses(misses, near, next_to_hits(inc.evidence.counts(wider).hits)[1:-1, 1:-1])
    assert inc.calibration.surface_weight != 1.0 and surface.sum() > 0
    np.testing.assert_array_equal(
        inc.grid_counts(on)[1], inc.calibration.misses(misses, near, inc.evidence.path_passes(on), surface)
    )


def test_tile_refit_reusing_covariances_matches_a_fresh_fit(room):
    model = TiledGPOM(n_workers=1, ray_evidence=False, **OPTS).fit(room[:10])
    model.absorb(room[10:14])
    model._build_blocks(sorted(model._dirty))
    key = sorted(model.tiles_)[0]
    jobs, _ = model._fit_jobs([key], reuse=True)
    task = jobs[0][1][0]
    assert task.previous is not None
    reused = tiles.fit_tile_task(task)
    exact = tiles.fit_tile_task(dataclasses.replace(task, previous=None))
    assert reused.n_cells == exact.n_cells
    np.testing.assert_allclose(reused.posterior.L, exact.posterior.L, rtol=0, atol=1e-10)
    np.testing.assert_allclose(reused.posterior.weights, exact.posterior.weights, rtol=0, atol=1e-8)


def test_stream_then_finish_equals_the_batch_map(room):
    stream = StreamingGPOM(warmup_scans=6, **OPTS)
    versions = []
    for i, s in enumerate(room):
        stream.add_scan(s)
        if stream.ready_ and i % 3 == 0:
            stream.refresh()
            versions.append(stream.version_)
    assert versions == sorted(versions) and len(set(versions)) > 1
    stream.finish()
    assert stream.pending_tiles_ == 0
    batch = TiledGPOM(n_workers=1, **OPTS).fit(room, hyperparameters=stream.hyperparameters_)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 20, 3000), rng.uniform(0, 16, 3000)])
    ps, vs = stream.predict_proba(pts, return_var=True)
    pb, vb = batch.predict_proba(pts, return_var=True)
    np.testing.assert_allclose(ps, pb, rtol=0, atol=1e-9)
    np.testing.assert_allclose(vs, vb, rtol=0, atol=1e-9)
    extent = (0.0, 20.0, 0.0, 16.0)
    # On the counted lattice and off it (0.1 m cells' centres lie on the 5 cm lattice's borders).
    for resolution in (0.05, 0.1):
        a, b = stream.grid(resolution, extent).probability, batch.grid(resolution, extent).probability
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert stream.stats()["add_scan"]["n"] == len(room) - 6


def test_the_calibration_is_refitted_when_the_scans_have_doubled(room):
    stream = StreamingGPOM(warmup_scans=5, **OPTS)
    stream.add_scans(room[:5])
    warmup = stream.model_.evidence_.calibration
    stream.add_scans(room[5:9])
    stream.refresh()
    assert stream.model_.evidence_.calibration is warmup  # 9 scans: not yet twice the 5 it was fitted on
    stream.add_scan(room[9])
    stream.refresh()
    # Ten scans: refitted on all of them, as a batch fit of the ten with the same hyperparameters.
    batch = TiledGPOM(n_workers=1, **OPTS).fit(room[:10], hyperparameters=stream.hyperparameters_)
    refitted, expected = stream.model_.evidence_.calibration, batch.evidence_.calibration
    assert refitted != warmup
    for field in dataclasses.fields(expected):
        assert getattr(refitted, field.name) == pytest.approx(getattr(expected, field.name), rel=1e-6, abs=1e-9)


def test_refresh_is_bounded_and_catches_up(room):
    stream = StreamingGPOM(warmup_scans=8, max_refits=1, **OPTS)
    stream.add_scans(room[:8])
    stream.add_scans(room[8:])
    waiting = stream.pending_tiles_
    assert waiting > 0
    first = stream.refresh()
    assert len(first) <= 1
    for _ in range(50):
        if stream.pending_tiles_ == 0:
            break
        assert len(stream.refresh()) <= 1
    assert stream.pending_tiles_ == 0


def test_reading_before_the_warmup_is_over_says_so(room):
    stream = StreamingGPOM(warmup_scans=5, **OPTS)
    stream.add_scans(room[:3])
    assert not stream.ready_
    with pytest.raises(NotFittedError, match="3 of 5 scans"):
        stream.grid()
    stream.add_scans(room[3:6])
    assert stream.ready_
    om = stream.grid()
    # The default grid sits on the ray counts' lattice: cells there are the counted cells.
    assert om.grid.resolution == pytest.approx(0.05)
    assert np.allclose(np.asarray(om.grid.origin) / 0.05, np.round(np.asarray(om.grid.origin) / 0.05))


def test_changed_since_covers_the_new_scan(room):
    stream = StreamingGPOM(warmup_scans=5, **OPTS)
    stream.add_scans(room[:5])
    v = stream.version_
    stream.add_scan(room[10])
    v2, extents = stream.changed_since(v)
    assert v2 > v and extents
    x, y = room[10].pose[:2]
    assert any(e[0] <= x <= e[1] and e[2] <= y <= e[3] for e in extents)
    assert stream.changed_since(v2) == (v2, [])


@pytest.mark.parametrize("bad", [dict(warmup_scans=0), dict(max_refits=0), dict(tile_size=-1.0)])
def test_bad_settings_are_refused_at_once(bad):
    with pytest.raises(ValueError):
        StreamingGPOM(**{**OPTS, **bad})


def test_tiles_in_3d_are_columns_and_one_column_is_the_plain_map():
    from gpomap.gp import SupportGP
    from gpomap.settings import MapSettings
    from gpomap.supports import Supports
    from gpomap.voxels import VoxelMap
    from tests.world3d import ORIGINS, lidar_clouds

    clouds = lidar_clouds(ORIGINS, n_rays=200)
    opts = dict(kernel="se", optimise=False, length_scale=0.6, noise=0.1)
    # One tile holding the whole 6 x 4 m room, however tall, its squash fitted on every cell:
    # exactly one GP over the cuboid cells of all the rays, built here by hand.
    one = TiledGPOM(tile_size=50.0, origin=(-10.0, -10.0), n_workers=1, hyper_sample=10**6, **opts).fit(clouds)
    settings = MapSettings(**opts)
    cells = settings.make_cells(settings.make_observations(clouds))
    gp = SupportGP(settings.make_kernel(), noise=0.1, noise_model=settings.noise_model, optimise=False)
    gp.fit(cells.to_supports(), cells.labels)
    assert len(one.tiles_) == 1
    rng = np.random.default_rng(2)
    pts = rng.uniform([0, 0, 0], [6, 4, 2.5], (2000, 3))
    # The same prediction (local where it pays, as the tile's) as the one GP's.
    plain = gp.squash(*gp.predict_latent(Supports.from_points(pts)))
    np.testing.assert_allclose(one.predict_proba_gp(pts), plain, rtol=0, atol=1e-9)
    # 2 m columns: several tiles, blended; the voxel map of the columns is a VoxelMap.
    cols = TiledGPOM(tile_size=2.0, n_workers=1, **opts).fit(clouds, hyperparameters=one.hyperparameters_)
    assert len(cols.tiles_) >= 6 and {k[0] for k in cols.tiles_} >= {0, 1, 2}
    gap = np.abs(cols.predict_proba_gp(pts) - plain)
    assert np.median(gap) < 0.02
    vm = cols.grid(0.25)
    assert isinstance(vm, VoxelMap) and vm.probability.shape == vm.spec.shape


def test_scan_extent_caps_no_return_beams_by_hand():
    from gpomap.scans import scan_extent

    # One hit 2 m up, one no-return beam (recorded 30 m, the max range) along +x, from (1, 1).
    s = Scan(np.array([1.0, 1.0, 0.0]), np.array([0.0, np.pi / 2]), np.array([30.0, 2.0]), 30.0)
    assert scan_extent([s]) == pytest.approx((1.0, 1.0, 1.0, 3.0))
    assert scan_extent([s], include_no_return=True) == pytest.approx((1.0, 31.0, 1.0, 3.0))
    assert scan_extent([s], include_no_return=True, no_return_cap=10.0) == pytest.approx((1.0, 11.0, 1.0, 3.0))


def test_streaming_tiles_are_the_planar_batch_default():
    # Stated twice (the streaming module must not import SciPy for --help): they must agree.
    from gpomap import streaming

    assert tiles.DEFAULT_TILE_SIZE[2] == streaming.DEFAULT_TILE_SIZE
