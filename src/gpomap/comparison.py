"""gpomap's map against the occupancy grids a robot would otherwise build, on one split of a log.

The comparison ``gpomap evaluate --compare`` prints and ``benchmarks/quality.py`` runs on every
log: MSK-GPOM as ``gpomap map`` builds it, and the standard grids built from the same training
scans (OctoMap's log-odds model with OctoMap's defaults at 0.05 and 0.1 m, the counting grid
``(hits + 1) / (hits + misses + 2)`` at 0.05 m), each scored on the same test points of the same
held-out scans (:func:`gpomap.evaluation.prepare`, :func:`gpomap.evaluation.run_method`). Then
the targets gpomap's written map must meet beside them (:func:`targets`).
"""

from __future__ import annotations

import multiprocessing as mp
import sys
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from gpomap.evaluation import GRID_METHODS, GRID_RESOLUTION, REGISTRY, EvalData, run_method
from gpomap.resources import rss_mb

if TYPE_CHECKING:
    from gpomap.plot import ScoreCurve

#: gpomap's name in a comparison.
GPOMAP: str = "msk"
#: Every method of a comparison, name: (method of :data:`gpomap.evaluation.methods.REGISTRY`,
#: grid cell side in metres; None for gpomap, which predicts anywhere and is scored on the map it writes).
METHODS: dict[str, tuple[str, float | None]] = {
    GPOMAP: ("msk", None),
    "ogm-logodds-0.05": ("ogm-logodds", 0.05),
    "ogm-logodds-0.1": ("ogm-logodds", 0.1),
    "ogm-counting-0.05": ("ogm-counting", 0.05),
}
#: How tables name them: the method's label, and a grid's cell side.
LABELS: dict[str, str] = {
    name: REGISTRY[method].label + ("" if cell is None else f" {cell:g}") for name, (method, cell) in METHODS.items()
}
#: How figures draw them.
COLOURS: dict[str, str] = {
    GPOMAP: "tab:blue",
    "ogm-logodds-0.05": "tab:red",
    "ogm-logodds-0.1": "tab:orange",
    "ogm-counting-0.05": "tab:green",
}
#: The written map's mean prediction far from all data must lie within this of 1/2.
FAR_TOLERANCE: float = 0.05

# Metric key, column title, higher is better.
COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("auc", "AUC", True),
    ("boundary_auc", "bnd AUC", True),
    ("observed_auc", "obs AUC", True),
    ("unobserved_auc", "unobs AUC", True),
    ("fpr_at_tpr95", "FPR95", False),
    ("log_loss", "log loss", False),
    ("brier", "Brier", False),
    ("ece", "ECE", False),
)
# Against a true plan, pixel by pixel where the log looked (:mod:`gpomap.truth`): the written map only.
TRUTH_COLUMNS: tuple[tuple[str, str, bool], ...] = (
    ("auc", "truth AUC", True),
    ("boundary_auc", "truth bnd AUC", True),
    ("log_loss", "truth log loss", False),
    ("brier", "truth Brier", False),
    ("ece", "truth ECE", False),
    ("iou", "truth IoU p>0.5", True),
    ("ternary_iou", "truth IoU ternary", True),
)


def compare(
    data: EvalData,
    seed: int = 0,
    grid_resolution: float = GRID_RESOLUTION,
    n_workers: int | None = None,
    kernel: str | None = None,
    progress: Callable[[str], None] | None = None,
    return_roc: bool = False,
    **gpomap_options: Any,
) -> list[dict[str, Any]]:
    """Fit gpomap and every standard grid on ``data.train`` and score each on ``data``'s test points.

    Parameters
    ----------
    data : EvalData
        One split of a log and its test points (:func:`gpomap.evaluation.prepare`).
    seed : int
        Seeds gpomap.
    grid_resolution : float
        Cell side of gpomap's written map, metres (a grid's written map is itself).
    n_workers : int, optional
        gpomap's tile workers (default: the CPU count, as ``gpomap map``).
    kernel : str, optional
        gpomap's point kernel (default: the library's).
    progress : callable, optional
        Told each method's label before it runs.
    return_roc : bool
        Also return each score's ROC curve (:func:`gpomap.evaluation.score`).
    **gpomap_options
        gpomap's constructor options (the grids take their standard settings).

    Returns
    -------
    list of dict
        :func:`gpomap.evaluation.run_method`'s result per method of :data:`METHODS`, in order,
        each with its ``"name"``.
    """
    results = []
    for name in METHODS:
        if progress is not None:
            progress(LABELS[name])
        results.append(run_apart(data, name, seed, grid_resolution, n_workers, kernel, return_roc, **gpomap_options))
    return results


