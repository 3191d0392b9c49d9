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
    _, test = ev.holdout_split(100, "every:5", 3)
    assert len(test) == 20 and np.all(np.diff(test) == 5)
    _train, test = ev.holdout_split(200, "blocks:10", 3)
    assert 0.1 <= len(test) / 200 <= 0.3
    # Held-out scans come in runs of consecutive indices (blocks), at most LEN long.
    runs = np.split(test, np.flatnonzero(np.diff(test) > 1) + 1)
    assert max(len(r) for r in runs) <= 10 and sum(len(r) == 10 for r in runs) >= 2


def test_split_rejects_bad_specs():
    for bad in ["every:", "every:x", "blocks:2:1", "every:1", "random:3", "blocks:0"]:
        with pytest.raises(ValueError):
            ev.holdout_split(10, bad)
    # The protocol's names stand for their specs.
    for name, spec in (("every", "every:10"), ("blocks", "blocks:40:5")):
        for a, b in zip(ev.holdout_split(200, name, seed=3), ev.holdout_split(200, spec, seed=3), strict=True):
            np.testing.assert_array_equal(a, b)


def test_test_points_keep_natural_frequencies_and_are_seeded():
    scans = paper_room_scans(n_beams=12)[:4]
    p, y = ev.test_points(scans, 0.3, seed=1)
    every = ev.protocol_points(scans, 0.3)
    # Without a cap, every candidate point, in order: hits keep their share.
    np.testing.assert_array_equal(p, every.points)
    np.testing.assert_array_equal(y, every.occupied)
    assert y.sum() == sum(len(s.hits()) for s in scans) and y.mean() < 0.5
    p2, _y2 = ev.test_points(scans, 0.3, seed=1, max_points=20)
    p3, y3 = ev.test_points(scans, 0.3, seed=1, max_points=20)
    np.testing.assert_array_equal(p2, p3)
    assert y3.size == 20
    # A uniform draw: over many seeds the hits' share of the sample is the data's share.
    shares = [ev.test_points(scans, 0.3, seed=k, max_points=20)[1].mean() for k in range(200)]
    assert abs(np.mean(shares) - y.mean()) < 0.02
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


@pytest.mark.parametrize("method", ["msk", "gpomik", "gpom", "ogm", "ogm-counting"])
def test_evaluate_returns_documented_keys(method):
    scans = paper_room_scans(n_beams=12)
    opts = {} if method.startswith("ogm") else dict(FAST_GP)
    if method == "gpom":
        opts.update(max_points=300, free_step=0.5)
    if method == "msk":
        opts.update(min_cell=1.0, max_cell=1.0)
    res = ev.evaluate(
        scans,
        method=method,
        kernel="se",
        holdout="every:4",
        n_scans=10,
        n_beams=12,
        scan_range="0:24",
        seed=0,
        max_test_points=1000,
        return_roc=True,
        resolution=0.25,
        grid_resolution=0.5,
        **opts,
    )
    for key in (
        "auc",
        "fpr_at_tpr95",
        "log_loss",
        "seconds",
        "cpu_seconds",
        "n_inputs",
        "n_test_points",
        "settings",
        "roc",
        "points",
        "grid",
        "far",
        "peak_rss_mb",
    ):
        assert key in res
    for kind in ("points", "grid"):
        for key in (
            "auc",
            "boundary_auc",
            "observed_auc",
            "unobserved_auc",
            "fpr_at_tpr95",
            "log_loss",
            "brier",
            "ece",
            "reliability",
        ):
            assert key in res[kind]
        assert res[kind]["n_observed"] + res[kind]["n_unobserved"] == 1000
        # The ROC curve's area by the trapezoid rule is the rank statistic's AUC.
        fpr, tpr = np.asarray(res[kind]["roc"]["fpr"]), np.asarray(res[kind]["roc"]["tpr"])
        area = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
        assert area == pytest.approx(res[kind]["auc"], abs=1e-12)
    assert res["roc"] == res["points"]["roc"]
    if method.startswith("ogm"):
        assert res["grid"]["auc"] == res["points"]["auc"]  # a grid's written map is itself
    assert res["seconds"]["total"] >= res["seconds"]["fit"] > 0
    assert res["n_test_points"] == 1000 and res["n_train_scans"] == 10
    assert res["settings"]["scan_range"] == "0:24" and res["settings"]["n_scans_in_range"] == 24
    assert max(res["settings"]["test_scan_indices"]) < 24
    assert 0.5 < res["auc"] <= 1.0
    # Each map's ternary map is judged at its own occupied threshold: gpomap's calibrated map
    # (with ray evidence) calls occupied what is more likely occupied than not; every other map's is the paper's.
    assert res["occupied_threshold"] == (0.5 if method == "msk" else 0.66)
    json.dumps(res)


