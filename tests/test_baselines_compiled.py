"""The baselines' compiled kernels against the numpy paths they replace (which stay the reference).

GPOMIK's :class:`~gpomap.baselines.gpomik.CompiledLineKernel` against
:class:`~gpomap.kernels.line.LineKernel` (itself checked against brute-force integrals in
``tests/test_line_kernel.py``), and GPOM's one-node quadrature against the SE closed form it
replaced and the point kernel itself; then whole fits, hyperparameters learnt, on both paths.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpomap import _compiled_line
from gpomap.baselines.gpom import GPOM
from gpomap.baselines.gpomik import GPOMIK, CompiledLineKernel
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.line import POINT_LENGTH, LineKernel, Segments, concatenate_segments
from gpomap.kernels.point import make_point_kernel, squared_distances
from gpomap.simulate import paper_room_scans
from gpomap.supports import Supports

pytestmark = pytest.mark.skipif(not _compiled_line.AVAILABLE, reason="numba is not installed")

KERNELS = [
    ("se", "mean", 4, 1.0),
    ("se", "sum", 4, 1.0),
    ("se", "mean", 3, None),
    ("matern32", "mean", 3, 2.0),
    ("matern32", "sum", 4, 1.0),
]
IDS = [f"{b}-{n}-o{o}-p{p}" for b, n, o, p in KERNELS]

#: Agreement asked of the two paths, relative to the largest entry: round-off, another order of sums.
RTOL = 1e-12


def _pair(spec, length_scale=0.7, variance=1.3):
    """The numpy reference and the compiled kernel with the same rule and hyperparameters."""
    base, norm, order, panel = spec
    ref, fast = LineKernel(base, norm, order, panel), CompiledLineKernel(base, norm, order, panel)
    for k in (ref, fast):
        k.theta = np.log([variance, length_scale])
    return ref, fast


def _inputs(length_scale=0.7) -> Segments:
    """Skew, crossing, fan (shared start), parallel, collinear, reversed and very short segments, and points."""
    rng = np.random.default_rng(5)
    s = rng.uniform(0, 4, (9, 2))
    e = s + rng.uniform(-3, 3, (9, 2))
    fan_s = np.array([[1.0, 1.0]] * 3)
    fan_e = fan_s + np.array([[2.0, 0.0], [1.5, 1.5], [0.0, 2.5]])
    par_s = np.array([[0.0, 0.5], [0.5, 0.5], [3.0, 0.5], [0.2, 1.2], [4.0, 4.0]])
    par_e = np.array([[2.0, 0.5], [0.0, 0.5], [3.0 + 1e-2 * length_scale * POINT_LENGTH, 0.5], [2.2, 1.2], [2.0, 2.0]])
    rev_s, rev_e = e[:2].copy(), s[:2].copy()  # the first two segments, end to start
    tiny_s = np.array([[2.0, 2.0]])
    tiny_e = tiny_s + np.array([[0.5 * POINT_LENGTH * length_scale, 0.0]])  # shorter than the point length: its midpoint
    segs = Segments(np.r_[s, fan_s, par_s, rev_s, tiny_s], np.r_[e, fan_e, par_e, rev_e, tiny_e])
    return concatenate_segments([segs, Segments.from_points(rng.uniform(0, 4, (6, 2)))])


def _close(actual, desired, rtol=RTOL):
    np.testing.assert_allclose(actual, desired, rtol=0, atol=rtol * np.abs(desired).max())


@pytest.mark.parametrize("spec", KERNELS, ids=IDS)
def test_compiled_line_kernel_equals_numpy(spec):
    ref, fast = _pair(spec)
    X = _inputs()
    P = Segments.from_points(np.random.default_rng(1).uniform(-1, 5, (13, 2)))
    K0, dK0 = ref(X, eval_gradient=True)
    K1, dK1 = fast(X, eval_gradient=True)
    _close(K1, K0)
    _close(dK1, dK0)
    # What the hyperparameter search asks: K and d/dlog l, exactly symmetric.
    K2, dL2 = fast.gram_and_length_scale_gradient(X)
    _close(K2, K0)
    _close(dL2, dK0[:, :, 1])
    assert np.array_equal(K2, K2.T) and np.array_equal(dL2, dL2.T)
    # Prediction's cross covariances, either way round, and segments against segments.
    for A, B in [(X, P), (P, X), (X.subset(slice(0, 10)), X.subset(slice(5, None)))]:
        _close(fast(A, B), ref(A, B))


def test_compiled_line_kernel_other_length_scales():
    """Length scales that move segments across the point length and the closed forms' regimes."""
    X = _inputs(length_scale=0.05)
    for spec in (KERNELS[0], KERNELS[3]):
        for length_scale in (0.05, 3.0, 25.0):
            ref, fast = _pair(spec, length_scale=length_scale, variance=0.6)
            K0, dK0 = ref(X, eval_gradient=True)
            K1, dL1 = fast.gram_and_length_scale_gradient(X)
            _close(K1, K0)
            _close(dL1, dK0[:, :, 1])


