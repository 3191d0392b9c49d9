"""Invariants of the line (integral) kernels, over one list of kernels, plus brute-force checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from gpomap.kernels.line import LineKernel, Segments, concatenate_segments, segment_nodes

KERNELS = [
    ("se", "mean", 4, 1.0),
    ("se", "sum", 4, 1.0),
    ("se", "mean", 3, None),
    ("matern32", "mean", 6, 0.5),
    ("matern32", "sum", 4, 1.0),
]
IDS = [f"{b}-{n}-o{o}-p{p}" for b, n, o, p in KERNELS]


def make(spec, length_scale=0.7, variance=1.3) -> LineKernel:
    base, norm, order, panel = spec
    k = LineKernel(base, norm, order=order, max_panel=panel)
    k.theta = np.log([variance, length_scale])
    return k


def inputs() -> Segments:
    """Skew, parallel, collinear, crossing, sharing-a-start segments, and points."""
    rng = np.random.default_rng(3)
    s = rng.uniform(0, 3, (5, 2))
    e = rng.uniform(0, 3, (5, 2))
    fan_start = np.array([[1.0, 1.0]] * 3)
    fan_end = fan_start + np.array([[2.0, 0.0], [1.5, 1.5], [0.0, 2.5]])
    par_s = np.array([[0.0, 0.5], [0.5, 0.5], [4.0, 4.0]])
    par_e = np.array([[2.0, 0.5], [0.0, 0.5], [2.0, 2.0]])  # collinear pair, and a diagonal
    segs = Segments(np.r_[s, fan_start, par_s], np.r_[e, fan_end, par_e])
    pts = Segments.from_points(rng.uniform(0, 3, (3, 2)))
    return concatenate_segments([segs, pts])


def brute(kernel: LineKernel, X: Segments, i: int, j: int) -> float:
    """The line kernel by adaptive 2-D (or 1-D) quadrature of the point kernel."""

    def x(k, u):
        return X.starts[k] + u * (X.ends[k] - X.starts[k])

    def k2(u, v):
        return float(kernel.base(x(i, u)[None], x(j, v)[None])[0, 0])

    pi, pj = X.is_point[i], X.is_point[j]
    if pi and pj:
        val = k2(0.0, 0.0)
    elif pi:
        val = integrate.quad(lambda v: k2(0.0, v), 0, 1, epsabs=1e-12, limit=200)[0]
    elif pj:
        val = integrate.quad(lambda u: k2(u, 0.0), 0, 1, epsabs=1e-12, limit=200)[0]
    else:
        val = integrate.dblquad(lambda v, u: k2(u, v), 0, 1, 0, 1, epsabs=1e-10)[0]
    if kernel.normalisation == "sum":
        w = np.where(X.is_point, 1.0, X.lengths)
        val *= w[i] * w[j]
    return val


@pytest.mark.parametrize("spec", KERNELS, ids=IDS)
def test_gradient_matches_finite_differences(spec):
    k = make(spec)
    X = inputs()
    _, dK = k(X, eval_gradient=True)
    eps = 1e-6
    for j in range(2):
        tp, tm = k.theta.copy(), k.theta.copy()
        tp[j] += eps
        tm[j] -= eps
        fd = (k.clone_with_theta(tp)(X) - k.clone_with_theta(tm)(X)) / (2 * eps)
        np.testing.assert_allclose(dK[:, :, j], fd, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("spec", KERNELS, ids=IDS)
def test_gram_symmetric_psd_and_consistent(spec):
    k = make(spec)
    X = inputs()
    K = k(X)
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_allclose(K, k(X, X), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.diag(K), k.diag(X), rtol=1e-10, atol=1e-14)
    assert np.linalg.eigvalsh(K).min() > -1e-8 * np.abs(K).max()
    # Cross blocks agree with the full Gram matrix.
    A, B = X.subset(slice(0, 6)), X.subset(np.arange(4, len(X)))
    np.testing.assert_allclose(k(A, B), K[:6, 4:], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("spec", KERNELS, ids=IDS)
def test_against_brute_force_integration(spec):
    k = make(spec)
    X = inputs()
    K = k(X)
    # Skew, crossing / fan (shared start), parallel, collinear, segment-point, point-point.
    pairs = [(0, 1), (2, 3), (5, 6), (5, 7), (8, 9), (8, 10), (0, 11), (12, 13), (4, 4), (6, 6)]
    # SE with panels: closed forms and a smooth integrand; one panel of 3 nodes over segments
    # four length scales long, or Matern (GL across a kink), are looser.
    tol = 1e-6 if spec[0] == "se" and spec[3] is not None else 5e-3
    for i, j in pairs:
        ref = brute(k, X, i, j)
        assert K[i, j] == pytest.approx(ref, rel=tol, abs=tol), (i, j)


@pytest.mark.parametrize("spec", KERNELS, ids=IDS)
def test_zero_length_segment_is_the_point_kernel(spec):
    k = make(spec)
    rng = np.random.default_rng(1)
    p = rng.uniform(0, 2, (4, 2))
    K = k(Segments.from_points(p))
    np.testing.assert_allclose(K, k.base(p), rtol=1e-12)
    # A vanishingly short segment tends to the point kernel too (under "sum" it integrates to ~0).
    if k.normalisation == "sum":
        return
    short = Segments(p, p + 1e-7)
    np.testing.assert_allclose(k(short, Segments.from_points(p)), k.base(p), rtol=1e-6)


def test_nodes_weights_sum_to_one_and_panels():
    X = inputs()
    nodes = segment_nodes(X, 3, 0.5)
    sums = np.add.reduceat(nodes.weights, nodes.offsets[:-1])
    np.testing.assert_allclose(sums, 1.0)
    sizes = np.diff(nodes.offsets)
    expect = np.where(X.is_point, 1, 3 * np.maximum(1, np.ceil(X.lengths / 0.5 - 1e-9)))
    np.testing.assert_array_equal(sizes, expect)


def test_invalid_arguments():
    with pytest.raises(ValueError, match="normalisation"):
        LineKernel("se", "median")
    with pytest.raises(ValueError, match="order"):
        LineKernel("se", order=0)
    with pytest.raises(ValueError, match="same shape"):
        Segments(np.zeros((2, 2)), np.zeros((3, 2)))
