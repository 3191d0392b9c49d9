"""The paper's GP baselines, GPOMIK and GPOM, timed on the paper's subsets beside the times the paper reports.

The two experiments of ``gpomap benchmark --paper`` (:mod:`gpomap.benchmark`): the synthetic room
(31 poses x 36 beams, Table II) and Belgioioso's two rooms (scans 0:65, every 5th held out: the
paper's 52 poses x 37 beams, Table III). Each method is fitted on the training scans
(hyperparameters learnt) and predicts at the experiment's held-out test points, as the paper
benchmark times it, in a fresh process with its thread pools capped (threadpoolctl, ``--threads``)
after an untimed fit on 3 training scans (what a process pays once: imports, loading compiled code).

Sizes: ``benchmark`` is what ``gpomap benchmark --paper`` fits (GPOMIK on 12 evenly spaced beams
per scan, the paper's pre-selection of "relevant readings" standing in; GPOM on 1,500 points);
``full`` gives GPOMIK every beam of the subset (36 or 37 per scan) and GPOM its default 2,000 points.

The paper reports GPOMIK's times only (79.46 / 86.58 s on the synthetic room, 445.42 / 607.93 s on
the two rooms, Matern 3/2 / SE); GPOM is held to GPOMIK's. ``--reference`` also times the numpy
path the compiled one replaced in the same process (GPOMIK: :class:`gpomap.kernels.line.LineKernel`;
GPOM: the SE closed form over zero-width boxes) and gives the largest difference of the two
predictions. Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/baselines.py                      # benchmark sizes, 1 thread
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/baselines.py --reference --repeat 3
    .venv/bin/python benchmarks/baselines.py --sizes full --methods gpomik --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BELGIOIOSO = DATA / "belgioioso" / "belgioioso-corrected.log.gz"
EXPERIMENTS = ("synthetic", "belgioioso-rooms")
METHODS = ("gpomik", "gpom")
KERNELS = ("matern32", "se")
SIZES = ("benchmark", "full")


def _options(method: str, size: str) -> dict[str, Any]:
    from gpomap.benchmark import GPOM_POINTS, GPOMIK_BEAMS

    if method == "gpomik":
        return {"n_beams_per_scan": GPOMIK_BEAMS if size == "benchmark" else None}
    return {"max_points": GPOM_POINTS} if size == "benchmark" else {}


def _closed_form_gpom(kernel: str, **options: Any) -> Any:
    """GPOM with the SE closed form over zero-width boxes (the kernel before the one-node quadrature)."""
    from gpomap.baselines.gpom import GPOM
    from gpomap.kernels.area import AreaKernel
    from gpomap.kernels.point import make_point_kernel

    class ClosedFormGPOM(GPOM):
        def make_kernel(self) -> AreaKernel:
            base = make_point_kernel(
                self.kernel, variance=self.variance, length_scale=self.length_scale, length_scale_bounds=self.length_scale_bounds
            )
            return AreaKernel(base, "exact" if base.name == "se" else "quadrature", "mean", 1)

    return ClosedFormGPOM(kernel=kernel, **options)


def _evaluation_seconds(gp: Any) -> tuple[float, float]:
    """CPU seconds of one evaluation of the fit's hyperparameter objective at its optimum, and of the kernel's share.

    The search evaluates the leave-one-out objective and its gradient some tens of times: the
    kernel's Gram matrix and length-scale derivative, then the Cholesky factor, the inverse and
    one n^3 product (:meth:`gpomap.gp.SupportGP.loo_objective`).
    """
    X, y = gp.X_train_, gp.y_train_
    t = time.process_time()
    if hasattr(gp.kernel, "gram_and_length_scale_gradient"):
        gp.kernel.gram_and_length_scale_gradient(X)
    else:
        gp.kernel(X, eval_gradient=True)
    kernel_s = time.process_time() - t
    params = np.array(
        [*gp.kernel.theta, np.log(gp.noise), np.log(max(gp.squash.alpha, 1e-3)), gp.squash.beta / max(gp.squash.alpha, 1e-3)]
    )
    t = time.process_time()
    gp.loo_objective(X, y, params, eval_gradient=True)
    return kernel_s, time.process_time() - t


def child(experiment: str, method: str, kernel: str, size: str, threads: int, reference: bool, repeat: int) -> dict[str, Any]:
    """Fit and predict one case in this process; timings of each run, on the compiled path and the reference."""
    from threadpoolctl import threadpool_limits

    from gpomap import _compiled_line
    from gpomap.benchmark import ROOMS_RANGE, WARMUP_SCANS, _belgioioso, _synthetic
    from gpomap.evaluation import make_model, test_points
    from gpomap.io import read_scans
    from gpomap.metrics import roc_auc

    # After the imports: a cap reaches only the libraries loaded when it is set, and scipy's
    # OpenBLAS comes with gpomap's imports.
    threadpool_limits(limits=threads)

    if experiment == "synthetic":
        train, test, _, _ = _synthetic(0)
    else:
        train, test, _, _ = _belgioioso(read_scans(BELGIOIOSO), 0, False, ROOMS_RANGE)
    points, labels = test_points(test, free_step=0.2, seed=0, max_points=20000)
    options = _options(method, size)

    def build(path: str) -> Any:
        if path == "reference" and method == "gpom":
            return _closed_form_gpom(kernel, seed=0, **options)
        return make_model(method, kernel, 0, 0.1, None, **options)

    def timed(path: str) -> dict[str, Any]:
        _compiled_line.ENABLED = path == "compiled"
        build(path).fit(train[:WARMUP_SCANS])  # untimed: what a process pays once
        runs = []
        for _ in range(repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            model = build(path).fit(train)
            w1, c1 = time.perf_counter(), time.process_time()
            p = np.clip(model.predict_proba(points), 0.0, 1.0)
            w2, c2 = time.perf_counter(), time.process_time()
            runs.append({"fit": [w1 - w0, c1 - c0], "predict": [w2 - w1, c2 - c1]})
        report = model.gp_.fit_report_
        kernel_s, objective_s = _evaluation_seconds(model.gp_)
        return {
            "kernel_s": kernel_s,
            "objective_s": objective_s,
            "runs": runs,
            "p": p,
            "auc": roc_auc(labels, p),
            "inputs": int(model.n_inputs_),
            "evaluations": report.n_evaluations,
            "theta": [float(v) for v in model.gp_.kernel.theta],
        }

    out: dict[str, Any] = {"experiment": experiment, "method": method, "kernel": kernel, "size": size, "threads": threads}
    out["load"] = os.getloadavg()[0]
    out["compiled"] = timed("compiled")
    if reference:
        out["reference"] = timed("reference")
        out["max_dp"] = float(np.abs(out["compiled"]["p"] - out["reference"]["p"]).max())
    for path in ("compiled", "reference"):
        if path in out:
            out[path].pop("p")
    out["n_train_scans"], out["n_test_points"] = len(train), int(labels.size)
    return out


def _total(run: dict[str, Any], k: int) -> float:
    """Fit + predict, wall (k = 0) or CPU (k = 1) seconds."""
    return float(run["fit"][k] + run["predict"][k])


def _spread(values: list[float]) -> str:
    med = statistics.median(values)
    return f"{med:.2f}" if len(values) == 1 else f"{med:.2f} ({min(values):.2f}-{max(values):.2f})"


def print_tables(results: list[dict[str, Any]]) -> None:
    """The table of every case and a line of details per case."""
    from gpomap.benchmark import PAPER

    reference = any("reference" in r for r in results)
    print()
    print(
        "| experiment | method | kernel | size | inputs | fit + predict wall s | CPU s | paper's GPOMIK s | / 10 | within: wall / CPU | AUC "
        + ("| numpy reference wall s | CPU s | CPU speed-up | max abs diff of p " if reference else "")
        + "|"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|" + ("---|---|---|---|" if reference else ""))
    for r in results:
        paper = PAPER[(r["experiment"], "gpomik", r["kernel"])][0]
        runs = r["compiled"]["runs"]
        walls, cpus = [_total(x, 0) for x in runs], [_total(x, 1) for x in runs]
        within = " / ".join("yes" if max(v) <= paper / 10 else "no" for v in (walls, cpus))
        line = (
            f"| {r['experiment']} | {r['method']} | {r['kernel']} | {r['size']} | {r['compiled']['inputs']} | {_spread(walls)} "
            f"| {_spread(cpus)} | {paper:.2f} | {paper / 10:.2f} | {within} | {r['compiled']['auc']:.4f} |"
        )
        if reference and "reference" in r:
            ref = [_total(x, 0) for x in r["reference"]["runs"]]
            ref_cpu = [_total(x, 1) for x in r["reference"]["runs"]]
            line += f" {_spread(ref)} | {_spread(ref_cpu)} | {statistics.median(ref_cpu) / statistics.median(cpus):.1f}x | {r['max_dp']:.1e} |"
        elif reference:
            line += " - | - | - | - |"
        print(line)
    print()
    for r in results:
        c = r["compiled"]
        fit = ", ".join(f"{x['fit'][0]:.2f}" for x in c["runs"])
        pred = ", ".join(f"{x['predict'][0]:.2f}" for x in c["runs"])
        extra = ""
        if "reference" in r:
            extra = (
                f"; reference: {r['reference']['evaluations']} evaluations, theta {np.round(r['reference']['theta'], 6).tolist()}"
            )
        per = ""
        if "objective_s" in c:
            per = f"; one objective evaluation {c['objective_s']:.3f} CPU s, the kernel's share {c['kernel_s']:.3f}" + (
                f" (numpy reference {r['reference']['kernel_s']:.3f})"
                if "reference" in r and "kernel_s" in r["reference"]
                else ""
            )
        load = f"; load average {r['load']:.1f}" if "load" in r else ""
        print(
            f"{r['experiment']} {r['method']} {r['kernel']} {r['size']}: {r['n_train_scans']} training scans, {r['n_test_points']} "
            f"test points; fit wall s {fit}; predict wall s {pred}; {c['evaluations']} objective evaluations, theta "
            f"{np.round(c['theta'], 6).tolist()}{extra}{per}{load}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", default=",".join(EXPERIMENTS), help="comma-separated: " + ", ".join(EXPERIMENTS))
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated: " + ", ".join(METHODS))
    parser.add_argument("--kernels", default=",".join(KERNELS), help="comma-separated: " + ", ".join(KERNELS))
    parser.add_argument("--sizes", default="benchmark", help="comma-separated: " + ", ".join(SIZES) + " (default: benchmark)")
    parser.add_argument("--threads", type=int, default=1, help="thread pools capped at this many threads (default: 1)")
    parser.add_argument("--repeat", type=int, default=1, help="timed fits and predictions per case (default: 1)")
    parser.add_argument("--reference", action="store_true", help="also time the numpy path the compiled one replaced")
    parser.add_argument("--child", nargs=4, metavar=("EXPERIMENT", "METHOD", "KERNEL", "SIZE"), help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--from-json", type=Path, help="print the tables of results written by --json, running nothing")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(*args.child, args.threads, args.reference, args.repeat)))
        return
    if args.from_json:
        print_tables(json.loads(args.from_json.read_text()))
        return
    chosen = {}
    for name, allowed in (("experiments", EXPERIMENTS), ("methods", METHODS), ("kernels", KERNELS), ("sizes", SIZES)):
        values = getattr(args, name).split(",")
        bad = [v for v in values if v not in allowed]
        if bad:
            raise SystemExit(f"--{name}: unknown {', '.join(bad)}; expected some of {', '.join(allowed)}")
        chosen[name] = values
    if args.repeat < 1 or args.threads < 1:
        raise SystemExit("--repeat and --threads must be at least 1")

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(
        f"# The paper's GP baselines (commit {commit}, {os.cpu_count()} CPUs, threads capped at {args.threads}, {args.repeat} run(s) each)"
    )
    results = []
    for experiment in chosen["experiments"]:
        for size in chosen["sizes"]:
            for method in chosen["methods"]:
                for kernel in chosen["kernels"]:
                    cmd = [sys.executable, __file__, "--child", experiment, method, kernel, size]
                    cmd += ["--threads", str(args.threads), "--repeat", str(args.repeat)] + (
                        ["--reference"] if args.reference else []
                    )
                    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
                    if out.returncode != 0:
                        raise SystemExit(f"{experiment} {method} {kernel} {size} failed:\n{out.stderr}")
                    r = json.loads(out.stdout.strip().splitlines()[-1])
                    results.append(r)
                    walls = [_total(run, 0) for run in r["compiled"]["runs"]]
                    print(f"done {experiment} {method} {kernel} {size}: {_spread(walls)} s", file=sys.stderr, flush=True)
    print_tables(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
