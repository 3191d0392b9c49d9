"""The counts of some scans as every scan's less the others': against counting those scans alone,
and the map of a held-out stretch's others made either way."""

import numpy as np

import gpomap.counted_cells as counted_cells
import gpomap.fusion.layer as layer
from gpomap.counted_cells import EXACT_BELOW, CountsNear, count_cells, count_cells_without
from gpomap.evidence import RayEvidence, lattice_grid
from gpomap.lattice import flat_index
from gpomap.simulate import paper_room, simulate_scans


def _scans(laps: int = 1):
    # Poses off the room's round coordinates: no beam runs along a cell border, where grids of
    # two origins may put it on either side (gpomap.counted_cells).
    world, poses = paper_room()
    poses = np.concatenate([poses] * laps)
    poses = poses + np.random.default_rng(2).normal(0.0, [0.01, 0.01, 0.002], poses.shape)
    return simulate_scans(world, poses, 60, noise_std=0.02, seed=3)


def test_every_scans_counts_less_the_others_are_the_kept_scans_own():
    scans = _scans()
    n = len(scans)
    held = list(range(n // 3, n // 3 + n // 4))
    kept = [i for i in range(n) if i not in held]
    every = RayEvidence.from_scans(scans)
    lattice = lattice_grid(every.extent(), 0.05, margin=0.3)
    whole = tuple(np.asarray(a, dtype=np.float32) for a in every.counts(lattice))
    own = RayEvidence.from_scans([scans[i] for i in kept])
    left_out = RayEvidence.from_scans([scans[i] for i in held])
    # The kept scans' lattice on another origin (a narrower margin), within the whole's.
    rest = lattice_grid(own.extent(), 0.05, margin=0.15)
    assert rest.origin != lattice.origin
    rng = np.random.default_rng(0)
    ends = own.ends[own.hit]
    points = np.concatenate([ends[::5], ends[::5] + 0.04, rng.uniform(own.extent()[::2], own.extent()[1::2], (300, 2))])
    near = CountsNear.of(lattice, whole, points)
    cells, inside = flat_index(rest, points)
    got = count_cells_without(near, left_out, own, rest, cells[inside], np.float32)
    want = count_cells(own, rest, cells[inside], np.float32)
    assert got is not None
    for name in ("cells", "hits", "misses", "near", "path", "at_surface"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert want.hits.sum() > 0 and want.near.sum() > 0 and want.at_surface.any() and not want.at_surface.all()
    # The left-out scans did count here: the difference is not the whole.
    assert np.any(near.at(np.sort(near.keys))[0] > 0)
    # Counts too large to take from exactly, or a cell the whole's counts were not taken at: None.
    large = CountsNear(near.lattice, near.keys, near.hits + EXACT_BELOW, near.misses, near.near, near.silent)
    assert count_cells_without(large, left_out, own, rest, cells[inside], np.float32) is None
    far = np.ravel_multi_index((np.array([rest.shape[0] - 1]), np.array([rest.shape[1] - 1])), rest.shape)
    assert count_cells_without(near, left_out, own, rest, far, np.float32) is None


#: Held in the fits below: the stage under test is the later visit's, not the search.
HYPERPARAMETERS = {"variance": 1.0, "length_scale": 0.5, "noise": 0.1, "alpha": 1.0, "beta": 0.0, "variance_scale": 1.0}


def test_the_later_visits_map_is_the_same_with_counts_taken_out(monkeypatch):
    # The map of a held-out stretch's others counted its rays as the fitted map's less the
    # stretch's, or walked them all (forced): the same recalibration, to the bit.
    from gpomap.tiles import TiledGPOM

    scans = _scans(laps=4)
    assert len(scans) >= 100  # enough for a held-out stretch of its own (gpomap.revisit.MIN_SCANS)
    real = counted_cells.count_cells_without
    calls: list[bool] = []
    fitted = []
    for taken_out in (True, False):

        def spy(*args, taken_out=taken_out, **kwargs):
            got = real(*args, **kwargs) if taken_out else None
            calls.append(got is not None)
            return got

        monkeypatch.setattr(layer, "count_cells_without", spy)
        fitted.append(TiledGPOM(tile_size=6.0, n_workers=1).fit(scans, hyperparameters=HYPERPARAMETERS).revisit_)
    assert calls == [True, False]
    assert fitted[0] == fitted[1] and "slope" in fitted[0]


def test_a_layer_takes_counts_out_only_of_a_lattice_counted_in_place():
    # Counts added from scans counted on another lattice (an update) may round a beam on a cell
    # border to another cell than the scans taken out would be: such a layer gives none.
    from gpomap.fusion import EvidenceCalibration, EvidenceLayer

    scans = _scans()
    points = np.array([[2.0, 2.0]])

    def layer_of(some):
        return EvidenceLayer(some, 0.05, lambda p: np.full(len(p), 0.5), calibration=EvidenceCalibration())

    once = layer_of(scans)
    near = once.counts_near(points)
    assert near is not None and near.keys.size == (2 * CountsNear.REACH + 1) ** 2
    grown = layer_of(scans[:5])
    grown.add_scans(scans[5:])
    assert grown.counts_near(points) is None
