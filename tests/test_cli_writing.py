"""Every command that writes a planar map writes it through one function, ``gpomap.cli.map.write_grid``.

Each command's files are checked against the library's own grid written directly by
``gpomap.io.export.write_map_files`` (map.yaml, map.pgm and map.png to the byte, map.npz's arrays
to the bit), and the commands that hand their model over (``render``, ``update``) are checked to
have let it go before the grid is put together, with map.gpom written already.
"""

from __future__ import annotations

import io
import sys
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import gpomap
from gpomap.cli import main
from gpomap.io.export import write_map_files

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
INTEL = DATA / "intel" / "intel-corrected.log.gz"
pytestmark = pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
# Scans of 45 beams, the length scale fixed: the writing is the point, not the fit.
READ = ["--beams", "45", "--workers", "1", "-q"]
FAST = [*READ, "--length-scale", "1"]
SHARED_PATH = ("gpomap.cli.map", "write_grid")


def record_writes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[tuple[str, str], dict[str, bytes]]]:
    """Each set of planar-map files a command writes from now on: the function that wrote it, and its files' bytes."""
    from gpomap.io import export

    sets: list[tuple[tuple[str, str], dict[str, bytes]]] = []

    def recorded(occupancy_map: Any, directory: Any, **options: Any) -> list[Path]:
        files = write_map_files(occupancy_map, directory, **options)
        caller = sys._getframe(1)
        sets.append(((caller.f_globals["__name__"], caller.f_code.co_name), {f.name: f.read_bytes() for f in files}))
        return files

    monkeypatch.setattr(export, "write_map_files", recorded)
    return sets


@pytest.fixture(scope="module")
def mapped_run(tmp_path_factory) -> tuple[Path, list[tuple[tuple[str, str], dict[str, bytes]]]]:
    """``gpomap map`` of the log's first 30 scans at 0.25 m: its output directory and the sets it wrote."""
    out = tmp_path_factory.mktemp("intel") / "map"
    with pytest.MonkeyPatch.context() as monkeypatch:
        sets = record_writes(monkeypatch)
        assert main(["map", str(INTEL), "--range", "0:30", "--resolution", "0.25", "-o", str(out), *FAST]) == 0
    return out, sets


@pytest.fixture(scope="module")
def mapped(mapped_run) -> Path:
    return mapped_run[0]


@pytest.fixture
def writes(monkeypatch) -> list[tuple[tuple[str, str], dict[str, bytes]]]:
    """Each set of planar-map files a command writes: the function that wrote it, and its files' bytes."""
    return record_writes(monkeypatch)


@pytest.fixture
def put_together(monkeypatch) -> list[tuple[bool, list[str]]]:
    """At each planar grid put together by gpomap.fitted.LaterGrid: whether every model whose fitted
    map had been asked is gone, and the files in the output set being written."""
    from gpomap import fitted
    from gpomap.cli.common import Run
    from gpomap.tiles import TiledGPOM

    models: list[weakref.ref[Any]] = []
    seen: list[tuple[bool, list[str]]] = []
    fitted_map, grid_later = TiledGPOM.map_, fitted.FittedMap.grid_later

    def asked(self: Any) -> Any:
        models.append(weakref.ref(self))
        return fitted_map.fget(self)

    def watched(self: Any, resolution: float, extent: Any = None) -> Any:
        later = grid_later(self, resolution, extent)

        def make() -> Any:
            staging = Run.sets[-1].path if Run.sets else None  # the set being written; gone once in place
            staged = sorted(p.name for p in staging.iterdir()) if staging is not None and staging.is_dir() else []
            seen.append((all(m() is None for m in models), staged))
            return later()

        return fitted.LaterGrid(later.grid, make)

    monkeypatch.setattr(TiledGPOM, "map_", property(asked))
    monkeypatch.setattr(fitted.FittedMap, "grid_later", watched)
    return seen


def expected_files(occupancy_map: Any, directory: Path, title: str) -> dict[str, bytes]:
    """The files of `occupancy_map` written directly, as gpomap map's options write them."""
    directory.mkdir(parents=True)
    return {f.name: f.read_bytes() for f in write_map_files(occupancy_map, directory, title=title)}


def same_files(got: dict[str, bytes], expected: dict[str, bytes]) -> None:
    """The same four files: yaml, pgm and png to the byte, the npz's arrays to the bit (its info
    holds timings)."""
    assert sorted(got) == sorted(expected) == ["map.npz", "map.pgm", "map.png", "map.yaml"]
    for name in ("map.yaml", "map.pgm", "map.png"):
        assert got[name] == expected[name], name
    with np.load(io.BytesIO(got["map.npz"])) as a, np.load(io.BytesIO(expected["map.npz"])) as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            if key != "info":
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def in_directory(out: Path, files: dict[str, bytes]) -> None:
    """The set written is the one in place in `out`."""
    for name, data in files.items():
        assert (out / name).read_bytes() == data, name


