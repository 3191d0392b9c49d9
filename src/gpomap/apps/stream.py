"""``gpomap stream INPUT -o OUTDIR``: replay a recorded log through the streaming mapper.

The scans of a CARMEN log or a ROS bag go to :class:`gpomap.streaming.StreamingGPOM` one at a
time, paced by their time stamps (``--rate 1`` real time, ``--rate 2`` twice as fast, ``--rate 0``
as fast as possible), as a robot would deliver them. Every ``--every`` seconds of wall time the
current map replaces the previous set of outputs in OUTDIR as a whole
(:func:`gpomap.io.atomic.output_set`), so OUTDIR always holds a complete map; when the log ends,
the map of all its scans is fitted as ``gpomap map`` fits it and written last, so the final outputs
are ``gpomap map``'s. Ctrl-C (or SIGTERM) stops the replay between two steps: the summary so
far is printed and OUTDIR keeps the last complete map.

:func:`replay` is the loop, free of the command line; :func:`add_parser` and :func:`cmd_stream`
are the subcommand (registered in :mod:`gpomap.cli`).
"""

from __future__ import annotations

import argparse
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

from gpomap.config import MapConfig
from gpomap.errors import GpomapError
from gpomap.scans import Scan, scan_extent
from gpomap.streaming import DEFAULT_TILE_SIZE, DEFAULT_WARMUP_SCANS

__all__ = ["ReplayResult", "replay_times", "deferred_signals", "replay", "add_parser", "mapper_from_args", "cmd_stream"]


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

    Time stamps that step back (a few in the Intel log) are held at the latest one so far: the
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


