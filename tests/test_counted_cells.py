"""Counts of a few cells, window by window, against the whole lattice's counts of the same beams."""

import numpy as np
import pytest

from gpomap.clouds import CloudScan
from gpomap.counted_cells import count_cells
from gpomap.evidence import RayEvidence, lattice_grid, next_to_hits
from gpomap.simulate import paper_room, simulate_scans


def _evidence_and_lattice(resolution: float = 0.1):
    # Poses off the room's round coordinates: no beam runs along a cell border, where grids of
    # two origins may put it on either side (gpomap.counted_cells).
    world, poses = paper_room()
    poses = poses[::3] + np.random.default_rng(2).normal(0.0, [0.01, 0.01, 0.002], poses[::3].shape)
    scans = simulate_scans(world, poses, 60, noise_std=0.02, seed=3)
    evidence = RayEvidence.from_scans(scans)
    return evidence, lattice_grid(evidence.extent(), resolution, margin=0.3)


@pytest.mark.parametrize("window", [5, 16, 4096])
def test_counted_cells_equal_the_whole_lattice_at_those_cells(window):
    evidence, lattice = _evidence_and_lattice()
    whole = evidence.counts(lattice)
    passes = evidence.path_passes(lattice)
    surface = next_to_hits(whole.hits)
    rng = np.random.default_rng(0)
    size = int(np.prod(lattice.shape))
    # Random cells, cells beams ended in with their neighbours (windows' edges among them), and
    # cells on the robot's path.
    ended = np.flatnonzero(whole.hits.reshape(-1) > 0)
    driven = np.flatnonzero(passes.reshape(-1) > 0)[::5]
    cells = np.concatenate([rng.integers(0, size, 400), ended[::7], ended[::7] + 1, ended[::7] - lattice.shape[1], driven])
    cells = cells[(cells >= 0) & (cells < size)]
    got = count_cells(evidence, lattice, cells, window=window)
    np.testing.assert_array_equal(got.cells, np.unique(cells))
    for counted, full in zip((got.hits, got.misses, got.near, got.silent), whole, strict=True):
        np.testing.assert_array_equal(counted, full.reshape(-1)[got.cells])
    np.testing.assert_array_equal(got.path, passes.reshape(-1)[got.cells])
    np.testing.assert_array_equal(got.at_surface, surface.reshape(-1)[got.cells])
    assert got.hits.sum() > 0 and got.misses.sum() > 0 and got.path.sum() > 0 and got.at_surface.any()


def test_reading_counted_cells_gives_zeros_outside_and_refuses_cells_not_counted():
    evidence, lattice = _evidence_and_lattice()
    whole = evidence.counts(lattice).hits.reshape(-1)
    cells = np.flatnonzero(whole > 0)[:5]
    got = count_cells(evidence, lattice, cells, dtype=np.float32)
    assert got.hits.dtype == np.float32
    inside = np.array([True, True, False, True, True])
    hits, *_ = got.at(cells, inside)
    np.testing.assert_array_equal(hits, np.where(inside, whole[cells], 0.0))
    with pytest.raises(ValueError, match="only at the cells"):
        got.at(cells + 1, np.ones(5, dtype=bool))


def test_counted_voxels_equal_the_whole_lattice():
    rng = np.random.default_rng(1)
    clouds = []
    for k in range(4):
        origin = np.array([0.3 * k, 0.2, 0.5]) + rng.normal(0.0, 0.01, 3)
        ends = origin + rng.uniform(-1.5, 1.5, (300, 3))
        clouds.append(CloudScan(origin, ends))
    evidence = RayEvidence.from_scans(clouds)
    lattice = lattice_grid(evidence.extent(), 0.1, margin=0.2)
    whole = evidence.counts(lattice)
    size = int(np.prod(lattice.shape))
    cells = rng.integers(0, size, 300)
    got = count_cells(evidence, lattice, cells, window=6)
    for counted, full in zip((got.hits, got.misses, got.near, got.silent), whole, strict=True):
        np.testing.assert_array_equal(counted, full.reshape(-1)[got.cells])
    np.testing.assert_array_equal(got.at_surface, next_to_hits(whole.hits).reshape(-1)[got.cells])