def test_map_writes_through_the_shared_path(mapped_run, tmp_path):
    # The module's run of gpomap map, its writes recorded as the other commands' are below.
    out, writes = mapped_run
    [(caller, files)] = writes
    assert caller == SHARED_PATH
    expected = gpomap.load_map(out / "map.gpom").grid(0.25)
    same_files(files, expected_files(expected, tmp_path / "expected", f"gpomap: {INTEL.name}"))
    in_directory(out, files)


@pytest.mark.parametrize("resolution", [0.25, 0.1])
def test_render_writes_through_the_shared_path_and_lets_the_model_go_first(mapped, tmp_path, writes, put_together, resolution):
    out = tmp_path / "render"
    assert main(["render", str(mapped / "map.gpom"), "-o", str(out), "--resolution", str(resolution), "-q"]) == 0
    [(caller, files)] = writes
    assert caller == SHARED_PATH
    # The loaded map was gone when its grid was put together; render writes no map file.
    assert put_together == [(True, [])]
    expected = gpomap.load_map(mapped / "map.gpom").grid(resolution)
    same_files(files, expected_files(expected, tmp_path / "expected", f"gpomap: map.gpom at {resolution:g} m"))
    in_directory(out, files)
    if resolution == 0.25:  # gpomap map's own cells: its own files but for map.png's title
        for name in ("map.yaml", "map.pgm"):
            assert files[name] == (mapped / name).read_bytes()


@pytest.mark.parametrize("relearn", [False, True])
def test_update_writes_through_the_shared_path_and_lets_the_model_go_first(mapped, tmp_path, writes, put_together, relearn):
    from gpomap.apps.update import unfitted_like
    from gpomap.io import read_scans
    from gpomap.scans import select_scans

    out = tmp_path / "update"
    tail = ["--relearn"] if relearn else []
    assert (
        main(
            [
                "update",
                str(mapped / "map.gpom"),
                str(INTEL),
                "--range",
                "30:40",
                "--resolution",
                "0.25",
                "-o",
                str(out),
                *READ,
                *tail,
            ]
        )
        == 0
    )
    [(caller, files)] = writes
    assert caller == SHARED_PATH
    # Every model of the run (the loaded one, and with --relearn the one fitted again) was gone
    # when the grid was put together, its map file written already.
    assert put_together == [(True, ["map.gpom"])]
    new = select_scans(read_scans(INTEL)[30:40], None, 45)
    model = gpomap.load_map(mapped / "map.gpom")
    if relearn:
        model = unfitted_like(model).fit(list(model._scans) + new)
    else:
        model.update(new)
    title = f"gpomap: map.gpom + {INTEL.name}"
    same_files(files, expected_files(model.grid(0.25), tmp_path / "expected", title))
    in_directory(out, files)
    updated = gpomap.load_map(out / "map.gpom")
    assert updated._n_scans == 40 and updated.hyperparameters_ == model.hyperparameters_


def test_stream_writes_each_map_through_the_shared_path(tmp_path, writes):
    from gpomap.cli import build_parser
    from gpomap.cli.common import load_scans
    from gpomap.cli.options import resolve_library_defaults
    from gpomap.cli.stream import mapper_from_args

    out = tmp_path / "live"
    line = ["stream", str(INTEL), "--range", "0:11", "--warmup", "10", "--rate", "0", "--every", "0", "--resolution", "0.5"]
    assert main([*line, "-o", str(out), *FAST]) == 0
    # After each scan once warmed up (10, 11), and the map of all 11 fitted again at the end.
    assert len(writes) == 3 and all(caller == SHARED_PATH for caller, _ in writes)
    # The same replay, each map the streaming mapper's grid written directly.
    args = build_parser().parse_args([*line, "-o", str(out), *FAST])
    resolve_library_defaults(args)
    scans = load_scans(args)
    mapper = mapper_from_args(args)
    grids = []
    for n, scan in enumerate(scans, 1):
        mapper.add_scan(scan)
        if mapper.ready_:
            grids.append((n, mapper.grid(0.5)))
    mapper.relearn()
    grids.append((len(scans), mapper.model_.grid(0.5)))
    assert [n for n, _ in grids] == [10, 11, 11]
    for i, ((n, grid), (_, files)) in enumerate(zip(grids, writes, strict=True)):
        title = f"gpomap stream: {INTEL.name} ({n} of {len(scans)} scans)"
        same_files(files, expected_files(grid, tmp_path / f"expected-{i}", title))
    in_directory(out, writes[-1][1])


def test_convert_writes_through_the_shared_path(mapped, tmp_path, writes, monkeypatch):
    import gpomap.convert

    converted = []
    convert_grid = gpomap.convert.convert_grid

    def kept(*args: Any, **kwargs: Any) -> Any:
        converted.append(convert_grid(*args, **kwargs))
        return converted[-1]

    monkeypatch.setattr(gpomap.convert, "convert_grid", kept)
    out = tmp_path / "converted"
    assert main(["convert", str(mapped / "map.npz"), "-o", str(out), "--resolution", "0.5", "-q"]) == 0
    [(caller, files)] = writes
    assert caller == SHARED_PATH
    [result] = converted
    same_files(files, expected_files(result.map, tmp_path / "expected", "gpomap convert: map.npz"))
    in_directory(out, files)
