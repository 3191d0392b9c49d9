"""``gpomap demo -o OUTDIR``: the paper's synthetic room, simulated and mapped end to end, as ``gpomap map`` maps a log."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gpomap.cli.common import EXIT_OK, check_before_work, print_map_summary, status
from gpomap.cli.map import fitted_model, plan_map, save_model, write_map
from gpomap.cli.model_options import add_model_options, add_tiling_options
from gpomap.cli.options import Default
from gpomap.cli.output_options import add_output_options

__all__ = ["DEMO_RESOLUTION", "add_parser", "run"]

#: Cell side of the map ``gpomap demo`` writes, metres (the paper's synthetic room is 20 x 16 m: a 40 x 32 grid).
DEMO_RESOLUTION = 0.5


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap demo`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "demo",
        help="map the paper's synthetic room (built-in simulator)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="The paper's synthetic room: 31 poses x 36 noiseless beams, mapped end to end.",
        epilog="example:\n  gpomap demo -o demo-output",
    )
    add_model_options(p)
    add_tiling_options(p)
    add_output_options(p, Default(DEMO_RESOLUTION))
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap demo``: the map's files, the cell tree as a figure beside them (cells.png) and the fitted map (map.gpom)."""
    import numpy as np

    from gpomap.plot import plot_inputs, save_figure
    from gpomap.simulate import paper_room_scans

    check_before_work(args)
    scans = paper_room_scans()
    status(args, f"simulated the paper's synthetic room: {len(scans)} poses x {scans[0].n_beams} beams over 360 degrees")
    plan_map(args, scans)

    def cell_figure(model: Any, directory: Path) -> Path:
        # The cell tree as a figure too (the paper's Fig. 5a), in the same set of outputs.
        lower, upper, labels = model.cell_boxes()
        points, occupied = model.training_points()
        fig = plot_inputs(points, occupied, boxes=np.stack([lower, upper], axis=1), box_labels=labels)
        return save_figure(fig, directory / "cells.png")

    # The model is handed over: cells.png is drawn from it and map.gpom written (for gpomap render,
    # query and update) before it is let go.
    files, summary, bound = write_map(
        args, [fitted_model(args, scans)], "gpomap demo: the paper's synthetic room", [cell_figure, save_model]
    )
    print_map_summary(summary, files, bound)
    return EXIT_OK
