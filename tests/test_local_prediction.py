"""Local tile prediction (the cells within the kernel's cutoff of each block of queries) equals the dense one."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import gpomap.gp.posterior
import gpomap.tiles.blending as tile_blending
from gpomap import _compiled_local
from gpomap.gp import LOCAL_TOL, LOCAL_VARIANCE_TOL, local_blocks
from gpomap.simulate import paper_room_scans
from gpomap.supports import Supports
from gpomap.tiles import TiledGPOM, predict_tile_task, taper

# Short length scales, so each block of queries sees a few metres of a tile: local is taken.
OPTS = dict(optimise=False, noise=0.1, free_step=0.3)


@pytest.fixture
def tight(monkeypatch):
    """Covariances below 1e-9 of the variance left out, not LOCAL_TOL's and LOCAL_VARIANCE_TOL's: the
    blocks' bookkeeping (which cells, which entries of K^-1) is then checked against the dense
    prediction to 1e-8."""
    monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_TOL", 1e-9)
    monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_VARIANCE_TOL", 1e-9)


def _both(model: TiledGPOM, key: tuple[int, int], points: np.ndarray):
    state = model.tiles_[key]
    # The local path is the one taken (not the dense fallback).
    assert state.posterior.local_blocks(Supports.from_points(points), 4096) is not None
    local = predict_tile_task(state, points, 4096, local=True)
    dense = predict_tile_task(state, points, 4096, local=False)
    return local, dense


def _dense_blended(model: TiledGPOM, points: np.ndarray) -> np.ndarray:
    """The map's blended probability at points with every tile predicted densely (the reference)."""
    tiles_before = tile_blending.predict_tile_task
    try:
        tile_blending.predict_tile_task = lambda *a: tiles_before(*a, local=False)
        return model.predict_proba_gp(points)
    finally:
        tile_blending.predict_tile_task = tiles_before


@pytest.fixture(params=["numpy", "compiled"])
def path(request, monkeypatch):
    """Each test once with numpy's block loop and once with the compiled one (:mod:`gpomap._compiled_local`)."""
    if request.param == "compiled" and not _compiled_local.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(_compiled_local, "ENABLED", request.param == "compiled")
    return request.param


@pytest.fixture(scope="module")
def room_maps():
    scans = paper_room_scans()[:8]
    return {
        k: TiledGPOM(n_workers=1, kernel=k, length_scale=0.3 if k == "se" else 0.15, **OPTS).fit(scans)
        for k in ("se", "matern32")
    }