def run_one(
    data: EvalData,
    name: str,
    seed: int = 0,
    grid_resolution: float = GRID_RESOLUTION,
    n_workers: int | None = None,
    kernel: str | None = None,
    return_roc: bool = False,
    **gpomap_options: Any,
) -> dict[str, Any]:
    """One method of :data:`METHODS` on ``data`` (see :func:`compare` for the parameters).

    Returns
    -------
    dict
        :func:`gpomap.evaluation.run_method`'s result, with its ``"name"``.
    """
    method, cell = METHODS[name]
    if name == GPOMAP:
        r = run_method(
            data,
            method,
            kernel,
            seed,
            grid_resolution=grid_resolution,
            n_workers=n_workers,
            return_roc=return_roc,
            **gpomap_options,
        )
    else:
        assert cell is not None
        r = run_method(data, method, seed=seed, resolution=cell, return_roc=return_roc)
    r["name"] = name
    return r


def can_run_apart() -> bool:
    """Whether :func:`run_apart` runs each method in a process of its own: where processes fork
    safely (Linux; on macOS a forked process that had threads may hang, and Windows cannot fork)."""
    return sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods()


def run_apart(
    data: EvalData,
    name: str,
    seed: int = 0,
    grid_resolution: float = GRID_RESOLUTION,
    n_workers: int | None = None,
    kernel: str | None = None,
    return_roc: bool = False,
    **gpomap_options: Any,
) -> dict[str, Any]:
    """:func:`run_one` in a forked child process, so that the peak memory it reports is its own.

    The child starts as a copy of this process, so its peak counts this process's size at the fork
    too, reported beside it as ``rss_at_start_mb``. Where processes cannot fork safely
    (:func:`can_run_apart`), the method runs in this process, whose peak is every method's so far,
    and the result has no ``rss_at_start_mb``.

    Returns
    -------
    dict
        :func:`run_one`'s result, with ``rss_at_start_mb`` where it ran apart.

    Raises
    ------
    Exception
        What the method raised in the child (re-raised here when it can be sent back; otherwise a
        RuntimeError with the child's traceback).
    """
    if not can_run_apart():
        return run_one(data, name, seed, grid_resolution, n_workers, kernel, return_roc, **gpomap_options)
    ctx = mp.get_context("fork")
    receiver, sender = ctx.Pipe(duplex=False)
    arguments = (data, name, seed, grid_resolution, n_workers, kernel, return_roc)
    child = ctx.Process(target=_run_in_child, args=(sender, arguments, gpomap_options))
    child.start()
    sender.close()
    try:
        status, payload = receiver.recv()
    except EOFError:  # the child died without a word (killed, out of memory)
        child.join()
        raise RuntimeError(f"{LABELS.get(name, name)} ended without a result (exit code {child.exitcode})") from None
    finally:
        receiver.close()
    child.join()
    if status == "raised":
        raise payload
    if status == "failed":
        raise RuntimeError(f"{LABELS.get(name, name)} failed:\n{payload}")
    return dict(payload)


def _run_in_child(sender: Any, arguments: tuple[Any, ...], gpomap_options: dict[str, Any]) -> None:
    """:func:`run_apart`'s child: the result, or what it raised, sent back over `sender`."""
    import pickle

    try:
        start = rss_mb()
        result = run_one(*arguments, **gpomap_options)
        if start is not None:
            result["rss_at_start_mb"] = start
        sender.send(("ok", result))
    except BaseException as exc:  # the parent reports it; the child must not die silently
        try:
            pickle.loads(pickle.dumps(exc))
            sender.send(("raised", exc))
        except Exception:
            sender.send(("failed", traceback.format_exc()))
    finally:
        sender.close()


