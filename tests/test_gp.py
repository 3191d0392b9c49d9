"""The GP core: objectives and their gradients, optimisation, leave-one-out moments, Cholesky."""

import numpy as np
import pytest

from gpomap.errors import NumericalError
from gpomap.gp import SupportGP, cholesky_in_place, compact_groups, inverse_diagonal, robust_cholesky
from gpomap.kernels import AreaKernel, Matern32, SquaredExponential
from gpomap.squash import ProbitSquash, class_weights, loo_moments, loo_probit
from gpomap.supports import Supports, concatenate


def _data(seed=0, n=25):
    rng = np.random.default_rng(seed)
    lower = rng.uniform(0, 5, (n, 2))
    upper = lower + rng.uniform(0.1, 1.0, (n, 2))
    y = np.where(lower[:, 0] + 0.3 * rng.normal(size=n) > 2.5, 1.0, -1.0)
    return Supports.from_boxes(lower, upper, rng.integers(1, 30, n).astype(float)), y


def _fd(f, x, eps=1e-6):
    g = np.empty_like(x)
    for j in range(x.size):
        up, down = x.copy(), x.copy()
        up[j] += eps
        down[j] -= eps
        g[j] = (f(up) - f(down)) / (2 * eps)
    return g


KERNELS = [AreaKernel(SquaredExponential(1.2, 0.9), "exact"), AreaKernel(Matern32(0.8, 1.3), "quadrature")]


