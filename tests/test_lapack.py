"""gpomap.lapack: LAPACK and BLAS called without the GIL, against numpy's and scipy's own wrappers."""

import threading

import numpy as np
import pytest
from scipy.linalg import blas as scipy_blas
from scipy.linalg import lapack as scipy_lapack

from gpomap import lapack


def _spd(n, seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    return A @ A.T / n + 0.5 * np.eye(n)


@pytest.mark.parametrize("n", [1, 7, 150])
def test_cholesky_inverse_and_solve_are_those_of_numpy_and_of_scipy_wrappers(n):
    K = _spd(n, n)
    L = np.asfortranarray(K.copy())
    assert lapack.potrf(L) == 0
    # The independent truth: numpy's factor; the same library through scipy's wrapper: the same bits.
    np.testing.assert_allclose(np.tril(L), np.linalg.cholesky(K), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.tril(L), np.tril(scipy_lapack.dpotrf(K, lower=1)[0]))
    # The upper triangle is left as it was.
    np.testing.assert_array_equal(np.triu(L, 1), np.triu(K, 1))

    inv = np.asfortranarray(np.tril(L))
    assert lapack.potri(inv) == 0
    full = np.tril(inv) + np.tril(inv, -1).T
    np.testing.assert_allclose(full, np.linalg.inv(K), rtol=1e-9, atol=1e-10)
    np.testing.assert_array_equal(np.tril(inv), np.tril(scipy_lapack.dpotri(np.tril(L), lower=1)[0]))

    tri = np.asfortranarray(np.tril(L))
    assert lapack.trtri(tri) == 0
    np.testing.assert_allclose(np.tril(tri) @ np.tril(L), np.eye(n), atol=1e-10)

    rng = np.random.default_rng(1)
    for b in (rng.normal(size=n), np.asfortranarray(rng.normal(size=(n, 3)))):
        x = b.copy(order="F")
        assert lapack.potrs(L, x) == 0
        np.testing.assert_allclose(K @ x, b, rtol=1e-9, atol=1e-9)


def test_a_matrix_that_is_not_positive_definite_is_reported_by_info():
    K = np.asfortranarray(np.diag([1.0, 2.0, -1.0, 4.0]))
    assert lapack.potrf(K) == 3  # the order of the first minor that is not positive definite


def test_syrk_updates_the_lower_triangle_only():
    rng = np.random.default_rng(2)
    A = np.asfortranarray(rng.normal(size=(40, 25)))
    C = np.asfortranarray(_spd(40, 3))
    before = C.copy()
    lapack.syrk(-0.5, A, 2.0, C)
    expected = -0.5 * A @ A.T + 2.0 * before
    np.testing.assert_allclose(np.tril(C), np.tril(expected), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.triu(C, 1), np.triu(before, 1))
    np.testing.assert_array_equal(np.tril(C), np.tril(scipy_blas.dsyrk(-0.5, A, beta=2.0, c=before, lower=1)))


def test_arrays_lapack_cannot_take_in_place_are_refused():
    K = _spd(5, 4)
    with pytest.raises(ValueError, match="Fortran-ordered"):
        lapack.potrf(np.ascontiguousarray(K))  # C-ordered: LAPACK would read its transpose
    with pytest.raises(ValueError, match="float64"):
        lapack.potrf(np.asfortranarray(K.astype(np.float32)))
    with pytest.raises(ValueError, match="rows"):
        lapack.potrs(np.asfortranarray(K), np.zeros(4))


def test_threads_factorising_at_once_get_the_factors_of_one_thread():
    # Two threads factorising at once get the same factors as one thread alone (each its own
    # matrix; LAPACK's routines are reentrant).
    mats = [_spd(120, s) for s in range(4)]
    alone = []
    for K in mats:
        L = np.asfortranarray(K.copy())
        lapack.potrf(L)
        alone.append(np.tril(L))
    together = [None] * 4

    def work(i):
        L = np.asfortranarray(mats[i].copy())
        lapack.potrf(L)
        together[i] = np.tril(L)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a, b)


def _blas_threads():
    """{library path: threads} of this process's BLAS libraries, as threadpoolctl reads them now."""
    controller = lapack.blas_controller()
    return {lib.filepath: lib.num_threads for lib in controller.select(user_api="blas").lib_controllers}


def _two_libraries():
    """numpy's and scipy's BLAS library paths where the wheels brought one each, else skip."""
    pytest.importorskip("threadpoolctl")
    paths = list(_blas_threads())
    numpy_own = [p for p in paths if lapack._belongs_to(p, "numpy")]
    scipy_own = [p for p in paths if lapack._belongs_to(p, "scipy")]
    if len(numpy_own) != 1 or len(scipy_own) != 1:
        pytest.skip("numpy and scipy do not each bring a BLAS library of their own here")
    return numpy_own[0], scipy_own[0]


def test_blas_on_gives_the_threads_to_one_library_and_one_to_the_other():
    numpy_lib, scipy_lib = _two_libraries()
    controller = lapack.blas_controller()
    with controller.limit(limits=2):
        before = _blas_threads()
        threads = min(2, lapack.available_cores())
        with lapack.blas_on("scipy"):
            assert _blas_threads() == {scipy_lib: threads, numpy_lib: 1}
        assert _blas_threads() == before
        with lapack.blas_on("numpy"):
            assert _blas_threads() == {numpy_lib: threads, scipy_lib: 1}
        assert _blas_threads() == before


def test_blas_on_keeps_a_cap_of_one_thread():
    # OMP_NUM_THREADS=1 or a worker's limit: neither library gets more than it had.
    numpy_lib, scipy_lib = _two_libraries()
    with lapack.blas_controller().limit(limits=1), lapack.blas_on("scipy"):
        assert _blas_threads() == {scipy_lib: 1, numpy_lib: 1}


def test_a_library_is_told_by_the_package_that_brought_it(tmp_path):
    numpy_dirs = lapack._package_dirs("numpy")
    assert lapack._belongs_to(str(numpy_dirs[1] / "libopenblas.so"), "numpy")
    assert lapack._belongs_to(str(numpy_dirs[0] / "_core" / "x.so"), "numpy")
    assert not lapack._belongs_to(str(tmp_path / "libopenblas.so"), "numpy")
    assert not lapack._belongs_to(str(lapack._package_dirs("scipy")[1] / "libopenblas.so"), "numpy")
