"""``gpomap info INPUT``: what a range-data file holds, read as ``gpomap map`` reads it, or one of
gpomap's own files (a fitted map ``map.gpom``, a written grid or voxel map ``map.npz``)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from gpomap.apps.map3d import is_cloud_input
from gpomap.cli.common import EXIT_OK
from gpomap.cli.input_options import (
    add_cloud_reader_options,
    add_reader_options,
    check_2d_options,
    cloud_reader_options,
    reader_options,
)

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap info`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "info",
        help="what a range-data file or a map gpomap wrote holds",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Format, scans, beams, extent and max range of a CARMEN log, ROS bag or 3-D scans; "
        "or what a map gpomap wrote holds: a fitted map (map.gpom: its model, scans, tiles and "
        "hyperparameters, read from its header) or a written grid (map.npz: its cells and classes).",
        epilog="examples:\n  gpomap info ../shared/data/fr079/freiburg-079-corrected.log.gz\n  gpomap info out/map.gpom",
    )
    p.add_argument("input")
    add_reader_options(p)
    add_cloud_reader_options(p)  # read as gpomap map reads them
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap info``: the description of :func:`gpomap.io.describe` (of
    :func:`gpomap.apps.own_files.describe_own_file` for a file gpomap wrote), as text or JSON."""
    from gpomap.apps.own_files import describe_own_file, own_format
    from gpomap.io import describe

    own = own_format(args.input)
    if own is not None:
        return _print(describe_own_file(args.input, own), args.json)
    if is_cloud_input(args.input):
        options = cloud_reader_options(args)
    else:
        check_2d_options(args)
        options = reader_options(args, args.input)
    info = describe(args.input, **options)
    if args.json:
        return _print(info, True)
    no_return = info.pop("no_return", None)
    notes = info.pop("notes", [])
    for key in ("no_return_code", "no_return_source"):
        info.pop(key, None)
    _print(info, False)
    # The no-return decision, one block per laser (message type): code, count, how decided.
    for d in no_return if isinstance(no_return, list) else [no_return] if no_return else []:
        label = f" ({d['message']})" if "message" in d else ""
        code = ", ".join(f"{c:g}" for c in d["code"]) + " m" if d["code"] else "none found in the data"
        print(f"{'no-return code':<16}{code}{label}")
        print(f"{'no-return count':<16}{d['n_no_return']} of {d['n_readings']} readings (>= {d['max_range']:g} m)")
        print(f"{'decided by':<16}{d['source']}" + (f" ({d['header']['name']} {d['header']['value']:g})" if d["header"] else ""))
        if d["contradiction"]:
            print(f"{'contradiction':<16}{d['contradiction']}")
    for note in notes:
        print(f"{'note':<16}{note}")
    return EXIT_OK


def _print(info: dict[str, Any], as_json: bool) -> int:
    """Print `info` as one JSON object, or a line a key (lists of floats to 3 decimals)."""
    if as_json:
        print(json.dumps(info, indent=2, default=str))
        return EXIT_OK
    width = max([16, *(len(k) + 1 for k in info)])  # a long key keeps a space before its value
    for key, value in info.items():
        if isinstance(value, (tuple, list)) and value and all(isinstance(v, float) for v in value):
            # Rounded before formatting, so a value a hair below zero does not print as -0.000.
            value = ", ".join(f"{round(v, 3) + 0.0:.3f}" for v in value)
        print(f"{key:<{width}}{value}")
    return EXIT_OK
