"""Where a stage's tile tasks run: in this process, on threads, in a local process pool, or on a Dask cluster."""

from __future__ import annotations

import concurrent.futures as cf
from collections.abc import Callable, MutableMapping
from typing import Any

from gpomap.lapack import limit_blas_threads
from gpomap.progress import Progress
from gpomap.tiles.tasks import predict_tile_task

#: A prediction stage of fewer query points than this over all its tiles (one chunk of
#: :func:`predict_tile_task`; a point in the blend of several tiles counts once for each) runs
#: in this process: its tasks are too small for threads, which then
#: contend for the GIL more than they share the work; larger stages (a benchmark's test points)
#: stay on the threads (docs/choices.md, "Measured for the code").
SMALL_PREDICTION_POINTS: int = 4096


def _few_queries(fn: Callable[..., Any], jobs: list[tuple[tuple[int, int], tuple[Any, ...]]]) -> bool:
    """Whether `jobs` are tile predictions of fewer than :data:`SMALL_PREDICTION_POINTS` points, summed over the tiles."""
    return fn is predict_tile_task and sum(len(args[1]) for _, args in jobs) < SMALL_PREDICTION_POINTS


def _collect(
    futures: dict[cf.Future, tuple[int, int]], bar: Progress, results: MutableMapping[tuple[int, int], Any] | None = None
) -> tuple[MutableMapping[tuple[int, int], Any], dict[tuple[int, int], Exception]]:
    """Each tile's result into `results` (a new dict by default), as its task finishes, and the
    exception of each task that failed."""
    results = {} if results is None else results
    failed: dict[tuple[int, int], Exception] = {}
    for f in cf.as_completed(futures):
        # Each future let go once read: it holds its result (a fit's factor) as long as it lives.
        key = futures.pop(f)
        try:
            results[key] = f.result()
            bar.update()
        except Exception as e:  # reported per tile after the retry
            failed[key] = e
    return results, failed


def _worker_init(blas_threads: int) -> None:
    """Initialiser of the local pool's worker processes."""
    limit_blas_threads(blas_threads)


#: The tasks of each local pool stage running now, by a token: forked workers read them from the
#: memory they inherit (:func:`_inherited_task`) instead of each task's arguments being pickled
#: to them. A prediction stage sends every tile's state (its Cholesky factor: n^2 numbers), which
#: pickled cost a large share of a whole log's CPU (docs/choices.md, "Measured for the code").
_INHERITED: dict[str, tuple[Callable[..., Any], list[tuple[Any, ...]]]] = {}


def _inherited_task(token: str, index: int) -> Any:
    """Run task `index` of the stage `token` of :data:`_INHERITED` (in a forked pool worker)."""
    fn, args = _INHERITED[token]
    return fn(*args[index])