@pytest.mark.parametrize("kernel", KERNELS, ids=["se-exact", "matern-quadrature"])
@pytest.mark.parametrize("noise_model", ["constant", "per_count"])
def test_lml_gradient_matches_finite_differences(kernel, noise_model):
    X, y = _data()
    gp = SupportGP(kernel, noise_model=noise_model)
    params = np.array([np.log(1.2), np.log(0.9), np.log(0.05)])
    _, grad = gp.log_marginal_likelihood(X, y, params, eval_gradient=True)
    np.testing.assert_allclose(grad, _fd(lambda p: gp.log_marginal_likelihood(X, y, p), params), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kernel", KERNELS, ids=["se-exact", "matern-quadrature"])
@pytest.mark.parametrize("noise_model", ["constant", "per_count"])
def test_loo_gradient_matches_finite_differences(kernel, noise_model):
    X, y = _data(1)
    gp = SupportGP(kernel, noise_model=noise_model)
    params = np.array([0.0, np.log(1.1), np.log(0.2), np.log(1.7), -0.3])
    _, grad = gp.loo_objective(X, y, params, eval_gradient=True)
    np.testing.assert_allclose(grad, _fd(lambda p: gp.loo_objective(X, y, p), params), rtol=1e-5, atol=1e-6)


def test_lml_by_hand_for_one_input():
    # One point with k = 2 and noise 0.5: y ~ N(0, 2.5).
    X = Supports.from_points(np.array([[0.0, 0.0]]))
    gp = SupportGP(AreaKernel(SquaredExponential(2.0, 1.0), "exact"))
    value = gp.log_marginal_likelihood(X, np.array([1.0]), np.log([2.0, 1.0, 0.5]))
    assert value == pytest.approx(-0.5 * 1 / 2.5 - 0.5 * np.log(2.5) - 0.5 * np.log(2 * np.pi))


@pytest.mark.parametrize("objective", ["lml", "loo"])
def test_optimisation_improves_its_objective(objective):
    X, y = _data(2, 40)
    kernel = AreaKernel(SquaredExponential(1.0, 3.0), "exact")
    gp = SupportGP(kernel, noise=1.0, objective=objective, n_restarts=1)
    if objective == "lml":
        start = gp.log_marginal_likelihood(X, y, np.array([0.0, np.log(3.0), 0.0]))
    else:
        start = gp.loo_objective(X, y, np.array([0.0, np.log(3.0), 0.0, 0.0, 0.0]))
    gp.fit(X, y)
    assert gp.fit_report_.value > start + 1.0
    assert gp.fit_report_.n_evaluations > 2
    # The learnt length scale is the GP's; the kernel handed in is left as it was.
    assert kernel.base.length_scale == 3.0 and kernel.base.variance == 1.0
    assert gp.kernel is not kernel and gp.kernel.base.length_scale != 3.0


def test_loo_moments_equal_refitting_without_the_point():
    X, y = _data(3, 15)
    kernel = AreaKernel(Matern32(1.0, 1.2), "quadrature")
    noise = 0.3
    K = kernel(X) + noise * np.eye(len(X))
    mu, var = loo_moments(np.linalg.inv(K), y)
    for i in range(len(X)):
        keep = np.delete(np.arange(len(X)), i)
        Kk = K[np.ix_(keep, keep)]
        k = K[keep, i]
        assert mu[i] == pytest.approx(k @ np.linalg.solve(Kk, y[keep]), rel=1e-8)
        assert var[i] == pytest.approx(K[i, i] - k @ np.linalg.solve(Kk, k), rel=1e-8)


def test_balanced_class_weights_by_hand():
    y = np.array([1.0, -1.0, -1.0, -1.0])
    # n / (2 n_class): 4 / 2 for the one hit, 4 / 6 for each free input; both classes sum to 2.
    assert class_weights(y) == pytest.approx([2.0, 2 / 3, 2 / 3, 2 / 3])
    assert class_weights(y, None) is None
    assert class_weights(-np.ones(3)) is None  # one class: nothing to balance
    with pytest.raises(ValueError, match="class_weight"):
        class_weights(y, "auto")


def test_weighted_loo_probit_and_its_gradient():
    from scipy.stats import norm

    rng = np.random.default_rng(5)
    y = np.where(rng.random(30) < 0.3, 1.0, -1.0)
    mu, var, w = rng.normal(size=30), rng.uniform(0.1, 0.5, 30), class_weights(y)
    value, g = loo_probit(y, mu, var, 1.7, -0.3, w)
    by_hand = np.sum(w * norm.logcdf(y * (1.7 * mu - 0.3) / np.sqrt(1 + 1.7**2 * var)))
    assert value == pytest.approx(by_hand, rel=1e-10)
    h = 1e-6
    for name, step in [("alpha", (h, 0)), ("beta", (0, h))]:
        up = loo_probit(y, mu, var, 1.7 + step[0], -0.3 + step[1], w)[0]
        down = loo_probit(y, mu, var, 1.7 - step[0], -0.3 - step[1], w)[0]
        assert g[name] == pytest.approx((up - down) / (2 * h), rel=1e-5)
    e = np.zeros(30)
    e[3] = h
    assert g["mu"][3] == pytest.approx(
        (loo_probit(y, mu + e, var, 1.7, -0.3, w)[0] - loo_probit(y, mu - e, var, 1.7, -0.3, w)[0]) / (2 * h), rel=1e-5
    )
    assert g["var"][3] == pytest.approx(
        (loo_probit(y, mu, var + e, 1.7, -0.3, w)[0] - loo_probit(y, mu, var - e, 1.7, -0.3, w)[0]) / (2 * h), rel=1e-5
    )


def test_squash_fit_raises_the_loo_probability():
    rng = np.random.default_rng(4)
    y = np.where(rng.random(200) < 0.4, 1.0, -1.0)
    mu = 0.6 * y + 0.5 * rng.normal(size=200) - 0.2
    var = rng.uniform(0.05, 0.3, 200)
    before = loo_probit(y, mu, var, 1.0, 0.0)[0]
    sq = ProbitSquash().fit(y, mu, var)
    assert loo_probit(y, mu, var, sq.alpha, sq.beta)[0] > before
    # The squash itself by hand: Phi((2 * 0.5 + 0.1) / sqrt(1 + 4 * 0.21)).
    from scipy.stats import norm

    assert ProbitSquash(2.0, 0.1)(0.5, 0.21) == pytest.approx(norm.cdf(1.1 / np.sqrt(1.84)))


def test_cholesky_in_place_is_the_factor_in_the_matrix_own_memory():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(60, 60))
    K = A @ A.T + 60 * np.eye(60)
    expected = np.linalg.cholesky(K)
    work = K.copy()
    L = cholesky_in_place(work)
    assert L is not None and np.shares_memory(L, work)
    np.testing.assert_allclose(L, expected, rtol=0, atol=1e-12)  # the upper triangle zeroed too
    np.testing.assert_array_equal(L, robust_cholesky(K)[0])  # the same numbers as the copying path
    assert cholesky_in_place(np.ones((3, 3))) is None  # singular: the caller falls back on jitter


