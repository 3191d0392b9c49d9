"""Checks before work: options, the output directory and the memory a run needs, refused up front."""

import math
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from gpomap import cli, resources
from gpomap.cli.map import model as map_model
from gpomap.cli.model_options import tiling_config
from gpomap.cli.options import non_negative, number, positive, resolve_library_defaults
from gpomap.errors import GpomapError
from gpomap.resources import MemoryLimitError

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
INTEL = DATA / "intel" / "intel-corrected.log.gz"


def run_main(argv, capsys):
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- options
@pytest.mark.parametrize(
    "option, value",
    [
        ("--resolution", "nan"),
        ("--resolution", "inf"),
        ("--resolution", "0"),
        ("--resolution", "-1"),
        ("--free-step", "nan"),
        ("--tile-size", "inf"),
        ("--extent", "0,nan,0,1"),
        ("--extent", "-inf,1,0,1"),
        ("--thresholds", "nan,0.6"),
        ("--memory-limit", "nan"),
        ("--no-return-cap", "-1"),
        ("--free-clearance", "inf"),
        ("--time-offset", "nan"),
        ("--threads", "0"),
    ],
)
def test_bad_numbers_are_usage_errors_before_anything_is_read(tmp_path, capsys, option, value):
    code, _, err = run_main(["map", tmp_path / "does-not-exist.log", "-o", tmp_path / "out", f"{option}={value}"], capsys)
    assert code == 2
    assert (option in err and "expected" in err) or "must" in err
    assert "does-not-exist" not in err  # the input was never opened
    assert not (tmp_path / "out").exists()


def test_threads_reach_the_tile_workers():
    args = cli.build_parser().parse_args(["map", "x.log", "-o", "out", "--threads", "3", "--workers", "2"])
    resolve_library_defaults(args)
    model = map_model(args)
    assert (model.blas_threads, model.n_workers) == (3, 2)
    assert tiling_config(args).kwargs()["blas_threads"] == 3
    args = cli.build_parser().parse_args(["map", "x.log", "-o", "out"])
    resolve_library_defaults(args)
    assert map_model(args).blas_threads is None  # the cores divided by the workers


def test_number_type_edges():
    positive_float, non_negative_float = positive(float), non_negative(float)
    assert positive_float("1e-9") == 1e-9 and non_negative_float("0") == 0.0 and number(float)("-3") == -3.0
    for parse, text in [
        (positive_float, "0"),
        (non_negative_float, "-0.1"),
        (positive_float, "nan"),
        (number(float), "inf"),
        (positive(int), "1.5"),
    ]:
        with pytest.raises(Exception, match="expected"):
            parse(text)


def test_output_directory_checked_before_reading(tmp_path, capsys):
    missing_input = tmp_path / "nope.log"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    code, _, err = run_main(["map", missing_input, "-o", a_file], capsys)
    assert code == 1 and f"-o {a_file}: exists and is not a directory" in err and "nope.log" not in err
    code, _, err = run_main(["demo", "-o", a_file / "sub"], capsys)
    assert code == 1 and f"cannot be created, {a_file} is not a directory" in err
    code, _, err = run_main(["convert", missing_input, "-o", a_file], capsys)
    assert code == 1 and "not a directory" in err
    code, _, err = run_main(["benchmark", "--paper", "-o", a_file], capsys)
    assert code == 1 and "not a directory" in err


def test_unwritable_output_directory(tmp_path, monkeypatch):
    from gpomap.io import atomic

    # os.access is what the check asks (root may write anywhere, so the answer is simulated).
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: Path(path) != tmp_path)
    with pytest.raises(GpomapError, match=f"cannot be created, {tmp_path} is not writable"):
        atomic.check_output_dir(tmp_path / "new" / "deeper")
    (tmp_path / "exists").mkdir()
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: False)
    with pytest.raises(GpomapError, match="directory is not writable"):
        atomic.check_output_dir(tmp_path / "exists")


