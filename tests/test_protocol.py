"""Every map-maker answers the same protocol, and answers it about the same room."""

from __future__ import annotations

import numpy as np
import pytest

from gpomap.baselines.gpom import GPOM
from gpomap.baselines.gpomik import GPOMIK
from gpomap.baselines.ogm import OccupancyGridMapper
from gpomap.grid import OccupancyMap
from gpomap.mapping import AreaGPOM
from gpomap.metrics import roc_auc
from gpomap.observations import observations_from_scans
from gpomap.protocol import Mapper
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
