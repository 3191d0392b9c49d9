"""The ``gpomap`` command: a thin layer over the library, one module per command.

Each command's module (:mod:`~gpomap.cli.map`, :mod:`~gpomap.cli.demo`, :mod:`~gpomap.cli.info`,
:mod:`~gpomap.cli.evaluate`, :mod:`~gpomap.cli.convert`, :mod:`~gpomap.cli.benchmark`,
:mod:`~gpomap.cli.stream`, :mod:`~gpomap.cli.render`, :mod:`~gpomap.cli.query`,
:mod:`~gpomap.cli.update`) registers its options with ``add_parser(sub)`` and runs with
``run(args)``: it checks its options, calls the library (:mod:`gpomap.apps` holds the jobs only a
command does) and prints a short summary. What they share is in :mod:`gpomap.cli.options` (numeric
argument types, defaults stated once), the option groups by what they set with the configs they make
(:mod:`~gpomap.cli.input_options`: what is read; :mod:`~gpomap.cli.model_options`: the model and its
tiles; :mod:`~gpomap.cli.output_options`: the written map) and :mod:`gpomap.cli.common` (status
lines, checks before work, output sets, summaries, error reporting). :func:`main` turns errors into one
line on stderr (``gpomap: error: ...``) with a non-zero exit code; ``--debug`` shows the traceback
instead. No module outside this package imports it.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Sequence
from typing import NoReturn

from gpomap._version import __version__
from gpomap.cli import benchmark, convert, demo, evaluate, info, map, query, render, stream, update
from gpomap.cli.common import EXIT_ERROR, EXIT_OK, EXIT_USAGE, Parser, run_command
from gpomap.cli.options import resolve_library_defaults

__all__ = ["COMMANDS", "EXIT_OK", "EXIT_ERROR", "EXIT_USAGE", "build_parser", "main", "console"]

#: The commands' modules, in the order ``gpomap --help`` lists them.
COMMANDS = (map, demo, info, evaluate, convert, benchmark, stream, render, query, update)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``gpomap`` command."""
    parser = Parser(
        prog="gpomap",
        description="Continuous occupancy maps from laser scans or occupancy grids with area-kernel Gaussian processes (MSK-GPOM).",
        epilog="Run 'gpomap COMMAND --help' for a command's options. Start with 'gpomap demo -o demo-output'.",
    )
    parser.add_argument("--version", action="version", version=f"gpomap {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for command in COMMANDS:
        command.add_parser(sub)
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
    resolve_library_defaults(args)
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