def test_a_tile_whose_covariance_is_singular_is_fitted_with_jitter():
    # Two identical cells with opposite labels and almost no noise: the in-place factorisation
    # fails on the tile's covariance, and the tile is formed again and factorised with jitter.
    from gpomap.tiles import TileCells, TileFitTask, TileSettings, fit_tile_task

    box = np.array([[0.0, 0.0], [0.0, 0.0], [2.0, 0.0]]), np.array([[0.5, 0.5], [0.5, 0.5], [2.5, 0.5]])
    settings = TileSettings(area="exact", kernel="se", length_scale_bounds=(1e-2, 1e2), noise_model="constant")
    cells = TileCells(box[0], box[1], np.ones(3), np.array([1.0, -1.0, 1.0]))
    hyperparameters = {"variance": 1.0, "length_scale": 1.0, "noise": 1e-300, "alpha": 1.0, "beta": 0.0}
    state = fit_tile_task(TileFitTask((0, 0), cells, settings, hyperparameters))
    post = state.posterior
    assert post.jitter > 0 and np.all(np.isfinite(post.L)) and np.all(np.isfinite(post.weights))


def test_robust_cholesky_adds_jitter_only_when_needed():
    A = np.array([[2.0, 1.0], [1.0, 2.0]])
    L, jitter = robust_cholesky(A)
    assert jitter == 0.0 and np.allclose(L @ L.T, A)
    singular = np.ones((3, 3))
    L, jitter = robust_cholesky(singular)
    assert jitter > 0 and np.allclose(L @ L.T, singular, atol=1e-6)
    with pytest.raises(NumericalError, match="not positive definite"):
        robust_cholesky(-np.eye(2))


@pytest.mark.parametrize("kernel", [SquaredExponential(1.0, 0.4), Matern32(1.0, 0.3)], ids=["se", "matern32"])
def test_local_prediction_equals_dense(kernel, monkeypatch):
    # A 40 m strip of cells and a short length scale: each block of queries sees a few metres of
    # the map, so local prediction is taken, and must agree with the dense solve (covariances
    # below 1e-9 of the variance left out, so to 1e-9; the default tolerances are checked in
    # test_local_prediction).
    import gpomap.gp.posterior

    monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_TOL", 1e-9)
    monkeypatch.setattr(gpomap.gp.posterior, "LOCAL_VARIANCE_TOL", 1e-9)
    rng = np.random.default_rng(6)
    lo = np.column_stack([rng.uniform(0, 40, 500), rng.uniform(0, 4, 500)])
    X = Supports.from_boxes(lo, lo + rng.uniform(0.1, 0.5, (500, 2)), rng.integers(1, 20, 500).astype(float))
    y = np.where(np.sin(lo[:, 0]) > 0.3, 1.0, -1.0)
    area = "exact" if isinstance(kernel, SquaredExponential) else "quadrature"
    gp = SupportGP(AreaKernel(kernel, area), noise=0.05, noise_model="per_count", optimise=False).fit(X, y)
    Q = Supports.from_points(np.column_stack([rng.uniform(-1, 41, 3000), rng.uniform(-1, 5, 3000)]))
    assert gp.posterior_.local_blocks(Q, 4096) is not None
    mean, var = gp.predict_latent(Q, local=True)
    dense_mean, dense_var = gp.predict_latent(Q, local=False)
    np.testing.assert_allclose(mean, dense_mean, atol=1e-9)
    np.testing.assert_allclose(var, dense_var, atol=1e-9)


