"""What every command does around its work: status lines and warnings, checks before work, output sets, summaries, errors.

A command reports progress on stderr (:func:`status`, silenced by ``--quiet``), warnings as one
``warning: ...`` line (:func:`warn`), and writes its files as one output set
(:func:`outputs`), so that :func:`run_command` can say truly what the output directory holds when
a run fails, runs out of memory or is interrupted.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, ClassVar, NoReturn

from gpomap.errors import GpomapError

__all__ = [
    "EXIT_OK",
    "EXIT_ERROR",
    "EXIT_USAGE",
    "Parser",
    "status",
    "warn",
    "Run",
    "outputs",
    "check_before_work",
    "GRID_ADVICE",
    "check_grid_memory",
    "check_fit_memory",
    "check_voxel_memory",
    "limit_threads",
    "load_scans",
    "report_fit",
    "peak_memory",
    "ray_counts",
    "bound_source",
    "print_map_summary",
    "run_command",
]

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are two lines: what was wrong, and where the options are
    (the whole usage of ``gpomap map`` is twenty lines above the one that matters)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n(run '{self.prog} --help' for the options)\n")


def status(args: argparse.Namespace, message: str) -> None:
    """A progress line on stderr, unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(message, file=sys.stderr, flush=True)


def warn(message: str) -> None:
    """A one-line warning on stderr."""
    print("warning: " + " ".join(str(message).split()), file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- output sets
class Run:
    """What this process has written (for a true message on interrupt)."""

    outdir: str | None = None
    sets: ClassVar[list[Any]] = []


@contextmanager
def outputs(args: argparse.Namespace) -> Iterator[Any]:
    """One set of outputs in ``args.output``, put in place together at the end of the block."""
    from gpomap.io.atomic import output_set

    Run.outdir = args.output
    with output_set(args.output) as output:
        Run.sets.append(output)
        yield output


def _where_outputs_stand() -> str:
    """What the output directory holds now, for a message that must be true."""
    if Run.outdir is None:
        return "nothing was written"
    if any(s.committed for s in Run.sets):
        return f"{Run.outdir} holds the last complete set of outputs this run wrote"
    return f"the previous outputs in {Run.outdir} are unchanged"


# --------------------------------------------------------------------------- checks before any work
def check_before_work(args: argparse.Namespace) -> None:
    """The cheap checks, run before anything is read or fitted: the output directory, option pairs."""
    from gpomap.io.atomic import check_output_dir, recover_output_dir

    if (
        getattr(args, "min_cell", None) is not None
        and getattr(args, "max_cell", None) is not None
        and args.min_cell > args.max_cell
    ):
        raise GpomapError(f"--min-cell ({args.min_cell}) must not exceed --max-cell ({args.max_cell})")
    if getattr(args, "output", None) is not None:
        check_output_dir(args.output, "-o")
        # A run killed earlier (SIGKILL) may have left its staging directory: finish or remove it.
        for note in recover_output_dir(args.output):
            status(args, f"  {note}")


GRID_ADVICE = "use a coarser --resolution, a smaller --extent, or a larger --memory-limit GB if the machine has the memory"


def check_grid_memory(args: argparse.Namespace, shape: tuple[int, int], extent: Sequence[float], n_cells: int) -> None:
    """Refuse a written grid of `shape` (ny, nx) over `extent`, with GPs of `n_cells`, that needs more than ``--memory-limit``."""
    from gpomap.resources import check_memory, grid_memory, memory_limit

    limit, source = memory_limit(args.memory_limit)
    ny, nx = shape
    xmin, xmax, ymin, ymax = extent
    origin = "--extent" if args.extent is not None else "the data's extent"
    what = (
        f"a {nx} x {ny} grid ({nx * ny:.3g} cells) at --resolution {args.resolution:g} m over x {xmin:.6g}..{xmax:.6g}, "
        f"y {ymin:.6g}..{ymax:.6g} m ({origin})"
    )
    check_memory(grid_memory(shape, 1, n_cells), limit, what, GRID_ADVICE, source)


def check_fit_memory(args: argparse.Namespace, n_cells: int, n_at_once: int, where: str) -> None:
    """Refuse fitting `n_at_once` GPs of `n_cells` cells at once when they need more than ``--memory-limit``."""
    from gpomap.resources import check_memory, fit_memory, memory_limit

    limit, source = memory_limit(args.memory_limit)
    what = f"fitting {n_at_once} GP(s) of {n_cells} cells at once ({where})"
    advice = "use a larger --min-cell, a smaller --tile-size, fewer --workers, or a larger --memory-limit GB"
    check_memory(fit_memory(n_cells, n_at_once), limit, what, advice, source)


def check_voxel_memory(args: argparse.Namespace, lo: Any, hi: Any, n_cells: int) -> None:
    """Refuse a voxel map between corners `lo` and `hi` (shape (3,) each) at ``--resolution`` that needs more than ``--memory-limit``."""
    from gpomap.resources import check_memory, memory_limit, voxel_grid_memory, voxel_shape

    limit, source = memory_limit(args.memory_limit)
    nz, ny, nx = voxel_shape(lo, hi, args.resolution)
    origin = "--extent / --z-range" if args.extent is not None or args.z_range is not None else "the data's extent"
    what = (
        f"a {nx} x {ny} x {nz} voxel grid ({nx * ny * nz:.3g} voxels) at --resolution {args.resolution:g} m over "
        f"x {lo[0]:.6g}..{hi[0]:.6g}, y {lo[1]:.6g}..{hi[1]:.6g}, z {lo[2]:.6g}..{hi[2]:.6g} m ({origin})"
    )
    advice = GRID_ADVICE.replace("--extent", "--extent / --z-range")
    check_memory(voxel_grid_memory((nz, ny, nx), n_cells), limit, what, advice, source)


def limit_threads(args: argparse.Namespace) -> None:
    """Cap this process's BLAS threads at ``--threads`` (the workers get theirs from TiledGPOM)."""
    if getattr(args, "threads", None) is not None:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=args.threads)  # for the rest of the run, not as a context


