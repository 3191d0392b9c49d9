"""Whether gpomap's numba-compiled fast paths are used.

The quadrature kernel's node sums (:mod:`gpomap.kernels._compiled`), the ray counts
(:mod:`gpomap._compiled_counts`), the free samples near hits (:mod:`gpomap._compiled_clearance`)
and the cell tree (:mod:`gpomap._compiled_cells`) each have a compiled path and a numpy one, which
stays the tests' reference. The compiled ones are taken when numba imports, unless the environment
variable :data:`FORCE_NUMPY_ENV` is set (to anything but "" or "0") when gpomap is imported.

Compiled code is cached on disk (``cache=True``), so only a first run compiles: numba writes the
cache beside the sources (``__pycache__``, an editable install's), else, where the package is
read-only, in the user's cache directory (``~/.cache/numba``), or in ``NUMBA_CACHE_DIR`` when it
is set. Where none of these can be written (a read-only install run by a user without a home),
:func:`jit` compiles without caching instead of failing as numba does when the module is imported.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: Environment variable that, set to anything but "" or "0", makes every compiled path use numpy.
FORCE_NUMPY_ENV: str = "GPOMAP_NUMPY_KERNELS"


def plain_decorator(*args: Any, **kwargs: Any) -> Any:
    """Stand-in for numba's decorators without numba: the function stays plain Python (and unused)."""
    return lambda f: f


try:
    import numba

    #: Whether numba imports.
    NUMBA_AVAILABLE: bool = True
except ImportError:  # pragma: no cover - numba is a dependency; the numpy paths remain the reference
    NUMBA_AVAILABLE = False


def _njit(*args: Any, **options: Any) -> Any:
    """``numba.njit(*args, **options)``, but ``cache=True`` is dropped where numba has nowhere to cache.

    numba picks the cache directory when a function is decorated and raises RuntimeError ("no
    locator available") if no candidate is writable; here the function is compiled uncached then
    (each process compiles it again). Used bare (``@jit``) or with options (``@jit(cache=True)``).
    """
    if len(args) == 1 and callable(args[0]) and not options:
        return numba.njit(args[0])

    def decorate(f: Any) -> Any:
        try:
            return numba.njit(*args, **options)(f)
        except RuntimeError as error:
            if not options.get("cache") or "no locator available" not in str(error):
                raise
            return numba.njit(*args, **{**options, "cache": False})(f)

    return decorate


#: ``numba.njit`` that compiles uncached where nothing can be cached (:func:`_njit`), or
#: :func:`plain_decorator` without numba.
jit: Any = _njit if NUMBA_AVAILABLE else plain_decorator


def compiled_by_default() -> bool:
    """Whether a compiled path starts enabled: numba is there and the environment does not force numpy."""
    return NUMBA_AVAILABLE and os.environ.get(FORCE_NUMPY_ENV, "") in ("", "0")


@contextmanager
def compile_time() -> Iterator[list[float]]:
    """Seconds numba spends compiling inside the block, summed into the one-element list it yields.

    A first run compiles the fast paths (cached on disk after: ``cache=True``), which a fit's
    timings would otherwise count as fitting.
    """
    total = [0.0]
    if not NUMBA_AVAILABLE:
        yield total
        return
    from numba.core import event

    def add(seconds: float) -> None:
        total[0] += seconds

    with event.install_timer("numba:compile", add):
        yield total
