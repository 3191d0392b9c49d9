"""The tensor-product quadrature kernel against the node sums it replaces (the reference).

Every test runs twice: on the compiled path (:mod:`gpomap.kernels._compiled`, numba) and on the
numpy one. ``tests/test_tensor_compiled.py`` compares the two directly.
"""

import numpy as np
import pytest

from gpomap.kernels import AreaKernel, Matern32, SquaredExponential, _compiled
from gpomap.kernels.nodes import quadrature_nodes, weighted_gram, weighted_self
from gpomap.kernels.tensor import tensor_gram, tensor_rules, tensor_self
from gpomap.supports import Supports, concatenate


class _NoUnitForm(Matern32):
    """Matern 3/2 without its unit profile: the tensor path's generic branch (values_into)."""

    @property
    def unit_scale(self):
        return None


KERNELS = [Matern32(1.3, 0.7), SquaredExponential(0.8, 1.1), _NoUnitForm(1.3, 0.7)]


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def kernel_path(request, monkeypatch):
    """The tensor kernel's evaluation: numba's (when it imports) or numpy's."""
    if request.param == "compiled" and not _compiled.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(_compiled, "ENABLED", request.param == "compiled")
    return request.param


def _boxes(rng, n, dim, zero_every=7):
    """`n` boxes, every `zero_every`-th of zero width (a point, as ambiguous cells can be)."""
    lo = rng.uniform(0, 5, (n, dim))
    hi = lo + rng.uniform(0.05, 1.2, (n, dim))
    hi[::zero_every] = lo[::zero_every]
    return Supports.from_boxes(lo, hi)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("order", [1, 2, 3])