# --------------------------------------------------------------------------- reading
def load_scans(args: argparse.Namespace) -> list[Any]:
    """The planar scans of ``args.input``, read with the reading options and selected (``--range``, ``--scans``, ``--beams``).

    Raises
    ------
    GpomapError
        ``--range`` selects no scan.
    """
    from gpomap.cli.input_options import reader_options
    from gpomap.io import read_scans
    from gpomap.scans import select_scans

    scans = read_scans(args.input, **reader_options(args, args.input))
    above = scans[0].meta.get("frames_above") if scans and getattr(args, "fixed_frame", None) is None else None
    if above:
        # A bag recorded while a SLAM ran: the corrected frame is there for the asking.
        status(
            args,
            f"  poses in {scans[0].meta['fixed_frame']!r}, which tf places in {above[-1]!r}: --fixed-frame {above[-1]} maps in that frame",
        )
    if args.scan_range is not None:
        first, last = args.scan_range
        n_all = len(scans)
        scans = scans[slice(first, last)]
        if not scans:
            raise GpomapError(f"--range {first}:{last} selects no scans from {args.input}, which has {n_all} scans")
    return select_scans(scans, args.scans, args.beams)


# --------------------------------------------------------------------------- summaries
def report_fit(model: Any, occupancy_map: Any) -> None:
    """Print what the fit's numbers say about the map's trustworthiness (see gpomap.diagnostics)."""
    from gpomap.diagnostics import fit_warnings

    for message in fit_warnings(model, occupancy_map):
        warn(message)


def peak_memory(peak: dict[str, float]) -> str:
    """``"self N MB, children M MB"`` from :func:`gpomap.resources.peak_rss_mb`; "unknown" where the system keeps no record."""
    known = {k: v for k, v in peak.items() if math.isfinite(v)}
    return ", ".join(f"{k} {v:.0f} MB" for k, v in known.items()) if known else "unknown on this system"


def ray_counts(evidence: dict[str, float]) -> str:
    """What a map's ray-count calibration weighs (:meth:`gpomap.fusion.EvidenceLayer.summary`), in a line."""
    line = (
        f"against a miss in open space, a hit weighs {evidence['hit_weight']:.3g}, a miss beside a hit "
        f"{evidence['surface_weight']:.3g}, a near miss {evidence['near_weight']:.3g} (and {evidence['near_hit_weight']:.3g} "
        f"hits), the GP {evidence['prior_weight']:.3g}; surprise rate {evidence['surprise_rate']:.3g}"
    )
    if evidence.get("silent_mix", 0.0) > 0.0:
        mix, rate = evidence["silent_mix"], evidence["silent_rate"]
        line += f"; where only beams without a return went, p -> {1.0 - mix:.3g} p + {mix * rate:.3g}"
    return line


def bound_source(model: Any) -> str | None:
    """ "at bound: ..." when a learnt hyperparameter sits at a bound, else None (the model's own words)."""
    from gpomap.diagnostics import hyperparameter_source

    source = hyperparameter_source(model)
    return source if source.startswith("at bound") else None


def _free_points(summary: dict[str, Any]) -> str:
    """The summary's free points, with the samples they stand for where a scan's were merged by cube."""
    n_free = summary["n_points"] - summary["n_occupied_points"]
    samples = summary.get("n_free_samples", n_free)
    return f"{n_free} free" if samples == n_free else f"{n_free} free (standing for {samples} samples, merged by cube)"


