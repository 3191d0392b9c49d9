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
from gpomap.cli import demo, info, map
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


def cmd_evaluate(args: argparse.Namespace) -> int:
    from gpomap.comparison import score_curves
    from gpomap.evaluation import Truth, evaluate, resolve_split
    from gpomap.truth import PlanTruth

    if args.demo == (args.input is not None):
        raise GpomapError("give either INPUT or --demo")
    if args.demo and args.truth is not None:
        raise GpomapError("--demo is scored against the room's true geometry already; drop --truth")
    if args.figure is not None:
        _check_figure_path(args.figure)
    arguments = _evaluate_arguments(args)  # refuses an option --method does not take, before any reading
    if args.input is not None and Path(args.input).exists():
        from gpomap.apps.map3d import is_cloud_input

        if is_cloud_input(args.input):
            raise GpomapError(
                f"{args.input} holds 3-D scans; gpomap evaluate scores planar maps only: score a voxel map on "
                "held-out scans and simulated scenes against OctoMap with benchmarks/quality3d.py"
            )
    truth = plan = None
    if args.demo:
        from gpomap.simulate import paper_room, paper_room_scans

        scans, source = paper_room_scans(), "demo: the paper's synthetic room"
        truth = Truth.from_world(paper_room()[0], args.grid_resolution)
        plan = PlanTruth.from_world(paper_room()[0])
    else:
        from gpomap.io import read_scans

        # The true map first: it is small, and a bad one should not wait for the log.
        if args.truth is not None:
            truth, plan = _read_truth(args)
        scans, source = read_scans(args.input, **_reader_options(args, args.input)), args.input
        if truth is not None:
            _check_truth_frame(args, truth, scans)
    if args.compare:
        return _compare(args, scans, truth, plan, arguments, source)
    _status(args, f"evaluating {args.method} on {source} ({len(scans)} scans)...")
    result = evaluate(scans, truth=truth, plan=plan, return_roc=args.figure is not None, **arguments)
    result["settings"]["input"] = source
    if args.figure is not None:
        _evaluation_figure(args.figure, [(resolve_split(args.split), score_curves([result]))], source)
        _without_roc(result)
    if args.json:
        print(json.dumps(result, default=str))
    else:
        _print_evaluation(args, result, source, resolve_split(args.split))
    if args.figure is not None and not args.json:
        print(f"wrote         {args.figure}")
    return EXIT_OK


def _check_figure_path(path: Path) -> None:
    """``--figure``: a PNG file's name in a directory that exists (checked before any work)."""
    if path.is_dir():
        raise GpomapError(f"--figure {path}: is a directory; give a file name ending in .png")
    if path.suffix.lower() != ".png":
        raise GpomapError(f"--figure {path}: the figure is written as a PNG; give a file name ending in .png")
    if not path.parent.is_dir():
        raise GpomapError(f"--figure {path}: the directory {path.parent} does not exist")


def _evaluation_figure(path: Path, panels: list[tuple[str, list[ScoreCurve]]], source: str) -> None:
    """``--figure``: the ROC curves and reliability diagrams, written atomically."""
    from gpomap.plot import plot_evaluation

    plot_evaluation(panels, path, title=f"gpomap evaluate: {source}")


def _without_roc(result: dict[str, Any]) -> None:
    """Drop the ROC curves drawn for ``--figure`` from a result, so its JSON is the one without it."""
    result.pop("roc", None)
    for key in ("points", "grid"):
        if isinstance(result.get(key), dict):
            result[key].pop("roc", None)


#: The splits ``gpomap evaluate --compare`` runs unless ``--split`` names others.
COMPARE_SPLITS: str = "blocks,every"


def _splits(text: str) -> list[str]:
    """The hold-out specs of ``--split`` (comma-separated names or specs), each checked.

    Raises
    ------
    GpomapError
        Naming the split that is neither "blocks", "every", ``every:K`` nor ``blocks:LEN[:K]``.
    """
    from gpomap.evaluation import check_split

    specs = []
    for part in str(text).split(","):
        try:
            specs.append(check_split(part.strip()))
        except ValueError as exc:
            raise GpomapError(f"--split {part.strip()}: {exc} (or 'blocks', 'every')") from None
    return specs