def score_curves(rows: Sequence[dict[str, Any]]) -> list[ScoreCurve]:
    """Each method's predictions on one split as :func:`gpomap.plot.plot_evaluation` draws them:
    a GP method's exact points (solid) and written map (dotted), each grid's own grid.

    Parameters
    ----------
    rows : sequence of dict
        :func:`compare`'s results for one split, or :func:`gpomap.evaluation.run_method`'s
        (named by their method).

    Returns
    -------
    list of gpomap.plot.ScoreCurve
    """
    from gpomap.plot import ScoreCurve  # matplotlib only when drawn

    curves = []
    for r in rows:
        name = r.get("name", r["method"])
        label, colour = LABELS.get(name, name), COLOURS.get(name)
        curves.append(ScoreCurve(label, r["points"], colour))
        if r.get("grid") is not None and r["method"] not in GRID_METHODS:  # a grid's written map is itself
            curves.append(ScoreCurve(f"{label} grid {r['settings']['grid_resolution']:g}", r["grid"], colour, ":"))
    return curves


@dataclass(frozen=True)
class Target:
    """One target of gpomap's written map beside the grids, and whether it was met.

    Attributes
    ----------
    name : str
    met : bool or None
        None: not checked (no grid to compare with, no true map, no lattice far from the data).
    detail : str
        The values, when missed ("0.950 < 0.960").
    """

    name: str
    met: bool | None
    detail: str = ""

    def cell(self) -> str:
        """ "yes", the values when missed, or "-" when not checked."""
        return "-" if self.met is None else ("yes" if self.met else self.detail)


#: The targets' names, in :func:`targets`' order: held-out scores, then scores against a true plan.
TARGET_NAMES: tuple[str, ...] = (
    "AUC",
    "boundary AUC",
    "log loss",
    "Brier",
    "ECE",
    "truth AUC",
    "truth boundary AUC",
    "truth log loss",
    "truth IoU p>0.5",
    "truth IoU ternary",
    "far p",
    "path cells",
)
#: Each target's metric (held-out or truth) and whether higher is better; None: checked apart.
_TARGET_METRICS: dict[str, tuple[str, str, bool] | None] = {
    "AUC": ("grid", "auc", True),
    "boundary AUC": ("grid", "boundary_auc", True),
    "log loss": ("grid", "log_loss", False),
    "Brier": ("grid", "brier", False),
    "ECE": ("grid", "ece", False),
    "truth AUC": ("plan", "auc", True),
    "truth boundary AUC": ("plan", "boundary_auc", True),
    "truth log loss": ("plan", "log_loss", False),
    "truth IoU p>0.5": ("plan", "iou", True),
    "truth IoU ternary": ("plan", "ternary_iou", True),
    "far p": None,
    "path cells": None,
}


def targets(rows: Sequence[dict[str, Any]]) -> list[Target]:
    """What gpomap's written map meets beside the grids of the same split.

    On the held-out points (natural frequencies): AUC and boundary AUC at least the best grid's;
    log loss, Brier score and ECE below every grid's. Against a true plan, where there is one: AUC,
    boundary AUC, occupied IoU at p > 0.5 and of the ternary map at least the best grid's, log loss
    below every grid's. The mean prediction on lattice points far from all data within
    :data:`FAR_TOLERANCE` of 1/2; no cell of the robot's own path called occupied.

    Parameters
    ----------
    rows : sequence of dict
        :func:`compare`'s results for one split: gpomap's (``"name"`` :data:`GPOMAP`, scored with
        its written map) and any grids'.

    Returns
    -------
    list of Target
        One per :data:`TARGET_NAMES`, in that order.

    Raises
    ------
    ValueError
        Without gpomap's row, or with its written map unscored.
    """
    mine = next((r for r in rows if r["name"] == GPOMAP), None)
    if mine is None or mine.get("grid") is None:
        raise ValueError("targets need gpomap's result with its written map scored")
    grids = [r for r in rows if r["name"] != GPOMAP]
    out = []
    for name in TARGET_NAMES:
        spec = _TARGET_METRICS[name]
        if spec is None:
            continue
        where, key, higher = spec
        value = (mine.get(where) or {}).get(key)
        # A grid's written map is itself: its held-out scores are its points' where not kept apart.
        scored = [g.get(where) or (g.get("points") if where == "grid" else None) for g in grids]
        vals = [s[key] for s in scored if s and s.get(key) is not None]
        if not vals or value is None:
            out.append(Target(name, None))
        elif higher:
            out.append(Target(name, bool(value >= max(vals)), f"{format_value(value)} < {format_value(max(vals))}"))
        else:
            out.append(Target(name, bool(value < min(vals)), f"{format_value(value)} >= {format_value(min(vals))}"))
    far = mine["far"]["lattice"].get("grid") or {}
    out.append(
        Target("far p", None)
        if not far.get("n")
        else Target("far p", bool(abs(far["mean"] - 0.5) <= FAR_TOLERANCE), format_value(far["mean"]))
    )
    path = mine["path"]["grid"]
    out.append(Target("path cells", path["n_occupied"] == 0, f"{path['n_occupied']} of {path['n_cells']}"))
    return out