@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
@pytest.mark.parametrize("block", [5, 100, 1 << 16])
def test_tensor_gram_equals_node_sums(dim, order, kernel, block):
    rng = np.random.default_rng(dim * 10 + order)
    A = _boxes(rng, 23, dim)
    B = concatenate([Supports.from_points(rng.uniform(0, 5, (17, dim))), _boxes(rng, 6, dim, zero_every=4)])
    na, nb = quadrature_nodes(A, order), quadrature_nodes(B, order)
    K0, dK0 = weighted_gram(kernel, na, nb, eval_gradient=True)
    K1, dK1 = tensor_gram(kernel, A, B, order, eval_gradient=True, block=block)
    np.testing.assert_allclose(K1, K0, rtol=0, atol=1e-14)
    assert dK1 is not None and dK0 is not None
    np.testing.assert_allclose(dK1, dK0, rtol=0, atol=1e-14)
    # The Gram matrix of one set: each pair once, mirrored, and the gradient with it.
    S0, dS0 = weighted_gram(kernel, na, na, eval_gradient=True)
    S1, dS1 = tensor_gram(kernel, A, None, order, eval_gradient=True, block=block)
    np.testing.assert_allclose(S1, S0, rtol=0, atol=1e-14)
    assert dS1 is not None and dS0 is not None
    np.testing.assert_allclose(dS1, dS0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(S1, S1.T, rtol=0, atol=1e-15)
    K2, none = tensor_gram(kernel, A, B, order, block=block)
    assert none is None
    np.testing.assert_array_equal(K2, K1)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("order", [1, 2, 3])
def test_tensor_self_equals_node_sums(dim, order):
    A = _boxes(np.random.default_rng(order), 19, dim)
    for kernel in KERNELS:
        np.testing.assert_allclose(tensor_self(kernel, A, order), weighted_self(kernel, quadrature_nodes(A, order)), atol=1e-14)


def test_rules_group_boxes_then_points():
    A = _boxes(np.random.default_rng(0), 10, 3, zero_every=3)
    index, rules = tensor_rules(A, 2)
    assert [len(r) for r in rules] == [6, 4]
    np.testing.assert_array_equal(np.sort(np.concatenate(index)), np.arange(10))
    assert rules[0].coords.shape == (3, 2, 6) and rules[1].coords.shape == (3, 1, 4)
    assert rules[0].weights.sum() == pytest.approx(1.0) and rules[1].weights.tolist() == [1.0]
    # Gauss-Legendre order 2 on [0, 1]: nodes at 1/2 -+ 1/(2 sqrt 3) of each side.
    lo, w = A.lower[index[0][0]], A.widths[index[0][0]]
    np.testing.assert_allclose(rules[0].coords[:, :, 0], lo[:, None] + w[:, None] * (0.5 + np.array([-1, 1]) / (2 * np.sqrt(3))))
    with pytest.raises(ValueError, match="at least 1"):
        tensor_rules(A, 0)


def test_area_kernel_takes_the_tensor_path_in_2d_and_3d():
    rng = np.random.default_rng(3)
    for dim in (2, 3):
        A, Q = _boxes(rng, 12, dim), Supports.from_points(rng.uniform(0, 5, (9, dim)))
        kern = AreaKernel(Matern32(1.0, 0.9), "quadrature", "mean", quadrature_order=2)
        K = kern(A, Q)
        ref, _ = weighted_gram(kern.base, quadrature_nodes(A, 2), quadrature_nodes(Q, 2))
        # The same node values summed in another order: equal to round-off, not bit for bit.
        np.testing.assert_allclose(K, ref, rtol=0, atol=1e-14)
        np.testing.assert_allclose(kern.diag(A), weighted_self(kern.base, quadrature_nodes(A, 2)), atol=1e-14)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_unit_profile_is_the_kernel_over_its_variance(kernel):
    d2 = np.random.default_rng(5).uniform(0, 30, (4, 9))
    K, dK = kernel.values(d2, True)
    out, grad = np.empty_like(d2), np.empty_like(d2)
    kernel.values_into(d2.copy(), out, grad)
    np.testing.assert_array_equal(out, K)
    np.testing.assert_array_equal(grad, dK)
    if kernel.unit_scale is None:
        return
    u2 = d2 * kernel.unit_scale**2
    for g in (None, np.empty_like(d2)):
        kernel.unit_profile_into(u2.copy(), out, g, np.empty_like(d2))
        np.testing.assert_allclose(kernel.variance * out, K, rtol=1e-13)
        if g is not None:
            np.testing.assert_allclose(kernel.variance * g, dK, rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
@pytest.mark.parametrize("block", [5, 100, 2000, 1 << 16])
def test_length_scale_gram_is_exactly_symmetric_and_the_full_gradients_part(dim, kernel, block):
    from gpomap.kernels.tensor import tensor_gram_length_scale

    rng = np.random.default_rng(dim)
    A = concatenate([_boxes(rng, 31, dim), Supports.from_points(rng.uniform(0, 5, (9, dim)))])
    K, dL = tensor_gram_length_scale(kernel, A, None, 2, eval_gradient=True, block=block)
    assert dL is not None
    # The diagonal blocks' pairs are computed both ways round; their mean makes K symmetric.
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_array_equal(dL, dL.T)
    S0, dS0 = weighted_gram(kernel, quadrature_nodes(A, 2), quadrature_nodes(A, 2), eval_gradient=True)
    assert dS0 is not None
    np.testing.assert_allclose(K, S0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(dL, dS0[:, :, 1], rtol=0, atol=1e-14)
    K1, dK1 = tensor_gram(kernel, A, None, 2, eval_gradient=True, block=block)
    assert dK1 is not None
    np.testing.assert_array_equal(K1, K)
    np.testing.assert_array_equal(dK1[:, :, 0], K)
    np.testing.assert_array_equal(dK1[:, :, 1], dL)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
@pytest.mark.parametrize("block", [5, 2000, 1 << 16])
def test_cached_node_distances_give_the_same_gram(dim, kernel, block):
    from gpomap.kernels.tensor import tensor_distances, tensor_gram_length_scale

    rng = np.random.default_rng(dim + 20)
    A = concatenate([_boxes(rng, 29, dim), Supports.from_points(rng.uniform(0, 5, (7, dim))), _boxes(rng, 5, dim)])
    distances = tensor_distances(A, 2, block)
    assert distances is not None and distances.fits(A, 2, block)
    K0, dL0 = tensor_gram_length_scale(kernel, A, None, 2, eval_gradient=True, block=block)
    K1, dL1 = tensor_gram_length_scale(kernel, A, None, 2, eval_gradient=True, block=block, distances=distances)
    assert dL0 is not None and dL1 is not None
    if kernel.unit_scale is None:
        # No unit form: the distances are not used.
        np.testing.assert_array_equal(K1, K0)
    np.testing.assert_allclose(K1, K0, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dL1, dL0, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(K1, K1.T)
    # Distances of other inputs, another rule or another block size are not taken.
    other = Supports.from_boxes(A.lower.copy(), A.upper.copy())
    for args in [(other, 2, block), (A, 3, block), (A, 2, block + 1)]:
        K2, _ = tensor_gram_length_scale(kernel, args[0], None, args[1], block=args[2], distances=distances)
        K3, _ = tensor_gram_length_scale(kernel, args[0], None, args[1], block=args[2])
        np.testing.assert_array_equal(K2, K3)
    # More pairs than allowed: none kept.
    assert tensor_distances(A, 2, block, max_pairs=100) is None


@pytest.mark.parametrize("kernel", [Matern32(1.3, 0.7), SquaredExponential(0.8, 1.1)], ids=lambda k: type(k).__name__)
def test_unit_profile_from_negated_distances_is_the_profile_of_their_squares(kernel):
    u = np.random.default_rng(3).uniform(0, 6, 1000)
    out0, grad0 = np.empty_like(u), np.empty_like(u)
    kernel.unit_profile_into(u * u, out0, grad0)
    out1, grad1 = np.empty_like(u), np.empty_like(u)
    kernel.unit_profile_from_negated_distance_into(-u, out1, grad1, np.empty_like(u))
    np.testing.assert_allclose(out1, out0, rtol=1e-14, atol=1e-300)
    np.testing.assert_allclose(grad1, grad0, rtol=1e-14, atol=1e-300)
    out2 = np.empty_like(u)
    kernel.unit_profile_from_negated_distance_into(-u, out2)
    np.testing.assert_allclose(out2, out1, rtol=1e-15, atol=1e-300)
