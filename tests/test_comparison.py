"""gpomap beside the standard grids: the runs on one split, the table's best marks, the targets."""

import json

import pytest

from gpomap.comparison import GPOMAP, METHODS, TARGET_NAMES, can_run_apart, compare, run_apart, score_curves, table, targets
from gpomap.evaluation import prepare, run_method
from gpomap.simulate import paper_room_scans


def _scores(auc, boundary, observed, log_loss, ece, brier=0.05):
    return {
        "auc": auc,
        "boundary_auc": boundary,
        "observed_auc": observed,
        "unobserved_auc": None,
        "fpr_at_tpr95": 0.1,
        "log_loss": log_loss,
        "brier": brier,
        "ece": ece,
    }


def _plan(auc, boundary, log_loss, iou, ternary):
    return {
        "auc": auc,
        "boundary_auc": boundary,
        "log_loss": log_loss,
        "brier": 0.03,
        "ece": 0.02,
        "iou": iou,
        "ternary_iou": ternary,
    }


def _row(name, scores, far_mean=0.5, path_occupied=0, plan=None):
    """A result as run_method gives it, gpomap's scores on its written map, a grid's on its own."""
    far = {"n": 10, "mean": far_mean, "std": 0.0}
    path = {"n_occupied": path_occupied, "n_cells": 100}
    row = {
        "name": name,
        "points": scores,
        "grid": None,
        "far": {"lattice": {"points": far, "grid": far}},
        "path": {"points": path, "grid": path},
        "truth": None,
        "plan": plan,
        "seconds": {"fit": 1.0, "predict": 0.1, "grid": 0.2},
        "cpu_seconds": {"fit": 1.0, "predict": 0.1, "grid": 0.2},
        "peak_rss_mb": {"self": 100.0, "children": 0.0},
        "settings": {"grid_resolution": 0.05},
    }
    if name == GPOMAP:
        row["grid"] = scores
    return row


def test_targets_read_each_comparison_as_the_issue_states_it():
    mine = _row(
        GPOMAP,
        _scores(0.95, 0.93, 0.97, 0.20, 0.049, 0.04),
        far_mean=0.56,
        path_occupied=2,
        plan=_plan(0.97, 0.85, 0.07, 0.30, 0.31),
    )
    grids = [
        _row("ogm-logodds-0.05", _scores(0.96, 0.90, 0.97, 0.30, 0.1, 0.05), plan=_plan(0.92, 0.80, 0.27, 0.29, 0.30)),
        _row("ogm-counting-0.05", _scores(0.90, 0.92, 0.96, 0.20, 0.1, 0.04), plan=_plan(0.97, 0.85, 0.08, 0.30, 0.22)),
    ]
    found = targets([mine, *grids])
    assert [t.name for t in found] == list(TARGET_NAMES)
    cells = {t.name: t.cell() for t in found}
    assert cells["AUC"] == "0.950 < 0.960"  # below the best grid's
    assert cells["boundary AUC"] == "yes"  # above both
    assert cells["log loss"] == "0.200 >= 0.200"  # must be below every grid's: a tie does not
    assert cells["Brier"] == "0.040 >= 0.040"
    assert cells["ECE"] == "yes"  # below both grids'
    assert cells["truth AUC"] == "yes" and cells["truth boundary AUC"] == "yes"  # ties with the best grid meet them
    assert cells["truth log loss"] == "yes"
    assert cells["truth IoU p>0.5"] == "yes" and cells["truth IoU ternary"] == "yes"
    assert cells["far p"] == "0.560"  # 0.06 from 1/2
    assert cells["path cells"] == "2 of 100"
    assert sum(t.met is True for t in found) == 7


def test_targets_without_grids_or_truth_check_what_they_can():
    mine = _row(GPOMAP, _scores(0.95, 0.93, 0.97, 0.20, 0.05), far_mean=0.54)
    found = {t.name: t for t in targets([mine])}
    for name in TARGET_NAMES[:10]:
        assert found[name].met is None and found[name].cell() == "-"
    assert found["far p"].met is True  # within 0.05 of 1/2
    assert found["path cells"].met is True