def _same_fits(fit0, fit1, pts):
    """Two fits of one model on two kernel paths: at fixed hyperparameters the same map to 1e-9; learnt, the same optimum.

    `fit0`, `fit1`: callables taking the model's keyword arguments and returning it fitted. A
    learnt search ends where its tolerance stops it, so kernels equal to round-off can stop it a
    step apart (hyperparameters 1e-7 apart); the optimum's value is the same.
    """
    fixed = {"optimise": False, "length_scale": 1.2, "noise": 0.05}
    (p0, v0), (p1, v1) = (f(**fixed).predict_proba(pts, return_var=True) for f in (fit0, fit1))
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v1, v0, rtol=0, atol=1e-9)
    r0, r1 = (f(n_restarts=0).gp_.fit_report_ for f in (fit0, fit1))
    assert abs(r1.value - r0.value) <= 1e-9 * abs(r0.value)


@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_gpomik_fit_same_on_both_paths(monkeypatch, kernel):
    scans = paper_room_scans(n_beams=8)[::3]
    pts = np.random.default_rng(2).uniform([-9, -7], [9, 7], (400, 2))

    def fit(enabled, **options):
        monkeypatch.setattr(_compiled_line, "ENABLED", enabled)
        return GPOMIK(kernel=kernel, **options).fit(scans)

    _same_fits(lambda **o: fit(False, **o), lambda **o: fit(True, **o), pts)


def test_gpom_kernel_is_the_point_kernel():
    """GPOM's inputs are points: its kernel, and the SE closed form it replaced, are the point kernel there."""
    rng = np.random.default_rng(4)
    X = Supports.from_points(rng.uniform(0, 6, (40, 2)))
    Q = Supports.from_points(rng.uniform(0, 6, (25, 2)))
    for name in ("se", "matern32"):
        kernel = GPOM(name, length_scale=0.8, variance=1.3).make_kernel()
        base = make_point_kernel(name, variance=1.3, length_scale=0.8)
        K, dL = kernel.gram_and_length_scale_gradient(X)
        truth, dtruth = base.values(squared_distances(X.lower, X.lower), True)
        _close(K, truth)
        _close(dL, dtruth)
        _close(kernel(X, Q), base.values(squared_distances(X.lower, Q.lower))[0])
        np.testing.assert_allclose(kernel.diag(Q), 1.3, rtol=1e-15)
        if name == "se":
            exact = AreaKernel(base, "exact", "mean", 1)
            _close(exact.gram_and_length_scale_gradient(X)[0], truth)


class _ClosedFormGPOM(GPOM):
    """GPOM as it was: the SE kernel by its closed form over zero-width boxes."""

    def make_kernel(self):
        base = make_point_kernel(self.kernel, variance=self.variance, length_scale=self.length_scale)
        return AreaKernel(base, "exact", "mean", 1)


@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_gpom_is_the_dense_point_gp(kernel):
    """At fixed hyperparameters GPOM's latent mean and variance are the dense GP's on its points, solved here."""
    scans = paper_room_scans(n_beams=12)[::2]
    pts = np.random.default_rng(3).uniform([-9, -7], [9, 7], (300, 2))
    m = GPOM(kernel, max_points=300, seed=1, optimise=False, length_scale=1.2, noise=0.05).fit(scans)
    X, y = m.observations_.points[m.kept_], m.observations_.labels[m.kept_]
    base = make_point_kernel(kernel, variance=m.gp_.kernel.base.variance, length_scale=1.2)
    K = base.values(squared_distances(X, X))[0] + m.gp_.noise * np.eye(len(X))
    Ks = base.values(squared_distances(X, pts))[0]
    mean, var = m.predict(pts, return_var=True)
    np.testing.assert_allclose(mean, Ks.T @ np.linalg.solve(K, y), rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, base.variance - np.einsum("ij,ij->j", Ks, np.linalg.solve(K, Ks)), rtol=0, atol=1e-9)


def test_gpom_search_reaches_the_closed_form_optimum():
    """The hyperparameter search on the one-node quadrature ends at the optimum the SE closed form's did."""
    scans = paper_room_scans(n_beams=12)[::2]
    fits = [cls("se", max_points=300, seed=1, n_restarts=0).fit(scans) for cls in (_ClosedFormGPOM, GPOM)]
    r0, r1 = (f.gp_.fit_report_ for f in fits)
    assert abs(r1.value - r0.value) <= 1e-9 * abs(r0.value)
    np.testing.assert_allclose(fits[1].gp_.kernel.theta, fits[0].gp_.kernel.theta, rtol=0, atol=1e-5)
