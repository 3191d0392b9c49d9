"""A block's clearance, worked out for the points appended since: the whole computation's answer."""

import numpy as np

from gpomap.observations import free_near_hits
from gpomap.tiles import _BlockPoints


def test_incremental_clearance_equals_the_whole_computation():
    rng = np.random.default_rng(4)
    parts = [
        (rng.uniform(0, 3, (n, 2)), rng.random(n) < q) for n, q in [(400, 0.1), (50, 0.0), (300, 0.3), (5, 1.0), (200, 0.05)]
    ]
    block = _BlockPoints(*parts[0])
    checked = [block.free_near_hits(0.3)]
    for pts, occ in parts[1:]:
        block.append(pts, occ)
        checked.append(block.free_near_hits(0.3))
    for k, got in enumerate(checked):
        pts = np.concatenate([p for p, _ in parts[: k + 1]])
        occ = np.concatenate([o for _, o in parts[: k + 1]])
        np.testing.assert_array_equal(got, free_near_hits(pts, occ, 0.3))
    # New hits clear old free points, and some free points stay: the comparison has both answers.
    assert checked[-1].any() and not checked[-1][~np.concatenate([o for _, o in parts])].all()
    # A call with nothing appended gives the same answer again.
    np.testing.assert_array_equal(block.free_near_hits(0.3), checked[-1])