def test_score_against_truth_on_the_room():
    world, _ = paper_room()
    from gpomap.baselines.ogm import OccupancyGridMapper

    model = OccupancyGridMapper(resolution=0.5).fit(paper_room_scans(n_beams=36))
    out = ev.score_against_truth(model, world, 0.5)
    assert out["auc"] > 0.7 and out["n_occupied_cells"] > 0
    out2 = ev.score_against_truth(model, world, GridSpec.from_extent(world.bounds, 0.5))
    assert out2["auc"] == pytest.approx(out["auc"])


def test_protocol_points_on_a_hand_built_scan():
    from gpomap.scans import Scan

    # Beam 0 along +x returns at 1.0 m: free at 0.1, ..., 0.9 (0.1 m short), a hit at (1, 0).
    # Beam 1 along +y returns at 0.15 m: stopping 0.1 short leaves 0.05 m, no free point.
    # Beam 2 along -x is a no-return (81.83 m, SICK's code): free 0.1 ... 10.0 m, no hit.
    scan = Scan([0.0, 0.0, 0.0], [0.0, np.pi / 2, np.pi], [1.0, 0.15, 81.83], max_range=80.0)
    obs = ev.protocol_points([scan])
    hits = obs.points[obs.occupied]
    np.testing.assert_allclose(hits, [[1.0, 0.0], [0.0, 0.15]], atol=1e-12)
    free = obs.points[~obs.occupied]
    on_x = free[free[:, 0] > 0]
    np.testing.assert_allclose(on_x[:, 0], np.arange(1, 10) / 10)
    np.testing.assert_allclose(on_x[:, 1], 0.0, atol=1e-12)
    back = free[free[:, 0] < 0]
    np.testing.assert_allclose(-back[:, 0], np.arange(1, 101) / 10)
    assert len(free) == 9 + 100  # nothing along beam 1
    # A sensor whose max range is below the cap (Stage's 5 m): no-return free to 5 m.
    short = Scan([0.0, 0.0, 0.0], [0.0], [5.0], max_range=5.0)
    obs = ev.protocol_points([short])
    assert obs.n_occupied == 0 and obs.points[:, 0].max() == pytest.approx(5.0)
    # Natural frequencies: every point of the pool above, two of them hits.
    _p, y = ev.test_points([scan], seed=3)
    assert y.sum() == 2 and y.size == 111


def test_the_two_protocol_splits():
    _, test = ev.holdout_split(1000, ev.resolve_split("every"), seed=4)
    assert np.all(np.diff(test) == 10) and len(test) == 100
    _train, test = ev.holdout_split(1000, ev.resolve_split("blocks"), seed=4)
    runs = np.split(test, np.flatnonzero(np.diff(test) > 1) + 1)
    starts = np.array([r[0] for r in runs])
    # Blocks of 40 consecutive scans, one in five held out: 200 scans from one block to the next.
    assert all(len(r) == 40 for r in runs[1:-1]) and np.all(np.diff(starts) == 200)
    assert len(runs[0]) <= 40 and len(runs[-1]) <= 40
    assert 160 <= len(test) <= 240
    assert ev.resolve_split("every:3") == "every:3"


def test_boundary_selection_by_hand():
    hits = np.array([[0.0, 0.0], [10.0, 0.0]])
    pts = np.array([[0.3, 0.39], [0.5, 0.11], [0.0, 0.0], [9.6, 0.0], [5.0, 0.0]])
    # Distances to the nearest hit: 0.492 (in), 0.512 (out), 0 (in), 0.4 (in), 5 (out).
    np.testing.assert_array_equal(ev.near(pts, hits, 0.5), [True, False, True, True, False])
    assert not ev.near(pts, hits[:0], 0.5).any()


def test_score_subsets_and_one_class_subsets():
    y = np.array([True, True, False, False, True, False])
    p = np.array([0.9, 0.4, 0.6, 0.1, 0.8, 0.2])
    sub = np.array([True, True, True, True, False, False])
    only_pos = np.array([True, True, False, False, False, False])
    out = ev.score(y, p, {"sub": sub, "pos": only_pos})
    # Subset (0.9 P, 0.4 P, 0.6 N, 0.1 N): pairs P>N: 0.9 beats both, 0.4 beats 0.1: 3 of 4.
    assert out["sub_auc"] == pytest.approx(0.75) and out["n_sub"] == 4
    assert out["pos_auc"] is None and out["n_pos"] == 2
    assert out["log_loss"] == pytest.approx(-np.mean(np.log([0.9, 0.4, 0.4, 0.9, 0.8, 0.8])))
    assert sum(out["reliability"]["counts"]) == 6


