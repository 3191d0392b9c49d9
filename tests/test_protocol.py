"""Every map-maker answers the same protocol, and answers it about the same room."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap.baselines.gpom import GPOM
from gpomap.baselines.gpomik import GPOMIK
from gpomap.baselines.ogm import OccupancyGridMapper
from gpomap.evaluation import METHODS, REGISTRY, make_model, written_grid
from gpomap.grid import OccupancyMap
from gpomap.mapping import AreaGPOM
from gpomap.metrics import roc_auc
from gpomap.observations import observations_from_scans
from gpomap.protocol import Mapper, OwnGrid, TernaryPredictor
from gpomap.simulate import paper_room_scans
from gpomap.tiles import TiledGPOM

FIXED = dict(kernel="se", optimise=False, length_scale=1.0, noise=0.1)
MAPPERS = {
    "msk-gpom": lambda: AreaGPOM(max_cell=1.0, **FIXED),
    "tiled-msk-gpom": lambda: TiledGPOM(tile_size=8.0, n_workers=1, max_cell=1.0, **FIXED),
    "gpom": lambda: GPOM(max_points=600, **FIXED),
    "gpomik": lambda: GPOMIK(n_beams_per_scan=12, **FIXED),
    "ogm-logodds": lambda: OccupancyGridMapper(resolution=0.1, sensor_model="logodds"),
    "ogm-counting": lambda: OccupancyGridMapper(resolution=0.1, sensor_model="counting"),
}


@pytest.fixture(scope="module")
def room():
    scans = paper_room_scans(n_beams=72)
    train, test = scans[::2], scans[1::2]
    obs = observations_from_scans(test, 0.2, 0.1)
    rng = np.random.default_rng(0)
    occ = np.flatnonzero(obs.occupied)
    free = rng.choice(np.flatnonzero(~obs.occupied), occ.size, replace=False)
    sel = np.concatenate([occ, free])
    return train, obs.points[sel], obs.occupied[sel]


@pytest.mark.parametrize("name", sorted(MAPPERS))
def test_every_mapper_answers_the_protocol(name, room):
    train, points, labels = room
    model = MAPPERS[name]()
    assert isinstance(model, Mapper)
    assert model.fit(train) is model
    p = model.predict_proba(points)
    mean, var = model.predict(points, return_var=True)
    assert p.shape == mean.shape == var.shape == (len(points),)
    assert np.all((p >= 0) & (p <= 1)) and np.all(var >= 0)
    # Held-out scans of the room: every mapper, GP or grid, must see its walls.
    assert roc_auc(labels, p) > 0.85
    om = model.grid(0.25, (0.0, 20.0, 0.0, 16.0)) if not name.startswith("ogm") else model.grid()
    assert isinstance(om, OccupancyMap) and om.probability.shape == om.grid.shape
    assert "method" in model.summary()


def test_the_narrower_protocols_are_what_the_maps_have():
    # A ternary map of its own: the GP maps; a map that is its own grid: the occupancy grids.
    for name, build in MAPPERS.items():
        model = build()
        grid = name.startswith("ogm")
        assert isinstance(model, TernaryPredictor) is (not grid), name
        assert isinstance(model, OwnGrid) is grid, name


def test_a_map_maker_missing_a_method_is_no_mapper():
    class NoGrid:
        def fit(self, scans):
            return self

        def predict(self, points, return_var=False):
            return points[:, 0]

        def predict_proba(self, points):
            return points[:, 0]

        def summary(self):
            return {"method": "none"}

    assert not isinstance(NoGrid(), Mapper)
    NoGrid.grid = lambda self, resolution, extent=None: None
    assert isinstance(NoGrid(), Mapper)


#: Light settings of each registered method for the room (the registry's own defaults are tested
#: where each method is: test_mapping, test_baselines).
LIGHT = {
    "msk": dict(max_cell=1.0, n_workers=1, **FIXED),
    "gpomik": dict(n_beams_per_scan=12, **FIXED),
    "gpom": dict(max_points=600, **FIXED),
}


@pytest.mark.parametrize("name", METHODS)
def test_every_registered_method_builds_a_mapper(name, room):
    train, points, labels = room
    entry = REGISTRY[name]
    options = dict(LIGHT.get(name, {}))
    n_workers = options.pop("n_workers", None)
    model = make_model(name, options.pop("kernel", None), 0, 0.1, n_workers, **options)
    assert type(model) is entry.estimator() and isinstance(model, Mapper)
    assert model.fit(train) is model
    p = model.predict_proba(points)
    assert p.shape == (len(points),) and roc_auc(labels, p) > 0.85
    written = written_grid(model, 0.25)
    assert isinstance(written, OccupancyMap)
    # A grid writes its own cells; a GP map the resolution asked.
    assert written.grid.resolution == (0.1 if entry.own_grid else 0.25)
    # The name's fixed settings reach the model: "ogm" and "ogm-logodds" are one log-odds grid.
    assert model.summary()["method"].startswith(f"ogm-{entry.fixed['sensor_model']}" if entry.own_grid else name)