def _read_truth(args: argparse.Namespace) -> tuple[Any, Any]:
    """``--truth``: a ROS map_server map as the true map, on the written map's cells and as a plan
    (:class:`gpomap.truth.PlanTruth`, scored pixel by pixel where the log looked)."""
    from gpomap.evaluation import Truth
    from gpomap.io.rosmap import read_rosmap
    from gpomap.truth import PlanTruth

    rosmap = read_rosmap(args.truth)
    truth = Truth.from_rosmap(rosmap, args.grid_resolution)
    assert truth.known is not None
    if not truth.occupied.any() or not (truth.known & ~truth.occupied).any():
        raise GpomapError(
            f"{args.truth}: a true map needs occupied and free pixels (by its YAML's thresholds); "
            f"it has {int(truth.occupied.sum())} occupied and {int((truth.known & ~truth.occupied).sum())} free cells "
            f"at {args.grid_resolution:g} m"
        )
    return truth, PlanTruth.from_rosmap(rosmap)


#: Below this share of a log's hits near an occupied cell of its true map, the two are likely in
#: different frames (``--truth``).
TRUTH_AGREEMENT_WARN: float = 0.5


def _check_truth_frame(args: argparse.Namespace, truth: Any, scans: Sequence[Any]) -> None:
    """Say how many of the log's hits lie on the true map's walls; warn when few do."""
    import numpy as np

    share = truth.agreement(np.concatenate([s.hits() for s in scans]))
    message = f"{args.truth}: {100 * share:.0f} % of the log's hits lie within 0.1 m of an occupied cell of the true map"
    if share < TRUTH_AGREEMENT_WARN:
        _warn(message + ": are the map and the scans in the same frame (the map's origin, --fixed-frame)?")
    else:
        _status(args, message)


def _compare(
    args: argparse.Namespace, scans: Sequence[Any], truth: Any, plan: Any, arguments: dict[str, Any], source: str
) -> int:
    """``gpomap evaluate --compare``: gpomap and the standard grids on each split, and the targets met."""
    from dataclasses import asdict

    from gpomap.comparison import TARGET_NAMES, compare, score_curves, table, tally, targets
    from gpomap.evaluation import TEST_FREE_STEP, prepare

    a = arguments
    gpomap_options = _method_options(args)  # what _evaluate_arguments merged into `arguments` for msk
    runs = []
    for split in _splits(a["holdout"]):
        _status(args, f"comparing gpomap with the standard grids on {source} ({len(scans)} scans), split {split}...")
        data = prepare(
            scans,
            split,
            a["scan_range"],
            a["scan_step"],
            a["n_scans"],
            a["n_beams"],
            a["seed"],
            TEST_FREE_STEP,
            a["max_test_points"],
            truth,
            plan,
        )
        results = compare(
            data,
            a["seed"],
            a["grid_resolution"],
            a["n_workers"],
            a["kernel"],
            progress=lambda label: _status(args, f"  {label}..."),
            return_roc=args.figure is not None,
            **gpomap_options,
        )
        found = targets(results)
        runs.append((split, data, results, found, tally(found)))
    if args.figure is not None:
        _evaluation_figure(args.figure, [(split, score_curves(results)) for split, _, results, *_ in runs], source)
        for _, _, results, *_ in runs:
            for r in results:
                _without_roc(r)
    met = sum(counts[0] for *_, counts in runs)
    checked = sum(counts[1] for *_, counts in runs)
    if args.json:
        out = {
            "splits": [
                {
                    "split": split,
                    "results": results,
                    "targets": [asdict(t) for t in found],
                    "met": n_met,
                    "checked": n_checked,
                    "settings": {**data.settings, "input": source},
                }
                for split, data, results, found, (n_met, n_checked) in runs
            ],
            "met": met,
            "checked": checked,
        }
        print(json.dumps(out, default=str))
        return EXIT_OK
    print("'*' marks the best of each metric; gpomap's map is the one `gpomap map` writes (grid), a grid's its own.")
    width = max(len(n) for n in TARGET_NAMES)
    for split, data, results, found, (n_met, n_checked) in runs:
        masks = data.masks
        print(f"\n## {split}\n")
        print(f"data          {source}: {len(data.train)} training scans, {len(data.test)} held-out scans")
        print(
            f"test points   {data.labels.size} ({int(data.labels.sum())} hits, natural frequencies): "
            f"{int(masks['boundary'].sum())} within 0.5 m of a held-out hit, "
            f"{int(masks['observed'].sum())} in cells a training beam crossed, {int(masks['unobserved'].sum())} not\n"
        )
        print("\n".join(table(results, truth is not None)))
        print(f"\ntargets met by gpomap's written map: {n_met} of {n_checked}")
        for t in found:
            print(f"  {t.name:<{width}}  {t.cell()}")
    if len(runs) > 1:
        print(f"\ntargets met over the {len(runs)} splits: {met} of {checked}")
    if args.figure is not None:
        print(f"\nwrote         {args.figure}")
    return EXIT_OK


