"""OctoMap baseline through pyoctomap: one ray's known log-odds, no-return rays free only, unknown 0.5."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap.baselines.octomap import OctoMapBaseline
from gpomap.clouds import CloudScan
from gpomap.errors import NotFittedError


def test_one_hit_and_one_no_return_ray():
    origin = np.array([0.05, 0.05, 0.05])  # a voxel centre at 0.1 m
    cloud = CloudScan(origin, np.array([[1.05, 0.05, 0.05], [0.05, 2.05, 0.05]]), hit=np.array([True, False]), max_range=2.0)
    m = OctoMapBaseline(0.1).fit([cloud])
    p = m.predict_proba([[1.05, 0.05, 0.05], [0.55, 0.05, 0.05], [0.05, 1.0, 0.05], [0.05, 2.0, 0.05], [5.0, 5.0, 5.0]])
    # OctoMap's default model, one update each: hit 0.7, miss 0.4; never observed 0.5.
    np.testing.assert_allclose(p[:3], [0.7, 0.4, 0.4], atol=1e-6)
    assert p[3] <= 0.5  # the no-return ray's end is free or unknown, never occupied
    assert p[4] == 0.5


def test_repeated_hits_clamp_at_octomap_bounds():
    origin = np.array([0.05, 0.05, 0.05])
    cloud = CloudScan(origin, np.array([[1.05, 0.05, 0.05]]))
    m = OctoMapBaseline(0.1).fit([cloud] * 20)
    np.testing.assert_allclose(m.predict_proba([[1.05, 0.05, 0.05], [0.45, 0.05, 0.05]]), [0.971, 0.1192], atol=1e-4)
    assert m.memory_bytes() > 0


def test_not_fitted():
    with pytest.raises(NotFittedError):
        OctoMapBaseline().predict_proba(np.zeros((1, 3)))
