"""The few LAPACK and BLAS routines a GP fit needs, called without holding the GIL.

scipy's wrappers (``scipy.linalg.lapack``, ``scipy.linalg.blas``) hold the GIL while the routine
runs, so the tiles that :class:`~gpomap.tiles.TiledGPOM` fits on threads of one process factorised
one at a time (docs/choices.md, "Measured for the code"). Here the same routines of the LAPACK and BLAS that scipy was built
with (exported for compiled callers by ``scipy.linalg.cython_lapack`` and ``cython_blas``) are
called through :mod:`ctypes`, which lets go of the GIL for the call: the same numbers, to the bit,
as scipy's wrappers give (``tests/test_lapack.py``).

Also here: how many threads BLAS runs (:func:`blas_limited`), so that a process's threads times
BLAS's never exceed the cores, and which of numpy's and scipy's BLAS gets them (:func:`blas_on`).

Every routine works in place on Fortran-ordered arrays (a symmetric C-ordered matrix passes as its
own transpose) and returns LAPACK's ``info``; the lower triangle is the one read and written.
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cython_blas, cython_lapack

# Prototypes of our own rather than setting ``ctypes.pythonapi``'s, which other libraries share.
_capsule_name = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
_capsule_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi)
)

_INT = ctypes.POINTER(ctypes.c_int)
_DOUBLE = ctypes.POINTER(ctypes.c_double)
_CHAR = ctypes.c_char_p
_ARRAY = ctypes.c_void_p


def _routine(module: Any, name: str, *argtypes: Any) -> Any:
    """The routine `name` that scipy's Cython module exports, as a ctypes function (GIL released while it runs)."""
    capsule = module.__pyx_capi__[name]
    return ctypes.CFUNCTYPE(None, *argtypes)(_capsule_pointer(capsule, _capsule_name(capsule)))


_dpotrf = _routine(cython_lapack, "dpotrf", _CHAR, _INT, _ARRAY, _INT, _INT)
_dpotri = _routine(cython_lapack, "dpotri", _CHAR, _INT, _ARRAY, _INT, _INT)
_dtrtri = _routine(cython_lapack, "dtrtri", _CHAR, _CHAR, _INT, _ARRAY, _INT, _INT)
_dpotrs = _routine(cython_lapack, "dpotrs", _CHAR, _INT, _INT, _ARRAY, _INT, _ARRAY, _INT, _INT)
_dsyrk = _routine(cython_blas, "dsyrk", _CHAR, _CHAR, _INT, _INT, _DOUBLE, _ARRAY, _INT, _DOUBLE, _ARRAY, _INT)

_LOWER = b"L"


def _square_fortran(a: NDArray[np.float64], name: str) -> int:
    """The order n of `a`, checked to be an (n, n) Fortran-ordered float64 array we may write."""
    if a.dtype != np.float64 or a.ndim != 2 or a.shape[0] != a.shape[1] or not a.flags.f_contiguous or not a.flags.writeable:
        raise ValueError(f"{name} must be a writeable Fortran-ordered float64 (n, n) array, got {a.dtype} {a.shape}")
    return int(a.shape[0])


def _int(v: int) -> Any:
    return ctypes.byref(ctypes.c_int(v))


def potrf(a: NDArray[np.float64]) -> int:
    """Lower Cholesky factor of the symmetric `a` (n, n), in place (``dpotrf``); 0, or LAPACK's info.

    The strict upper triangle is left as it was.
    """
    n = _square_fortran(a, "a")
    info = ctypes.c_int(0)
    _dpotrf(_LOWER, _int(n), a.ctypes.data, _int(max(n, 1)), ctypes.byref(info))
    return info.value


def potri(factor: NDArray[np.float64]) -> int:
    """(L L^T)^-1 from the lower factor L in `factor` (n, n), its lower triangle in place (``dpotri``)."""
    n = _square_fortran(factor, "factor")
    info = ctypes.c_int(0)
    _dpotri(_LOWER, _int(n), factor.ctypes.data, _int(max(n, 1)), ctypes.byref(info))
    return info.value


def trtri(factor: NDArray[np.float64]) -> int:
    """L^-1 of the lower triangular L in `factor` (n, n), its lower triangle in place (``dtrtri``, non-unit diagonal)."""
    n = _square_fortran(factor, "factor")
    info = ctypes.c_int(0)
    _dtrtri(_LOWER, b"N", _int(n), factor.ctypes.data, _int(max(n, 1)), ctypes.byref(info))
    return info.value


def potrs(factor: NDArray[np.float64], b: NDArray[np.float64]) -> int:
    """Solve (L L^T) x = b from the lower factor L in `factor` (n, n); `b` (n,) or (n, k), overwritten by x (``dpotrs``).

    `b` must be Fortran-ordered (a vector is), float64 and writeable.
    """
    n = _square_fortran(factor, "factor")
    if b.dtype != np.float64 or b.shape[0] != n or b.ndim > 2 or not b.flags.f_contiguous or not b.flags.writeable:
        raise ValueError(f"b must be a writeable Fortran-ordered float64 array of {n} rows, got {b.dtype} {b.shape}")
    k = 1 if b.ndim == 1 else int(b.shape[1])
    info = ctypes.c_int(0)
    _dpotrs(_LOWER, _int(n), _int(k), factor.ctypes.data, _int(max(n, 1)), b.ctypes.data, _int(max(n, 1)), ctypes.byref(info))
    return info.value


