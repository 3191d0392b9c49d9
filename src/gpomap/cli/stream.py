"""``gpomap stream INPUT -o OUTDIR``: replay a recorded log through the streaming mapper.

The scans of a CARMEN log or a ROS bag go to :class:`gpomap.streaming.StreamingGPOM` one at a
time, paced by their time stamps (``--rate 1`` real time, ``--rate 2`` twice as fast, ``--rate 0``
as fast as possible), as a robot would deliver them (:func:`gpomap.apps.stream.replay`). Every
``--every`` seconds of wall time the current map replaces the previous set of outputs in OUTDIR as
a whole (:func:`gpomap.io.atomic.output_set`), so OUTDIR always holds a complete map; when the log
ends, the map of all its scans is fitted as ``gpomap map`` fits it and written last, so the final
outputs are ``gpomap map``'s. Ctrl-C (or SIGTERM) stops the replay between two steps: the summary
so far is printed and OUTDIR keeps the last complete map.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.apps.stream import ReplayResult, replay, replay_times, same_scan
from gpomap.cli.common import EXIT_OK, check_before_work, check_grid_memory, load_scans, status
from gpomap.cli.input_options import add_reader_options, add_selection_options
from gpomap.cli.map import write_grid
from gpomap.cli.model_options import add_model_options, map_config, model_option_dests
from gpomap.cli.options import Default, flag, given, non_negative, positive
from gpomap.cli.output_options import add_output_options, resolution_from_evidence
from gpomap.config import MapConfig
from gpomap.errors import GpomapError
from gpomap.scans import Scan, scan_extent
from gpomap.streaming import DEFAULT_TILE_SIZE, DEFAULT_WARMUP_SCANS

__all__ = ["add_parser", "run", "mapper_from_args", "resumed_mapper"]

EPILOG = """examples:
  gpomap stream ../shared/data/intel/intel-corrected.log.gz -o intel-live --rate 0 --every 5
  gpomap stream robot1.bag --topic /base_scan --time-offset 0.1 -o arena-live --rate 1 --resolution 0.05
