"""The ``gpomap`` command: a thin layer over the library.

Each subcommand parses its options, calls library functions, prints a short summary, and turns
errors into one line on stderr (``gpomap: error: ...``) with a non-zero exit code. ``--debug``
shows the traceback instead.
"""

# ruff: noqa: F401 (the old names, which gpomap.apps and the tests reach until they move)
from __future__ import annotations

import argparse
import inspect
import json
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from gpomap._version import __version__
from gpomap.cli import benchmark, convert, demo, evaluate, info, map
from gpomap.cli.benchmark import benchmark_arguments as _benchmark_arguments
from gpomap.cli.common import EXIT_ERROR, EXIT_OK, EXIT_USAGE, GRID_ADVICE, Run, run_command
from gpomap.cli.common import Parser as _Parser
from gpomap.cli.common import bound_source as _bound_source
from gpomap.cli.common import check_before_work as _check_before_work
from gpomap.cli.common import check_fit_memory as _check_fit_memory
from gpomap.cli.common import check_grid_memory as _check_grid_memory
from gpomap.cli.common import limit_threads as _limit_threads
from gpomap.cli.common import load_scans as _load_scans
from gpomap.cli.common import outputs as _outputs
from gpomap.cli.common import peak_memory as _peak_memory
from gpomap.cli.common import print_map_summary as _print_map_summary
from gpomap.cli.common import ray_counts as _ray_counts
from gpomap.cli.common import report_fit as _report_fit
from gpomap.cli.common import status as _status
from gpomap.cli.common import warn as _warn
from gpomap.cli.convert import convert_options as _convert_options
from gpomap.cli.evaluate import evaluate_arguments as _evaluate_arguments
from gpomap.cli.evaluate import method_options as _method_options
from gpomap.cli.map import fitted_model as _fitted_model
from gpomap.cli.map import model as _model
from gpomap.cli.map import write_map as _write_map
from gpomap.cli.options import Default as _Default
from gpomap.cli.options import add_3d_output_options
from gpomap.cli.options import add_model_options as _add_model_options
from gpomap.cli.options import add_output_options as _add_output_options
from gpomap.cli.options import add_reader_options as _add_reader_options
from gpomap.cli.options import add_selection_options as _add_selection_options
from gpomap.cli.options import add_tiling_options as _add_tiling_options
from gpomap.cli.options import check_2d_options as _check_2d_options
from gpomap.cli.options import flag as _flag
from gpomap.cli.options import given as _given
from gpomap.cli.options import map_config as _map_config
from gpomap.cli.options import model_option_dests as _model_option_dests
from gpomap.cli.options import module_default as _module_default
from gpomap.cli.options import non_negative as _non_negative
from gpomap.cli.options import number as _number
from gpomap.cli.options import positive as _positive
from gpomap.cli.options import reader_options as _reader_options
from gpomap.cli.options import resolution_from_evidence as _resolution_from_evidence
from gpomap.cli.options import resolve_library_defaults as _resolve_library_defaults
from gpomap.cli.options import signature_default as _signature_default
from gpomap.cli.options import tiling_config as _tiling_config
from gpomap.config import DEFAULT_MAX_CELLS, MapConfig
from gpomap.errors import GpomapError

if TYPE_CHECKING:
    from gpomap.plot import ScoreCurve

# Until every command has its module, gpomap.apps reaches these by their old names.
_Run = Run
_GRID_ADVICE = GRID_ADVICE


# --------------------------------------------------------------------------- subcommands


# --------------------------------------------------------------------------- the parser


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``gpomap`` command."""
    parser = _Parser(
        prog="gpomap",
        description="Continuous occupancy maps from laser scans or occupancy grids with area-kernel Gaussian processes (MSK-GPOM).",
        epilog="Run 'gpomap COMMAND --help' for a command's options. Start with 'gpomap demo -o demo-output'.",
    )
    parser.add_argument("--version", action="version", version=f"gpomap {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for command in (map, demo, info, evaluate, convert, benchmark):
        command.add_parser(sub)

    # Its own module (the replay loop and its options): gpomap.apps.stream.
    from gpomap.apps.stream import add_parser as add_stream_parser

    add_stream_parser(sub)
    # A saved map (map.gpom) read again: gpomap.apps.render, .query and .update.
    from gpomap.apps import query, render, update

    render.add_parser(sub)
    query.add_parser(sub)
    update.add_parser(sub)
    # --debug after the command too ('gpomap map ... --debug'); hidden there, and unset unless given.
    for subparser in sub.choices.values():
        subparser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``gpomap`` command; returns the exit code."""
    from gpomap.progress import set_progress_mode

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    _resolve_library_defaults(args)
    set_progress_mode("quiet" if getattr(args, "quiet", False) else "auto")
    return run_command(args.func, args)


def console() -> NoReturn:
    """The ``gpomap`` command: :func:`main`, then exit with its code."""
    code = main()
    # The run is over and has said how it ended: a Ctrl-C while the interpreter shuts down (pools
    # and threads joining) must not turn it into a silent exit by SIGINT.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)