def test_min_cell_above_max_cell_is_refused_before_reading(tmp_path, capsys):
    code, _, err = run_main(["map", tmp_path / "nope.log", "-o", tmp_path / "o", "--min-cell", "2", "--max-cell", "1"], capsys)
    assert code == 1 and "--min-cell (2.0) must not exceed --max-cell (1.0)" in err


# --------------------------------------------------------------------------- memory
def test_grid_shape_matches_gridspec():
    from gpomap.grid import GridSpec

    for extent, res in [((0, 10, 0, 5), 0.1), ((-3.2, 1.1, 2, 2.05), 0.5), ((0, 1, 0, 1), 3.0)]:
        assert resources.grid_shape(extent, res) == GridSpec.from_extent(extent, res).shape
    assert resources.grid_shape((0, 1e9, 0, 10), 0.1) == (100, 10_000_000_000)
    with pytest.raises(ValueError, match="finite"):
        resources.grid_shape((0, math.inf, 0, 1), 0.1)


def test_memory_estimates_by_hand():
    # 100 x 200 cells, no supersampling: one band and every cell drawn, 20,000 x (8+8+1+1+8+8+16 =
    # 50 for the map, 150 for the band, 72 for the figure).
    assert (resources.BYTES_PER_MAP_CELL, resources.BYTES_PER_BAND_CELL, resources.BYTES_PER_FIGURE_CELL) == (50, 150, 72)
    assert resources.grid_memory((100, 200)) == 20_000 * 272
    # K = 2: four samples of 40 bytes per cell; plus one chunk of 4096 queries x 1000 cells x 3 float64 arrays.
    assert resources.grid_memory((100, 200), supersample=2, n_cells=1000) == 20_000 * (272 + 160) + 3 * 4096 * 1000 * 8
    # 6,000 x 6,000 cells (the Freiburg campus log at 0.05 m): 2^20 cells a band, every 3rd row
    # and column drawn (2,000 x 2,000).
    assert resources.grid_memory((6000, 6000)) == 36_000_000 * 50 + 2**20 * 150 + 4_000_000 * 72
    # A map a million cells wide: a band is 8 rows of it, the figure 1 x 2,045 cells (every 489th).
    assert resources.grid_memory((100, 1_000_000)) == 100_000_000 * 50 + 8_000_000 * 150 + 2045 * 72
    # 3,000 cells: 4 matrices of 3000^2 float64 = 288 MB; two workers, twice.
    assert resources.fit_memory(3000) == 288_000_000
    assert resources.fit_memory(3000, n_at_once=2) == 576_000_000


def test_largest_tile_cells_by_hand():
    # Tiles of 10 m from the origin, reach 1 m: a centre at (9.5, 5) is also seen by the tile to its right.
    centres = np.array([[1.0, 1.0], [2.0, 2.0], [9.5, 5.0], [15.0, 5.0]])
    assert resources.largest_tile_cells(centres, 10.0, 1.0) == 3  # tile (0, 0): three centres
    assert resources.largest_tile_cells(centres, 10.0, 0.0) == 3
    assert resources.largest_tile_cells(centres[2:], 10.0, 1.0) == 2  # tile (1, 0) holds both
    assert resources.largest_tile_cells(np.zeros((0, 2)), 10.0, 1.0) == 0


def test_largest_tile_cells_when_the_overlap_spans_several_tiles():
    # 2 m tiles seeing 4.5 m past their square: each centre is seen by up to 5 x 5 tiles. Brute
    # force: every tile's grown square [2 i - 4.5, 2 i + 6.5) x [2 j - 4.5, 2 j + 6.5), counted.
    centres = np.random.default_rng(3).uniform(0.0, 12.0, (300, 2))
    brute = max(
        int(np.sum(np.all((centres >= 2.0 * np.array([i, j]) - 4.5) & (centres < 2.0 * np.array([i, j]) + 6.5), axis=1)))
        for i in range(-4, 8)
        for j in range(-4, 8)
    )
    assert resources.largest_tile_cells(centres, 2.0, 4.5) == brute


