"""``gpomap evaluate``: fit a method on training scans and score it on held-out scans.

One method (:func:`gpomap.evaluation.evaluate`), or with ``--compare`` gpomap beside the standard
occupancy grids on the same splits and test points (:func:`gpomap.comparison.compare`), against a
true map too with ``--truth``. The model options reach each method as far as it takes them
(:func:`method_options`); an option a method has no use for is refused rather than ignored.
"""

from __future__ import annotations

import argparse
import inspect
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gpomap.cli.common import EXIT_OK, peak_memory, ray_counts, status, warn
from gpomap.cli.input_options import add_reader_options, add_selection_options, reader_options
from gpomap.cli.model_options import add_model_options, map_config, model_option_dests
from gpomap.cli.options import flag, given, module_default, positive, signature_default
from gpomap.errors import GpomapError
from gpomap.evaluation.methods import GP_METHODS, GRID_METHODS, METHODS, REGISTRY

if TYPE_CHECKING:
    from gpomap.plot import ScoreCurve

__all__ = ["COMPARE_SPLITS", "TRUTH_AGREEMENT_WARN", "add_parser", "run", "evaluate_arguments", "method_options"]

EPILOG = """examples:
  gpomap evaluate --demo --method msk --kernel se
  gpomap evaluate ../shared/data/intel/intel-corrected.log.gz --compare
  gpomap evaluate ../shared/data/belgioioso/belgioioso-corrected.log.gz --method ogm-counting --json
      (the paper's GP baselines, --method gpomik and gpom, take many minutes even on a few scans)
"""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap evaluate`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "evaluate",
        help="score a method on held-out scans",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Fit a method on training scans and score it on held-out scans (never trained on): "
        "ROC AUC, boundary AUC, AUC in observed and unobserved cells, FPR at TPR=95 %, log loss and "
        "calibration, for the exact-point predictions and for the written map, with stage timings.",
    )
    p.add_argument("input", nargs="?", help="CARMEN log or ROS bag (or --demo)")
    p.add_argument("--demo", action="store_true", help="use the built-in synthetic room (scored against its true geometry too)")
    p.add_argument(
        "--method",
        choices=METHODS,
        default="msk",
        help="ogm = ogm-logodds, OctoMap's model; ogm-counting: (hits+1)/(hits+misses+2) (default: %(default)s)",
    )
    p.add_argument(
        "--split",
        "--holdout",
        dest="split",
        default=signature_default("gpomap.evaluation", "evaluate", "holdout"),
        metavar="blocks|every|every:K|blocks:LEN[:K]",
        help="held-out scans: 'blocks' = blocks of 40 consecutive scans, every 5th held out; 'every' = every "
        "10th scan; or any every:K / blocks:LEN[:K]; with --compare, several, comma-separated (default: %(default)s; "
        "with --compare, blocks,every)",
    )
    p.add_argument(
        "--resolution",
        type=positive(float),
        default=signature_default("gpomap.evaluation", "evaluate", "resolution"),
        help="ogm: occupancy-grid cell side, m (default: %(default)s)",
    )
    p.add_argument(
        "--grid-resolution",
        type=positive(float),
        default=module_default("gpomap.evaluation", "GRID_RESOLUTION"),
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
        type=positive(int),
        default=signature_default("gpomap.evaluation", "evaluate", "scan_step"),
        metavar="K",
        help="use every K-th scan of the log (default: %(default)s)",
    )
    p.add_argument(
        "--test-points",
        type=positive(int),
        metavar="N",
        help="at most N test points (a seeded uniform subsample: each class keeps its share)",
    )
    p.add_argument("--workers", type=positive(int), help="msk: workers for tiles (default: the CPU count)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_reader_options(p)
    add_selection_options(p)
    add_model_options(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap evaluate``."""
    from gpomap.comparison import score_curves
    from gpomap.evaluation import Truth, evaluate, resolve_split
    from gpomap.truth import PlanTruth

    if args.demo == (args.input is not None):
        raise GpomapError("give either INPUT or --demo")
    if args.demo and args.truth is not None:
        raise GpomapError("--demo is scored against the room's true geometry already; drop --truth")
    if args.figure is not None:
        _check_figure_path(args.figure)
    arguments = evaluate_arguments(args)  # refuses an option --method does not take, before any reading
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
        scans, source = read_scans(args.input, **reader_options(args, args.input)), args.input
        if truth is not None:
            _check_truth_frame(args, truth, scans)
    if args.compare:
        return _compare(args, scans, truth, plan, arguments, source)
    status(args, f"evaluating {args.method} on {source} ({len(scans)} scans)...")
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
        warn(message + ": are the map and the scans in the same frame (the map's origin, --fixed-frame)?")
    else:
        status(args, message)


def _compare(
    args: argparse.Namespace, scans: Sequence[Any], truth: Any, plan: Any, arguments: dict[str, Any], source: str
) -> int:
    """``gpomap evaluate --compare``: gpomap and the standard grids on each split, and the targets met."""
    from dataclasses import asdict

    from gpomap.comparison import TARGET_NAMES, compare, score_curves, table, tally, targets
    from gpomap.evaluation import TEST_FREE_STEP, prepare

    a = arguments
    gpomap_options = method_options(args)  # what evaluate_arguments merged into `arguments` for msk
    runs = []
    for split in _splits(a["holdout"]):
        status(args, f"comparing gpomap with the standard grids on {source} ({len(scans)} scans), split {split}...")
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
            progress=lambda label: status(args, f"  {label}..."),
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


def method_options(args: argparse.Namespace) -> dict[str, Any]:
    """Constructor arguments of ``--method`` from the model options (``gpomap evaluate``).

    MSK-GPOM takes the whole :class:`~gpomap.config.MapConfig` (the map ``gpomap map`` builds);
    a baseline takes the options given that it has an argument for (its own defaults stand
    for the rest; ``--no-return-cap`` is the grids' ``max_range_free``); an option given that
    the method has no use for is refused.
    """
    config = map_config(args)
    if args.method == "msk":
        return {k: v for k, v in config.kwargs().items() if k not in ("kernel", "seed")}  # evaluate()'s own arguments
    # evaluate() passes the seed to every method (and seeds the test points with it), the kernel to the GP methods.
    own = ("seed",) if args.method in GRID_METHODS else ("seed", "kernel")
    dests = [d for d in model_option_dests() if d not in own]
    if args.method in GRID_METHODS:
        takes = {"no_return_cap": "max_range_free"}
    else:
        params = inspect.signature(REGISTRY[args.method].estimator()).parameters
        takes = {d: d for d in dests if d in params}
    set_here = given(args, dests)
    refused = [d for d in set_here if d not in takes]
    if refused:
        raise GpomapError(
            f"{', '.join(flag(d) for d in refused)}: not an option of --method {args.method}"
            + (f" (of the model options it takes {', '.join(flag(d) for d in takes)})" if takes else "")
        )
    options = {takes[d]: getattr(config, d) for d in set_here}
    if "length_scale" in options:
        options["optimise"] = config.optimise  # a given length scale is fixed, as for MSK-GPOM
    return options


def evaluate_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """The keyword arguments of :func:`gpomap.evaluation.evaluate` for the parsed options (all but the scans and the truth).

    Raises
    ------
    GpomapError
        An option given that ``--method`` does not take; ``--compare`` with another method than
        msk, or with ``--no-grid``.
    """
    # The options only some methods take (refused on the others, not ignored): the grids' cell
    # side, the GP methods' written map, the tiles of MSK-GPOM.
    tiled = tuple(name for name, method in REGISTRY.items() if method.tiles)
    only = {"resolution": GRID_METHODS, "grid_resolution": GP_METHODS, "workers": tiled}
    for dest, methods in only.items():
        if args.method not in methods and given(args, [dest]):
            raise GpomapError(f"{flag(dest)} is for --method {', '.join(methods)}, not {args.method}")
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
        "holdout": COMPARE_SPLITS if args.compare and not given(args, ["split"]) else args.split,
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
        **method_options(args),
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
        print("ray counts    " + ray_counts(result["evidence"]))
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
    print("peak memory   " + peak_memory(result["peak_rss_mb"]))