def test_inverse_diagonal_matches_the_inverse():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(40, 40))
    K = A @ A.T + 40 * np.eye(40)
    np.testing.assert_allclose(inverse_diagonal(np.linalg.cholesky(K)), np.diag(np.linalg.inv(K)), rtol=1e-10)


def _spd(n, seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    return A @ A.T / n + 0.5 * np.eye(n)


def test_in_place_inverse_is_the_cholesky_inverse():
    from scipy.linalg import lapack

    from gpomap.gp import FILL_BLOCK, _inverse_in_place, cholesky_inverse

    # Several blocks of the triangle mirror, the last one partial.
    n = 2 * FILL_BLOCK + 37
    K = _spd(n, 9)
    L = np.linalg.cholesky(K)
    # LAPACK's lower triangle, mirrored.
    lapack_inverse = lapack.dpotri(L, lower=1)[0]
    expected = np.tril(lapack_inverse) + np.tril(lapack_inverse, -1).T
    np.testing.assert_array_equal(cholesky_inverse(L), expected)
    # Garbage above the diagonal of the factor is never read.
    np.testing.assert_array_equal(cholesky_inverse(L + np.triu(np.ones((n, n)), 1)), expected)
    inv = _inverse_in_place(np.asfortranarray(L))
    np.testing.assert_array_equal(inv, expected)
    np.testing.assert_allclose(inv, np.linalg.inv(K), rtol=1e-9, atol=1e-12)
    assert inv.flags.c_contiguous


@pytest.mark.parametrize("signs", ["mixed", "positive", "negative", "zero"])
def test_weighted_outer_and_its_trace_against_dense_products(signs):
    from gpomap.gp import _trace_product_upper, _weighted_outer_upper

    n = 150
    C = np.linalg.inv(_spd(n, 10))
    C = 0.5 * (C + C.T)
    w = np.random.default_rng(11).normal(size=n)
    w = {"mixed": w, "positive": np.abs(w), "negative": -np.abs(w), "zero": 0 * w}[signs]
    M = C @ np.diag(w) @ C
    upper = _weighted_outer_upper(C, w)
    np.testing.assert_allclose(upper, np.triu(M), rtol=1e-10, atol=1e-12 * np.abs(M).max(initial=1.0))
    assert np.all(np.tril(upper, -1) == 0)
    G = _spd(n, 12)
    assert _trace_product_upper(G, upper) == pytest.approx(np.sum(G * M), rel=1e-10, abs=1e-12)


def _loo_by_the_direct_formulas(gp, X, y, params):
    """The LOO objective's gradient as R&W write it (one n^3 product per hyperparameter)."""
    kern = gp.kernel.clone_with_theta(params[:2])
    K, dK = kern(X, eval_gradient=True)
    nvec = np.exp(params[2]) * gp._noise_scale(X)
    K_inv = np.linalg.inv(K + np.diag(nvec))
    a, d = K_inv @ y, np.diag(K_inv)
    alpha, shift = np.exp(params[3]), params[4]
    value, g = loo_probit(y, y - a / d, 1.0 / d, alpha, alpha * shift, class_weights(y, gp.class_weight))
    grad = []
    for dKj in (dK[:, :, 0], dK[:, :, 1], np.diag(nvec)):
        Z = K_inv @ dKj
        zk = np.diag(Z @ K_inv)
        grad.append(g["mu"] @ ((Z @ a) / d - a * zk / d**2) + g["var"] @ (zk / d**2))
    return value, np.array(grad)


@pytest.mark.parametrize("kernel", KERNELS, ids=["se-exact", "matern-quadrature"])
def test_loo_gradient_equals_the_direct_formulas_on_a_larger_mixed_sample(kernel):
    # Boxes and points, more inputs than one block of the triangle mirror.
    rng = np.random.default_rng(13)
    lower = rng.uniform(0, 8, (220, 2))
    upper = lower + rng.uniform(0.1, 0.8, (220, 2))
    upper[::9] = lower[::9]
    X = Supports.from_boxes(lower, upper, rng.integers(1, 30, 220).astype(float))
    y = np.where(np.sin(lower[:, 0]) + 0.3 * rng.normal(size=220) > 0.2, 1.0, -1.0)
    gp = SupportGP(kernel, noise_model="per_count")
    params = np.array([np.log(1.3), np.log(0.7), np.log(0.05), np.log(2.0), 0.0])
    value, grad = gp.loo_objective(X, y, params, eval_gradient=True)
    ref_value, ref_grad = _loo_by_the_direct_formulas(gp, X, y, params)
    assert value == pytest.approx(ref_value, rel=1e-10)
    np.testing.assert_allclose(grad[:3], ref_grad, rtol=1e-7, atol=1e-9 * np.abs(ref_grad).max())
    fd = _fd(lambda p: gp.loo_objective(X, y, p), params, eps=1e-5)
    np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-5 * np.abs(grad).max())


