"""The compiled (numba) tensor kernel against the numpy path it replaces and the node sums."""

import os
import subprocess
import sys

import numpy as np
import pytest

from gpomap.compiled import FORCE_NUMPY_ENV
from gpomap.kernels import Matern32, SquaredExponential, _compiled
from gpomap.kernels.nodes import quadrature_nodes, weighted_gram
from gpomap.kernels.tensor import tensor_gram, tensor_gram_length_scale
from gpomap.supports import Supports, concatenate

pytestmark = pytest.mark.skipif(not _compiled.AVAILABLE, reason="numba is not installed")

KERNELS = [Matern32(1.3, 0.7), SquaredExponential(0.8, 1.1), Matern32(0.4, 2.5)]

#: Relative agreement asked of the two paths (of the largest entry): round-off, another order of sums.
RTOL = 1e-12


def _mixed(rng, n_boxes, n_points, dim):
    """Boxes (some of zero width, points as ambiguous cells can be) and points, interleaved at random."""
    lo = rng.uniform(0, 4, (n_boxes + n_points, dim))
    hi = lo + rng.uniform(0.05, 1.5, lo.shape)
    hi[n_boxes:] = lo[n_boxes:]
    hi[:n_boxes:5] = lo[:n_boxes:5]
    order = rng.permutation(lo.shape[0])
    return Supports.from_boxes(lo[order], hi[order])


def _both_paths(monkeypatch, f):
    """``f()`` on the compiled path, then on the numpy path."""
    monkeypatch.setattr(_compiled, "ENABLED", True)
    compiled = f()
    monkeypatch.setattr(_compiled, "ENABLED", False)
    return compiled, f()


def _close(actual, desired, rtol=RTOL):
    np.testing.assert_allclose(actual, desired, rtol=0, atol=rtol * np.abs(desired).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("order", [1, 2, 3])
@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: f"{type(k).__name__}-{k.length_scale}")
def test_compiled_equals_numpy_and_node_sums(monkeypatch, dim, order, kernel):
    rng = np.random.default_rng(100 * dim + order)
    A = _mixed(rng, 37, 11, dim)
    B = concatenate([Supports.from_points(rng.uniform(-1, 5, (41, dim))), _mixed(rng, 9, 3, dim)])
    na, nb = quadrature_nodes(A, order), quadrature_nodes(B, order)
    for X, Y, nx, ny in [(A, B, na, nb), (B, A, nb, na), (A, None, na, na)]:
        for gradient in (False, True):
            (K1, dL1), (K0, dL0) = _both_paths(
                monkeypatch, lambda X=X, Y=Y, g=gradient: tensor_gram_length_scale(kernel, X, Y, order, g)
            )
            _close(K1, K0)
            if Y is None:
                np.testing.assert_array_equal(K1, K1.T)
            if gradient:
                assert dL1 is not None and dL0 is not None
                _close(dL1, dL0)
                if Y is None:
                    np.testing.assert_array_equal(dL1, dL1.T)
            else:
                assert dL1 is None and dL0 is None
        ref, dref = weighted_gram(kernel, nx, ny, eval_gradient=True)
        assert dref is not None
        _close(K1, ref)
        _close(dL1, dref[:, :, 1])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kernel", KERNELS[:2], ids=lambda k: type(k).__name__)
def test_compiled_gradient_is_the_finite_difference(monkeypatch, dim, kernel):
    monkeypatch.setattr(_compiled, "ENABLED", True)
    rng = np.random.default_rng(7 + dim)
    A, Q = _mixed(rng, 25, 6, dim), Supports.from_points(rng.uniform(0, 5, (19, dim)))
    h = 1e-5
    for B in (None, Q):
        K, dK = tensor_gram(kernel, A, B, 2, eval_gradient=True)
        assert dK is not None
        for i in range(2):
            step = np.zeros(2)
            step[i] = h
            up, _ = tensor_gram(kernel.clone_with_theta(kernel.theta + step), A, B, 2)
            down, _ = tensor_gram(kernel.clone_with_theta(kernel.theta - step), A, B, 2)
            np.testing.assert_allclose(dK[:, :, i], (up - down) / (2 * h), rtol=0, atol=1e-8 * np.abs(K).max())


def test_compiled_exponential_is_within_two_ulp_of_numpys():
    x = np.concatenate([-np.linspace(0, -_compiled.EXP_MIN, 200_001), -np.random.default_rng(0).exponential(3, 10_000)])
    out = np.empty_like(x)
    _compiled.exp_into(x, out)
    ref = np.exp(x)
    assert np.max(np.abs(out - ref) / np.spacing(ref)) <= 2
    assert out[0] == 1.0
    # Below EXP_MIN: 0 where numpy has a subnormal or 0.
    tiny = np.array([_compiled.EXP_MIN - 1e-9, -720.0, -745.5, -1e4, -np.inf])
    out = np.empty_like(tiny)
    _compiled.exp_into(tiny, out)
    np.testing.assert_array_equal(out, 0.0)
    assert np.exp(tiny).max() < 3.4e-308


def test_profiles_are_compiled_only_for_the_kernels_they_are():
    class Overridden(Matern32):
        def unit_profile_into(self, u2, out, grad=None, work=None):
            super().unit_profile_into(u2, out, grad, work)

    class NoUnitForm(Matern32):
        @property
        def unit_scale(self):
            return None

    assert _compiled.profile_id(Matern32()) == _compiled.MATERN32
    assert _compiled.profile_id(SquaredExponential()) == _compiled.SQUARED_EXPONENTIAL
    assert _compiled.profile_id(Overridden()) is None
    assert _compiled.profile_id(NoUnitForm()) is None


def _run(code, **env):
    """`code` in a fresh interpreter with `env` added; its stdout."""
    full = {**os.environ, **env}
    return subprocess.run([sys.executable, "-c", code], env=full, check=True, capture_output=True, text=True).stdout


def test_environment_variable_forces_the_numpy_path():
    code = "from gpomap.kernels import _compiled; print(_compiled.AVAILABLE, _compiled.ENABLED)"
    assert _run(code, **{FORCE_NUMPY_ENV: "1"}).split() == ["True", "False"]
    assert _run(code, **{FORCE_NUMPY_ENV: "0"}).split() == ["True", "True"]


def test_without_numba_the_numpy_path_is_taken():
    code = (
        "import sys; sys.modules['numba'] = None\n"
        "import numpy as np\n"
        "from gpomap.kernels import Matern32, _compiled\n"
        "from gpomap.kernels.tensor import tensor_gram\n"
        "from gpomap.supports import Supports\n"
        "lo = np.random.default_rng(0).uniform(0, 3, (6, 2))\n"
        "K, _ = tensor_gram(Matern32(), Supports.from_boxes(lo, lo + 0.5))\n"
        "from gpomap import _compiled_counts\n"
        "from gpomap.evidence import RayEvidence, lattice_grid\n"
        "from gpomap.simulate import paper_room_scans\n"
        "ev = RayEvidence.from_scans(paper_room_scans()[:2])\n"
        "hits = ev.counts(lattice_grid(ev.extent(), 0.1)).hits\n"
        "print(_compiled.AVAILABLE, _compiled.ENABLED, K.shape, _compiled_counts.ENABLED, int(hits.sum()))"
    )
    assert _run(code, **{FORCE_NUMPY_ENV: ""}).split() == ["False", "False", "(6,", "6)", "False", "72"]
