"""The fitted map as a file (gpomap.io.mapfile): what is loaded is the model that was saved, every
attribute of it, and it predicts, grids, updates and streams on as the live model does, to the bit."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

import gpomap
from gpomap.clouds import CloudScan
from gpomap.errors import InputFormatError
from gpomap.fusion import EvidenceLayer
from gpomap.io import mapfile
from gpomap.io.mapfile import (
    FORMAT,
    NOT_SAVED,
    VERSION,
    load_fitted_map,
    load_streaming_state,
    save_fitted_map,
    save_streaming_state,
)
from gpomap.io.npz import save_map
from gpomap.lattice import cell_offset
from gpomap.mapping import AreaGPOM
from gpomap.observations import observations_from_scans
from gpomap.scans import Scan
from gpomap.simulate import paper_room_scans
from gpomap.streaming import StreamingGPOM
from gpomap.tiles import TiledGPOM, TileStore, _BlockPoints
from tests import world3d

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BAG = DATA / "stage-arena" / "robot1.bag"
needs_bag = pytest.mark.skipif(not BAG.exists(), reason="shared Stage arena bag not present")

# Small tiles over the paper's room: several tiles and blocks, fast fits (as tests/test_streaming.py).
ROOM_OPTS = dict(tile_size=6.0, overlap=2.5, free_step=0.5, max_cell=1.0, optimise=False, length_scale=1.0, noise=0.1)


# --------------------------------------------------------------------------- an independent comparison
def _not_saved(obj: object) -> set[str]:
    names: set[str] = set()
    for base in type(obj).__mro__:
        names |= set(NOT_SAVED.get(f"{base.__module__}.{base.__qualname__}", {}))
    return names


def assert_same(a, b, where="model", ignore=frozenset()):
    """`a` and `b` hold the same state, recursively and to the bit: every attribute of every object
    (the caches of NOT_SAVED aside), every field of every dataclass, arrays by dtype, shape and bytes;
    attributes and fields named in `ignore` (wall times) aside."""
    if where.rsplit(".", 1)[-1] in ignore:
        return
    assert type(a) is type(b), f"{where}: {type(a).__name__} against {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} against {b.dtype}{b.shape}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), where
    elif isinstance(a, float):
        assert a == b or (math.isnan(a) and math.isnan(b)), f"{where}: {a!r} against {b!r}"
    elif a is None or isinstance(a, (bool, int, str, bytes, set, frozenset)):
        assert a == b, f"{where}: {a!r} against {b!r}"
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: {len(a)} items against {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]", ignore)
    elif isinstance(a, TileStore):
        # Tile by tile, whichever factors wait in the store's file.
        assert sorted(a) == sorted(b), f"{where}: keys {sorted(a)[:8]} against {sorted(b)[:8]}"
        for k in sorted(a):
            assert_same(a[k], b[k], f"{where}[{k!r}]", ignore)
    elif isinstance(a, dict):
        # The blocks' points are filed in another order when recomputed (no reader depends on it).
        ka, kb = (sorted(a), sorted(b)) if where.endswith("_block_points") else (list(a), list(b))
        assert ka == kb, f"{where}: keys {ka[:8]} against {kb[:8]}"
        for k in ka:
            assert_same(a[k], b[k], f"{where}[{k!r}]", ignore)
    elif hasattr(a, "__func__"):  # a bound method (the ray evidence's GP apart): the same function of the same map
        assert a.__func__ is b.__func__, where
    elif isinstance(a, (Scan, CloudScan)):
        for f in dataclasses.fields(a):
            if f.compare:
                assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}", ignore)
    elif isinstance(a, _BlockPoints):
        for x, y, name in zip(a.arrays(), b.arrays(), ("points", "occupied"), strict=True):
            assert_same(x, y, f"{where}.{name}")
        assert_same(a._near, b._near, f"{where}._near")
        assert_same(a._n_checked, b._n_checked, f"{where}._n_checked")
        # A loaded block's points are made from the scans when first read (above): no wait is left.
        assert a._restore is None and b._restore is None, where
        waits = {"_restore", "_restore_count"}
        assert set(vars(a)) - waits == set(vars(b)) - waits == {"_parts", "_runs", "_near", "_n_checked"}, where
        # Each point's scan, however the points were split into parts.
        scans = [None if p._runs is None else np.repeat(*map(np.concatenate, zip(*p._runs))) for p in (a, b)]
        assert_same(*scans, f"{where}._runs")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.compare:
                assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}", ignore)
    else:
        skip = _not_saved(a)
        if isinstance(a, EvidenceLayer):
            # The beams of every part, joined (the loaded layer holds them as one part).
            skip |= {"_parts"}
            for name in ("starts", "ends", "hit", "scan", "path"):
                assert_same(getattr(a.evidence, name), getattr(b.evidence, name), f"{where}.evidence.{name}")
        assert set(vars(a)) - skip == set(vars(b)) - skip, f"{where}: attributes {sorted(set(vars(a)) ^ set(vars(b)))}"
        for k in sorted(set(vars(a)) - skip):
            assert_same(vars(a)[k], vars(b)[k], f"{where}.{k}", ignore)


def assert_same_predictions(live, loaded, points, grids=()):
    p1, v1 = live.predict_proba(points, return_var=True)
    p2, v2 = loaded.predict_proba(points, return_var=True)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(v1, v2)
    for resolution, extent in grids:
        g1, g2 = live.grid(resolution, extent), loaded.grid(resolution, extent)
        np.testing.assert_array_equal(g1.probability, g2.probability)
        np.testing.assert_array_equal(g1.variance, g2.variance)
        np.testing.assert_array_equal(g1.ternary, g2.ternary)
        assert g1.thresholds == g2.thresholds


def roundtrip(model, tmp_path, name="map.gpom"):
    path = save_fitted_map(model, tmp_path / name)
    return load_fitted_map(path)


# --------------------------------------------------------------------------- data
@pytest.fixture(scope="module")
def arena():
    from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag

    if not BAG.exists():
        pytest.skip("shared Stage arena bag not present")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)


@pytest.fixture(scope="module")
def arena_map(arena):
    # 110 scans: the map fits its recalibration for a later visit too (100 scans or more).
    return AreaGPOM(n_workers=1).fit(arena[:110])


@pytest.fixture(scope="module")
def room():
    return [Scan(s.pose + np.array([0.0123, 0.0177, 0.0]), s.angles, s.ranges, s.max_range) for s in paper_room_scans()]


# --------------------------------------------------------------------------- the model, to the bit
@needs_bag
def test_a_map_of_a_real_log_loads_as_the_model_that_was_saved(arena_map, tmp_path):
    assert "slope" in arena_map.revisit_ and arena_map.evidence_ is not None
    loaded = roundtrip(arena_map, tmp_path)
    assert type(loaded) is AreaGPOM
    assert_same(arena_map, loaded)
    rng = np.random.default_rng(0)
    lo, hi = arena_map.bounds_
    # Points over the map and well beyond it.
    points = rng.uniform(lo - 5.0, hi + 5.0, size=(20_000, 2))
    # The counts' own cells (the default grid), other cells (counted afresh from the beams), a window.
    grids = [(0.05, None), (0.031, None), (0.01, (0.0, 1.0, 0.0, 0.8))]
    assert_same_predictions(arena_map, loaded, points, grids)
    assert gpomap.load_map(tmp_path / "map.gpom").summary()["n_scans"] == 110


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"per_tile_hyperparameters": True, "optimise": True, "length_scale": 1.0, "hyper_subset": 60},
        {"fit_surprise_rate": True},
        {"ray_evidence": False},
        {"area": "summed", "kernel": "se", "free_step": 1.0},
    ],
    ids=["tiles", "per-tile-hyperparameters", "surprise-rate", "gp-alone", "summed-area"],
)
def test_every_attribute_is_saved_whatever_the_settings(room, tmp_path, options):
    # The summed area kernel sums over every member point: fewer scans keep it quick.
    model = TiledGPOM(n_workers=1, **{**ROOM_OPTS, **options}).fit(room[::4] if "area" in options else room[::2])
    assert len(model.tiles_) > 1
    loaded = roundtrip(model, tmp_path)
    assert_same(model, loaded)
    if options.get("fit_surprise_rate"):
        assert loaded.evidence_.gp_apart.__self__ is loaded  # the loaded map's own, not the live one's
    points = np.random.default_rng(1).uniform(-3, 23, size=(3000, 2))
    assert_same_predictions(model, loaded, points, [(0.1, None), (0.07, (2.0, 9.0, 1.0, 6.0))])


def test_a_map_of_labelled_points_keeps_its_points(room, tmp_path):
    obs = observations_from_scans(room, 0.5, None, 10.0, 0.3)
    model = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(obs)
    loaded = roundtrip(model, tmp_path)
    assert loaded._scans is None and loaded.evidence_ is None
    assert_same(model, loaded)
    assert_same_predictions(model, loaded, obs.points[::7], [(0.2, None)])


@pytest.mark.parametrize("merged", [False, True])
def test_a_3d_map_loads_as_the_model_that_was_saved(tmp_path, monkeypatch, merged):
    # Merged or not, its blocks' points are made again from its scans, with their weights.
    import gpomap.observations as observations

    if merged:
        monkeypatch.setattr(observations, "MERGE_MIN_SAMPLES", 0)
    clouds = world3d.lidar_clouds(world3d.ORIGINS[:3], n_rays=400, max_range=4.0)
    model = AreaGPOM(kernel="se", min_cell=1.0, max_cell=1.0).fit(clouds)
    loaded = roundtrip(model, tmp_path)
    assert loaded.dim_ == 3
    assert_same(model, loaded)
    for key, block in model._block_points.items():
        weights = block.weighted_arrays()[2]
        np.testing.assert_array_equal(loaded._block_points[key].weighted_arrays()[2], weights)
        assert (int(weights.max()) > 1) == merged
    points = np.random.default_rng(2).uniform([-1, -1, -1], [7, 5, 3.5], size=(4000, 3))
    assert_same_predictions(model, loaded, points)
    for resolution, extent in [(0.25, None), (0.1, (2.0, 4.0, 1.0, 3.0, 0.5, 1.5))]:
        v1, v2 = model.grid(resolution, extent), loaded.grid(resolution, extent)
        assert v1.spec == v2.spec
        np.testing.assert_array_equal(v1.probability, v2.probability)
        np.testing.assert_array_equal(v1.variance, v2.variance)
        np.testing.assert_array_equal(v1.observed, v2.observed)


def test_an_attribute_added_to_the_model_is_saved_and_one_that_cannot_be_is_refused(room, tmp_path):
    model = TiledGPOM(n_workers=1, ray_evidence=False, **ROOM_OPTS).fit(room[:8])
    model.added_ = {"weights": np.arange(5.0), (1, 2): {3, 4}}
    loaded = roundtrip(model, tmp_path)
    assert_same(model, loaded)
    model.callback_ = lambda x: x
    with pytest.raises(TypeError, match=r"cannot save a builtins.function \(map/callback_\)"):
        save_fitted_map(model, tmp_path / "never.gpom")
    assert not (tmp_path / "never.gpom").exists()


def _rewrite_header(path, change):
    """The map file at `path` with its header passed through `change` (the arrays as they were)."""
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    header = json.loads(str(np.load(path, allow_pickle=False)["header"]))
    change(header)
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            if name == "header.npy":
                buf = __import__("io").BytesIO()
                np.lib.format.write_array(buf, np.array(json.dumps(header)), allow_pickle=False)
                data = buf.getvalue()
            zf.writestr(name, data)


#: What a map file of format version 4 holds of each class (its attributes, or a dataclass's fields).
#: Version 2 kept version 1's layout, its ray counts a scan's shared updates (float32); version 3's
#: voxel maps make their blocks' points again with free samples merged by cube, and a map counts the
#: free samples its points stand for (``_n_free_samples``); version 4's evidence layer counts the
#: silent updates (``_silent``) and its calibration holds their rate (``silent_rate``, ``silent_mix``).
LAYOUT_V4 = {
    "gpomap.mapping.AreaGPOM": {
        "tile_size", "overlap", "blend", "origin", "n_workers", "hyper_sample", "per_tile_hyperparameters",
        "blas_threads", "worker_processes", "scheduler_timeout", "memory_limit", "base", "options", "_clearance",
        "_block_points", "_blocks", "_tiles_with_points", "_lower", "_upper", "_n_points", "_n_occupied_points", "_n_free_samples",
        "_dim", "tile_size_", "origin_", "_dirty", "_n_scans", "_n_invalid", "_n_no_return", "path_",
        "hyper_source_", "hyperparameters_", "overlap_", "blend_", "extrapolation_", "_scans", "tiles_",
        "_signatures", "timings_", "evidence_", "revisit_", "last_refit_", "_stale", "_reused",
    },
    "gpomap.fusion.EvidenceLayer": {
        "resolution", "gp_apart", "no_return_cap", "calibration_scans", "seed", "calibration", "report",
        "sample", "revisit", "_scans", "_parts", "_dim", "lattice", "_hits", "_beam_misses", "_near_misses", "_silent",
        "_path",
    },
    "gpomap.fusion.EvidenceCalibration": {
        "hit_weight", "prior_weight", "near_weight", "near_hit_weight", "surface_weight", "surprise_rate",
        "silent_rate", "silent_mix",
    },
    "gpomap.revisit.RevisitCalibration": {"slope", "shift"},
    "gpomap.tiles.TileState": {"key", "posterior", "hyperparameters", "seconds"},
    "gpomap.gp.GPPosterior": {"inputs", "L", "weights", "kernel", "squash", "jitter"},
    "gpomap.tiles._BlockPoints": {"_parts", "_near", "_n_checked"},
}  # fmt: skip


def _layout(state, out=None):
    """Class name to the attribute or field names the encoded `state` holds of it."""
    out = {} if out is None else out
    if isinstance(state, dict):
        for tag, names in (("$object", "state"), ("$dataclass", "fields")):
            if tag in state:
                out.setdefault(state[tag], set()).update(state[names])
        for v in state.values():
            _layout(v, out)
    elif isinstance(state, list):
        for v in state:
            _layout(v, out)
    return out


def test_the_saved_layout_is_the_format_versions(room, tmp_path):
    # A change to what is saved (an attribute or a field added, renamed or dropped) must come with
    # a new gpomap.io.mapfile.VERSION, so that older files are refused instead of loaded without it:
    # raise it, and pin the new layout here.
    model = AreaGPOM(n_workers=1, **ROOM_OPTS).fit(room[::3])
    path = save_fitted_map(model, tmp_path / "map.gpom")
    with np.load(path, allow_pickle=False) as archive:
        layout = _layout(json.loads(str(archive["header"]))["state"])
    assert model.evidence_._hits.dtype == np.float32
    assert VERSION == 4
    for name, names in LAYOUT_V4.items():
        assert layout[name] == names, f"{name}: {sorted(layout[name] ^ names)} changed: raise the format VERSION"


def test_a_calibration_dataclass_whose_fields_changed_is_refused_by_name(room, tmp_path):
    model = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:10])
    path = save_fitted_map(model, tmp_path / "map.gpom")

    def drop_field(header):
        calibration = header["state"]["state"]["evidence_"]["state"]["calibration"]
        assert calibration["$dataclass"] == "gpomap.fusion.EvidenceCalibration"
        del calibration["fields"]["surface_weight"]  # as if this gpomap's dataclass had gained it

    _rewrite_header(path, drop_field)
    with pytest.raises(InputFormatError) as err:
        load_fitted_map(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(path))
    assert "gpomap.fusion.EvidenceCalibration" in message and "surface_weight" in message


def test_the_file_is_numpy_arrays_and_json_without_pickles(room, tmp_path):
    model = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:10])
    path = save_fitted_map(model, tmp_path / "map.gpom")
    with np.load(path, allow_pickle=False) as archive:
        header = json.loads(str(archive["header"]))
        arrays = {k: archive[k] for k in archive.files}
    assert header["format"] == FORMAT and header["version"] == VERSION and header["kind"] == "map"
    assert header["summary"]["dim"] == 2 and header["summary"]["n_tiles"] == len(model.tiles_)
    assert all(not a.dtype.hasobject for a in arrays.values())
    # Each tile's Cholesky factor is stored as its lower triangle.
    n = next(iter(model.tiles_.values())).n_cells
    packed = [k for k in arrays if k.endswith("/posterior/L")]
    assert len(packed) == len(model.tiles_) and all(arrays[k].ndim == 1 for k in packed)
    assert arrays[packed[0]].size == n * (n + 1) // 2
    # The same model saved twice is the same bytes.
    again = save_fitted_map(model, tmp_path / "again.gpom")
    assert again.read_bytes() == path.read_bytes()


# --------------------------------------------------------------------------- extending a saved map
@needs_bag
def test_a_loaded_map_updates_as_the_live_one(arena, tmp_path):
    live = AreaGPOM(n_workers=1).fit(arena[:40])
    loaded = roundtrip(live, tmp_path)
    new = arena[40:70]
    live.update(new)
    loaded.update(new)
    assert_same(live, loaded, ignore={"seconds", "timings_"})
    points = np.random.default_rng(3).uniform(-2, 4, size=(5000, 2))
    assert_same_predictions(live, loaded, points, [(0.05, None)])
    # Its GP is the batch GP of every scan with the saved hyperparameters, on the saved map's tile
    # grid (a fit of the 70 scans alone would centre its one tile elsewhere), and so are the ray
    # counts; only the robot path's passes may differ, in cells a step of the simulated path runs
    # along the border of (the counts of the new scans are taken on a lattice of another origin).
    batch = AreaGPOM(n_workers=1, origin=loaded.origin_).fit(arena[:70], hyperparameters=loaded.hyperparameters_)
    np.testing.assert_allclose(loaded.predict_proba_gp(points), batch.predict_proba_gp(points), rtol=0, atol=1e-9)
    a, b = loaded.evidence_, batch.evidence_
    (i, j), (ny, nx) = cell_offset(b.lattice, a.lattice), b.lattice.shape
    for name in ("_hits", "_beam_misses", "_near_misses", "_silent"):
        grown, whole = getattr(a, name), getattr(b, name)
        np.testing.assert_array_equal(grown[i : i + ny, j : j + nx], whole)
        assert grown.sum() == whole.sum()  # nothing counted outside the batch's lattice
    assert a._hits.sum() > 0 and a._near_misses.sum() > 0


def test_an_updated_map_is_the_batch_map_with_the_saved_hyperparameters(room, tmp_path):
    scans = room[::2]
    loaded = roundtrip(TiledGPOM(n_workers=1, **ROOM_OPTS).fit(scans[:6]), tmp_path)
    loaded.update(scans[6:])
    batch = TiledGPOM(n_workers=1, **{**ROOM_OPTS, "origin": loaded.origin_}).fit(scans, hyperparameters=loaded.hyperparameters_)
    points = np.random.default_rng(5).uniform(0, 20, size=(3000, 2))
    p_loaded, v_loaded = loaded.predict_proba(points, return_var=True)
    p_batch, v_batch = batch.predict_proba(points, return_var=True)
    np.testing.assert_allclose(p_loaded, p_batch, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v_loaded, v_batch, rtol=0, atol=1e-9)
    for resolution in (0.05, 0.1):  # on the counted lattice and off it
        a, b = loaded.grid(resolution, (0.0, 20.0, 0.0, 16.0)), batch.grid(resolution, (0.0, 20.0, 0.0, 16.0))
        np.testing.assert_allclose(a.probability, b.probability, rtol=0, atol=1e-9)


def test_a_streaming_map_saved_with_tiles_waiting_goes_on_as_the_live_one(room, tmp_path):
    stream = StreamingGPOM(warmup_scans=6, max_refits=1, **ROOM_OPTS)
    for s in room[:14]:
        stream.add_scan(s)
        if stream.ready_ and len(stream._refresh_seconds) < 6:
            stream.refresh()
    assert stream.pending_tiles_ > 0  # blocks absorbed and tiles waiting, saved as they are
    points = np.random.default_rng(4).uniform(0, 20, size=(3000, 2))
    # The map alone (what the ROS node's save service writes): the model as it stands now.
    model = roundtrip(stream.model_, tmp_path, "model.gpom")
    assert_same(stream.model_, model)
    assert_same_predictions(stream.model_, model, points)
    # The whole mapper: resumed, it goes on scan by scan as the live one does, to the bit.
    save_streaming_state(stream, tmp_path / "state.gpom")
    resumed = load_streaming_state(tmp_path / "state.gpom")
    assert_same(stream, resumed, "stream")
    for s in room[14:18]:
        for m in (stream, resumed):
            m.add_scan(s)
            m.refresh()
    for m in (stream, resumed):
        m.finish()
    assert resumed.version_ == stream.version_ and resumed.n_scans_ == 18
    np.testing.assert_array_equal(stream.predict_proba(points, refresh=False), resumed.predict_proba(points, refresh=False))
    np.testing.assert_array_equal(stream.grid(0.1).probability, resumed.grid(0.1).probability)


def test_a_streaming_state_in_its_warm_up_keeps_its_scans(room, tmp_path):
    stream = StreamingGPOM(warmup_scans=10, **ROOM_OPTS)
    stream.add_scans(room[:4])
    save_streaming_state(stream, tmp_path / "warm.gpom")
    resumed = load_streaming_state(tmp_path / "warm.gpom")
    assert_same(stream, resumed, "stream")
    with pytest.raises(InputFormatError, match=r"warm.gpom: a streaming state still warming up \(4 of 10 scans\)"):
        load_fitted_map(tmp_path / "warm.gpom")
    resumed.add_scans(room[4:12])
    stream.add_scans(room[4:12])
    np.testing.assert_array_equal(stream.grid(0.2).probability, resumed.grid(0.2).probability)


# --------------------------------------------------------------------------- bad files
@pytest.fixture(scope="module")
def saved(room, tmp_path_factory):
    path = tmp_path_factory.mktemp("saved") / "map.gpom"
    return save_fitted_map(TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:8]), path)


def _one_line_error(path, loader=load_fitted_map) -> str:
    with pytest.raises(InputFormatError) as err:
        loader(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(path)), message
    return message


def test_a_map_file_of_another_version_is_refused(saved, tmp_path):
    path = tmp_path / "v2.gpom"
    path.write_bytes(saved.read_bytes())
    _rewrite_header(path, lambda h: h.update(version=VERSION + 1, written_by="gpomap 9.9"))
    message = _one_line_error(path)
    assert f"format version {VERSION + 1} (written by gpomap 9.9); this gpomap reads version {VERSION}" in message


@pytest.mark.parametrize("keep", [0.999, 0.5, 0.01, 0.0])
def test_a_truncated_map_file_is_refused(saved, tmp_path, keep):
    data = saved.read_bytes()
    path = tmp_path / "cut.gpom"
    path.write_bytes(data[: int(len(data) * keep)])
    message = _one_line_error(path)
    assert "expected a gpomap map file" in message or "truncated" in message


def test_files_that_are_not_map_files_are_refused(room, tmp_path):
    text = tmp_path / "notes.gpom"
    text.write_text("x,y\n1,2\n")
    assert "not a gpomap map file: a file starting with b'x,y" in _one_line_error(text)
    npy = tmp_path / "array.gpom"
    np.save(npy.with_suffix(".npy"), np.arange(3))
    npy.write_bytes(npy.with_suffix(".npy").read_bytes())
    assert "a single NumPy array (.npy)" in _one_line_error(npy)
    grid = save_map(TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:8]).grid(0.5), tmp_path / "map.npz")
    assert "a written grid: gpomap.io.npz.load_map reads it" in _one_line_error(grid)
    other = tmp_path / "other.npz"
    np.savez(other, header=np.array(json.dumps({"format": "something-else"})))
    assert "a header of format 'something-else'" in _one_line_error(other)
    assert "is a directory" in _one_line_error(tmp_path)
    assert "file not found" in _one_line_error(tmp_path / "missing.gpom")


def test_an_altered_state_is_a_one_line_error(saved, tmp_path):
    path = tmp_path / "altered.gpom"
    path.write_bytes(saved.read_bytes())

    def poses_are_offsets(header):  # the scans' poses read from another array
        scans = header["state"]["state"]["_scans"]["$scans"]["arrays"]
        scans["pose"] = scans["offsets"]

    _rewrite_header(path, poses_are_offsets)
    assert "an altered file" in _one_line_error(path)
    path.write_bytes(saved.read_bytes())
    _rewrite_header(path, lambda h: h["state"]["state"].update(tiles_={"$array": "nowhere"}))
    assert "array 'nowhere' is missing (a truncated or altered file)" in _one_line_error(path)


def test_a_map_file_is_not_a_streaming_state(saved):
    assert "holds a fitted map, not a streaming state" in _one_line_error(saved, load_streaming_state)


def test_only_the_maps_own_classes_are_made(saved, tmp_path):
    path = tmp_path / "evil.gpom"
    path.write_bytes(saved.read_bytes())
    _rewrite_header(path, lambda h: h["state"].update({"$object": "subprocess.Popen"}))
    assert "class 'subprocess.Popen' is not one a map file holds" in _one_line_error(path)


def test_saving_takes_a_fitted_tiled_map(room, tmp_path):
    with pytest.raises(TypeError, match="save its model_"):
        save_fitted_map(StreamingGPOM(warmup_scans=3, **ROOM_OPTS), tmp_path / "x.gpom")
    with pytest.raises(gpomap.errors.NotFittedError):
        save_fitted_map(TiledGPOM(), tmp_path / "x.gpom")
    assert mapfile.FILENAME == "map.gpom"


def test_points_waiting_in_a_spill_file_are_counted_not_read_back_when_saved(room, tmp_path, monkeypatch):
    # The file holds each block's number of points (its points are made again from the scans):
    # those of parts in the spill file and in memory alike, none read back to count them.
    import gpomap.tiles.points as tile_points
    import gpomap.tiles.tiled as tiled_map

    monkeypatch.setattr(tiled_map, "POINT_MEMORY", 1)
    model = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:8])
    # An update's points are appended in memory after the spilled ones.
    model.update(room[8:10])
    parts = [p for b in model._block_points.values() for p in b._parts]
    assert any(isinstance(p, tile_points._SpilledPart) for p in parts) and not all(
        isinstance(p, tile_points._SpilledPart) for p in parts
    )
    want = {k: b.arrays()[0].shape[0] for k, b in model._block_points.items()}
    reads = []
    load = tile_points._SpilledPart.load
    monkeypatch.setattr(tile_points._SpilledPart, "load", lambda self: reads.append(self) or load(self))
    path = save_fitted_map(model, tmp_path / "map.gpom")
    assert reads == []
    monkeypatch.undo()
    loaded = load_fitted_map(path)  # refused if a block's count were not that of its points made again
    assert {k: b.arrays()[0].shape[0] for k, b in loaded._block_points.items()} == want
    assert_same(model, loaded)


def test_a_loaded_maps_points_are_made_from_its_scans_only_when_read(saved, room):
    live = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:8])
    loaded = load_fitted_map(saved)
    blocks = list(loaded._block_points.values())
    assert blocks and all(b._restore is not None and b._parts == [] for b in blocks)
    # Predicting reads none of them: the map's answers are the live map's, every block still waiting.
    lo, hi = live.bounds_
    points = np.random.default_rng(3).uniform(lo - 1.0, hi + 1.0, size=(500, 2))
    np.testing.assert_array_equal(loaded.predict_proba(points), live.predict_proba(points))
    assert all(b._restore is not None for b in blocks)
    # The first read fills every block at once, with the live map's points.
    (p, o), (p_live, o_live) = loaded.training_points(), live.training_points()
    assert all(b._restore is None for b in blocks)
    order, order_live = np.lexsort((p[:, 1], p[:, 0], o)), np.lexsort((p_live[:, 1], p_live[:, 0], o_live))
    np.testing.assert_array_equal(p[order], p_live[order_live])
    np.testing.assert_array_equal(o[order], o_live[order_live])


def test_points_the_scans_do_not_give_are_refused_when_first_read(saved, tmp_path):
    def one_more_point(node: object) -> bool:
        """Add a point to the first block whose points are made from the scans."""
        if isinstance(node, dict):
            if "$from_scans" in node:
                node["$from_scans"] += 1
                return True
            return any(one_more_point(v) for v in node.values())
        return isinstance(node, list) and any(one_more_point(v) for v in node)

    path = tmp_path / "altered.gpom"
    path.write_bytes(Path(saved).read_bytes())
    _rewrite_header(path, lambda header: one_more_point(header["state"]))
    loaded = load_fitted_map(path)  # its predictions never read the points
    with pytest.raises(InputFormatError) as err:
        loaded.training_points()
    message = str(err.value)
    assert message.startswith(str(path)) and "\n" not in message and "labelled points" in message


def test_a_loaded_maps_points_are_made_a_run_of_scans_at_a_time_past_the_budget_in_a_file(saved, room, monkeypatch):
    import gpomap.observations as observations
    from gpomap.io.mapfile import encoding
    from gpomap.tiles.points import _SpilledPart

    made = observations.observation_parts
    runs: list[int] = []

    def counted(*args, **kwargs):
        for part in made(*args, **kwargs):
            runs.append(len(np.unique(part.scan_index)))  # the scans in this run
            yield part

    monkeypatch.setattr(observations, "observation_parts", counted)
    monkeypatch.setattr(observations, "PART_POINTS", 1)  # one scan a run
    monkeypatch.setattr(encoding, "POINT_MEMORY", 1)  # in the spill file from the first run on
    loaded = load_fitted_map(saved)
    live = TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room[:8])
    runs.clear()
    assert_same(live, loaded, ignore={"seconds", "timings_"})  # each block's points and their scans, made when first read
    assert runs == [1] * 8
    assert all(isinstance(p, _SpilledPart) for b in loaded._block_points.values() for p in b._parts)