def test_check_memory_and_limits(monkeypatch):
    resources.check_memory(10, 10, "x", "y")  # at the limit: fine
    resources.check_memory(10**20, None, "x", "y")  # no limit known: nothing checked
    with pytest.raises(
        MemoryLimitError,
        match=r"a grid would need about 2\.0 GB of memory, more than the limit of 1\.0 GB \(--memory-limit 1\); smaller",
    ):
        resources.check_memory(2 * 10**9, 10**9, "a grid", "smaller", "--memory-limit 1")
    total = resources.total_memory()
    assert total is None or total > 2**26
    assert resources.memory_limit(2.5) == (2_500_000_000, "--memory-limit 2.5")
    monkeypatch.setattr(resources, "total_memory", lambda: 8 * 10**9)
    assert resources.memory_limit(None) == (4 * 10**9, "0.5 of this machine's 8.0 GB")
    assert (
        resources.format_bytes(3.2e6) == "3 MB"
        and resources.format_bytes(2e5) == "200 kB"
        and resources.format_bytes(4.5e14) == "4.5e+05 GB"
    )


@pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
def test_a_pose_at_1e9_m_is_refused_in_seconds(tmp_path):
    import gzip

    lines = []
    with gzip.open(INTEL, "rt") as f:
        for line in f:
            if line.startswith("FLASER"):
                lines.append(line.split())
                if len(lines) == 12:
                    break
    n = int(lines[5][1])
    lines[5][2 + n] = lines[5][5 + n] = "1e9"  # laser and odometry x
    log = tmp_path / "far.log"
    log.write_text("".join(" ".join(f) + "\n" for f in lines))
    r = subprocess.run(
        [sys.executable, "-m", "gpomap.cli", "map", str(log), "-o", str(tmp_path / "out"), "--beams", "30"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 1, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    # 1e9 m at the default 0.05 m cells: 2e10 columns.
    assert last.startswith("gpomap: error: a 20000000")
    for word in ["--resolution", "--extent", "--memory-limit", "GB"]:
        assert word in last
    assert "fitting" not in r.stderr and not (tmp_path / "out").exists()


def test_memory_limit_refuses_a_small_grid_when_set_low(tmp_path, capsys):
    code, _, err = run_main(["demo", "-o", tmp_path / "out", "--resolution", "0.01", "--memory-limit", "0.01"], capsys)
    assert code == 1
    assert "grid" in err and "more than the limit of 10 MB (--memory-limit 0.01)" in err
    assert not (tmp_path / "out").exists()


def test_a_fit_too_large_for_the_memory_limit_is_refused_before_the_hyperparameters(tmp_path, capsys, monkeypatch):
    """The grid passes, the tiles' GPs do not: refused once the cells exist, nothing learnt or written."""
    from gpomap.tiles import TiledGPOM

    def never(self):
        raise AssertionError("hyperparameters learnt past a failed memory check")

    monkeypatch.setattr(TiledGPOM, "_learn_hyperparameters", never)
    # 1 m cells over the 20 x 16 m room: a few kB; the tiles' GPs of hundreds of cells: megabytes.
    argv = ["demo", "-o", tmp_path / "out", "--resolution", "1", "--memory-limit", "0.0002", "--workers", "2"]
    code, _, err = run_main(argv, capsys)
    assert code == 1
    last = err.strip().splitlines()[-1]
    assert "fitting 2 GP(s) of" in last and "more than the limit of 200 kB (--memory-limit 0.0002)" in last
    for word in ["--min-cell", "--tile-size", "--workers", "--memory-limit"]:
        assert word in last
    assert not (tmp_path / "out").exists()


def test_the_fit_checks_its_largest_tile_against_memory_limit():
    """TiledGPOM.check_fit_memory: the largest tile's cells by centre, brute force over the tiles."""
    from gpomap.mapping import AreaGPOM
    from gpomap.simulate import paper_room_scans
    from gpomap.tiles import tile_reach

    scans = paper_room_scans()
    # The SE kernel: the cells are the subject, and its exact area kernel fits them 3x faster than
    # the default Matern 3/2's quadrature.
    model = AreaGPOM(tile_size=4.0, n_workers=3, ray_evidence=False, kernel="se").fit(scans)
    per_tile = model.check_fit_memory(1.0)
    lower, upper, _ = model.cell_boxes()
    centres = 0.5 * (lower + upper)
    reach, (ox, oy), side = tile_reach(4.0, 1.0), model.origin_, 4.0
    brute = 0
    for ix in range(-10, 10):
        for iy in range(-10, 10):
            x0, y0 = ox + ix * side, oy + iy * side
            inside = (
                (centres[:, 0] >= x0 - reach)
                & (centres[:, 0] < x0 + side + reach)
                & (centres[:, 1] >= y0 - reach)
                & (centres[:, 1] < y0 + side + reach)
            )
            brute = max(brute, int(inside.sum()))
    assert per_tile == brute > 0
    need = resources.fit_memory(per_tile, 3)  # three workers fit at once
    model.set_params(memory_limit=0.999 * need / 1e9)
    with pytest.raises(MemoryLimitError, match=f"fitting 3 GP\\(s\\) of {per_tile} cells"):
        model.check_fit_memory(1.0)
    model.set_params(memory_limit=1.001 * need / 1e9)
    assert model.check_fit_memory(1.0) == per_tile


def test_memory_error_is_one_line(tmp_path, capsys, monkeypatch):
    def boom(args):
        raise MemoryError

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_func(parser(), boom))
    code, _, err = run_main(["demo", "-o", tmp_path / "o"], capsys)
    assert code == 1
    assert err.count("\n") == 1 and "out of memory" in err
    for word in ["--resolution", "--extent", "--memory-limit"]:
        assert word in err


def _with_func(parser, func):
    for action in parser._subparsers._group_actions:
        for sub in action.choices.values():
            sub.set_defaults(func=func)
    return parser


# --------------------------------------------------------------------------- warnings, quiet, imports
def test_python_warnings_become_one_line(tmp_path, capsys, monkeypatch):
    def warns(args):
        warnings.warn(f"{tmp_path}/x.bag: dropped 1 of 3 scans\noutside the pose time range", UserWarning, stacklevel=2)
        return 0

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_func(parser(), warns))
    code, _, err = run_main(["info", "x.bag"], capsys)
    assert code == 0
    assert err == f"warning: {tmp_path}/x.bag: dropped 1 of 3 scans outside the pose time range\n"