def test_reference_grid_and_far_field_by_hand():
    from gpomap.scans import Scan

    # One beam along +x from the origin, returning at 2 m: the counting grid observes the cells
    # from x = 0 to 2 along y = 0 (0.05 m cells).
    scan = Scan([0.0, 0.0, 0.0], [0.0], [2.0], max_range=80.0)
    ref = ev.reference_grid([scan])
    obs = ev.observed_at(ref, np.array([[1.0, 0.01], [1.0, 0.2], [2.01, 0.0], [30.0, 0.0]]))
    np.testing.assert_array_equal(obs, [True, False, True, False])
    far = ev.FarField.from_reference(ref)
    d = far.distance_at(np.array([[1.0, 6.0], [1.0, 0.0], [500.0, 0.0]]))
    assert d[0] == pytest.approx(6.0, abs=0.4) and d[1] == 0.0 and d[2] == np.inf
    pts = far.far_points()
    assert len(pts) > 0
    # Every far lattice point is more than 5 m from the beam's segment (to a lattice cell).
    dist_to_segment = np.hypot(pts[:, 0] - np.clip(pts[:, 0], 0.0, 2.0), pts[:, 1])
    assert dist_to_segment.min() > ev.FAR_DISTANCE - 0.4


def test_truth_from_plan_by_hand():
    # 4 x 4 pixels of 0.25 m from (-1, 0): on a 0.5 m grid, 2 x 2 cells. The occupied pixel is
    # image row 0 (the top), column 3 (the right): the top-right cell, grid row 1, column 1.
    img = np.zeros((4, 4), bool)
    img[0, 3] = True
    t = ev.Truth.from_plan(img, (-1.0, 0.0), (0.25, 0.25), 0.5)
    assert t.grid.shape == (2, 2) and t.grid.origin == (-1.0, 0.0)
    np.testing.assert_array_equal(t.occupied, [[False, False], [False, True]])
    assert t.known.all()
    out = ev.score_truth(t, np.array([0.1, 0.2, 0.3, 0.7]))
    assert out["auc"] == 1.0 and out["iou"] == 1.0 and out["n_occupied_cells"] == 1
    # A ternary map of its own (the map's, which may leave cells above the threshold unknown):
    # it alone decides the IoU, here 1 / 2; the AUC stays the probability's.
    out = ev.score_truth(t, np.array([0.1, 0.2, 0.3, 0.7]), occupied=np.array([False, False, True, True]))
    assert out["auc"] == 1.0 and out["iou"] == 0.5


def test_evaluate_against_truth_scores_the_room():
    world, _ = paper_room()
    res = ev.evaluate(
        paper_room_scans(n_beams=36),
        method="ogm-counting",
        holdout="every:4",
        resolution=0.25,
        truth=ev.Truth.from_world(world, 0.25),
        max_test_points=400,
    )
    for kind in ("points", "grid"):
        t = res["truth"][kind]
        assert 0.5 < t["auc"] <= 1.0 and 0.0 < t["iou"] <= 1.0 and t["n_observed_cells"] > 0
    # The grid knows nothing far from the data: exactly 0.5 there.
    assert res["far"]["lattice"]["points"]["mean"] == 0.5 and res["far"]["lattice"]["points"]["std"] == 0.0


def test_path_points_and_path_occupied_by_hand():
    from gpomap.scans import Scan

    # Three poses facing +y: a 1 m step along x, then a 3 m one, which, sideways to the robot's
    # heading, is a jump (a new session, not a path).
    scans = [Scan([x, 0.02, np.pi / 2], [0.0], [1.0], max_range=5.0) for x in (0.0, 1.0, 4.0)]
    pts = ev.path_points(scans, step=0.025)
    # The poses themselves plus 39 points strictly between 0 and 1 m; nothing between 1 and 4 m.
    assert len(pts) == 3 + 39
    assert not np.any((pts[:, 0] > 1.0) & (pts[:, 0] < 4.0))
    # The map says occupied on [0.5, 0.6) only: path cells 10 and 11 of 0.05 m.
    prob = np.where((pts[:, 0] >= 0.5) & (pts[:, 0] < 0.6), 0.9, 0.2)
    out = ev.path_occupied(prob, pts, cell=0.05)
    # Cells 0..20 along the drive (x = 1.0 falls in cell 20) and cell 80 at the jump's end.
    assert out["n_cells"] == 22
    assert out["n_occupied"] == 2
    # The ternary map's threshold decides: 0.66 exactly is not occupied.
    assert ev.path_occupied(np.full(len(pts), 0.66), pts)["n_occupied"] == 0
    # Or the map's own ternary map: occupied on cell 10 alone, whatever the probability.
    assert ev.path_occupied(None, pts, cell=0.05, occupied=(pts[:, 0] >= 0.5) & (pts[:, 0] < 0.55))["n_occupied"] == 1
    with pytest.raises(ValueError, match="probability or its occupied class"):
        ev.path_occupied(None, pts)


