"""The gpomap command: outputs, summaries, exit codes and error messages.

Most commands run through ``gpomap.cli.main`` in this process (the same parser, commands and
exit codes; a subprocess each only adds the interpreter's start-up and the imports). The entry
point itself, ``python -m gpomap.cli``, runs as a subprocess in test_help_everywhere and
test_debug_shows_the_traceback (and, with signals, in test_outputs_atomic and test_stream_cli).
"""

import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gpomap.cli import main

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
INTEL = DATA / "intel" / "intel-corrected.log.gz"
TB3 = DATA / "turtlebot3-world-map" / "map.yaml"


def gpomap(*args, cwd=None):
    """``python -m gpomap.cli ARGS`` as a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "gpomap.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600
    )


@pytest.fixture
def run(capsys):
    """``gpomap ARGS`` through main() in this process: returncode, stdout and stderr, as from gpomap()."""

    def call(*args):
        capsys.readouterr()
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse's usage errors and --help
            code = exc.code
        out, err = capsys.readouterr()
        return SimpleNamespace(returncode=code, stdout=out, stderr=err)

    return call


def test_help_everywhere(capsys):
    top = gpomap("--help")
    assert top.returncode == 0 and "map" in top.stdout and "demo" in top.stdout
    # Each command's help through the same main() in this process (a subprocess each only adds imports).
    capsys.readouterr()
    for cmd in ["map", "demo", "info", "evaluate", "convert", "benchmark"]:
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0, cmd
        assert "example" in capsys.readouterr().out, cmd


def test_demo_writes_every_output(tmp_path, run):
    # One worker: the tiles in this process (a pool's start-up is test_tiles').
    r = run("demo", "-o", tmp_path / "out", "--kernel", "se", "--workers", "1")
    assert r.returncode == 0, r.stderr
    for name in ["map.yaml", "map.pgm", "map.npz", "map.png", "cells.png", "map.gpom"]:
        assert (tmp_path / "out" / name).stat().st_size > 0, name
    assert "cells" in r.stdout and "hyperparams" in r.stdout and "timings" in r.stdout
    from gpomap.io.npz import load_map
    from gpomap.io.rosmap import read_rosmap

    m = load_map(tmp_path / "out" / "map.npz")
    assert m.grid.shape == (36, 44) and m.grid.resolution == 0.5
    # All four walls of the 20 x 16 m room, those on the data's box too: most of their cells occupied.
    t = np.linspace(1.0, 15.0, 29)
    for wall in (
        np.c_[np.zeros_like(t), t],
        np.c_[np.full_like(t, 20.0), t],
        np.c_[t, np.zeros_like(t)],
        np.c_[t, np.full_like(t, 16.0)],
    ):
        rows, cols, inside = m.grid.index_of(wall)
        assert inside.all() and np.mean(m.ternary[rows, cols] == 1) > 0.6, wall[0]
    ros = read_rosmap(tmp_path / "out" / "map.yaml")
    np.testing.assert_array_equal(ros.occupied, m.ternary == 1)
    # The fitted map kept beside them writes the same grid again (what gpomap render does).
    import gpomap

    again = gpomap.load_map(tmp_path / "out" / "map.gpom").grid(m.grid.resolution, m.grid.extent)
    assert again.grid == m.grid
    np.testing.assert_array_equal(again.probability, m.probability)


@pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
def test_map_and_info_on_a_real_log(tmp_path, run):
    info = run("info", INTEL, "--json")
    assert info.returncode == 0, info.stderr
    d = json.loads(info.stdout)
    assert d["format"] == "carmen" and d["n_scans"] == 910
    r = run(
        "map",
        INTEL,
        "-o",
        tmp_path,
        "--workers",
        "1",
        "--range",
        "0:120",
        "--scans",
        "30",
        "--beams",
        "45",
        "--kernel",
        "se",
        "--resolution",
        "0.5",
        "--no-return-cap",
        "5",
        # Hardly a cell occupied: a written map the fit warns about.
        "--thresholds",
        "0.3,0.999",
    )
    assert r.returncode == 0, r.stderr
    assert "scans        30" in r.stdout
    # The ray counts' weights, and the prior surprise rate (not asked to fit it).
    assert "ray counts   against a miss in open space, a hit weighs" in r.stdout and "surprise rate 0.01\n" in r.stdout
    assert re.search(r"a miss beside a hit [0-9.e-]+, a near miss", r.stdout)
    assert (tmp_path / "map.pgm").read_bytes().startswith(b"P5")
    # The fit's warnings, those about the written grid among them (taken before the grid is let
    # go to save map.gpom), each once on stderr.
    from gpomap.diagnostics import fit_warnings
    from gpomap.io.mapfile import load_fitted_map
    from gpomap.io.npz import load_map

    expected = fit_warnings(load_fitted_map(tmp_path / "map.gpom"), load_map(tmp_path / "map.npz"))
    assert any("the map is almost all free" in m for m in expected)
    assert [line for line in r.stderr.splitlines() if line.startswith("warning: ")] == [f"warning: {m}" for m in expected]


@pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
def test_map_says_how_it_recalibrated_for_a_later_visit_and_skips_it_when_asked(tmp_path, run):
    # 110 scans: enough for a held-out stretch of the log to be a visit of its own.
    args = ("map", INTEL, "--workers", "1", "--range", "0:110", "--beams", "45", "--kernel", "se", "--resolution", "0.5")
    r = run(*args, "-o", tmp_path / "a")
    assert r.returncode == 0, r.stderr
    pattern = r"later visit  log-odds times [0-9.]+, [+-][0-9.e-]+ away from 1/2 \(fitted on a held-out stretch, \d+ points\)"
    assert re.search(pattern, r.stdout), r.stdout
    # The ternary thresholds hold on the recalibrated probabilities, with the recalibration or without.
    assert "ternary      free below 0.196, occupied above 0.500" in r.stdout
    r = run(*args, "--no-revisit", "-o", tmp_path / "b")
    assert r.returncode == 0, r.stderr
    assert "later visit" not in r.stdout and "ternary      free below 0.196, occupied above 0.500" in r.stdout


def test_bad_input_is_one_clear_line(tmp_path, run):
    missing = run("map", tmp_path / "nope.log", "-o", tmp_path / "out")
    assert missing.returncode == 1
    last = missing.stderr.strip().splitlines()[-1]
    assert last.startswith("gpomap: error:") and "nope.log" in last
    assert "Traceback" not in missing.stderr
    assert not (tmp_path / "out").exists()

    log = tmp_path / "bad.log"
    log.write_text("FLASER 3 1.0 2.0 x 0 0 0 0 0 0 1.0 host 1.0\n")
    bad = run("map", log, "-o", tmp_path / "out2")
    assert bad.returncode == 1
    assert "bad.log, line 1: non-numeric field" in bad.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "out2" / "map.yaml").exists()

    usage = run("map", log, "-o", tmp_path, "--extent", "1,0,0,1")
    assert usage.returncode == 2 and "XMIN<XMAX" in usage.stderr


def test_debug_shows_the_traceback(tmp_path):
    r = gpomap("--debug", "info", tmp_path / "nope.log")
    assert r.returncode != 0 and "Traceback" in r.stderr
    # After the command too.
    r = gpomap("info", tmp_path / "nope.log", "--debug")
    assert r.returncode != 0 and "Traceback" in r.stderr
    assert "Traceback" not in gpomap("info", tmp_path / "nope.log").stderr


def test_a_usage_error_is_the_error_and_where_the_options_are(run):
    r = run("map", "--resolution", "0.05")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert lines == [
        "gpomap map: error: the following arguments are required: input, -o/--output",
        "(run 'gpomap map --help' for the options)",
    ]


def test_evaluate_demo_json(run):
    r = run("evaluate", "--demo", "--method", "ogm", "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    for key in ["auc", "fpr_at_tpr95", "log_loss", "seconds", "n_inputs", "settings"]:
        assert key in d
    assert 0.5 < d["auc"] <= 1.0
    assert run("evaluate", "--method", "msk").returncode == 1


def test_evaluate_figure(run, tmp_path):
    from PIL import Image

    fig = tmp_path / "scores.png"
    r = run("evaluate", "--demo", "--method", "ogm", "--json", "--figure", fig)
    assert r.returncode == 0, r.stderr
    with Image.open(fig) as img:
        assert img.format == "PNG" and img.size[0] > 0
    d = json.loads(r.stdout)
    assert "roc" not in d and "roc" not in d["points"]  # the JSON is the one without --figure

    # Refused before any reading or fitting, the file never written.
    for bad, message in (
        (tmp_path / "scores.pdf", "give a file name ending in .png"),
        (tmp_path / "absent" / "scores.png", f"the directory {tmp_path / 'absent'} does not exist"),
        (tmp_path, "is a directory"),
    ):
        r = run("evaluate", tmp_path / "absent.log", "--figure", bad)
        assert r.returncode == 1 and message in r.stderr and "absent.log" not in r.stderr
    assert not (tmp_path / "scores.pdf").exists()


def test_points_csv_input(tmp_path, run):
    from gpomap.io import write_points
    from gpomap.observations import observations_from_scans
    from gpomap.simulate import paper_room_scans

    write_points(tmp_path / "pts.csv", observations_from_scans(paper_room_scans()[:8], free_step=0.5))
    # Fixed length scale, one worker: the test is about reading labelled points, not learning.
    r = run(
        "map",
        tmp_path / "pts.csv",
        "-o",
        tmp_path / "out",
        "--kernel",
        "se",
        "--resolution",
        "0.5",
        "--length-scale",
        "1",
        "--workers",
        "1",
    )
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out" / "map.npz").exists()
    from gpomap.io.npz import load_map

    m = load_map(tmp_path / "out" / "map.npz")
    assert m.grid.resolution == 0.5 and (m.ternary == 1).any() and (m.ternary == 0).any()


def _tb3_corner(path):
    """A 72 x 72 pixel corner of the TurtleBot3 map (walls, free space and unknown pixels), as map_server files.

    The whole map is converted in-process by test_convert; through the command a corner takes the
    same path in a quarter of the time.
    """
    from gpomap.grid import GridSpec, OccupancyMap
    from gpomap.io.rosmap import read_rosmap, write_rosmap

    whole = read_rosmap(TB3).to_occupancy_map()
    r0, c0, n = 180, 180, 72
    res = whole.grid.resolution
    grid = GridSpec((whole.grid.origin[0] + c0 * res, whole.grid.origin[1] + r0 * res), res, (n, n))
    corner = OccupancyMap(grid, whole.probability[r0 : r0 + n, c0 : c0 + n], thresholds=whole.thresholds)
    return write_rosmap(corner, path)[0]


@pytest.mark.skipif(not TB3.exists(), reason="shared TurtleBot3 map not present")
def test_convert_writes_the_same_outputs(tmp_path, run):
    source = _tb3_corner(tmp_path / "corner.yaml")
    r = run("convert", source, "-o", tmp_path / "out", "--resolution", "0.1")
    assert r.returncode == 0, r.stderr
    assert "agreement" in r.stdout
    from gpomap.io.rosmap import read_rosmap

    out = read_rosmap(tmp_path / "out" / "map.yaml")
    src = read_rosmap(source)
    assert src.occupied.any() and src.free.any() and src.unknown.any()
    assert out.grid.origin == src.grid.origin and out.grid.resolution == 0.1
    assert out.grid.extent == pytest.approx(src.grid.extent)


@pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
def test_map_in_one_go_and_in_chunks(tmp_path, run):
    common = [
        "--range",
        "0:60",
        "--scans",
        "20",
        "--beams",
        "45",
        "--kernel",
        "se",
        "--no-return-cap",
        "5",
        "--tile-size",
        "5",
        "--workers",
        "1",
        # Only the two maps' grids are compared: a coarse written map.
        "--resolution",
        "0.5",
        # Fixed: the tiled hyperparameter search (test_tiles) would take most of the run.
        "--length-scale",
        "1",
    ]
    auto = run("map", INTEL, "-o", tmp_path / "auto", *common)
    assert auto.returncode == 0, auto.stderr
    assert "tiles " in auto.stdout and (tmp_path / "auto" / "map.yaml").exists()

    chunks = run("map", INTEL, "-o", tmp_path / "chunks", "--chunk-scans", "10", *common)
    assert chunks.returncode == 0, chunks.stderr
    assert "scans 0..9:" in chunks.stderr and "scans 10..19:" in chunks.stderr
    from gpomap.io.npz import load_map

    a, b = load_map(tmp_path / "auto" / "map.npz"), load_map(tmp_path / "chunks" / "map.npz")
    assert a.grid == b.grid
    # Both through the one writing path: the same files, the fitted map (map.gpom) among them.
    for r, out in ((auto, "auto"), (chunks, "chunks")):
        wrote = [line.split()[-1] for line in r.stdout.splitlines() if line.startswith("wrote")]
        assert wrote == [str(tmp_path / out / n) for n in ("map.yaml", "map.pgm", "map.npz", "map.png", "map.gpom")]


def test_write_map_lets_a_handed_over_model_go_before_the_grid_is_put_together(tmp_path, monkeypatch):
    """``gpomap map``'s one writing path: the model's files written (map.gpom), the model handed
    over let go, and only then the grid put together, which is the grid ``grid()`` gives."""
    import weakref

    from gpomap import cli, fitted
    from gpomap.cli import map as map_command
    from gpomap.cli.options import resolve_library_defaults
    from gpomap.io.mapfile import load_fitted_map
    from gpomap.io.npz import load_map
    from gpomap.mapping import AreaGPOM
    from gpomap.simulate import paper_room_scans

    model = AreaGPOM(kernel="se", length_scale=0.4, optimise=False, n_workers=1).fit(paper_room_scans()[::2])
    expected, n_cells = model.grid(0.5), model.n_inputs_
    gone = weakref.ref(model)
    seen: list[tuple[bool, list[str]]] = []
    grid_later = fitted.FittedMap.grid_later

    def watched(self, resolution, extent=None):
        later = grid_later(self, resolution, extent)

        def make():
            seen.append((gone() is None, sorted(p.name for p in tmp_path.rglob("map.*"))))
            return later()

        return fitted.LaterGrid(later.grid, make)

    monkeypatch.setattr(fitted.FittedMap, "grid_later", watched)
    args = cli.build_parser().parse_args(["map", "x.log", "-o", str(tmp_path / "out"), "-q", "--resolution", "0.5"])
    resolve_library_defaults(args)
    holder = [model]
    del model
    files, summary, _ = map_command.write_map(args, holder, "title", [map_command.save_model])
    assert holder == [] and seen == [(True, ["map.gpom"])]
    assert [f.name for f in files] == ["map.yaml", "map.pgm", "map.npz", "map.png", "map.gpom"]
    assert all(f.parent == tmp_path / "out" and f.exists() for f in files)
    written = load_map(tmp_path / "out" / "map.npz")
    assert written.grid == expected.grid
    np.testing.assert_array_equal(written.probability, expected.probability)
    np.testing.assert_array_equal(written.ternary, expected.ternary)
    # The saved model is the one fitted: its grid is the same, read back from map.gpom.
    np.testing.assert_array_equal(load_fitted_map(files[-1]).grid(0.5).probability, expected.probability)
    assert summary["n_cells"] == n_cells  # the summary taken before the model was let go


def test_every_help_example_parses():
    # Each example a command's --help prints is a command line the parser takes as it stands.
    import shlex

    from gpomap.cli import build_parser

    parser = build_parser()
    checked = 0
    for action in parser._subparsers._group_actions:
        for name, sub in action.choices.items():
            for line in (sub.epilog or "").splitlines():
                if not line.strip().startswith(f"gpomap {name}"):
                    continue
                words = shlex.split(re.sub(r"\s{2,}\(.*\)\s*$", "", line.strip()))
                try:
                    parser.parse_args(words[1:])
                except SystemExit:
                    pytest.fail(f"--help example of {name} does not parse: {line.strip()}")
                checked += 1
    assert checked >= 10


def test_info_keeps_a_space_after_a_long_key(run):
    r = run("info", DATA / "octomap" / "geb079.bt")
    assert r.returncode == 0, r.stderr
    assert re.search(r"^occupancy_threshold +0\.5$", r.stdout, flags=re.M), r.stdout


def test_numba_compilation_is_timed_apart_from_fitting():
    import numba

    from gpomap.compiled import compile_time

    @numba.njit
    def twice(x):
        return 2.0 * x

    with compile_time() as first:
        assert twice(1.5) == 3.0
    with compile_time() as second:
        assert twice(2.5) == 5.0
    assert first[0] > 0.0 and second[0] == 0.0  # compiled once, on the first call