def syrk(alpha: float, a: NDArray[np.float64], beta: float, c: NDArray[np.float64]) -> None:
    """``c = alpha a a^T + beta c`` on and below the diagonal of `c` (n, n), in place (``dsyrk``); `a` is (n, k).

    Both Fortran-ordered; the strict upper triangle of `c` is left as it was.
    """
    n = _square_fortran(c, "c")
    if a.dtype != np.float64 or a.ndim != 2 or a.shape[0] != n or not a.flags.f_contiguous:
        raise ValueError(f"a must be a Fortran-ordered float64 array of {n} rows, got {a.dtype} {a.shape}")
    k = int(a.shape[1])
    _dsyrk(
        _LOWER,
        b"N",
        _int(n),
        _int(k),
        ctypes.byref(ctypes.c_double(alpha)),
        a.ctypes.data,
        _int(max(n, 1)),
        ctypes.byref(ctypes.c_double(beta)),
        c.ctypes.data,
        _int(max(n, 1)),
    )


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def blas_libraries() -> int:
    """BLAS libraries loaded in this process, at least one.

    numpy's and scipy's wheels each bring their own OpenBLAS, with a thread pool of its own whose
    threads spin for a while after each call: a numpy product and a scipy factorisation in turn
    then run four threads on two cores, and a small fit's hyperparameter stage slows several
    times over (docs/choices.md, "BLAS threads").
    """
    controller = blas_controller()
    if controller is None:
        return 1
    return max(1, len({lib.filepath for lib in controller.lib_controllers if lib.user_api == "blas"}))


def cores_share(threads: int) -> int:
    """BLAS threads for each of `threads` threads (or processes) of work running at once, in each
    of the process's BLAS libraries (:func:`blas_libraries`): the cores shared out, at least one."""
    return max(1, available_cores() // (max(1, int(threads)) * blas_libraries()))


@functools.lru_cache(maxsize=1)
def blas_controller() -> Any:
    """threadpoolctl's view of this process's BLAS and OpenMP libraries, found once (None without
    threadpoolctl).

    Finding them walks every loaded library, which a small map would pay again on each stage of
    :class:`~gpomap.tiles.TiledGPOM`; a limit set through the found controller is cheap.
    """
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    return ThreadpoolController()


def limit_blas_threads(n: int) -> None:
    """Cap the BLAS (and OpenMP) threads of this process at `n` for the rest of its life.

    Pool workers call it on start so that ``workers x threads`` never exceeds the cores. Best
    effort: without threadpoolctl the libraries keep their own defaults.
    """
    controller = blas_controller()
    if controller is not None:
        controller.limit(limits=max(1, int(n)))  # not used as a context: the limit must stay


@contextmanager
def blas_limited(n: int) -> Iterator[None]:
    """BLAS (and OpenMP) threads of this process capped at `n` within the block (best effort, as
    :func:`limit_blas_threads`)."""
    controller = blas_controller()
    if controller is None:
        yield
        return
    with controller.limit(limits=max(1, int(n))):
        yield


@functools.cache
def _package_dirs(package: str) -> tuple[Path, ...]:
    """Where `package`'s own shared libraries lie: its folder, and the ``<package>.libs`` beside
    it where its wheels keep the OpenBLAS they bring."""
    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        return ()
    root = Path(spec.origin).resolve().parent
    return root, root.parent / f"{package}.libs"


def _belongs_to(filepath: str, package: str) -> bool:
    """Whether the library at `filepath` is one `package` brought with it."""
    path = Path(filepath).resolve()
    return any(path.is_relative_to(d) for d in _package_dirs(package))


@contextmanager
def blas_on(package: str) -> Iterator[None]:
    """Within the block, the BLAS threads go to the library `package` ("numpy" or "scipy") calls,
    and every other BLAS library runs one thread.

    A dense GP's work runs in one library at a time: its factorisations in scipy's (the routines
    of this module), its predictions' products in numpy's. With both libraries at their default
    threads each one's pool spins while the other works; with both at one thread a core idles.
    The threads given are the most any BLAS library runs on entry, at most the cores, so a cap the
    user set (``OMP_NUM_THREADS=1``, :func:`limit_blas_threads`) holds. With one BLAS library
    (numpy and scipy linked to the same), or where `package`'s cannot be told apart, nothing
    changes.

    Parameters
    ----------
    package : {"numpy", "scipy"}
    """
    controller = blas_controller()
    if controller is None:
        yield
        return
    libraries = controller.select(user_api="blas").lib_controllers
    own = [lib.filepath for lib in libraries if _belongs_to(lib.filepath, package)]
    others = [lib.filepath for lib in libraries if lib.filepath not in own]
    if not own or not others:
        yield
        return
    threads = min(available_cores(), max(lib.num_threads for lib in libraries))
    with ExitStack() as stack:
        stack.enter_context(controller.select(filepath=own).limit(limits=threads))
        stack.enter_context(controller.select(filepath=others).limit(limits=1))
        yield
