"""Invariants of every kernel, and area kernels against brute-force references."""

import numpy as np
import pytest

from gpomap.kernels import AreaKernel, Matern32, SquaredExponential
from gpomap.supports import Supports, concatenate
from tests import reference


def _cells(seed=0, n=6, dim=2):
    """A few cells with member points inside their boxes, plus two zero-width points."""
    rng = np.random.default_rng(seed)
    lower = rng.uniform(0, 3, (n, dim))
    upper = lower + rng.uniform(0.2, 1.2, (n, dim))
    sizes = rng.integers(1, 6, n)
    members = np.concatenate([rng.uniform(lower[i], upper[i], (sizes[i], dim)) for i in range(n)])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    cells = Supports(lower, upper, sizes.astype(float), members, offsets)
    return concatenate([cells, Supports.from_points(rng.uniform(0, 4, (2, dim)))])


POINT_KERNELS = [SquaredExponential(1.3, 0.8), Matern32(0.7, 1.1)]
AREA_KERNELS = [
    AreaKernel(SquaredExponential(1.3, 0.8), "exact", "mean"),
    AreaKernel(SquaredExponential(1.3, 0.8), "exact", "sum"),
    AreaKernel(SquaredExponential(1.3, 0.8), "quadrature", "mean"),
    AreaKernel(SquaredExponential(1.3, 0.8), "summed", "mean"),
    AreaKernel(Matern32(0.7, 1.1), "quadrature", "mean"),
    AreaKernel(Matern32(0.7, 1.1), "quadrature", "sum", quadrature_order=4),
    AreaKernel(Matern32(0.7, 1.1), "summed", "mean"),
    AreaKernel(Matern32(0.7, 1.1), "summed", "sum"),
]
# Every invariant in 2-D and in 3-D (boxes become cuboids; nothing else changes).
ALL = [(k, f"points{d}") for d in (2, 3) for k in POINT_KERNELS] + [(k, f"cells{d}") for d in (2, 3) for k in AREA_KERNELS]
IDS = [f"{kind}-{k!r}" for k, kind in ALL]


def _inputs(kind, seed=0):
    dim = int(kind[-1])
    if kind.startswith("points"):
        return np.random.default_rng(seed).uniform(0, 3, (7, dim))
    return _cells(seed, dim=dim)


@pytest.mark.parametrize("kernel,kind", ALL, ids=IDS)
def test_gradient_matches_finite_differences(kernel, kind):
    X = _inputs(kind)
    _, dK = kernel(X, eval_gradient=True)
    theta = kernel.theta
    eps = 1e-6
    for j in range(theta.size):
        up, down = theta.copy(), theta.copy()
        up[j] += eps
        down[j] -= eps
        fd = (kernel.clone_with_theta(up)(X) - kernel.clone_with_theta(down)(X)) / (2 * eps)
        np.testing.assert_allclose(dK[:, :, j], fd, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("kernel,kind", ALL, ids=IDS)
def test_gram_is_symmetric_psd_and_consistent(kernel, kind):
    X = _inputs(kind)
    K = kernel(X)
    np.testing.assert_allclose(K, kernel(X, X), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-14)
    assert np.linalg.eigvalsh(K).min() > -1e-10 * np.abs(K).max()
    np.testing.assert_allclose(kernel.diag(X), np.diag(K), rtol=1e-10)


@pytest.mark.parametrize("kernel,kind", ALL, ids=IDS)
def test_cross_covariance_is_the_transpose(kernel, kind):
    X, Y = _inputs(kind, 0), _inputs(kind, 1)
    np.testing.assert_allclose(kernel(X, Y), kernel(Y, X).T, rtol=1e-12, atol=1e-14)


def test_point_kernels_by_hand():
    x, y = np.array([[0.0, 0.0]]), np.array([[3.0, 4.0]])  # distance 5
    assert SquaredExponential(2.0, 5.0)(x, y)[0, 0] == pytest.approx(2.0 * np.exp(-0.5))
    s = np.sqrt(3.0)
    assert Matern32(2.0, 5.0)(x, y)[0, 0] == pytest.approx(2.0 * (1 + s) * np.exp(-s))


BOX_PAIRS = [
    # (lower_a, upper_a, lower_b, upper_b): disjoint, overlapping, identical, point-box, thin box
    ((0.0, 0.0), (1.0, 0.5), (1.5, -0.5), (2.5, 0.7)),
    ((0.0, 0.0), (1.0, 1.0), (0.5, 0.3), (1.4, 1.2)),
    ((0.2, 0.1), (0.9, 0.6), (0.2, 0.1), (0.9, 0.6)),
    ((0.4, 0.4), (0.4, 0.4), (0.0, 0.0), (1.0, 0.8)),
    ((0.0, 0.0), (2.0, 0.0), (0.5, 0.5), (1.0, 1.5)),
    # 3-D: disjoint cuboids, overlapping, identical, point-cuboid, a flat plate against a cube
    ((0.0, 0.0, 0.0), (1.0, 0.5, 0.7), (1.5, -0.5, 0.4), (2.5, 0.7, 1.0)),
    ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.5, 0.3, -0.2), (1.4, 1.2, 0.6)),
    ((0.2, 0.1, 0.3), (0.9, 0.6, 0.8), (0.2, 0.1, 0.3), (0.9, 0.6, 0.8)),
    ((0.4, 0.4, 0.4), (0.4, 0.4, 0.4), (0.0, 0.0, 0.0), (1.0, 0.8, 0.9)),
    ((0.0, 0.0, 0.5), (2.0, 1.0, 0.5), (0.5, 0.5, 0.0), (1.0, 1.5, 1.0)),
]
PAIR_IDS = [f"{len(p[0])}d-{i}" for i, p in enumerate(BOX_PAIRS)]