@pytest.mark.parametrize("objective", ["loo", "lml"])
def test_objectives_fall_back_to_jitter_when_plain_factorisation_fails(objective):
    # Three copies of one box and a noise far below round-off: K + noise is singular, so the
    # in-place factorisation fails and robust_cholesky's jitter takes over.
    X = Supports.from_boxes(np.zeros((3, 2)), np.ones((3, 2)))
    y = np.array([1.0, -1.0, 1.0])
    gp = SupportGP(AreaKernel(SquaredExponential(1.0, 1.0), "exact"))
    params = np.array([0.0, 0.0, np.log(1e-30), 0.0, 0.0])
    K = gp.kernel(X) + 1e-30 * np.eye(3)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(K)
    L, jitter = robust_cholesky(K)
    assert jitter > 0
    K_inv = np.linalg.inv(L @ L.T)
    if objective == "loo":
        value, grad = gp.loo_objective(X, y, params, eval_gradient=True)
        a, d = K_inv @ y, np.diag(K_inv)
        expected = loo_probit(y, y - a / d, 1.0 / d, 1.0, 0.0, class_weights(y, gp.class_weight))[0]
    else:
        value, grad = gp.log_marginal_likelihood(X, y, params[:3], eval_gradient=True)
        expected = -0.5 * y @ K_inv @ y - np.log(np.diag(L)).sum() - 1.5 * np.log(2 * np.pi)
    assert value == pytest.approx(expected, rel=1e-6)
    assert np.all(np.isfinite(grad))


def test_loo_objective_with_the_kernels_prepared_distances():
    # The search reuses the quadrature kernel's node distances from one evaluation to the next:
    # the same objective and gradient to round-off, and the gradient still exact.
    X, y = _data(4, 40)
    gp = SupportGP(AreaKernel(Matern32(1.0, 1.0), "quadrature"), noise_model="per_count")
    prepared = gp.kernel.prepare(X)
    assert prepared is not None
    params = np.array([0.0, np.log(0.8), np.log(0.1), np.log(1.5), 0.0])
    value, grad = gp.loo_objective(X, y, params, eval_gradient=True)
    value1, grad1 = gp._loo_objective(X, y, params, True, prepared)
    assert value1 == pytest.approx(value, rel=1e-12)
    np.testing.assert_allclose(grad1, grad, rtol=1e-10, atol=1e-12)
    fd = _fd(lambda p: gp._loo_objective(X, y, p, False, prepared), params)
    np.testing.assert_allclose(grad1, fd, rtol=1e-5, atol=1e-6)
    lml, lml_grad = gp.log_marginal_likelihood(X, y, params[:3], eval_gradient=True)
    lml1, lml_grad1 = gp._log_marginal_likelihood(X, y, params[:3], True, prepared)
    assert lml1 == pytest.approx(lml, rel=1e-12)
    np.testing.assert_allclose(lml_grad1, lml_grad, rtol=1e-10, atol=1e-12)
    # The exact SE kernel has nothing to prepare.
    assert AreaKernel(SquaredExponential(1.0, 1.0), "exact").prepare(X) is None