def tally(found: Sequence[Target]) -> tuple[int, int]:
    """Targets met and targets checked among `found`."""
    return sum(t.met is True for t in found), sum(t.met is not None for t in found)


def table(rows: Sequence[dict[str, Any]], has_truth: bool) -> list[str]:
    """Markdown table of one split: gpomap's exact points and written map, each grid's own grid.

    '*' marks the best value of each metric among the rows (within 5e-4).

    Parameters
    ----------
    rows : sequence of dict
        :func:`compare`'s results for one split.
    has_truth : bool
        Add the columns against the true map.

    Returns
    -------
    list of str
        The table's lines.
    """
    lines_data = []
    for r in rows:
        for kind in ("points", "grid"):
            s = r[kind]
            # A grid's written map is itself (the same numbers): one row, "own grid".
            if s is None or (kind == "grid" and r["name"] != GPOMAP):
                continue
            far = r["far"]["lattice"].get(kind, {})
            # The plan scores the written map (a grid's is its own): nothing on gpomap's exact points.
            truth = (r.get("plan") or {}) if (kind == "grid" or r["name"] != GPOMAP) else {}
            lines_data.append((r, kind, s, {**far, "path": (r.get("path") or {}).get(kind)}, truth))
    truth_columns = TRUTH_COLUMNS if has_truth else ()
    best: dict[str, float] = {}
    for key, _, higher in COLUMNS:
        vals = [s[key] for _, _, s, _, _ in lines_data if s.get(key) is not None]
        if vals:
            best[key] = max(vals) if higher else min(vals)
    for key, _, higher in truth_columns:
        vals = [t[key] for *_, t in lines_data if t.get(key) is not None and not np.isnan(t[key])]
        if vals:
            best["truth_" + key] = max(vals) if higher else min(vals)
    head = (
        ["method", "map"]
        + [c[1] for c in COLUMNS + truth_columns]
        + ["far p (mean ± sd)", "path occ", "fit s (wall/CPU)", "predict s", "grid s", "peak MB"]
    )
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r, kind, s, far, truth in lines_data:
        own = r["name"] != GPOMAP
        cells = [
            LABELS.get(r["name"], r["name"]),
            "own grid" if own else ("points" if kind == "points" else f"grid {r['settings']['grid_resolution']:g}"),
        ]
        for key, _, _ in COLUMNS:
            cells.append(_marked(s.get(key), best.get(key), key == "fpr_at_tpr95"))
        for key, _, _ in truth_columns:
            cells.append(_marked(truth.get(key), best.get("truth_" + key)))
        cells.append(f"{far['mean']:.3f} ± {far['std']:.3f}" if far.get("n") else "-")
        path = far["path"]
        cells.append(f"{path['n_occupied']} / {path['n_cells']}" if path else "-")
        sec, cpu = r["seconds"], r["cpu_seconds"]
        if kind == "points":
            # A method's own peak memory only where it ran in a process of its own, which started at
            # its parent's size (benchmarks/quality.py); in one process the peak is every method's so far.
            pk = r["peak_rss_mb"]
            peak = (
                f"{pk['self']:.0f} (+{pk['children']:.0f} workers; {r['rss_at_start_mb']:.0f} at start)"
                if "rss_at_start_mb" in r
                else "-"
            )
            cells += [f"{sec['fit']:.1f} / {cpu['fit']:.1f}", f"{sec['predict']:.2f}", "", peak]
        else:
            cells += ["", "", f"{sec.get('grid', 0):.1f} / {cpu.get('grid', 0):.1f}", ""]
        out.append("| " + " | ".join(cells) + " |")
    return out


def _marked(value: float | None, best: float | None, pct: bool = False) -> str:
    """`value` formatted, with '*' when it is the best (within 5e-4)."""
    is_best = value is not None and best is not None and bool(np.isclose(value, best, rtol=0, atol=5e-4))
    return format_value(value, pct) + ("*" if is_best else "")


def format_value(v: Any, pct: bool = False) -> str:
    """A metric as the tables print it: 3 decimals, a percentage with 1, "-" for none."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "-"
    return f"{100 * v:.1f} %" if pct else f"{v:.3f}"