def _brute(base, la, ua, lb, ub):
    """The fine midpoint rule over both boxes in 2-D; in 3-D (where that is 50^6 node pairs) the
    integral over the difference of the two boxes' points."""
    if la.size == 2:
        return reference.box_average(base, la, ua, lb, ub, n=50)
    return reference.box_average_by_difference(base, la, ua, lb, ub, n=80)


@pytest.mark.parametrize("pair", BOX_PAIRS, ids=PAIR_IDS)
def test_exact_se_matches_brute_force_integration(pair):
    base = SquaredExponential(1.0, 0.7)
    la, ua, lb, ub = (np.array(v, float)[None, :] for v in pair)
    exact = AreaKernel(base, "exact")(Supports.from_boxes(la, ua), Supports.from_boxes(lb, ub))[0, 0]
    brute = _brute(base, la[0], ua[0], lb[0], ub[0])
    assert exact == pytest.approx(brute, rel=5e-4)


def test_box_difference_reference_agrees_with_the_plain_midpoint_rule():
    """The 3-D reference checked against the obvious one where that is still affordable (2-D boxes)."""
    for base in (SquaredExponential(1.0, 0.7), Matern32(1.0, 0.9)):
        for la, ua, lb, ub in BOX_PAIRS[:5]:
            a = reference.box_average(base, np.array(la), np.array(ua), np.array(lb), np.array(ub), n=50)
            b = reference.box_average_by_difference(base, np.array(la), np.array(ua), np.array(lb), np.array(ub), n=200)
            assert b == pytest.approx(a, rel=5e-4)


@pytest.mark.parametrize("pair", BOX_PAIRS, ids=PAIR_IDS)
@pytest.mark.parametrize("base", [SquaredExponential(1.0, 0.7), Matern32(1.0, 0.9)], ids=["se", "matern32"])
def test_quadrature_matches_brute_force_integration(pair, base):
    la, ua, lb, ub = (np.array(v, float)[None, :] for v in pair)
    A, B = Supports.from_boxes(la, ua), Supports.from_boxes(lb, ub)
    brute = _brute(base, la[0], ua[0], lb[0], ub[0])
    # The default rule is close; a higher order converges (Matern 3/2 is not smooth at r = 0,
    # so boxes that overlap converge more slowly).
    assert AreaKernel(base, "quadrature", quadrature_order=3)(A, B)[0, 0] == pytest.approx(brute, rel=2e-2)
    assert AreaKernel(base, "quadrature", quadrature_order=10)(A, B)[0, 0] == pytest.approx(brute, rel=1e-3)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("base", [SquaredExponential(1.3, 0.8), Matern32(0.7, 1.1)], ids=["se", "matern32"])