@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_local_equals_dense_in_2d(room_maps, kernel, tight, path):
    model = room_maps[kernel]
    key = max(model.tiles_, key=lambda k: model.tiles_[k].n_cells)
    state = model.tiles_[key]
    rng = np.random.default_rng(0)
    points = rng.uniform(
        state.posterior.inputs.lower.min(axis=0) - 1.0, state.posterior.inputs.upper.max(axis=0) + 1.0, (6000, 2)
    )
    (mean, var), (dense_mean, dense_var) = _both(model, key, points)
    np.testing.assert_allclose(mean, dense_mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(var, dense_var, rtol=0, atol=1e-8)
    # The mean alone (a written map's samples between its variance's) is the same to the bit.
    for local in (True, False):
        alone, none = predict_tile_task(state, points, 4096, variance=False, local=local)
        assert none is None
        np.testing.assert_array_equal(alone, mean if local else dense_mean)
    # The blended map too, through every tile.
    p, p_dense = model.predict_proba_gp(points), _dense_blended(model, points)
    np.testing.assert_allclose(p, p_dense, rtol=0, atol=1e-8)


def test_local_equals_dense_in_3d(tight, path):
    from tests.world3d import ORIGINS, lidar_clouds

    model = TiledGPOM(tile_size=3.0, n_workers=1, kernel="se", length_scale=0.1, **OPTS).fit(lidar_clouds(ORIGINS, n_rays=100))
    key = max(model.tiles_, key=lambda k: model.tiles_[k].n_cells)
    rng = np.random.default_rng(1)
    points = rng.uniform([-0.5, -0.5, -0.5], [6.5, 4.5, 3.0], (6000, 3))
    (mean, var), (dense_mean, dense_var) = _both(model, key, points)
    np.testing.assert_allclose(mean, dense_mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(var, dense_var, rtol=0, atol=1e-8)


def test_points_with_no_cell_near_get_the_prior(room_maps, tight, path):
    model = room_maps["se"]
    key = max(model.tiles_, key=lambda k: model.tiles_[k].n_cells)
    state = model.tiles_[key]
    # Many points far beyond the cutoff of every cell (J empty), and some near, so local pays.
    far = state.posterior.inputs.upper.max(axis=0) + 50.0 + np.random.default_rng(2).uniform(0, 10, (3000, 2))
    near = np.random.default_rng(3).uniform(
        state.posterior.inputs.lower.min(axis=0), state.posterior.inputs.upper.max(axis=0), (3000, 2)
    )
    (mean, var), (dense_mean, dense_var) = _both(model, key, np.concatenate([far, near]))
    np.testing.assert_array_equal(mean[:3000], 0.0)
    np.testing.assert_array_equal(var[:3000], state.hyperparameters["variance"])
    np.testing.assert_allclose(mean, dense_mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(var, dense_var, rtol=0, atol=1e-8)


def test_local_is_within_the_tolerance_of_dense_at_the_default(room_maps, path):
    # Every covariance left out of the mean is below LOCAL_TOL * variance (see test_blocks_...
    # below), so the mean moves by at most that times the sum of |weights|; every one left out of
    # the variance is below LOCAL_VARIANCE_TOL * variance, so its reduction k^T K^-1 k moves by at
    # most (2 tol + tol^2) variance^2 sum |K^-1| (each |k_j| <= variance).
    from gpomap.gp import cholesky_inverse

    model = room_maps["se"]
    key = max(model.tiles_, key=lambda k: model.tiles_[k].n_cells)
    state = model.tiles_[key]
    points = np.random.default_rng(9).uniform(
        state.posterior.inputs.lower.min(axis=0) - 1.0, state.posterior.inputs.upper.max(axis=0) + 1.0, (6000, 2)
    )
    (mean, var), (dense_mean, dense_var) = _both(model, key, points)
    s2 = state.hyperparameters["variance"]
    mean_bound = LOCAL_TOL * s2 * np.abs(state.posterior.weights).sum()
    var_bound = (2 * LOCAL_VARIANCE_TOL + LOCAL_VARIANCE_TOL**2) * s2**2 * np.abs(cholesky_inverse(state.posterior.L)).sum()
    assert np.abs(mean - dense_mean).max() <= mean_bound
    assert np.abs(var - dense_var).max() <= var_bound
    # The bounds are loose; what the map's probabilities move by, measured: below 1e-5 here.
    p, p_dense = model.predict_proba_gp(points), _dense_blended(model, points)
    assert 0 < np.abs(p - p_dense).max() < 1e-5


def test_blocks_cover_every_query_once_and_keep_every_cell_within_reach():
    rng = np.random.default_rng(4)
    lo = rng.uniform(0, 20, (400, 2))
    cells = Supports.from_boxes(lo, lo + rng.uniform(0.1, 0.6, (400, 2)))
    queries = Supports.from_points(rng.uniform(-2, 22, (5000, 2)))
    radius = 1.5
    inner_radius = 0.8
    blocks, _ = local_blocks(queries, cells, radius, chunk_size=50, inner_radius=inner_radius)
    seen = np.concatenate([q for q, _, _ in blocks])
    np.testing.assert_array_equal(np.sort(seen), np.arange(5000))
    assert any(0 < n_inner < near.size for _, near, n_inner in blocks)
    for q, near, n_inner in blocks:
        assert q.size <= 50
        # Every cell nearer than the radius to any query of the block is in the block, and every
        # cell nearer than the inner radius among its first n_inner.
        p = queries.lower[q]
        gap = np.maximum(np.maximum(cells.lower[None] - p[:, None], p[:, None] - cells.upper[None]), 0.0)
        d2 = np.sum(gap**2, axis=2)
        assert np.isin(np.flatnonzero(np.any(d2 < radius**2, axis=0)), near).all()
        assert np.isin(np.flatnonzero(np.any(d2 < inner_radius**2, axis=0)), near[:n_inner]).all()
        # ... and no cell beyond the inner radius of the block's bounding box is among them.
        lo_b, hi_b = p.min(axis=0), p.max(axis=0)
        box_gap = np.maximum(np.maximum(cells.lower[near] - hi_b, lo_b - cells.upper[near]), 0.0)
        box_d2 = np.sum(box_gap**2, axis=1)
        assert (box_d2[:n_inner] < inner_radius**2).all() and (box_d2[n_inner:] >= inner_radius**2).all()


def test_the_cached_inverse_is_not_pickled_or_compared(room_maps):
    model = room_maps["se"]
    state = next(iter(model.tiles_.values()))
    model.predict_proba_gp(np.random.default_rng(5).uniform(0, 10, (20000, 2)))
    assert any(s.posterior.precision is not None for s in model.tiles_.values())
    assert pickle.loads(pickle.dumps(state)).posterior.precision is None
    assert "precision" not in repr(state)


def test_summed_kernel_keeps_the_dense_path():
    model = TiledGPOM(n_workers=1, kernel="se", area="summed", length_scale=0.3, **OPTS).fit(paper_room_scans()[:4])
    state = next(iter(model.tiles_.values()))
    points = Supports.from_points(np.random.default_rng(6).uniform(0, 10, (5000, 2)))
    assert state.posterior.local_blocks(points, 4096) is None
    assert LOCAL_TOL > 0


def test_blended_prediction_is_the_taper_weighted_mean_of_the_tiles(room_maps):
    """Each point's blended moments from its own loop over the tiles (no sorting, no index sets), against the map's."""
    from scipy.special import ndtr

    model = room_maps["se"]
    lo, hi = model.bounds_
    rng = np.random.default_rng(8)
    # Random points, and points on tile and blend-region edges where the weights switch on.
    points = rng.uniform(lo - 0.5, hi + 0.5, (300, 2))
    keys = sorted(model.tiles_)
    edges = np.array([model._blend_region(k)[0] for k in keys] + [model._core(k)[0] for k in keys])
    points = np.concatenate([points, np.column_stack([edges, rng.uniform(lo[1], hi[1], edges.size)])])
    p, mean, var, _ = model._predict_blended(points)
    h = 0.5 * model.blend_
    for i, x in enumerate(points):
        num = den = lat_m = lat_v = wsum = 0.0
        for key in keys:
            bx0, bx1, by0, by1 = model._blend_region(key)
            if not (bx0 < x[0] < bx1 and by0 < x[1] < by1):
                continue
            x0, x1, y0, y1 = model._core(key)
            w = float(taper(np.array([x[0]]), x0, x1, h)[0] * taper(np.array([x[1]]), y0, y1, h)[0])
            if w <= 0:
                continue
            (mu,), (v,) = predict_tile_task(model.tiles_[key], x[None, :], local=False)
            a, b = model.tiles_[key].hyperparameters["alpha"], model.tiles_[key].hyperparameters["beta"]
            num, den, lat_m, lat_v, wsum = num + w * (a * mu + b), den + w * a * a * v, lat_m + w * mu, lat_v + w * v, wsum + w
        if wsum == 0:  # reached by no tile: the map takes the nearest core's tile alone
            continue
        assert mean[i] == pytest.approx(lat_m / wsum, abs=1e-8)
        assert var[i] == pytest.approx(lat_v / wsum, abs=1e-8)
        assert p[i] == pytest.approx(ndtr((num / wsum) / np.sqrt(1.0 + den / wsum)), abs=1e-8)


@pytest.mark.skipif(not _compiled_local.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_blocks_equal_numpys_to_round_off(monkeypatch, dim):
    """Boxes of every kind (wide, thin, a point's width along some axes), random weights and a
    random K^-1, blocks with and without inputs: the compiled loop gives numpy's numbers."""
    from gpomap.gp import GPPosterior
    from gpomap.kernels.area import AreaKernel
    from gpomap.kernels.closed_form import POINT_WIDTH
    from gpomap.squash import ProbitSquash

    rng = np.random.default_rng(11)
    n, l = 300, 0.4
    lo = np.round(rng.uniform(0, 8, (n, dim)) / 0.05) * 0.05  # ends on a lattice repeat, as cells' do
    width = rng.choice([0.0, 0.5 * POINT_WIDTH * l, 0.05, 0.2, 0.5], size=(n, dim))
    X = Supports.from_boxes(lo, lo + width)
    kernel = AreaKernel("se")
    kernel.base.length_scale, kernel.base.variance = l, 1.7
    A = rng.normal(size=(n, n))
    L = np.linalg.cholesky(A @ A.T / n + np.eye(n))
    posterior = GPPosterior(X, L, rng.normal(size=n), kernel, ProbitSquash(1.0, 0.0))
    # Points inside the boxes' span, on a lattice (repeated coordinates) and scattered, points in
    # reach of the mean only (4.5 length scales past the boxes along x: inner inputs none), and far.
    beyond = rng.uniform(0, 8, (300, dim))
    beyond[:, 0] = 8.5 + 4.5 * l + rng.uniform(0, 0.1, 300)
    points = np.concatenate(
        [
            rng.uniform(-1, 9, (3000, dim)),
            np.round(rng.uniform(0, 8, (2000, dim)) / 0.1) * 0.1,
            beyond,
            rng.uniform(30, 40, (500, dim)),
        ]
    )
    Q = Supports.from_points(points)
    blocks = posterior.local_blocks(Q, 4096)
    assert blocks is not None and any(near.size == 0 for _, near, _ in blocks)
    # Blocks whose variance takes some of their inputs, and blocks whose variance takes none.
    assert any(0 < n_inner < near.size for _, near, n_inner in blocks)
    assert any(n_inner == 0 < near.size for _, near, n_inner in blocks)
    out = {}
    for compiled in (False, True):
        monkeypatch.setattr(_compiled_local, "ENABLED", compiled)
        posterior.precision = None
        out[compiled] = posterior.latent(Q), posterior.latent(Q, variance=False)
    (m0, v0), _ = out[False]
    (m1, v1), (a1, none) = out[True]
    assert none is None
    np.testing.assert_allclose(m1, m0, rtol=0, atol=1e-12 * np.abs(posterior.weights).sum())
    np.testing.assert_allclose(v1, v0, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(a1, m1)
    # Far points: the prior.
    np.testing.assert_array_equal(m1[-500:], 0.0)
    np.testing.assert_array_equal(v1[-500:], 1.7)


@pytest.mark.skipif(not _compiled_local.AVAILABLE, reason="numba is not installed")
@pytest.mark.parametrize("half_width", [0.05, 0.4, 1.0, 2.5, 5.0])
def test_interpolated_factors_equal_the_direct_ones(half_width):
    """A block's factors interpolated from Chebyshev nodes (as the compiled kernel takes them for
    scattered points) against each coordinate's own erf, sides of every width and placement."""
    from gpomap.kernels.closed_form import POINT_WIDTH

    rng = np.random.default_rng(12)
    l = 0.5
    lo = np.round(rng.uniform(-4, 4, 300) / 0.05) * 0.05
    hi = lo + rng.choice([0.0, 0.5 * POINT_WIDTH * l, 0.05, 0.3, 1.0, 3.0], 300)
    used = np.arange(300, dtype=np.int64)
    centre = rng.uniform(-1, 1)
    a, b = centre - half_width * l, centre + half_width * l
    n_nodes = _compiled_local.chebyshev_nodes_needed(half_width * l, l, _compiled_local.INTERPOLATION_ERROR)
    nodes, B = _compiled_local._interpolation_matrix(a, b, n_nodes, np.zeros(0))
    # Scattered coordinates, the interval's ends, and a node itself (the basis there is exact).
    x = np.concatenate([rng.uniform(a, b, 2000), [a, b, nodes[3]]])
    nodes, B = _compiled_local._interpolation_matrix(a, b, n_nodes, x)
    direct = _compiled_local._factors_at(lo, hi, used, 300, x, l, POINT_WIDTH)
    interpolated = _compiled_local._factors_at(lo, hi, used, 300, nodes, l, POINT_WIDTH) @ B
    assert direct.max() > 0.5  # sides near and far
    np.testing.assert_allclose(interpolated, direct, rtol=0, atol=5e-14)
    np.testing.assert_array_equal(B[:, -1], np.eye(n_nodes)[3])