# --------------------------------------------------------------------------- the subcommand
EPILOG = """examples:
  gpomap stream ../shared/data/intel/intel-corrected.log.gz -o intel-live --rate 0 --every 5
  gpomap stream robot1.bag --topic /base_scan --time-offset 0.1 -o arena-live --rate 1 --resolution 0.05
"""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap stream`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    from gpomap import cli

    p: argparse.ArgumentParser = sub.add_parser(
        "stream",
        help="replay a log or bag through the streaming mapper, writing the map as it grows",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Replay a CARMEN log or ROS bag as recorded (or as fast as possible), one scan at a time, "
        "into the streaming mapper; write map.yaml/.pgm, map.npz and map.png every --every seconds as one set; "
        "print progress and the per-scan latency. Ctrl-C stops it, leaving the last complete map.",
    )
    p.add_argument("input", help="CARMEN log (.log, .gz) or ROS bag (.bag, ROS2 directory, .db3, .mcap)")
    g = p.add_argument_group("the replay")
    g.add_argument(
        "--rate",
        type=cli._non_negative(float),
        default=1.0,
        help="replay speed from the scans' time stamps: 1 real time, 0 as fast as possible (default: %(default)s)",
    )
    g.add_argument(
        "--every",
        type=cli._non_negative(float),
        default=10.0,
        metavar="SECONDS",
        help="write the map every SECONDS of wall time, and at the end (default: %(default)s; 0: after every scan)",
    )
    g.add_argument(
        "--warmup",
        type=cli._positive(int),
        default=cli._Default(DEFAULT_WARMUP_SCANS),
        metavar="N",
        help="scans seen before the hyperparameters are learnt and the first map is written (default: %(default)s)",
    )
    g.add_argument(
        "--tile-size",
        type=cli._positive(float),
        default=cli._Default(DEFAULT_TILE_SIZE),
        help="tile side, m (default: %(default)s)",
    )
    g.add_argument(
        "--max-refits",
        type=cli._positive(int),
        default=None,
        metavar="N",
        help="refit at most N tiles per map written, oldest first; the rest wait for the next write "
        "(default: all, every map sees the GP of every scan; the ray counts are always current)",
    )
    g.add_argument(
        "--workers",
        type=cli._positive(int),
        help="workers refitting tiles (default: the mapper's, one: a scan's refits are too small for a pool)",
    )
    g = p.add_argument_group("saving and resuming")
    g.add_argument(
        "--save-state",
        metavar="FILE",
        help="when the replay stops (Ctrl-C, SIGTERM, or the end of the log, before its last fit), save the streaming "
        "mapper's state to FILE (a map file: gpomap render and query read its map) to carry on with --resume FILE",
    )
    g.add_argument(
        "--resume",
        metavar="FILE",
        help="carry on from a state saved with --save-state: the input's first scans must be those it holds (the same "
        "log and selection); the replay goes on from the next one with the state's settings",
    )
    cli._add_reader_options(p)
    cli._add_selection_options(p)
    cli._add_model_options(p)
    # As ``gpomap map``: the written map's cells are the ray counts' (--evidence-resolution).
    cli._add_output_options(p, cli._Default(MapConfig.evidence_resolution))
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_stream)
    return p


def mapper_from_args(args: argparse.Namespace) -> Any:
    """The unfitted :class:`~gpomap.streaming.StreamingGPOM` of a parsed ``gpomap stream`` command line."""
    from gpomap import cli
    from gpomap.streaming import StreamingGPOM

    # --workers left out keeps the mapper's own default.
    workers = {} if args.workers is None else {"n_workers": args.workers}
    return StreamingGPOM(
        warmup_scans=args.warmup,
        max_refits=args.max_refits,
        tile_size=args.tile_size,
        **workers,
        **cli._map_config(args).kwargs(),
    )


def _same_scan(a: Any, b: Any) -> bool:
    """Whether two planar scans are the same reading (pose, angles, ranges, max range)."""
    return (
        np.array_equal(a.pose, b.pose)
        and np.array_equal(a.angles, b.angles)
        and np.array_equal(a.ranges, b.ranges, equal_nan=True)
        and a.max_range == b.max_range
    )


def resumed_mapper(args: argparse.Namespace, scans: Sequence[Scan]) -> Any:
    """The :class:`~gpomap.streaming.StreamingGPOM` saved in ``--resume FILE``, checked against this run.

    The input's first scans must be those the state holds, and a model or replay option given on
    the command line must be the state's (those left out take the state's); ``--workers`` may change.

    Raises
    ------
    GpomapError
        Naming the first scan that differs, or the option and both values.
    """
    from gpomap import cli
    from gpomap.io.mapfile import load_streaming_state

    mapper = load_streaming_state(args.resume)
    held = mapper.model_._scans if mapper.model_ is not None else mapper._buffer
    n = int(mapper.n_scans_)
    where = f"--resume {args.resume}"
    if n > len(scans):
        raise GpomapError(f"{where}: the state holds {n} scans; {args.input} gives only {len(scans)} with these options")
    for i, (a, b) in enumerate(zip(held, scans, strict=False)):
        if not _same_scan(a, b):
            raise GpomapError(
                f"{where}: scan {i} of {args.input} is not the state's: resume with the log and the reading and "
                "selecting options (--range, --scans, --beams, --time-offset, ...) the state was saved from"
            )
    fresh = mapper_from_args(args)
    given = set(cli._given(args, [*cli._model_option_dests(), "tile_size", "warmup", "max_refits"]))
    pairs = {"warmup": (mapper.warmup_scans, fresh.warmup_scans), "max_refits": (mapper.max_refits, fresh.max_refits)}
    for key in mapper.options:
        if key != "n_workers":
            pairs[key] = (mapper.options[key], fresh.options.get(key))
    if "length_scale" in given:
        given.add("optimise")
    for dest in sorted(given & set(pairs)):
        saved, now = pairs[dest]
        if saved != now:
            raise GpomapError(
                f"{where}: the state was saved with {cli._flag(dest)} {saved!r}; this command line gives {now!r} "
                "(leave it out to keep the state's)"
            )
    if args.workers is not None:
        mapper.options["n_workers"] = args.workers
        if mapper.model_ is not None:
            mapper.model_.n_workers = args.workers
    return mapper


def _save_state(args: argparse.Namespace, mapper: Any, saved: list[str]) -> None:
    """``--save-state FILE``: the mapper's state written there; what was written noted in `saved`."""
    from gpomap import cli
    from gpomap.io.mapfile import save_streaming_state

    if args.save_state is not None:
        save_streaming_state(mapper, args.save_state)
        saved[:] = [f"{args.save_state}: {mapper.n_scans_} scans (carry on with --resume {args.save_state})"]
        cli._status(args, f"  saved the state of {mapper.n_scans_} scans to {args.save_state}")


def _check_state_path(args: argparse.Namespace) -> None:
    """``--save-state FILE``: a file in an existing directory (checked before any work)."""
    if args.save_state is None:
        return
    p = Path(args.save_state)
    if p.is_dir():
        raise GpomapError(f"--save-state {p}: is a directory; expected a file to write")
    if not p.resolve().parent.is_dir():
        raise GpomapError(f"--save-state {p}: the directory {p.parent} does not exist")


def cmd_stream(args: argparse.Namespace) -> int:
    """Run ``gpomap stream``."""
    from gpomap import cli
    from gpomap.io.export import write_map_files
    from gpomap.resources import grid_shape

    cli._check_before_work(args)
    _check_state_path(args)
    cli._resolution_from_evidence(args)  # as gpomap map writes them
    cli._status(args, f"reading scans from {args.input}...")
    scans = cli._load_scans(args)
    cli._status(args, f"  {len(scans)} scans of {scans[0].n_beams} beams")
    due = replay_times(scans, args.rate, args.input)
    if args.rate > 0:
        cli._status(args, f"  replaying {due[-1] * args.rate:.1f} s of recording at rate {args.rate:g}: {due[-1]:.1f} s")
    # The largest map this replay can write, checked against the memory limit before any work.
    extent = (
        args.extent if args.extent is not None else scan_extent(scans, include_no_return=True, no_return_cap=args.no_return_cap)
    )
    cli._check_grid_memory(args, grid_shape(extent, args.resolution), extent, 0)
    mapper = resumed_mapper(args, scans) if args.resume is not None else mapper_from_args(args)
    done = int(mapper.n_scans_)  # scans the state resumed from holds already
    if done:
        cli._status(args, f"  resuming after scan {done} of {len(scans)} ({args.resume})")
    title = f"gpomap stream: {Path(args.input).name}"

    ended: list[bool] = []
    saved: list[str] = []

    def relearn() -> None:
        # The log has ended: every scan is in, so the last map is gpomap map's of the same scans
        # (hyperparameters, variance scale and recalibration learnt on all of them, not the warm-up's).
        _save_state(args, mapper, saved)
        cli._status(args, f"  the log has ended: fitting the map of all {len(scans)} scans, as gpomap map does...")
        mapper.relearn()
        ended.append(True)

    def write(n: int) -> list[Path]:
        occupancy_map = mapper.model_.grid(args.resolution, args.extent) if ended else mapper.grid(args.resolution, args.extent)
        with cli._outputs(args) as outputs:
            staged = write_map_files(
                occupancy_map, outputs.path, pgm_mode=args.pgm_mode, title=f"{title} ({done + n} of {len(scans)} scans)"
            )
        return [outputs.final(f) for f in staged]

    result = ReplayResult()
    try:
        replay(
            scans[done:],
            mapper,
            args.rate,
            args.every,
            write,
            lambda m: cli._status(args, m),
            args.input,
            result=result,
            finish=relearn,
        )
    except KeyboardInterrupt:
        if not ended:  # after the last fit, the state was saved before it
            _save_state(args, mapper, saved)
        _print_summary(args, mapper, result, len(scans), done, saved)
        raise
    _print_summary(args, mapper, result, len(scans), done, saved)
    return cli.EXIT_OK


def _print_summary(
    args: argparse.Namespace, mapper: Any, result: ReplayResult, n_total: int, done: int = 0, saved: Sequence[str] = ()
) -> None:
    lat = result.latency_ms()
    rate = "as fast as possible" if args.rate == 0 else f"at rate {args.rate:g}"
    resumed = f" ({done} from {args.resume})" if done else ""
    lines = [
        f"scans        {done + result.n_scans} of {n_total}{resumed}" + (" (interrupted)" if result.interrupted else ""),
        f"replay       {rate}: {result.wall:.2f} s wall, {result.n_scans / result.wall if result.wall > 0 else math.nan:.1f} scans/s"
        + (f", at most {result.lag:.2f} s behind the recording" if args.rate > 0 else ""),
        f"latency      add_scan median {lat['median']:.2f} ms, p95 {lat['p95']:.2f} ms, max {lat['max']:.2f} ms",
    ]
    if result.writes:
        w = np.asarray(result.writes)
        lines.append(f"maps         {w.size} written (median {np.median(w):.2f} s, max {w.max():.2f} s each, refits included)")
    if getattr(mapper, "ready_", False):
        hp = mapper.hyperparameters_
        lines.append("hyperparams  " + ", ".join(f"{k} {v:.4g}" for k, v in hp.items()))
    lines += [f"wrote        {f}" for f in result.files]
    lines += [f"state        {line}" for line in saved]
    print("\n".join(lines), flush=True)