def test_targets_need_gpomaps_written_map():
    mine = _row(GPOMAP, _scores(0.95, 0.93, 0.97, 0.20, 0.05))
    mine["grid"] = None
    with pytest.raises(ValueError, match="written map"):
        targets([mine])
    with pytest.raises(ValueError):
        targets([_row("ogm-logodds-0.05", _scores(0.9, 0.9, 0.9, 0.3, 0.1))])


def test_table_marks_the_best_of_each_metric():
    mine = _row(GPOMAP, _scores(0.99, 0.90, 0.9702, 0.20, 0.03))
    grid = _row("ogm-logodds-0.1", _scores(0.98, 0.95, 0.9700, 0.30, 0.01))
    lines = table([mine, grid], has_truth=False)
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    assert [r[:2] for r in rows] == [["MSK-GPOM", "points"], ["MSK-GPOM", "grid 0.05"], ["OGM log-odds 0.1", "own grid"]]
    col = {name: head.index(name) for name in ("AUC", "bnd AUC", "obs AUC", "log loss", "ECE", "peak MB")}
    assert rows[0][col["AUC"]] == "0.990*" and rows[2][col["AUC"]] == "0.980"
    assert rows[0][col["bnd AUC"]] == "0.900" and rows[2][col["bnd AUC"]] == "0.950*"
    assert rows[0][col["obs AUC"]] == "0.970*" and rows[2][col["obs AUC"]] == "0.970*"  # within 5e-4: both
    assert rows[0][col["log loss"]] == "0.200*" and rows[2][col["log loss"]] == "0.300"  # lower is better
    assert rows[2][col["ECE"]] == "0.010*"
    assert rows[0][col["peak MB"]] == "-"  # one process: the peak is not the method's own


@pytest.fixture(scope="module")
def room_split():
    return prepare(paper_room_scans(), "every", seed=0)


def test_compare_scores_every_method_on_the_same_test_points(room_split):
    # gpomap at a 0.3 m free clearance (at the planar 0.1 m its fit on these thin scans takes most of
    # the test) with the SE kernel's exact area kernel (the default Matern 3/2's quadrature fits 2.4x
    # slower): the comparison's plumbing is the subject, not gpomap's map.
    results = compare(room_split, seed=0, n_workers=1, kernel="se", free_clearance=0.3)
    assert [r["name"] for r in results] == list(METHODS)
    # Each grid as run_method scores it alone on the same split: the same points, the same scores.
    for r in results[1:]:
        method, cell = METHODS[r["name"]]
        alone = run_method(room_split, method, seed=0, resolution=cell)
        assert r["settings"]["resolution"] == cell
        for key in ("auc", "log_loss", "ece", "boundary_auc"):
            assert r["points"][key] == pytest.approx(alone["points"][key], abs=1e-12)
    mine = results[0]
    assert mine["grid"] is not None and mine["settings"]["grid_resolution"] == 0.05
    # gpomap's options reach gpomap alone.
    assert mine["settings"]["method_options"] == {"free_clearance": 0.3}
    assert all(r["settings"]["method_options"] == {} for r in results[1:])
    assert all(r["n_test_points"] == room_split.labels.size for r in results)
    # Drawn: gpomap's exact points and written map, each grid once (its written map is itself),
    # whether named by the comparison or, as one method's result, by its method.
    labels = [c.label for c in score_curves(results)]
    assert labels == ["MSK-GPOM", "MSK-GPOM grid 0.05", "OGM log-odds 0.05", "OGM log-odds 0.1", "OGM counting 0.05"]
    alone = [{k: v for k, v in r.items() if k != "name"} for r in results]
    assert [c.label for c in score_curves(alone[:2])] == ["MSK-GPOM", "MSK-GPOM grid 0.05", "ogm-logodds"]
    if can_run_apart():  # each in a child: its peak is its own, and no lower than its size at the fork
        assert all(r["peak_rss_mb"]["self"] >= r["rss_at_start_mb"] > 0 for r in results)


