"""``gpomap update --relearn`` fits a map of all the scans again from an unfitted map like the saved
one (:func:`gpomap.apps.update.unfitted_like`): the saved map's class with the arguments it was
made with, its tiling as given (not as its fit resolved it), and the settings in use when it is
fitted again (``--workers`` and ``--thresholds`` set on the loaded map included)."""

from __future__ import annotations

import pytest

from gpomap.apps.update import unfitted_like
from gpomap.mapping import AreaGPOM
from gpomap.simulate import paper_room_scans
from gpomap.tiles import TiledGPOM

#: Arguments differing from their defaults in the tiling and in the map settings alike.
SETTINGS = dict(
    kernel="se",
    free_step=0.5,
    min_cell=0.5,
    max_cell=3.0,
    optimise=False,
    length_scale=1.0,
    noise=0.1,
    thresholds=(0.3, 0.7),
)
TILED = dict(overlap=2.0, blend=1.0, hyper_sample=300, per_tile_hyperparameters=False, scheduler_timeout=7.0, memory_limit=3.0)


@pytest.fixture(scope="module")
def scans() -> list:
    return paper_room_scans()[::4]


@pytest.mark.parametrize(
    ("cls", "given"),
    [
        (TiledGPOM, {"tile_size": None, "origin": (0.5, -0.5), **TILED, **SETTINGS}),
        (TiledGPOM, {"tile_size": 4.0, **TILED, **SETTINGS}),
        (AreaGPOM, {"tile_size": None, **SETTINGS}),
    ],
    ids=["tiled-side-chosen", "tiled-side-given", "area"],
)
def test_the_unfitted_map_is_the_saved_maps_class_and_arguments(scans, cls, given):
    model = cls(**given).fit(scans)
    assert model.tile_size_ > 0  # the fit chose or kept a side; the unfitted map is told none
    fresh = unfitted_like(model)
    assert type(fresh) is cls
    assert not hasattr(fresh, "tiles_")
    assert fresh.get_params() == cls(**given).get_params()
    assert {k: fresh.get_params()[k] for k in given} == given
    # Fitted again on the same scans, the same map.
    again = fresh.fit(scans)
    assert again.hyperparameters_ == model.hyperparameters_
    assert sorted(again.tiles_) == sorted(model.tiles_)


def test_the_settings_set_on_the_loaded_map_are_the_ones_fitted_again(scans, tmp_path):
    from gpomap.io.mapfile import load_fitted_map, save_fitted_map

    model = TiledGPOM(tile_size=4.0, **SETTINGS).fit(scans)
    save_fitted_map(model, tmp_path / "map.gpom")
    loaded = load_fitted_map(tmp_path / "map.gpom")
    # As gpomap update's --workers and --thresholds set them (gpomap.cli.render.configure).
    loaded.n_workers = 2
    loaded.base = loaded.base.replace(thresholds=(0.2, 0.8))
    fresh = unfitted_like(loaded)
    assert type(fresh) is TiledGPOM
    assert fresh.get_params() == TiledGPOM(tile_size=4.0, n_workers=2, **{**SETTINGS, "thresholds": (0.2, 0.8)}).get_params()