def _no_return(summary: dict[str, Any]) -> str:
    """The readings that returned nothing, where there were any: they say free space only, up to
    ``--no-return-cap``, so a reader sees how much of the map rests on them."""
    n = summary.get("n_no_return_readings", 0)
    return f"; {n} readings without a return (free space only, to --no-return-cap)" if n else ""


def print_map_summary(summary: dict[str, Any], files: Sequence[Path], source: str | None = None) -> None:
    """The summary a fitted map's command prints: data, tiles, model, hyperparameters, calibration, timings, files."""
    per = summary["cells_per_tile"]
    kappa = summary.get("variance_scale_fit") or {}
    # A variance scale left at 1 unsearched has its own line, saying why, not the learnt ones'.
    unsearched = "reason" in kappa and kappa.get("kappa") == 1.0
    hyperparameters = {k: v for k, v in summary["hyperparameters"].items() if not (unsearched and k == "variance_scale")}
    lines = [
        f"scans        {summary['n_scans']}",
        f"points       {_free_points(summary)}, {summary['n_occupied_points']} occupied{_no_return(summary)}",
        f"tiles        {summary['n_tiles']} of {summary['tile_size']:g} m (overlap {summary['overlap']:.2f} m), "
        f"{summary['n_cells']} cells, {per['min']}/{per['median']:.0f}/{per['max']} per tile (min/median/max), {summary['executor']}",
        f"model        {summary['kernel']} kernel, {summary['area']} area kernel",
        "hyperparams  "
        + ", ".join(f"{k} {v:.4g}" for k, v in hyperparameters.items())
        + f" ({source or summary['hyperparameter_source'].get('how', '')})",
        "ternary      free below {:.3f}, occupied above {:.3f}".format(*summary["thresholds"]),
    ]
    if unsearched:
        # Not learnt, whatever the line above says of the others: say why.
        lines.insert(-1, f"unseen space the GP's own variance ({kappa['reason']})")
    if summary.get("evidence"):
        lines.append("ray counts   " + ray_counts(summary["evidence"]))
    later = summary.get("revisit") or {}
    if "slope" in later:
        lines.append(
            f"later visit  log-odds times {later['slope']:.3g}, {later['shift']:+.3g} away from 1/2 (fitted on a held-out "
            f"stretch, {later['n_points']} points)"
        )
    lines += [
        "timings (s)  " + ", ".join(f"{k} {v:.2f}" for k, v in summary["timings"].items()),
        "peak memory  " + peak_memory(summary["peak_memory"]),
    ]
    lines += [f"wrote        {f}" for f in files]
    print("\n".join(lines))


# --------------------------------------------------------------------------- running a command
class _Terminated(KeyboardInterrupt):
    """SIGTERM, turned into the same clean path as Ctrl-C (staging removed, previous outputs kept)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise _Terminated()


def _show_warning(
    message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None, line: str | None = None
) -> None:
    """Python warnings (a library's, a reader's) as one ``warning: ...`` line, without a source path."""
    warn(str(message))


def run_command(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run a parsed command: its errors as one line on stderr (``--debug``: the traceback), its exit code returned.

    Interrupts (Ctrl-C, SIGTERM) and running out of memory say what the output directory holds.
    """
    Run.outdir, Run.sets = None, []
    # Signal handlers can only be installed from the main thread (main() may be called from others).
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous_sigterm = signal.signal(signal.SIGTERM, _on_sigterm) if in_main_thread else None
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return func(args)
    except (GpomapError, OSError, ValueError) as exc:
        if args.debug:
            raise
        message = str(exc)
        if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in message:
            message = f"{exc.filename}: {message}"
        print(f"gpomap: error: {message}", file=sys.stderr)
        return EXIT_ERROR
    except MemoryError:
        if args.debug:
            raise
        print(
            f"gpomap: error: out of memory ({_where_outputs_stand()}); use a coarser --resolution or a smaller --extent, "
            "or a lower --memory-limit GB so that such a run is refused before it starts",
            file=sys.stderr,
        )
        return EXIT_ERROR
    except KeyboardInterrupt as exc:
        print(
            f"gpomap: interrupted{' (SIGTERM)' if isinstance(exc, _Terminated) else ''}; {_where_outputs_stand()}",
            file=sys.stderr,
        )
        return 128 + (signal.SIGTERM if isinstance(exc, _Terminated) else signal.SIGINT)
    finally:
        if previous_sigterm is not None:
            signal.signal(signal.SIGTERM, previous_sigterm)
