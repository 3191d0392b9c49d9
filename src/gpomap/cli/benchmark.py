"""``gpomap benchmark --paper -o OUTDIR``: the paper's Tables II and III, with ROC curves and map figures (:mod:`gpomap.benchmark`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gpomap.cli.common import EXIT_ERROR, EXIT_OK, check_before_work, outputs, status
from gpomap.cli.options import module_default, signature_default
from gpomap.errors import GpomapError

__all__ = ["add_parser", "run", "benchmark_arguments"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``gpomap benchmark`` on the subparsers of :func:`gpomap.cli.build_parser`."""
    p: argparse.ArgumentParser = sub.add_parser(
        "benchmark",
        help="reproduce the paper's Tables II and III",
        formatter_class=argparse.RawDescriptionHelpFormatter,
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
        default=module_default("gpomap.benchmark", "METHODS", ",".join),
        help="comma-separated methods (default: %(default)s)",
    )
    p.add_argument(
        "--experiments",
        default=module_default("gpomap.benchmark", "EXPERIMENTS", ",".join),
        help="comma-separated experiments (default: %(default)s)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=signature_default("gpomap.benchmark", "run_paper_benchmark", "seed"),
        help="seed of every method (default: %(default)s)",
    )
    p.add_argument(
        "--timed-runs",
        type=int,
        default=signature_default("gpomap.benchmark", "run_paper_benchmark", "timed_runs"),
        metavar="N",
        help="fewest timed fits and predictions of each method after its warm-up (fast methods get more, until"
        " the runs fill gpomap.benchmark.MIN_TIMED_SECONDS); the fastest is reported (default: %(default)s)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress messages")
    p.set_defaults(func=run)
    return p


def benchmark_arguments(args: argparse.Namespace) -> dict[str, Any]:
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


def run(args: argparse.Namespace) -> int:
    """Run ``gpomap benchmark``: the tables, ROC curves and maps written as one output set, the tables printed."""
    from gpomap.benchmark import run_paper_benchmark

    if not args.paper:
        raise GpomapError("choose a benchmark: --paper (the paper's Tables II and III)")
    arguments = benchmark_arguments(args)
    check_before_work(args)
    # Tables, ROC curves and maps are one set: they replace the previous run's together.
    with outputs(args) as output:
        result = run_paper_benchmark(output.path, progress=lambda m: status(args, m), **arguments)
    table = Path(args.output) / "tables.md"
    if table.exists():
        print(table.read_text())
    return EXIT_OK if result is not None else EXIT_ERROR
