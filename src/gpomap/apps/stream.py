"""Replaying a recorded log through a streaming mapper, as a robot would deliver its scans.

:func:`replay` feeds the scans one at a time, paced by their time stamps (:func:`replay_times`:
rate 1 real time, 0 as fast as possible), writes the map every so many seconds of wall time, and
stops between two steps on Ctrl-C or SIGTERM (:func:`deferred_signals`), so that the last map
written is complete. ``gpomap stream`` (:mod:`gpomap.cli.stream`) is this loop on the command line.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError
from gpomap.scans import Scan

__all__ = ["ReplayResult", "replay_times", "deferred_signals", "replay", "same_scan"]


@dataclass
class ReplayResult:
    """What a replay did.

    Attributes
    ----------
    n_scans : int
        Scans given to the mapper.
    latency : list of float
        Seconds each ``add_scan`` took, in scan order.
    writes : list of float
        Seconds each map write took (grid prediction, which refits the dirty tiles, and the files).
    wall : float
        Seconds from the first scan to the end (or the interrupt).
    lag : float
        Most seconds the replay fell behind the recording (0 with ``rate=0``).
    interrupted : bool
        Whether Ctrl-C / SIGTERM stopped it.
    files : list of Path
        The files of the last map written.
    """

    n_scans: int = 0
    latency: list[float] = field(default_factory=list)
    writes: list[float] = field(default_factory=list)
    wall: float = 0.0
    lag: float = 0.0
    interrupted: bool = False
    files: list[Path] = field(default_factory=list)

    def latency_ms(self) -> dict[str, float]:
        """Median, 95th percentile and maximum of the per-scan latency, milliseconds."""
        lat = np.asarray(self.latency, dtype=float) * 1e3
        if not lat.size:
            return {"median": math.nan, "p95": math.nan, "max": math.nan}
        return {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95)), "max": float(lat.max())}


def replay_times(scans: Sequence[Scan], rate: float, source: str = "input") -> NDArray[np.float64]:
    """Seconds after the start at which each scan is due: its recorded time divided by `rate`.

    Time stamps that step back (some recorded logs have them) are held at the latest one so far: the
    scan is then due at once, never before the one recorded ahead of it.

    Parameters
    ----------
    scans : sequence of Scan
    rate : float
        Replay speed (1 real time); 0 means as fast as possible (every scan due at 0).
    source : str
        The input's name, for the error message.

    Returns
    -------
    ndarray of shape (n,)

    Raises
    ------
    GpomapError
        `rate` > 0 and some scans have no (finite) time stamp.
    """
    n = len(scans)
    if rate == 0 or n == 0:
        return np.zeros(n)
    missing = [i for i, s in enumerate(scans) if s.time is None or not math.isfinite(s.time)]
    if missing:
        raise GpomapError(
            f"{source}: {len(missing)} of {n} scans have no time stamp (first: scan {missing[0]}), "
            "so they cannot be replayed as recorded; use --rate 0 (as fast as possible)"
        )
    t = np.maximum.accumulate(np.array([float(s.time) for s in scans]))  # type: ignore[arg-type]
    return (t - t[0]) / rate


@contextmanager
def deferred_signals(signums: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[Callable[[], None]]:
    """Hold Ctrl-C and SIGTERM until the caller reaches a point where stopping is safe.

    Inside the block, each of `signums` whose handler is a Python function (Ctrl-C's default
    raises KeyboardInterrupt; ``gpomap``'s SIGTERM handler raises its subclass) is recorded
    instead of raised. The yielded ``check()`` runs the recorded signal's own handler, so the
    interrupt is raised where the caller calls it, between two scans. Raised anywhere, it may
    land in code that swallows it (a callback run while an object is torn down reports it as
    "Exception ignored" and goes on). A second signal before ``check()`` is raised at once: a
    user pressing Ctrl-C twice is not kept waiting. Outside the main thread nothing changes.

    Yields
    ------
    check : callable
        Raises the recorded signal's exception, if any.
    """
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    pending: list[int] = []
    previous = {s: signal.getsignal(s) for s in signums}
    handlers = {s: h for s, h in previous.items() if callable(h)}

    def record(signum: int, frame: Any) -> None:
        if pending:
            handlers[signum](signum, frame)
        pending.append(signum)

    def check() -> None:
        if pending:
            signum = pending[0]
            pending.clear()
            handlers[signum](signum, None)

    for s in handlers:
        signal.signal(s, record)
    try:
        yield check
    finally:
        for s in handlers:
            signal.signal(s, previous[s])


def replay(
    scans: Sequence[Scan],
    mapper: Any,
    rate: float,
    every: float,
    write: Callable[[int], list[Path]],
    progress: Callable[[str], None] | None = None,
    source: str = "input",
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    result: ReplayResult | None = None,
    finish: Callable[[], None] | None = None,
) -> ReplayResult:
    """Feed `scans` to `mapper` as recorded and write the map every `every` seconds.

    Parameters
    ----------
    scans : sequence of Scan
    mapper : StreamingGPOM
        Anything with ``add_scan(scan)`` and ``ready_``.
    rate : float
        Replay speed: 1 real time, 0 as fast as possible.
    every : float
        Wall-clock seconds between map writes (0: after every scan once the mapper is ready).
    write : callable
        ``write(n_scans_so_far)`` writes the current map and returns its files; called only when
        the mapper is ready, and once more at the end.
    progress : callable, optional
        Receives one status line per write.
    source : str
        The input's name, for messages.
    clock, sleep : callable
        Monotonic seconds and a sleep (tests may pass their own).
    result : ReplayResult, optional
        Filled as the replay goes, so a caller that catches the KeyboardInterrupt (re-raised
        here) still has the numbers so far.
    finish : callable, optional
        Called once the log has ended, before the last write.

    Returns
    -------
    ReplayResult
    """
    due = replay_times(scans, rate, source)
    result = ReplayResult() if result is None else result
    start = clock()
    next_write = start + every

    def do_write() -> None:
        t = time.perf_counter()
        result.files = write(result.n_scans)
        result.writes.append(time.perf_counter() - t)
        if progress is not None:
            lat = result.latency_ms()
            behind = f", {result.lag:.1f} s behind the recording at most" if rate > 0 else ""
            progress(
                f"  scan {result.n_scans}/{len(scans)}: add_scan median {lat['median']:.1f} ms, p95 {lat['p95']:.1f} ms; "
                f"map written in {result.writes[-1]:.2f} s{behind}"
            )

    try:
        with deferred_signals() as stop_if_asked:
            for i, scan in enumerate(scans):
                if rate > 0:
                    wait = start + due[i] - clock()
                    if wait > 0:
                        sleep(wait)
                    else:
                        result.lag = max(result.lag, -wait)
                stop_if_asked()
                t = time.perf_counter()
                mapper.add_scan(scan)
                result.latency.append(time.perf_counter() - t)
                result.n_scans = i + 1
                if progress is not None and not mapper.ready_ and i == 0:
                    progress("  warming up: the first map comes once the hyperparameters are learnt")
                if mapper.ready_ and clock() >= next_write:
                    stop_if_asked()
                    do_write()
                    next_write = clock() + every
            stop_if_asked()
            if not mapper.ready_:
                raise GpomapError(
                    f"{source}: {len(scans)} scans were not enough to learn the hyperparameters; "
                    "use a smaller --warmup or a longer log"
                )
            if finish is not None:
                finish()
                stop_if_asked()
            do_write()
    except KeyboardInterrupt:
        result.interrupted = True
        raise
    finally:
        result.wall = clock() - start
    return result


def same_scan(a: Any, b: Any) -> bool:
    """Whether two planar scans are the same reading (pose, angles, ranges, max range)."""
    return (
        np.array_equal(a.pose, b.pose)
        and np.array_equal(a.angles, b.angles)
        and np.array_equal(a.ranges, b.ranges, equal_nan=True)
        and a.max_range == b.max_range
    )