@pytest.mark.skipif(not can_run_apart(), reason="methods run apart only where processes fork safely")
def test_a_method_run_apart_raises_what_it_raised() -> None:
    data = prepare(paper_room_scans()[:20], "every", seed=0)
    with pytest.raises(KeyError, match="no-such-method"):
        run_apart(data, "no-such-method")
    with pytest.raises(TypeError, match="not_an_option"):
        run_apart(data, GPOMAP, n_workers=1, not_an_option=1)


def test_evaluate_compare_prints_each_split_and_the_targets(capsys, tmp_path):
    from gpomap.cli import main

    # gpomap's written map at 0.2 m, a 0.3 m free clearance and the SE kernel: at the defaults (0.05
    # m, the planar 0.1 m clearance, Matern 3/2) each split takes 27 s instead of 4, mostly in
    # predicting the room's truth cells (one per written cell); the plumbing of --compare is the
    # subject here, and the options reach gpomap's fit.
    options = ["--workers", "1", "-q", "--grid-resolution", "0.2", "--free-clearance", "0.3", "--kernel", "se"]
    assert main(["evaluate", "--demo", "--compare", *options, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["split"] for s in out["splits"]] == ["blocks:40:5", "every:10"]  # both of the protocol's by default
    for run in out["splits"]:
        assert [r["name"] for r in run["results"]] == list(METHODS)
        assert [t["name"] for t in run["targets"]] == list(TARGET_NAMES)
        assert run["met"] == sum(t["met"] is True for t in run["targets"])
        assert run["checked"] == len(TARGET_NAMES)  # the room has a truth: every target is checked
        mine = run["results"][0]["settings"]
        assert mine["grid_resolution"] == 0.2 and mine["method_options"]["free_clearance"] == 0.3 and mine["kernel"] == "se"
    assert out["met"] == sum(run["met"] for run in out["splits"])

    figure = tmp_path / "compare.png"
    assert main(["evaluate", "--demo", "--compare", "--split", "every", *options, "--figure", str(figure)]) == 0
    text = capsys.readouterr().out
    assert f"wrote         {figure}" in text and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "## every:10" in text and "## blocks" not in text
    for label in ("MSK-GPOM", "OGM log-odds 0.05", "OGM log-odds 0.1", "OGM counting 0.05"):
        assert f"| {label} |" in text
    every = out["splits"][1]
    assert f"targets met by gpomap's written map: {every['met']} of {every['checked']}" in text
    # The same split and seed give the same scores as the JSON.
    auc = float(text.split("| MSK-GPOM | grid 0.2 |")[1].split("|")[0].strip().rstrip("*"))
    assert auc == pytest.approx(every["results"][0]["grid"]["auc"], abs=5e-4)
    if can_run_apart():  # the method's own peak memory, not "-"
        assert text.split("| MSK-GPOM | points |")[1].split("\n")[0].rstrip(" |").endswith(" at start)")


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--method", "ogm"], "drop --method ogm"),
        (["--no-grid"], "drop --no-grid"),
        (["--split", "blocks,every:1"], "--split every:1: 'every:K' needs K >= 2"),
        (["--split", "blocks:40:1"], "--split blocks:40:1: hold-out sizes must be >= 1 and periods >= 2"),
    ],
)
def test_evaluate_compare_refuses_what_it_cannot_compare(capsys, extra, message):
    from gpomap.cli import main

    assert main(["evaluate", "--demo", "--compare", *extra]) == 1
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("split", "message"),
    [("bogus", "--split bogus: holdout must be"), ("blocks,every", "several splits are for --compare")],
)
def test_evaluate_checks_its_splits_before_reading(capsys, tmp_path, split, message):
    from gpomap.cli import main

    # A log that does not exist: the split is refused before any reading.
    assert main(["evaluate", str(tmp_path / "absent.log"), "--split", split]) == 1
    assert message in capsys.readouterr().err


def test_labels_come_from_the_registry():
    from gpomap.comparison import LABELS

    assert LABELS == {
        GPOMAP: "MSK-GPOM",
        "ogm-logodds-0.05": "OGM log-odds 0.05",
        "ogm-logodds-0.1": "OGM log-odds 0.1",
        "ogm-counting-0.05": "OGM counting 0.05",
    }