def test_quiet_sets_the_progress_mode(tmp_path, capsys, monkeypatch):
    from gpomap import progress

    seen = []
    parser = cli.build_parser
    monkeypatch.setattr(
        cli, "build_parser", lambda: _with_func(parser(), lambda a: seen.append(progress.get_progress_mode()) or 0)
    )
    for argv in (["info", "x", "-q"], ["map", "x", "-o", tmp_path, "--quiet"], ["evaluate", "--demo", "-q"], ["info", "x"]):
        run_main(argv, capsys)
    assert seen == ["quiet", "quiet", "quiet", "auto"]
    progress.set_progress_mode("auto")


def test_help_and_info_stay_light():
    probe = textwrap.dedent(
        f"""
        import sys
        from gpomap.cli import main
        for argv in (["--help"], ["info", {str(INTEL)!r}], ["info", "--help"]):
            try:
                main(argv)
            except SystemExit:
                pass
        heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("matplotlib", "dask", "distributed")
                       or m.startswith("scipy.optimize"))
        print("HEAVY", heavy, file=sys.stderr)
        """
    )
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert "HEAVY []" in r.stderr, r.stderr[-2000:]


def test_one_default_kernel():
    from inspect import signature

    from gpomap.mapping import AreaGPOM

    parser = cli.build_parser()
    default = signature(AreaGPOM).parameters["kernel"].default
    for cmd in (["map", "x", "-o", "o"], ["demo", "-o", "o"], ["evaluate", "--demo"]):
        args = parser.parse_args(cmd)
        resolve_library_defaults(args)
        assert args.kernel == default, cmd


def test_help_texts_have_no_doubled_percent():
    parser = cli.build_parser()
    for action in parser._subparsers._group_actions:
        for name, sub in action.choices.items():
            assert "%%" not in sub.format_help(), name
    assert "TPR=95 %" in action.choices["evaluate"].format_help()
