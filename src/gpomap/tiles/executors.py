"""Where a stage's tile tasks run: in this process, on threads, in a local process pool, or on a Dask cluster.

:class:`TileExecutors` is the part of :class:`~gpomap.tiles.TiledGPOM` that runs a stage's tasks,
one per tile, retrying each failed task once; holds a Dask client for the length of a stage; and
shares the cores among the workers' BLAS threads (:func:`_blas_shared` for the stages that run in
this process).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import multiprocessing
import os
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from contextlib import contextmanager
from typing import Any, Concatenate, ParamSpec, TypeVar

from gpomap.errors import DistributedError, GpomapError
from gpomap.lapack import blas_limited, cores_share, limit_blas_threads
from gpomap.progress import Progress, progress
from gpomap.tiles.attributes import TiledAttributes
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


_Tiled = TypeVar("_Tiled", bound="TileExecutors")
_P = ParamSpec("_P")
_R = TypeVar("_R")
#: A stage's tasks (each tile's key and its task's arguments), where their results go, and what
#: a runner gives back: the results and each failed task's exception (:meth:`TiledGPOM._run`).
_Jobs = list[tuple[tuple[int, int], tuple[Any, ...]]]
_Results = MutableMapping[tuple[int, int], Any]
_Outcome = tuple[_Results, Mapping[tuple[int, int], BaseException]]


def _blas_shared(method: Callable[Concatenate[_Tiled, _P], _R]) -> Callable[Concatenate[_Tiled, _P], _R]:
    """Run a :class:`TiledGPOM` stage with this process's BLAS held to one worker's share of the
    cores (:meth:`TiledGPOM._workers_and_threads`), as its workers' is: the stages that run here
    (the hyperparameter search, the variance scale, the ray evidence, small predictions) would
    otherwise take every core in each BLAS library while workers or the other library spin on
    them (see :func:`gpomap.lapack.blas_libraries`)."""

    @functools.wraps(method)
    def shared(self: _Tiled, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with blas_limited(self._workers_and_threads(self.n_workers_)[1]):
            return method(self, *args, **kwargs)

    return shared


def _check_scheduler_address(addr: str) -> None:
    """Refuse a Dask scheduler address whose scheme no Dask transport knows, before a client is made:
    a client built on one fails half-made, and its clean-up waits two minutes on exit."""
    from distributed.comm import parse_address
    from distributed.comm.registry import get_backend

    try:
        get_backend(parse_address(addr)[0])
    except ValueError as e:
        raise DistributedError(f"Dask scheduler address {addr!r}: {e}; expected e.g. tcp://HOST:8786") from None


class TileExecutors(TiledAttributes):
    """Runs a stage's tile tasks where the map's arguments say (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    @property
    def n_workers_(self) -> int:
        """Local workers used."""
        return int(self.n_workers) if self.n_workers is not None else max(1, os.cpu_count() or 1)

    def _scheduler_address(self) -> str:
        s = self.scheduler
        return str(s) if isinstance(s, str) else str(getattr(getattr(s, "scheduler", None), "address", s))

    @contextmanager
    def _connected(self) -> Iterator[None]:
        """Hold a Dask client for one stage (fit, update, prediction) when a scheduler is set.

        Connecting first, before the stage's local work, makes a wrong or unreachable address fail
        within `scheduler_timeout` instead of after it. Nested stages share the outer client.
        """
        if self.scheduler is None or self._client is not None:
            yield
            return
        try:
            from distributed import Client
        except ImportError as e:
            raise DistributedError(
                "running tiles on a Dask scheduler needs dask distributed: pip install 'gpomap[distributed]'"
            ) from e
        if isinstance(self.scheduler, Client):
            self._client = self.scheduler
            try:
                yield
            finally:
                self._client = None  # the caller's client: theirs to close
            return
        addr = self._scheduler_address()
        _check_scheduler_address(addr)
        try:
            # Never the default client: this one is only ours, passed explicitly everywhere.
            client = Client(addr, timeout=self.scheduler_timeout, set_as_default=False)
        except (OSError, TimeoutError, ValueError, TypeError) as e:
            raise DistributedError(
                f"could not connect to the Dask scheduler at {addr} within {self.scheduler_timeout:g} s "
                f"({type(e).__name__}: {e}); check that a scheduler runs there ('dask scheduler'), or allow "
                "longer with --scheduler-timeout (scheduler_timeout)"
            ) from e
        self._client = client
        try:
            yield
        finally:
            self._client = None
            client.close()

    def _run(
        self,
        fn: Callable[..., Any],
        jobs: list[tuple[tuple[int, int], tuple[Any, ...]]],
        what: str,
        desc: str,
        into: MutableMapping[tuple[int, int], Any] | None = None,
    ) -> MutableMapping[tuple[int, int], Any]:
        """Run ``fn(*args)`` for every (tile, args); each failed task is retried once.

        Parameters
        ----------
        fn : callable
            A top-level (picklable) task function.
        jobs : list of ((ix, iy), args)
        what : str
            The stage, for error messages ("tile fit").
        desc : str
            The stage, for progress ("fitting tiles").
        into : mutable mapping, optional
            Where each result goes as its task finishes (a :class:`TileStore`: a fit's factors
            never all in memory at once); default a new dict.

        Returns
        -------
        dict or `into`
            Tile key to ``fn``'s result, for every job.

        Raises
        ------
        GpomapError
            Naming every tile whose task failed twice.
        DistributedError
            When the scheduler had no workers for `scheduler_timeout` seconds.
        """
        if not jobs:
            return {} if into is None else into
        # Results go straight into `into` when given (a runner's own dict otherwise).
        where: dict[str, Any] = {} if into is None else {"results": into}
        if self.scheduler is not None:
            runner = self._run_dask
        elif self.n_workers_ <= 1 or len(jobs) == 1 or _few_queries(fn, jobs):
            runner = self._run_inprocess
        elif self.worker_processes:
            runner = self._run_pool
        else:
            runner = self._run_threads
        with self._connected(), progress(len(jobs), desc, unit="tile") as bar:
            results, failed = runner(fn, jobs, bar, what, **where)
            if failed:
                retry = [j for j in jobs if j[0] in failed]
                more, failed2 = runner(fn, retry, bar, what, **where)
                if into is None:
                    results.update(more)
                if failed2:
                    names = ", ".join(f"tile {k} ({type(e).__name__}: {e})" for k, e in failed2.items())
                    raise GpomapError(f"{what} failed twice (retried once) for {len(failed2)} tile(s): {names}")
        return results

    @staticmethod
    def _run_inprocess(
        fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        results = {} if results is None else results
        failed: dict[tuple[int, int], Exception] = {}
        for key, args in jobs:
            try:
                results[key] = fn(*args)
                bar.update()
            except Exception as e:  # reported per tile after the retry
                failed[key] = e
        return results, failed

    def _workers_and_threads(self, n_jobs: int) -> tuple[int, int]:
        """Local workers for `n_jobs` tasks, and BLAS threads for each (the cores shared out)."""
        workers = min(self.n_workers_, n_jobs)
        return workers, self.blas_threads if self.blas_threads is not None else cores_share(workers)

    def _run_threads(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        """The jobs on threads of this process, BLAS held to the cores' share of each meanwhile."""
        workers, threads = self._workers_and_threads(len(jobs))
        with blas_limited(threads), cf.ThreadPoolExecutor(workers) as pool:
            return _collect({pool.submit(fn, *args): key for key, args in jobs}, bar, results)

    def _run_pool(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        ctx = multiprocessing.get_context("fork") if "fork" in multiprocessing.get_all_start_methods() else None
        workers, threads = self._workers_and_threads(len(jobs))
        # With fork, the workers are forked after the tasks are filed and read them from there.
        token = uuid.uuid4().hex
        if ctx is not None:
            _INHERITED[token] = (fn, [args for _, args in jobs])
        try:
            with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=(threads,)) as pool:
                if ctx is not None:
                    futs = {pool.submit(_inherited_task, token, i): key for i, (key, _) in enumerate(jobs)}
                else:
                    futs = {pool.submit(fn, *args): key for key, args in jobs}
                return _collect(futs, bar, results)  # a dead worker breaks the pool: its tasks are retried
        finally:
            _INHERITED.pop(token, None)

    def _run_dask(
        self, fn: Callable[..., Any], jobs: _Jobs, bar: Progress, what: str, results: _Results | None = None
    ) -> _Outcome:
        """Run the jobs on the scheduler of ``self._client`` (see :meth:`_connected`).

        A task whose worker dies is rescheduled by the scheduler itself onto another worker (same
        function, same arguments, so the same result); the tasks are not given ``retries=``,
        since exceptions they raise already get the one retry of :meth:`_run`.
        """
        from distributed import as_completed

        client = self._client
        self._check_client(client, what, len(jobs), len(jobs))
        tag = uuid.uuid4().hex[:8]
        futs: dict[Any, tuple[int, int]] = {}  # Dask futures to their tiles
        for key, args in jobs:
            f = client.submit(fn, *args, key=f"gpomap-{fn.__name__}-{key[0]}_{key[1]}-{tag}", pure=False)
            futs[f] = key
        # as_completed takes the event loop of the futures' client; without it, it looks for a
        # default client and fails with "No clients found". It also fetches the results in the
        # background: a result lost with its worker before we fetched it is recomputed there,
        # while this loop keeps watching for workers (a blocking f.result() would hang).
        pending = as_completed(list(futs), loop=client.loop, with_results=True, raise_errors=False)
        results = {} if results is None else results
        failed: dict[tuple[int, int], BaseException] = {}
        n_done = 0
        timeout = self.scheduler_timeout
        alive = time.monotonic()  # last time a worker was seen or a task finished
        next_check = alive
        try:
            while not pending.is_empty():
                done = pending.next_batch(block=False)
                for f, res in done:
                    key = futs[f]
                    if f.status == "finished":
                        results[key] = res
                        n_done += 1
                        bar.update()
                    elif f.status == "error":  # res is (type, exception, traceback): retried
                        failed[key] = res[1]
                    else:  # cancelled (the scheduler forgot it): retried
                        failed[key] = res if isinstance(res, BaseException) else RuntimeError(f"task {f.key} {f.status}")
                    f.release()
                now = time.monotonic()
                if done:
                    alive = now
                    continue
                if now >= next_check:
                    next_check = now + min(1.0, timeout / 5)
                    self._check_client(client, what, len(jobs) - n_done - len(failed), len(jobs))
                    if self._n_dask_workers(client) > 0:
                        alive = now
                    elif now - alive > timeout:
                        left = len(jobs) - n_done - len(failed)
                        raise DistributedError(
                            f"{what}: no Dask worker has been connected to the scheduler at {self._scheduler_address()} "
                            f"for {timeout:g} s, with {left} of {len(jobs)} tile(s) left; start workers "
                            f"('dask worker {self._scheduler_address()}'), or allow longer with --scheduler-timeout "
                            "(scheduler_timeout)"
                        )
                time.sleep(0.05)
        finally:
            pending.clear()
            unfinished = [f for f in futs if not f.done()]
            if unfinished:  # stopped early: drop our tasks from the cluster
                client.cancel(unfinished)
        return results, failed

    def _check_client(self, client: Any, what: str, left: int, total: int) -> None:
        """Raise DistributedError once the client has given up on its scheduler."""
        if client.status in ("closing", "closed"):
            raise DistributedError(
                f"{what}: lost the connection to the Dask scheduler at {self._scheduler_address()}, with {left} of "
                f"{total} tile(s) left; check that the scheduler still runs, then run again"
            )

    @staticmethod
    def _n_dask_workers(client: Any) -> int:
        """Workers connected to the client's scheduler (0 when the scheduler does not answer)."""
        try:
            return len(client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # a lost scheduler counts as no workers
            return 0
