"""The SE area kernel between boxes and points (prediction's cross-covariances) against independent references."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from gpomap.kernels import AreaKernel, Matern32, SquaredExponential
from gpomap.kernels import box_points as bp
from gpomap.kernels import closed_form as cf
from gpomap.supports import Supports


def _boxes(rng: np.random.Generator, n: int, dim: int, thin: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Boxes on a coarse lattice (so sides repeat, as a cell tree's do); with `thin`, some sides of zero or sub-POINT_WIDTH width."""
    lower = np.round(rng.uniform(0.0, 3.0, (n, dim)), 1)
    upper = lower + rng.choice([0.0, 1e-5, 0.1, 0.25, 0.5, 1.0] if thin else [0.1, 0.25, 0.5, 1.0], (n, dim))
    return lower, upper


def _points(rng: np.random.Generator, m: int, dim: int, grid: bool) -> np.ndarray:
    p = rng.uniform(-1.0, 4.0, (m, dim))
    return np.round(p, 1) if grid else p  # rounded: coordinates repeat, as a grid's rows and columns


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("grid", [False, True], ids=["scattered", "grid"])
@pytest.mark.parametrize("thin", [True, False], ids=["thin-sides", "intervals"])
def test_box_point_average_is_the_box_average_bit_for_bit(dim, grid, thin):
    rng = np.random.default_rng(dim)
    lower, upper = _boxes(rng, 200, dim, thin)
    points = _points(rng, 300, dim, grid)
    reference, _ = cf.se_box_average(lower, upper, points, points, 1.3, 0.37)
    np.testing.assert_array_equal(bp.se_box_point_average(lower, upper, points, 1.3, 0.37), reference)


def test_box_point_average_by_hand():
    # A point at the centre of [-a, a]: (1 / 2a) * integral of exp(-s^2 / 2 l^2) = l sqrt(pi / 2) erf(a / (sqrt(2) l)) / a.
    a, l = 0.4, 0.3
    expected = l * np.sqrt(np.pi / 2) * erf(a / (np.sqrt(2) * l)) / a
    K = bp.se_box_point_average(np.array([[-a]]), np.array([[a]]), np.array([[0.0]]), 1.0, l)
    assert K[0, 0] == pytest.approx(expected, rel=1e-14)
    # A zero-width box is the point kernel.
    K = bp.se_box_point_average(np.array([[0.5, 1.0]]), np.array([[0.5, 1.0]]), np.array([[0.2, 1.4]]), 2.0, l)
    assert K[0, 0] == pytest.approx(2.0 * np.exp(-(0.3**2 + 0.4**2) / (2 * l * l)), rel=1e-14)


def test_box_point_average_matches_brute_force_integration():
    """The midpoint rule over each 2-D box, on a fine grid (no separability assumed)."""
    rng = np.random.default_rng(7)
    variance, l = 1.7, 0.45
    lower = rng.uniform(0.0, 2.0, (5, 2))
    upper = lower + rng.uniform(0.05, 1.2, (5, 2))
    points = rng.uniform(-0.5, 3.0, (6, 2))
    K = bp.se_box_point_average(lower, upper, points, variance, l)
    n = 400
    t = (np.arange(n) + 0.5) / n
    for i in range(5):
        xs = lower[i, 0] + t * (upper[i, 0] - lower[i, 0])
        ys = lower[i, 1] + t * (upper[i, 1] - lower[i, 1])
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        for j in range(6):
            d2 = (X - points[j, 0]) ** 2 + (Y - points[j, 1]) ** 2
            brute = variance * np.mean(np.exp(-0.5 * d2 / l**2))
            assert K[i, j] == pytest.approx(brute, rel=2e-4, abs=1e-10)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("grid", [False, True], ids=["scattered", "grid"])
@pytest.mark.parametrize("table_limit", [bp.MAX_FACTOR_TABLE, 0], ids=["tabled", "per-block"])
@pytest.mark.parametrize("thin", [True, False], ids=["thin-sides", "intervals"])
def test_box_point_factors_blocks_are_the_box_point_average(dim, grid, table_limit, thin, monkeypatch):
    monkeypatch.setattr(bp, "MAX_FACTOR_TABLE", table_limit)
    rng = np.random.default_rng(10 + dim)
    lower, upper = _boxes(rng, 250, dim, thin)
    points = _points(rng, 400, dim, grid)
    factors = bp.BoxPointFactors(lower, upper, points, 0.8, 0.3)
    assert all((table is not None) == (grid and table_limit > 0) for *_, table, _ in factors.axes)
    for _ in range(3):
        rows = np.sort(rng.choice(250, 90, replace=False))
        cols = rng.choice(400, 120, replace=False)
        expected = bp.se_box_point_average(lower[rows], upper[rows], points[cols], 0.8, 0.3)
        np.testing.assert_array_equal(factors.block(rows, cols), expected)


@pytest.mark.parametrize(
    "kernel",
    [AreaKernel(SquaredExponential(1.3, 0.4)), AreaKernel(Matern32(0.7, 0.5), "quadrature")],
    ids=["se-exact", "matern32-quadrature"],
)
def test_point_blocks_are_the_kernel(kernel):
    rng = np.random.default_rng(3)
    lower, upper = _boxes(rng, 60, 2)
    A = Supports.from_boxes(lower, upper)
    points = _points(rng, 80, 2, grid=True)
    full = kernel(A, Supports.from_points(points))
    rows, cols = np.arange(5, 40), rng.choice(80, 30, replace=False)
    np.testing.assert_allclose(kernel.point_blocks(A, points).block(rows, cols), full[rows][:, cols], rtol=1e-14, atol=0)
    # Points against boxes: the transpose.
    np.testing.assert_allclose(kernel(Supports.from_points(points), A), full.T, rtol=1e-14, atol=0)