"""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap stream`` on the subparsers of :func:`gpomap.cli.build_parser`."""

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
        type=non_negative(float),
        default=1.0,
        help="replay speed from the scans' time stamps: 1 real time, 0 as fast as possible (default: %(default)s)",
    )
    g.add_argument(
        "--every",
        type=non_negative(float),
        default=10.0,
        metavar="SECONDS",
        help="write the map every SECONDS of wall time, and at the end (default: %(default)s; 0: after every scan)",
    )
    g.add_argument(
        "--warmup",
        type=positive(int),
        default=Default(DEFAULT_WARMUP_SCANS),
        metavar="N",
        help="scans seen before the hyperparameters are learnt and the first map is written (default: %(default)s)",
    )
    g.add_argument(
        "--tile-size",
        type=positive(float),
        default=Default(DEFAULT_TILE_SIZE),
        help="tile side, m (default: %(default)s)",
    )
    g.add_argument(
        "--max-refits",
        type=positive(int),
        default=None,
        metavar="N",
        help="refit at most N tiles per map written, oldest first; the rest wait for the next write "
        "(default: all, every map sees the GP of every scan; the ray counts are always current)",
    )
    g.add_argument(
        "--workers",
        type=positive(int),
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
    add_reader_options(p)
    add_selection_options(p)
    add_model_options(p)
    # As ``gpomap map``: the written map's cells are the ray counts' (--evidence-resolution).
    add_output_options(p, Default(MapConfig.evidence_resolution))
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def mapper_from_args(args: argparse.Namespace) -> Any:
    """The unfitted :class:`~gpomap.streaming.StreamingGPOM` of a parsed ``gpomap stream`` command line."""
    from gpomap.streaming import StreamingGPOM

    # --workers left out keeps the mapper's own default.
    workers = {} if args.workers is None else {"n_workers": args.workers}
    return StreamingGPOM(
        warmup_scans=args.warmup,
        max_refits=args.max_refits,
        tile_size=args.tile_size,
        **workers,
        **map_config(args).kwargs(),
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
    from gpomap.io.mapfile import load_streaming_state

    mapper = load_streaming_state(args.resume)
    held = mapper.model_._scans if mapper.model_ is not None else mapper._buffer
    n = int(mapper.n_scans_)
    where = f"--resume {args.resume}"
    if n > len(scans):
        raise GpomapError(f"{where}: the state holds {n} scans; {args.input} gives only {len(scans)} with these options")
    for i, (a, b) in enumerate(zip(held, scans, strict=False)):
        if not same_scan(a, b):
            raise GpomapError(
                f"{where}: scan {i} of {args.input} is not the state's: resume with the log and the reading and "
                "selecting options (--range, --scans, --beams, --time-offset, ...) the state was saved from"
            )
    fresh = mapper_from_args(args)
    set_here = set(given(args, [*model_option_dests(), "tile_size", "warmup", "max_refits"]))
    pairs = {"warmup": (mapper.warmup_scans, fresh.warmup_scans), "max_refits": (mapper.max_refits, fresh.max_refits)}
    for key in mapper.options:
        if key != "n_workers":
            pairs[key] = (mapper.options[key], fresh.options.get(key))
    if "length_scale" in set_here:
        set_here.add("optimise")
    for dest in sorted(set_here & set(pairs)):
        saved, now = pairs[dest]
        if saved != now:
            said = "its default" if saved is None else repr(saved)
            raise GpomapError(
                f"{where}: the state was saved with {flag(dest)} {said}; this command line gives {now!r} "
                "(leave it out to keep the state's)"
            )
    if args.workers is not None:
        mapper.options["n_workers"] = args.workers
        if mapper.model_ is not None:
            mapper.model_.n_workers = args.workers
    return mapper


def _save_state(args: argparse.Namespace, mapper: Any, saved: list[str]) -> None:
    """``--save-state FILE``: the mapper's state written there; what was written noted in `saved`."""
    from gpomap.io.mapfile import save_streaming_state

    if args.save_state is not None:
        save_streaming_state(mapper, args.save_state)
        saved[:] = [f"{args.save_state}: {mapper.n_scans_} scans (carry on with --resume {args.save_state})"]
        status(args, f"  saved the state of {mapper.n_scans_} scans to {args.save_state}")


def _check_state_path(args: argparse.Namespace) -> None:
    """``--save-state FILE``: a file in an existing directory (checked before any work)."""
    if args.save_state is None:
        return
    p = Path(args.save_state)
    if p.is_dir():
        raise GpomapError(f"--save-state {p}: is a directory; expected a file to write")
    if not p.resolve().parent.is_dir():
        raise GpomapError(f"--save-state {p}: the directory {p.parent} does not exist")


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap stream``."""
    from gpomap.resources import grid_shape

    check_before_work(args)
    _check_state_path(args)
    resolution_from_evidence(args)  # as gpomap map writes them
    status(args, f"reading scans from {args.input}...")
    scans = load_scans(args)
    status(args, f"  {len(scans)} scans of {scans[0].n_beams} beams")
    due = replay_times(scans, args.rate, args.input)
    if args.rate > 0:
        status(args, f"  replaying {due[-1] * args.rate:.1f} s of recording at rate {args.rate:g}: {due[-1]:.1f} s")
    # The largest map this replay can write, checked against the memory limit before any work.
    extent = (
        args.extent if args.extent is not None else scan_extent(scans, include_no_return=True, no_return_cap=args.no_return_cap)
    )
    check_grid_memory(args, grid_shape(extent, args.resolution), extent, 0)
    mapper = resumed_mapper(args, scans) if args.resume is not None else mapper_from_args(args)
    done = int(mapper.n_scans_)  # scans the state resumed from holds already
    if done:
        status(args, f"  resuming after scan {done} of {len(scans)} ({args.resume})")
    title = f"gpomap stream: {Path(args.input).name}"

    ended: list[bool] = []
    saved: list[str] = []

    def relearn() -> None:
        # The log has ended: every scan is in, so the last map is gpomap map's of the same scans
        # (hyperparameters, variance scale and recalibration learnt on all of them, not the warm-up's).
        _save_state(args, mapper, saved)
        status(args, f"  the log has ended: fitting the map of all {len(scans)} scans, as gpomap map does...")
        mapper.relearn()
        ended.append(True)

    def write(n: int) -> list[Path]:
        from gpomap.fitted import LaterGrid

        # Through gpomap map's writing path, but no model handed over to be let go: the mapper
        # keeps it, to map on (and --save-state and the summary read it).
        if ended:
            later = mapper.model_.map_.grid_later(args.resolution, args.extent)
        else:
            made = mapper.grid(args.resolution, args.extent)  # the mapper's refresh, its statistics in the map's info
            later = LaterGrid(made.grid, lambda: made)
        files, _ = write_grid(args, later, f"{title} ({done + n} of {len(scans)} scans)")
        return files

    result = ReplayResult()
    try:
        replay(
            scans[done:],
            mapper,
            args.rate,
            args.every,
            write,
            lambda m: status(args, m),
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
    return EXIT_OK


def _print_summary(
    args: argparse.Namespace, mapper: Any, result: ReplayResult, n_total: int, done: int = 0, saved: Sequence[str] = ()
) -> None:
    """The summary of a replay: scans, pace, latency, maps written, hyperparameters, files and saved state."""
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