def _method_options(args: argparse.Namespace) -> dict[str, Any]:
    """Constructor arguments of ``--method`` from the model options (``gpomap evaluate``).

    MSK-GPOM takes the whole :class:`~gpomap.config.MapConfig` (the map ``gpomap map`` builds);
    a baseline takes the options given that it has an argument for (its own defaults stand
    for the rest; ``--no-return-cap`` is the grids' ``max_range_free``); an option given that
    the method has no use for is refused.
    """
    from gpomap.evaluation import GRID_METHODS

    config = _map_config(args)
    if args.method == "msk":
        return {k: v for k, v in config.kwargs().items() if k not in ("kernel", "seed")}  # evaluate()'s own arguments
    # evaluate() passes the seed to every method (and seeds the test points with it), the kernel to the GP methods.
    own = ("seed",) if args.method in GRID_METHODS else ("seed", "kernel")
    dests = [d for d in _model_option_dests() if d not in own]
    if args.method in GRID_METHODS:
        takes = {"no_return_cap": "max_range_free"}
    else:
        from gpomap.baselines.gpom import GPOM
        from gpomap.baselines.gpomik import GPOMIK

        params = inspect.signature({"gpom": GPOM, "gpomik": GPOMIK}[args.method]).parameters
        takes = {d: d for d in dests if d in params}
    given = _given(args, dests)
    refused = [d for d in given if d not in takes]
    if refused:
        raise GpomapError(
            f"{', '.join(_flag(d) for d in refused)}: not an option of --method {args.method}"
            + (f" (of the model options it takes {', '.join(_flag(d) for d in takes)})" if takes else "")
        )
    options = {takes[d]: getattr(config, d) for d in given}
    if "length_scale" in options:
        options["optimise"] = config.optimise  # a given length scale is fixed, as for MSK-GPOM
    return options


