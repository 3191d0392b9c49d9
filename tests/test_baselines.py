"""GPOM and GPOMIK on the paper room: held-out accuracy, input counts, interface."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap import evaluation as ev
from gpomap.baselines.gpom import GPOM
from gpomap.baselines.gpomik import GPOMIK, beam_segments
from gpomap.errors import NotFittedError
from gpomap.evaluation import holdout_split
from gpomap.scans import Scan
from gpomap.simulate import paper_room_scans

# Fixed hyperparameters keep the tests fast; the learning itself is SupportGP's (tested there).
FIXED = {"optimise": False, "length_scale": 1.5, "noise": 0.05}


@pytest.fixture(scope="module")
def room():
    scans = paper_room_scans(n_beams=12)
    train, test = holdout_split(len(scans), "every:4", seed=0)
    pts, labels = ev.test_points([scans[i] for i in test], 0.3, seed=0, max_points=300)
    # Every other training scan: a small GP keeps the test fast.
    return [scans[i] for i in train[::2]], pts, labels


@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_gpomik_high_auc_and_inputs(room, kernel):
    from gpomap.metrics import roc_auc

    train, pts, labels = room
    m = GPOMIK(kernel=kernel, **FIXED).fit(train)
    n_beams = sum(s.n_beams for s in train)
    n_hits = sum(len(s.hits()) for s in train)
    assert m.n_inputs_ == n_beams + n_hits
    p, var = m.predict_proba(pts, return_var=True)
    assert p.shape == var.shape == (len(pts),) and np.all((p >= 0) & (p <= 1)) and np.all(var >= 0)
    assert roc_auc(labels, p) > 0.9
    s = m.summary()
    assert s["method"] == "gpomik" and s["n_segments"] == n_beams and s["n_hits"] == n_hits
    assert set(m.hyperparameters_) == {"variance", "length_scale", "noise", "alpha", "beta", "variance_scale"}
    assert m.hyperparameters_["variance_scale"] == 1.0  # fitted by MSK-GPOM only (gpomap.extrapolation)
    g = m.grid(1.0)
    assert g.probability.shape == g.grid.shape


def test_gpomik_beam_thinning_and_no_return():
    scans = paper_room_scans(n_beams=12)[:3]
    free, hits, counts = beam_segments(scans, 0.1, None, n_beams_per_scan=5)
    assert len(free) == 15 and len(hits) == 15 and counts["n_beams"] == 15
    # Free segments end the margin short of the hit.
    np.testing.assert_allclose(np.hypot(*(hits.starts - free.ends).T), 0.1, atol=1e-9)
    s = scans[0]
    ranges = s.ranges.copy()
    ranges[:4] = s.max_range
    ranges[4] = np.nan
    odd = Scan(s.pose, s.angles, ranges, s.max_range)
    free, hits, counts = beam_segments([odd], 0.1, no_return_cap=2.0)
    assert len(free) == 11 and len(hits) == 7 and counts["n_no_return"] == 4 and counts["n_invalid"] == 1
    np.testing.assert_allclose(free.lengths[:4], 2.0)


@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_gpom_high_auc_and_cap(room, kernel):
    from gpomap.metrics import roc_auc

    train, pts, labels = room
    m = GPOM(kernel=kernel, free_step=0.5, max_points=250, seed=3, **FIXED).fit(train)
    assert m.n_inputs_ == 250
    s = m.summary()
    assert s["subsampled"] and s["max_points"] == 250
    # More hits than half the cap: half the cap of them, the rest free points.
    assert s["n_occupied_inputs"] == min(s["n_occupied_points"], 125)
    assert roc_auc(labels, m.predict_proba(pts)) > 0.9
    again = GPOM(kernel=kernel, free_step=0.5, max_points=250, seed=3, **FIXED).fit(train)
    np.testing.assert_array_equal(again.kept_, m.kept_)


def test_gpom_cap_limits_hits_to_half():
    m = GPOM(max_points=10, seed=0)
    occ = np.r_[np.ones(30, bool), np.zeros(30, bool)]
    keep = m.subsample(occ)
    assert keep.size == 10 and occ[keep].sum() == 5
    assert GPOM(max_points=None).subsample(occ).size == 60
    few = np.r_[np.ones(3, bool), np.zeros(30, bool)]
    keep = m.subsample(few)
    assert keep.size == 10 and few[keep].sum() == 3  # all hits kept when under half the cap


def test_not_fitted():
    with pytest.raises(NotFittedError):
        GPOMIK().predict(np.zeros((1, 2)))
    with pytest.raises(NotFittedError):
        GPOM().summary()