def test_lookup_occupied_reads_the_written_ternary_map():
    from gpomap.grid import GridSpec, OccupancyMap

    # Two cells above the occupied threshold, the second seen through by beams: only the first is
    # occupied; a point off the map is not.
    m = OccupancyMap(GridSpec((0.0, 0.0), 1.0, (1, 3)), np.array([[0.9, 0.9, 0.1]]), seen_through=np.array([[False, True, True]]))
    np.testing.assert_array_equal(m.ternary, [[1, -1, 0]])
    got = ev.lookup_occupied(m, np.array([[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [5.0, 0.5]]))
    np.testing.assert_array_equal(got, [True, False, False, False])
    with pytest.raises(ValueError, match="seen_through has shape"):
        OccupancyMap(GridSpec((0.0, 0.0), 1.0, (1, 3)), np.zeros((1, 3)), seen_through=np.zeros((3, 1), bool))


def test_truth_from_plan_lies_on_the_maps_lattice():
    # 4 x 1 pixels of 0.1 m whose lower-left corner is (0.03, 0.0): on a 0.2 m grid the cells start
    # at x = 0 (a multiple of 0.2, as every written map's do), not at 0.03. Pixel centres 0.08,
    # 0.18, 0.28, 0.38 fall in cells 0, 0, 1, 1; the extent reaches 0.43, so a third cell.
    img = np.array([[False, True, True, False]])
    t = ev.Truth.from_plan(img, (0.03, 0.0), (0.1, 0.1), 0.2)
    assert t.grid.origin == (0.0, 0.0) and t.grid.shape == (1, 3)
    np.testing.assert_array_equal(t.occupied, [[True, True, False]])
    np.testing.assert_array_equal(t.known, [[True, True, False]])
    # A map written at 0.2 m over any extent has the same cells: its occupied cells are the plan's.
    from gpomap.grid import GridSpec

    written = GridSpec.from_extent((0.01, 0.39, 0.0, 0.1), 0.2, align=True)
    assert written.origin == t.grid.origin


def test_the_registry_names_every_method_once():
    assert ev.METHODS == tuple(ev.REGISTRY) == ("msk", "gpomik", "gpom", "ogm", "ogm-logodds", "ogm-counting")
    assert ev.GRID_METHODS == ("ogm", "ogm-logodds", "ogm-counting")
    assert ev.GP_METHODS == ("msk", "gpomik", "gpom")
    assert all(name == m.name and m.label and m.description for name, m in ev.REGISTRY.items())
    with pytest.raises(ValueError, match="unknown method 'ogm-bayes'; expected one of"):
        ev.make_model("ogm-bayes")


def test_make_model_hands_each_method_its_arguments():
    from gpomap.baselines.gpom import GPOM
    from gpomap.baselines.ogm import OccupancyGridMapper
    from gpomap.mapping import AreaGPOM

    # A grid: the cell side and the name's sensor model; no seed, no kernel.
    grid = ev.make_model("ogm-counting", "matern32", seed=3, resolution=0.25, max_range_free=4.0)
    assert isinstance(grid, OccupancyGridMapper)
    assert (grid.resolution, grid.sensor_model, grid.max_range_free) == (0.25, "counting", 4.0)
    assert ev.make_model("ogm").sensor_model == ev.make_model("ogm-logodds").sensor_model == "logodds"
    # A GP method: the seed, and the kernel when given (else its own default).
    gp = ev.make_model("gpom", "matern32", 5, resolution=0.25)
    assert isinstance(gp, GPOM) and (gp.kernel, gp.seed) == ("matern32", 5)
    assert ev.make_model("gpom").kernel == GPOM().kernel
    # The tiled map takes workers too.
    msk = ev.make_model("msk", "se", 2, n_workers=3)
    assert isinstance(msk, AreaGPOM) and msk.n_workers == 3 and msk.seed == 2
    # An option the method has no argument for is refused by its constructor, not dropped.
    with pytest.raises(TypeError):
        ev.make_model("ogm", no_such_option=1)
