"""The evaluation protocol: leak-free splits, balanced test points, evaluate() keys."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gpomap import evaluation as ev
from gpomap.grid import GridSpec
from gpomap.simulate import paper_room, paper_room_scans

FAST_GP = {"optimise": False, "length_scale": 1.5, "noise": 0.05}


@pytest.mark.parametrize("holdout", ["every:5", "every:3", "blocks:4", "blocks:3:4", "blocks:1"])
@pytest.mark.parametrize("seed", [0, 1, 2, 7])
@pytest.mark.parametrize("n", [2, 5, 31, 100])
def test_split_never_leaks(holdout, seed, n):
    train, test = ev.holdout_split(n, holdout, seed)
    assert len(train) > 0 and len(test) > 0
    assert np.intersect1d(train, test).size == 0
    np.testing.assert_array_equal(np.sort(np.r_[train, test]), np.arange(n))
    again = ev.holdout_split(n, holdout, seed)
    np.testing.assert_array_equal(again[1], test)


def test_split_fractions_and_blocks():
    train, test = ev.holdout_split(100, "every:5", 3)
    assert len(test) == 20 and np.all(np.diff(test) == 5)
    train, test = ev.holdout_split(200, "blocks:10", 3)
    assert 0.1 <= len(test) / 200 <= 0.3
    # Held-out scans come in runs of consecutive indices (blocks), at most LEN long.
    runs = np.split(test, np.flatnonzero(np.diff(test) > 1) + 1)
    assert max(len(r) for r in runs) <= 10 and sum(len(r) == 10 for r in runs) >= 2


def test_split_rejects_bad_specs():
    for bad in ["every", "every:x", "blocks:2:1", "every:1", "random:3"]:
        with pytest.raises(ValueError):
            ev.holdout_split(10, bad)


def test_test_points_balanced_and_seeded():
    scans = paper_room_scans(n_beams=12)[:4]
    p, y = ev.test_points(scans, 0.3, seed=1)
    assert p.shape == (y.size, 2) and y.sum() * 2 == y.size
    p2, y2 = ev.test_points(scans, 0.3, seed=1)
    np.testing.assert_array_equal(p, p2)
    p3, y3 = ev.test_points(scans, 0.3, seed=1, max_points=20)
    assert y3.size == 20 and y3.sum() == 10
    # Hits are the held-out beams' end points.
    hits = np.concatenate([s.hits() for s in scans])
    d = np.abs(p[y][:, None, :] - hits[None]).sum(axis=2).min(axis=1)
    assert d.max() < 1e-12


def test_no_return_beams_give_free_points_only():
    scans = paper_room_scans(n_beams=12)[:3]
    from gpomap.scans import Scan

    s = scans[0]
    clipped = Scan(s.pose, s.angles, np.full(s.n_beams, 100.0), max_range=3.0)
    p, y = ev.test_points([clipped, scans[1]], 0.3, seed=0)
    hits = scans[1].hits()
    d = np.abs(p[y][:, None, :] - hits[None]).sum(axis=2).min(axis=1)
    assert d.max() < 1e-12  # every occupied test point is a real hit of the scan that returned


@pytest.mark.parametrize("method", ["msk", "gpomik", "gpom", "ogm"])
def test_evaluate_returns_documented_keys(method):
    scans = paper_room_scans(n_beams=12)
    opts = {} if method == "ogm" else dict(FAST_GP)
    if method == "gpom":
        opts.update(max_points=300, free_step=0.5)
    if method == "msk":
        opts.update(min_cell=1.0, max_cell=1.0)
    res = ev.evaluate(
        scans, method=method, kernel="se", holdout="every:4", n_scans=10, n_beams=12, scan_range="0:24",
        seed=0, max_test_points=100, return_roc=True, resolution=0.25, **opts,
    )
    for key in ("auc", "fpr_at_tpr95", "log_loss", "seconds", "n_inputs", "n_test_points", "settings", "roc"):
        assert key in res
    assert res["seconds"]["total"] >= res["seconds"]["fit"] > 0
    assert res["n_test_points"] == 100 and res["n_train_scans"] == 10
    assert res["settings"]["scan_range"] == "0:24" and res["settings"]["n_scans_in_range"] == 24
    assert max(res["settings"]["test_scan_indices"]) < 24
    assert 0.5 < res["auc"] <= 1.0
    json.dumps(res)


def test_score_against_truth_on_the_room():
    world, _ = paper_room()
    from gpomap.baselines.ogm import OccupancyGridMapper

    model = OccupancyGridMapper(resolution=0.5).fit(paper_room_scans(n_beams=36))
    out = ev.score_against_truth(model, world, 0.5)
    assert out["auc"] > 0.7 and out["n_occupied_cells"] > 0
    out2 = ev.score_against_truth(model, world, GridSpec.from_extent(world.bounds, 0.5))
    assert out2["auc"] == pytest.approx(out["auc"])
