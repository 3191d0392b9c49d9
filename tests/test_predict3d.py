"""Predictions whiten by an explicit L^-1 (when it pays): the same mean and variance as the triangular solve."""

import numpy as np
import pytest
from scipy.linalg import solve_triangular

from gpomap.gp import SupportGP, lower_product, triangular_inverse_for
from gpomap.kernels import AreaKernel, Matern32
from gpomap.supports import Supports


def _fitted(dim: int, n: int = 40, seed: int = 0) -> SupportGP:
    rng = np.random.default_rng(seed)
    lo = rng.uniform(0, 4, (n, dim))
    X = Supports.from_boxes(lo, lo + rng.uniform(0.2, 0.8, (n, dim)))
    y = np.where(rng.random(n) < 0.4, 1.0, -1.0)
    kern = AreaKernel(Matern32(1.0, 0.9), "quadrature", "mean", quadrature_order=2)
    return SupportGP(kern, noise=0.05, optimise=False).fit(X, y)


def test_triangular_inverse_only_where_it_pays():
    L = np.linalg.cholesky(np.eye(5) * 2.0 + 0.3)
    assert triangular_inverse_for(L, 100, 1) is None  # a dimension that keeps the solve
    assert triangular_inverse_for(L, 4, 3) is None  # fewer queries than inputs
    L_inv = triangular_inverse_for(L, 5, 3)
    assert L_inv is not None
    np.testing.assert_allclose(L_inv @ L, np.eye(5), atol=1e-14)
    assert np.all(np.triu(L_inv, 1) == 0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_prediction_equals_the_triangular_solve(dim):
    gp = _fitted(dim)
    Q = Supports.from_points(np.random.default_rng(1).uniform(-1, 5, (300, dim)))
    mean, var = gp.predict_latent(Q, return_var=True, chunk_size=128, local=False)
    Ks = gp.kernel(gp.X_train_, Q)
    v = solve_triangular(gp.L_, Ks, lower=True)
    ref_var = np.maximum(gp.kernel.diag(Q) - np.einsum("ij,ij->j", v, v), 0.0)
    np.testing.assert_allclose(mean, Ks.T @ gp.alpha_, rtol=0, atol=1e-12)
    np.testing.assert_allclose(var, ref_var, rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", [1, 5, 8, 37])
def test_lower_product_equals_the_full_product(n):
    rng = np.random.default_rng(n)
    L_inv = np.tril(rng.normal(size=(n, n)))
    K = rng.normal(size=(n, 11))
    np.testing.assert_allclose(lower_product(L_inv, K), L_inv @ K, rtol=0, atol=1e-13)