def test_compact_groups_halve_at_the_median_of_the_widest_axis():
    # Eight points on a 4 x 2 lattice, groups of at most 2: first cut across x (the wider axis)
    # between x = 1 and x = 2, then across x again, leaving the four columns of two points.
    centres = np.array([[x, y] for x in range(4) for y in range(2)], dtype=float)
    groups = compact_groups(centres, 2)
    assert sorted(tuple(g) for g in groups) == [(0, 1), (2, 3), (4, 5), (6, 7)]
    # Uneven sizes differ by at most one and cover every index once.
    groups = compact_groups(np.random.default_rng(0).uniform(0, 1, (11, 2)), 3)
    assert sorted(np.concatenate(groups).tolist()) == list(range(11))
    assert sorted(g.size for g in groups) == [2, 3, 3, 3]
    with pytest.raises(ValueError, match="max_size"):
        compact_groups(centres, 0)


def _far_apart(first, second):
    """Two data sets, the second moved 200 m away, and both as one: ((X1, y1), (X2, y2), (X, y))."""
    (X1, y1), (X2, y2) = first, second
    X2 = Supports.from_boxes(X2.lower + 200.0, X2.upper + 200.0, X2.counts)
    return (X1, y1), (X2, y2), (concatenate([X1, X2]), np.concatenate([y1, y2]))