def test_summed_kernel_equals_explicit_double_loop(base, dim):
    X = _cells(3, dim=dim)
    K_sum = AreaKernel(base, "summed", "sum")(X)
    K_mean = AreaKernel(base, "summed", "mean")(X)
    off = X.member_offsets
    for i in range(len(X)):
        for j in range(len(X)):
            mi = X.member_points[off[i] : off[i + 1]]
            mj = X.member_points[off[j] : off[j + 1]]
            loops = reference.summed_by_loops(base, mi, mj)
            assert K_sum[i, j] == pytest.approx(loops, rel=1e-10)
            assert K_mean[i, j] == pytest.approx(loops / (len(mi) * len(mj)), rel=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("method", ["exact", "quadrature"])
def test_cell_shrunk_to_a_point_gives_the_point_kernel(method, dim):
    base = SquaredExponential(1.1, 0.6)
    rng = np.random.default_rng(5)
    p = rng.uniform(0, 2, (1, dim))
    q = rng.uniform(0, 2, (4, dim))
    kernel = AreaKernel(base, method)
    for half in [1e-2, 1e-3, 1e-5]:
        cell = Supports.from_boxes(p - half, p + half)
        np.testing.assert_allclose(kernel(cell, Supports.from_points(q)), base(p, q), rtol=dim * half / 0.6 + 1e-9)
    # And exactly zero width takes the point formula.
    np.testing.assert_allclose(kernel(Supports.from_points(p), Supports.from_points(q)), base(p, q), rtol=1e-12)


def test_matern_quadrature_shrinks_to_point_kernel():
    base = Matern32(1.0, 0.9)
    p, q = np.array([[0.3, 0.2]]), np.array([[1.5, -0.4], [2.0, 2.0]])
    cell = Supports.from_boxes(p - 1e-4, p + 1e-4)
    np.testing.assert_allclose(AreaKernel(base, "quadrature")(cell, Supports.from_points(q)), base(p, q), rtol=1e-5)


def test_mixed_inputs_follow_eq_14():
    """K over [cells; points] is the block matrix of cell-cell, cell-point and point-point parts."""
    kernel = AreaKernel(SquaredExponential(1.0, 0.9), "exact")
    cells = Supports.from_boxes(np.array([[0.0, 0.0], [2.0, 1.0]]), np.array([[1.0, 1.0], [3.0, 1.5]]))
    pts = Supports.from_points(np.array([[0.5, 2.0], [2.5, 0.0], [1.0, 1.0]]))
    K = kernel(concatenate([cells, pts]))
    np.testing.assert_allclose(K[:2, :2], kernel(cells))
    np.testing.assert_allclose(K[:2, 2:], kernel(cells, pts))
    np.testing.assert_allclose(K[2:, 2:], kernel.base(pts.lower))


def test_exact_needs_the_squared_exponential():
    with pytest.raises(ValueError, match="closed form only for the squared exponential"):
        AreaKernel(Matern32(), "exact")


@pytest.mark.parametrize("kernel", [SquaredExponential(2.0, 0.7), Matern32(0.5, 1.3)], ids=["se", "matern32"])
def test_cutoff_is_where_the_kernel_falls_below_the_tolerance(kernel):
    r = kernel.cutoff(1e-9)
    assert kernel.values(np.array(r * r))[0] <= 1e-9 * kernel.variance
    assert kernel.values(np.array((0.99 * r) ** 2))[0] > 1e-9 * kernel.variance


@pytest.mark.parametrize("kernel", AREA_KERNELS, ids=repr)
@pytest.mark.parametrize("dim", [2, 3])
def test_gram_and_length_scale_gradient_is_the_full_gradient_without_the_variance(kernel, dim):
    X = _cells(dim=dim)
    K, dL = kernel.gram_and_length_scale_gradient(X)
    # Exactly symmetric (the objectives factorise it in place, reading one triangle).
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_array_equal(dL, dL.T)
    assert K.flags.c_contiguous and dL.flags.c_contiguous
    K_full, dK_full = kernel(X, eval_gradient=True)
    np.testing.assert_array_equal(K, K_full)
    np.testing.assert_array_equal(dL, dK_full[:, :, 1])
    np.testing.assert_array_equal(K, dK_full[:, :, 0])
    # Against finite differences in log length scale.
    eps = 1e-6
    up, down = kernel.theta.copy(), kernel.theta.copy()
    up[1] += eps
    down[1] -= eps
    fd = (kernel.clone_with_theta(up)(X) - kernel.clone_with_theta(down)(X)) / (2 * eps)
    np.testing.assert_allclose(dL, fd, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "compiled"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_se_box_gram_equals_the_box_average_symmetrised(dim, compiled, monkeypatch):
    from gpomap.kernels import _compiled_box
    from gpomap.kernels.closed_form import se_box_average, se_box_gram

    monkeypatch.setattr(_compiled_box, "ENABLED", compiled)

    rng = np.random.default_rng(dim)
    # Boxes on a coarse grid share their sides (as cells from the tree do), some of zero width.
    lower = rng.integers(0, 8, (60, dim)) * 0.25
    upper = lower + rng.integers(0, 4, (60, dim)) * 0.25
    K0, dK0 = se_box_average(lower, upper, lower, upper, 1.7, 0.6, eval_gradient=True)
    assert dK0 is not None
    K, dL = se_box_gram(lower, upper, 1.7, 0.6, eval_gradient=True)
    assert dL is not None
    # The compiled path takes libm's erf, not scipy's, and sums in another order: the corners'
    # cancellation (four G2 terms of order l^2 for an entry of order w^2) shows it at 1e-15.
    atol = 2e-15 if compiled else 1e-16
    np.testing.assert_allclose(K, 0.5 * (K0 + K0.T), rtol=1e-14, atol=atol)
    np.testing.assert_allclose(dL, 0.5 * (dK0[:, :, 1] + dK0[:, :, 1].T), rtol=1e-13, atol=atol)
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_array_equal(dL, dL.T)
    # In row blocks (bounded memory): the same numbers.
    Kb, dLb = se_box_gram(lower, upper, 1.7, 0.6, eval_gradient=True, max_block=7 * 60)
    np.testing.assert_array_equal(Kb, K)
    np.testing.assert_array_equal(dLb, dL)
    Kv, none = se_box_gram(lower, upper, 1.7, 0.6)
    assert none is None
    np.testing.assert_array_equal(Kv, K)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("scale", [0.05, 0.6, 5.0])
def test_compiled_se_box_gram_gives_the_numpy_paths_numbers(dim, scale, monkeypatch):
    from gpomap.kernels import _compiled_box
    from gpomap.kernels.closed_form import se_box_gram

    rng = np.random.default_rng(21)
    # Shared sides, repeated boxes, points, and sides narrower than the point width at the
    # small length scale (points there, intervals at the others).
    lower = rng.integers(0, 16, (250, dim)) * 0.125
    upper = lower + rng.integers(0, 5, (250, dim)) * 0.125
    upper[::13, 0] = lower[::13, 0] + 1e-5
    lower[7], upper[7] = lower[3], upper[3]
    monkeypatch.setattr(_compiled_box, "ENABLED", False)
    K0, dL0 = se_box_gram(lower, upper, 1.3, scale, eval_gradient=True)
    monkeypatch.setattr(_compiled_box, "ENABLED", True)
    K, dL = se_box_gram(lower, upper, 1.3, scale, eval_gradient=True)
    # To round-off: the corners lose (l / w)^2 of it to cancellation in both paths (sides of
    # 0.125 m at l = 5 m: about 1e-13).
    np.testing.assert_allclose(K, K0, rtol=0, atol=4e-15 * max(1.0, (scale / 0.125) ** 2))
    np.testing.assert_allclose(dL, dL0, rtol=0, atol=4e-15 * max(1.0, (scale / 0.125) ** 2))
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_array_equal(dL, dL.T)
    np.testing.assert_array_equal(se_box_gram(lower, upper, 1.3, scale)[0], K)  # without the derivative
    assert se_box_gram(lower[:0], upper[:0], 1.3, scale)[0].shape == (0, 0)


@pytest.mark.parametrize("scale", [0.05, 0.6, 5.0])
def test_interval_gram_is_the_interval_average_symmetrised(scale):
    from gpomap.kernels.closed_form import distinct_intervals, interval_average, interval_gram

    rng = np.random.default_rng(14)
    # Shared ends (cells from a tree), points among the intervals, and intervals narrower than
    # the point width at the small length scale.
    lo = rng.integers(0, 12, 80) * 0.125
    hi = lo + rng.integers(0, 5, 80) * 0.125
    hi[::11] = lo[::11] + 1e-5
    a, b, inverse = distinct_intervals(lo, hi)
    np.testing.assert_array_equal(np.column_stack([a, b])[inverse], np.column_stack([lo, hi]))
    expected, _ = np.unique(np.column_stack([lo, hi]), axis=0, return_inverse=True)
    np.testing.assert_array_equal(np.column_stack([a, b]), expected)
    F0, dF0 = interval_average(a, b, a, b, scale, eval_gradient=True)
    assert dF0 is not None
    F, dF = interval_gram(a, b, scale, eval_gradient=True)
    # The same corner differences and formulas: the same numbers, to the last bit.
    np.testing.assert_array_equal(F, 0.5 * (F0 + F0.T))
    np.testing.assert_array_equal(dF, 0.5 * (dF0 + dF0.T))
    F1, none = interval_gram(a, b, scale)
    assert none is None
    np.testing.assert_array_equal(F1, F)