def _evaluate_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword arguments of :func:`gpomap.evaluation.evaluate` for the parsed options (all but the scans and the truth).

    Raises
    ------
    GpomapError
        An option given that ``--method`` does not take; ``--compare`` with another method than
        msk, or with ``--no-grid``.
    """
    from gpomap.evaluation import GRID_METHODS, METHODS

    gp_methods = tuple(m for m in METHODS if m not in GRID_METHODS)
    # The options only some methods take (refused on the others, not ignored): the grids' cell
    # side, the GP methods' written map, the tiles of MSK-GPOM.
    only = {"resolution": GRID_METHODS, "grid_resolution": gp_methods, "workers": ("msk",)}
    for dest, methods in only.items():
        if args.method not in methods and _given(args, [dest]):
            raise GpomapError(f"{_flag(dest)} is for --method {', '.join(methods)}, not {args.method}")
    if len(_splits(args.split)) > 1 and not args.compare:
        raise GpomapError(f"--split {args.split}: several splits are for --compare; give one")
    if args.compare and (args.method != "msk" or args.no_grid):
        raise GpomapError(
            "--compare scores gpomap's written map (--method msk) against the standard grids; "
            + ("drop --no-grid" if args.method == "msk" else f"drop --method {args.method}")
        )
    return {
        "method": args.method,
        "kernel": None if args.method in GRID_METHODS else args.kernel,
        # --compare without --split: both of the protocol's splits.
        "holdout": COMPARE_SPLITS if args.compare and not _given(args, ["split"]) else args.split,
        "n_scans": args.scans,
        "n_beams": args.beams,
        "scan_range": args.scan_range,
        "scan_step": args.scan_step,
        "seed": args.seed,
        "resolution": args.resolution,
        "grid_resolution": args.grid_resolution,
        "max_test_points": args.test_points,
        "n_workers": args.workers,
        "score_grid": not args.no_grid,
        **_method_options(args),
    }


def _print_evaluation(args: argparse.Namespace, result: dict[str, Any], source: str, split: str) -> None:
    """The metrics of ``gpomap evaluate``: exact-point and written-grid predictions side by side."""
    st = result["settings"]
    pts, grd = result["points"], result["grid"]
    grid_label = f"grid {st['grid_resolution']:g} m" if grd else "grid -"
    print(f"method        {args.method}" + (f" ({st['kernel']})" if st.get("kernel") else f" ({st['resolution']:g} m cells)"))
    print(f"data          {source}: {result['n_train_scans']} training scans, {result['n_test_scans']} held-out scans ({split})")
    print(f"inputs        {result['n_inputs']}" + (f" in {st['tiles']} tiles" if st.get("tiles") else ""))
    print(
        f"test points   {result['n_test_points']} (natural frequencies): {pts['n_boundary']} within 0.5 m of a held-out hit, "
        f"{pts['n_observed']} in observed cells, {pts['n_unobserved']} not"
    )

    def fmt(v: Any, pct: bool = False) -> str:
        if v is None:
            return "-"
        return f"{100 * v:.2f} %" if pct else f"{v:.4f}"

    print(f"{'':<16}{'points':>12}{grid_label:>14}")
    rows = [
        ("ROC AUC", "auc", False),
        ("boundary AUC", "boundary_auc", False),
        ("observed AUC", "observed_auc", False),
        ("unobserved AUC", "unobserved_auc", False),
        ("FPR@TPR=95%", "fpr_at_tpr95", True),
        ("log loss", "log_loss", False),
        ("ECE (10 bins)", "ece", False),
    ]
    for name, key, pct in rows:
        print(f"{name:<16}{fmt(pts[key], pct):>12}{fmt(grd[key], pct) if grd else '-':>14}")
    for where, label in (("test_points", "far test pts"), ("lattice", "far lattice")):
        f = result["far"][where]
        cells = [
            f"{f[k]['mean']:.3f} +- {f[k]['std']:.3f} (n {f[k]['n']})" if f.get(k) and f[k]["n"] else "-"
            for k in ("points", "grid")
        ]
        print(f"{label:<16}" + "   ".join(cells) + "   (> 5 m from any training beam: mean +- std)")
    path = result["path"]
    counts = "   ".join(f"{path[k]['n_occupied']} of {path[k]['n_cells']}" if path.get(k) else "-" for k in ("points", "grid"))
    print(
        f"{'path occupied':<16}{counts}   (robot's path cells the ternary map calls occupied, above {result['occupied_threshold']:.3f})"
    )
    if result.get("evidence"):
        print("ray counts    " + _ray_counts(result["evidence"]))
    if result.get("truth"):
        for k, t in result["truth"].items():
            print(
                f"truth ({k:<6})  AUC {fmt(t['auc'])}, occupied IoU {fmt(t['iou'])} on {t['n_cells']} cells; "
                f"observed cells AUC {fmt(t['observed_auc'])}, IoU {fmt(t['observed_iou'])}"
            )
    if result.get("plan"):
        t = result["plan"]
        print(
            f"true plan       written map on {t['n_points']} plan pixels the log observed: AUC {fmt(t['auc'])}, "
            f"boundary AUC {fmt(t['boundary_auc'])}, log loss {fmt(t['log_loss'])}, Brier {fmt(t['brier'])}, "
            f"ECE {fmt(t['ece'])}, occupied IoU {fmt(t['iou'])} (p > 0.5), {fmt(t['ternary_iou'])} (ternary)"
        )
    print("seconds       " + ", ".join(f"{k} {v:.3f}" for k, v in result["seconds"].items()))
    print("cpu seconds   " + ", ".join(f"{k} {v:.3f}" for k, v in result["cpu_seconds"].items()))
    print("peak memory   " + _peak_memory(result["peak_rss_mb"]))


def cmd_convert(args: argparse.Namespace) -> int:
    from gpomap.apps import convert3d
    from gpomap.convert import convert_grid, converter_for, grid_to_observations, load_grid, output_grid
    from gpomap.io.export import write_map_files

    _check_before_work(args)
    # OctoMap trees become voxel maps: gpomap.apps.convert3d.
    if convert3d.is_octree_input(args.input):
        return convert3d.cmd_convert3d(args)
    _check_2d_options(args)
    if "max_cells" not in args.library_defaults:
        raise GpomapError(f"--max-cells is for OctoMap trees; {args.input} is converted as one GP over its cells")
    _status(args, f"converting {args.input}...")
    options = _convert_options(args)
    # Read once, check the memory the output grid and the GP need, then convert what was read.
    source = load_grid(args.input)
    spec = output_grid(source.grid, args.resolution, args.extent)
    if args.resolution is None:
        args.resolution = spec.resolution  # the source's pixel size (named in the messages)
    _check_grid_memory(args, spec.shape, spec.extent, 0)
    # The converter's own inputs (wall-aware, several per wall pixel), not a plain cell tree's.
    n_cells = len(converter_for(source.grid.resolution, **options).make_cells(grid_to_observations(source, args.values)))
    _check_fit_memory(args, n_cells, 1, f"one GP over the cells of {args.input}")
    _check_grid_memory(args, spec.shape, spec.extent, n_cells)
    result = convert_grid(source, resolution=args.resolution, extent=args.extent, values=args.values, **options)
    with _outputs(args) as outputs:
        staged = write_map_files(
            result.map, outputs.path, pgm_mode=args.pgm_mode, title=f"gpomap convert: {Path(args.input).name}"
        )
    files = [outputs.final(f) for f in staged]
    _report_fit(result.model, result.map)
    r = result.report
    print(json.dumps(r, indent=2, default=str) if args.json else _convert_text(r))
    for f in files:
        print(f"wrote        {f}")
    return EXIT_OK


def _convert_options(args: argparse.Namespace) -> dict[str, Any]:
    """The model options of ``gpomap convert`` (the rest are the converter's own, see gpomap.convert.model_defaults)."""
    options: dict[str, Any] = {"thresholds": args.thresholds}
    if args.kernel:
        options["kernel"] = args.kernel
    if args.occupied_fraction is not None:
        if args.occupied_fraction > 1:
            raise GpomapError(f"--occupied-fraction must be in (0, 1], got {args.occupied_fraction:g}")
        options["occupied_fraction"] = args.occupied_fraction
    return options


def _convert_text(report: dict[str, Any]) -> str:
    px, cells, agree = report["pixels"], report["cells"], report["agreement"]
    hp = report["hyperparameters"]
    return "\n".join(
        [
            f"pixels       {px.get('free')} free, {px.get('occupied')} occupied, {px.get('unknown')} unknown",
            f"cells        {cells.get('n')}",
            "hyperparams  " + ", ".join(f"{k} {v:.4g}" for k, v in hp.items()),
            f"agreement    {100 * agree['ternary']:.2f} % of known pixels keep their label (AUC {agree['auc']:.4f})",
            "timings (s)  " + ", ".join(f"{k} {v:.2f}" for k, v in report["timings"].items() if isinstance(v, float)),
        ]
    )


def _benchmark_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`gpomap.benchmark.run_paper_benchmark` (all but the directory and the progress)."""
    from gpomap.benchmark import METHODS

    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise GpomapError(f"--methods: unknown method(s) {', '.join(unknown)}; expected {', '.join(METHODS)}")
    # run_paper_benchmark refuses unknown experiments with a ValueError, reported as one line.
    experiments = tuple(e.strip() for e in args.experiments.split(",") if e.strip())
    if args.timed_runs < 1:
        raise GpomapError(f"--timed-runs must be at least 1, got {args.timed_runs}")
    return {"methods": methods, "experiments": experiments, "quick": args.quick, "seed": args.seed, "timed_runs": args.timed_runs}


def cmd_benchmark(args: argparse.Namespace) -> int:
    from gpomap.benchmark import run_paper_benchmark

    if not args.paper:
        raise GpomapError("choose a benchmark: --paper (the paper's Tables II and III)")
    arguments = _benchmark_arguments(args)
    _check_before_work(args)
    # Tables, ROC curves and maps are one set: they replace the previous run's together.
    with _outputs(args) as outputs:
        result = run_paper_benchmark(outputs.path, progress=lambda m: _status(args, m), **arguments)
    table = Path(args.output) / "tables.md"
    if table.exists():
        print(table.read_text())
    return EXIT_OK if result is not None else EXIT_ERROR


# --------------------------------------------------------------------------- the parser
EPILOG_EVALUATE = """examples:
  gpomap evaluate --demo --method msk --kernel se
  gpomap evaluate ../shared/data/intel/intel-corrected.log.gz --compare
  gpomap evaluate ../shared/data/belgioioso/belgioioso-corrected.log.gz --method ogm-counting --json
      (the paper's GP baselines, --method gpomik and gpom, take many minutes even on a few scans)
"""


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
    fmt = argparse.RawDescriptionHelpFormatter

    for command in (map, demo, info):
        command.add_parser(sub)

    p = sub.add_parser(
        "evaluate",
        help="score a method on held-out scans",
        epilog=EPILOG_EVALUATE,
        formatter_class=fmt,
        description="Fit a method on training scans and score it on held-out scans (never trained on): "
        "ROC AUC, boundary AUC, AUC in observed and unobserved cells, FPR at TPR=95 %, log loss and "
        "calibration, for the exact-point predictions and for the written map, with stage timings.",
    )
    p.add_argument("input", nargs="?", help="CARMEN log or ROS bag (or --demo)")
    p.add_argument("--demo", action="store_true", help="use the built-in synthetic room (scored against its true geometry too)")
    p.add_argument(
        "--method",
        choices=["msk", "gpomik", "gpom", "ogm", "ogm-logodds", "ogm-counting"],
        default="msk",
        help="ogm = ogm-logodds, OctoMap's model; ogm-counting: (hits+1)/(hits+misses+2) (default: %(default)s)",
    )
    p.add_argument(
        "--split",
        "--holdout",
        dest="split",
        default=_signature_default("gpomap.evaluation", "evaluate", "holdout"),
        metavar="blocks|every|every:K|blocks:LEN[:K]",
        help="held-out scans: 'blocks' = blocks of 40 consecutive scans, every 5th held out; 'every' = every "
        "10th scan; or any every:K / blocks:LEN[:K]; with --compare, several, comma-separated (default: %(default)s; "
        "with --compare, blocks,every)",
    )
    p.add_argument(
        "--resolution",
        type=_positive(float),
        default=_signature_default("gpomap.evaluation", "evaluate", "resolution"),
        help="ogm: occupancy-grid cell side, m (default: %(default)s)",
    )
    p.add_argument(
        "--grid-resolution",
        type=_positive(float),
        default=_module_default("gpomap.evaluation", "GRID_RESOLUTION"),
        help="resolution of the written map scored for the GP methods, m (default: %(default)s)",
    )
    p.add_argument("--no-grid", action="store_true", help="score the exact-point predictions only")
    p.add_argument(
        "--truth",
        metavar="MAP.yaml",
        help="a true map (ROS map_server YAML and image, in the scans' frame) to score against as well, at the "
        "written map's resolution and on its cells: AUC and occupied-class IoU over its known cells, and over those a training beam reached",
    )
    p.add_argument(
        "--compare",
        action="store_true",
        help="score gpomap (--method msk) beside the standard occupancy grids on the same splits and test points "
        "(OctoMap's log-odds model at 0.05 and 0.1 m, the counting grid at 0.05 m): a table per split with the best of "
        "each metric marked, and the targets gpomap's written map meets",
    )
    p.add_argument(
        "--figure",
        type=Path,
        metavar="PATH.png",
        help="also write ROC curves above reliability diagrams as a PNG: the exact points and the written map (with "
        "--compare every method, a column per split)",
    )
    p.add_argument(
        "--scan-step",
        type=_positive(int),
        default=_signature_default("gpomap.evaluation", "evaluate", "scan_step"),
        metavar="K",
        help="use every K-th scan of the log (default: %(default)s)",
    )
    p.add_argument(
        "--test-points",
        type=_positive(int),
        metavar="N",
        help="at most N test points (a seeded uniform subsample: each class keeps its share)",
    )
    p.add_argument("--workers", type=_positive(int), help="msk: workers for tiles (default: the CPU count)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _add_reader_options(p)
    _add_selection_options(p)
    _add_model_options(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "convert",
        help="turn an occupancy grid into a continuous GP map",
        formatter_class=fmt,
        description="Read a ROS map_server map (or a gpomap .npz), merge its known pixels into cells, fit "
        "the GP and write the continuous map at any resolution.",
        epilog="examples:\n  gpomap convert ../shared/data/turtlebot3-world-map/map.yaml -o tb3 --resolution 0.025\n"
        "  gpomap convert ../shared/data/octomap/geb079.bt -o geb --resolution 0.04 --extent 5,6,-1.5,1.5",
    )
    p.add_argument("input", help="map.yaml (ROS map_server), map.npz, or an OctoMap tree (.bt, .ot)")
    p.add_argument("--kernel", choices=["se", "matern32"], help="point kernel (default: se, measured best for grids)")
    p.add_argument(
        "--values",
        choices=["auto", "fraction", "ternary"],
        default="auto",
        help="grids: a pixel's value is the fraction of it that is occupied, or free / occupied / unknown by the "
        "thresholds (auto: ternary for trinary ROS maps and gpomap's own maps, else fraction; docs/convert.md)",
    )
    p.add_argument(
        "--occupied-fraction",
        type=_positive(float),
        metavar="F",
        help="grids of 0s and 1s: what an occupied pixel holds (default: 0.7; 1.0 for grids pooled by majority)",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    _add_output_options(p, None)
    # Octrees' own options: gpomap.apps.convert3d.
    add_3d_output_options(p).add_argument(
        "--max-cells",
        type=_positive(int),
        default=_Default(DEFAULT_MAX_CELLS),
        help="octree: most cells of one GP; a larger region is converted in tiles of at most this many (default: %(default)s)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser(
        "benchmark",
        help="reproduce the paper's Tables II and III",
        formatter_class=fmt,
        description="Run every method on the synthetic room and on Belgioioso (the whole log, and the paper's "
        "two rooms); write tables.md, ROC curves and map figures.",
        epilog="examples:\n  gpomap benchmark --paper -o paper-results\n"
        "  gpomap benchmark --paper -o rooms --experiments belgioioso-rooms --methods msk,ogm",
    )
    p.add_argument("--paper", action="store_true", help="the paper's two experiments")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR")
    p.add_argument("--quick", action="store_true", help="a small, fast version (smoke test)")
    p.add_argument(
        "--methods",
        default=_module_default("gpomap.benchmark", "METHODS", ",".join),
        help="comma-separated methods (default: %(default)s)",
    )
    p.add_argument(
        "--experiments",
        default=_module_default("gpomap.benchmark", "EXPERIMENTS", ",".join),
        help="comma-separated experiments (default: %(default)s)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=_signature_default("gpomap.benchmark", "run_paper_benchmark", "seed"),
        help="seed of every method (default: %(default)s)",
    )
    p.add_argument(
        "--timed-runs",
        type=int,
        default=_signature_default("gpomap.benchmark", "run_paper_benchmark", "timed_runs"),
        metavar="N",
        help="fewest timed fits and predictions of each method after its warm-up (fast methods get more, until"
        " the runs fill gpomap.benchmark.MIN_TIMED_SECONDS); the fastest is reported (default: %(default)s)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=cmd_benchmark)

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