@pytest.mark.parametrize("kernel", KERNELS, ids=["se-exact", "matern-quadrature"])
def test_grouped_objectives_are_those_of_groups_that_do_not_covary(kernel):
    # Two clusters 200 m apart do not covary to double precision, so the objectives of one GP
    # over both equal those of the two groups as independent GPs, value and gradient; the
    # grouped gradient is also checked by finite differences.
    (X1, y1), (X2, y2), (X, y) = _far_apart(_data(5, 20), _data(6, 17))
    gp = SupportGP(kernel, noise_model="per_count")
    parts = [(X1, y1, None), (X2, y2, None)]
    params = np.array([0.0, np.log(0.9), np.log(0.1), np.log(1.4), -0.2])
    value, grad = gp.loo_objective(X, y, params, eval_gradient=True)
    value_g, grad_g = gp._parts_loo_objective(parts, params, True)
    assert value_g == pytest.approx(value, rel=1e-12)
    np.testing.assert_allclose(grad_g, grad, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(grad_g, _fd(lambda p: gp._parts_loo_objective(parts, p, False), params), rtol=1e-5, atol=1e-6)
    lml, lml_grad = gp.log_marginal_likelihood(X, y, params[:3], eval_gradient=True)
    lml_g, lml_grad_g = gp._parts_log_marginal_likelihood(parts, params[:3], True)
    assert lml_g == pytest.approx(lml, rel=1e-12)
    np.testing.assert_allclose(lml_grad_g, lml_grad, rtol=1e-9, atol=1e-12)
    # The profiled squash sees both groups' moments together, as one GP's would.
    s1, s2 = ProbitSquash(1.0, 0.0), ProbitSquash(1.0, 0.0)
    gp._loo_objective(X, y, params, False, None, s1)
    gp._parts_loo_objective(parts, params, False, s2)
    assert (s2.alpha, s2.beta) == pytest.approx((s1.alpha, s1.beta), rel=1e-9)


def test_a_grouped_search_learns_what_one_gp_learns_when_groups_are_apart():
    _, _, (X, y) = _far_apart(_data(7, 30), _data(8, 30))
    kernel = AreaKernel(SquaredExponential(1.0, 1.0), "exact")
    one = SupportGP(kernel, hyper_subset=None).fit(X, y)
    grouped = SupportGP(kernel, hyper_subset=None, hyper_group=30).fit(X, y)
    # The same optimum, to the search's own tolerance (the two paths' round-off differs).
    assert grouped.kernel.base.length_scale == pytest.approx(one.kernel.base.length_scale, rel=1e-4)
    assert grouped.noise == pytest.approx(one.noise, rel=1e-4)
    assert (grouped.fit_report_.groups, one.fit_report_.groups) == (2, 1)
    with pytest.raises(ValueError, match="hyper_group"):
        SupportGP(kernel, hyper_group=0)


@pytest.mark.parametrize("objective", ["lml", "loo"])
def test_the_search_per_input_learns_what_the_sum_learns_and_reports_the_sum(objective):
    X, y = _data(2, 40)
    kernel = AreaKernel(SquaredExponential(1.0, 3.0), "exact")
    whole = SupportGP(kernel, noise=1.0, objective=objective).fit(X, y)
    mean = SupportGP(kernel, noise=1.0, objective=objective, objective_per_input=True).fit(X, y)
    # The same optimum, to the search's tolerance.
    assert mean.kernel.base.length_scale == pytest.approx(whole.kernel.base.length_scale, rel=1e-3)
    assert mean.noise == pytest.approx(whole.noise, rel=1e-3)
    # The value reported is the objective's own (with the prior's term), not its mean.
    assert mean.fit_report_.value == pytest.approx(whole.fit_report_.value, rel=1e-6)
    params = [np.log(mean.kernel.base.variance), np.log(mean.kernel.base.length_scale), np.log(mean.noise)]
    if objective == "lml":
        value = mean.log_marginal_likelihood(X, y, np.array(params))
    else:
        value = mean.loo_objective(X, y, np.array([*params, np.log(mean.squash.alpha), mean.squash.beta / mean.squash.alpha]))
    start = np.log([3.0, 1.0])  # the prior's centre: the starting length scale and noise
    prior = -0.5 * float(np.sum(((np.array(params[1:]) - start) / mean.prior_std) ** 2))
    assert mean.fit_report_.value == pytest.approx(value + prior, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("objective", ["loo", "lml"])
def test_a_search_on_threads_learns_to_the_bit_what_it_learns_in_turn(objective):
    # Four groups evaluated on two threads: the same sums in the same order, so the same search
    # (BLAS on one thread in both, as the threads hold it: its threads split sums differently).
    from threadpoolctl import threadpool_limits

    X, y = _data(11, 120)
    kernel = AreaKernel(Matern32(1.0, 0.8), "quadrature")
    with threadpool_limits(1):
        fits = [SupportGP(kernel, hyper_subset=None, hyper_group=30, objective=objective, n_threads=t).fit(X, y) for t in (1, 2)]
    assert fits[0].fit_report_.groups == 4
    assert fits[1].kernel.theta.tolist() == fits[0].kernel.theta.tolist()
    assert fits[1].noise == fits[0].noise
    assert (fits[1].squash.alpha, fits[1].squash.beta) == (fits[0].squash.alpha, fits[0].squash.beta)
    assert fits[1].fit_report_.n_evaluations == fits[0].fit_report_.n_evaluations
    np.testing.assert_array_equal(fits[1].posterior_.weights, fits[0].posterior_.weights)
    with pytest.raises(ValueError, match="n_threads"):
        SupportGP(kernel, n_threads=0)
