"""Every option of every ``gpomap`` subcommand reaches the library, and its default is the config's.

For each subcommand and each of its options, the command line is parsed twice, once with the
base arguments and once with a value other than the default for that option; what the command
hands to the library (the :mod:`gpomap.config` objects, the unfitted models, the readers' and
``evaluate``'s keyword arguments) must differ between the two. An option that is parsed and
then dropped fails here. A few options are used by the command itself (the output directory,
the written grid, the memory limit): they are listed below with the reason, and must at least
be read by the command's code. No model is fitted: a few seconds in all.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import inspect
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from gpomap import cli
from gpomap.cli.benchmark import benchmark_arguments
from gpomap.cli.common import load_scans
from gpomap.cli.convert import convert_options
from gpomap.cli.evaluate import evaluate_arguments, method_options
from gpomap.cli.input_options import cloud_reader_options, reader_options
from gpomap.cli.map import model as map_model
from gpomap.cli.model_options import map_config, tiling_config
from gpomap.cli.options import Default, resolve_library_defaults
from gpomap.cli.render import configure
from gpomap.cli.stream import mapper_from_args
from gpomap.config import PROFILES, MapConfig, MapProfile, TilingConfig
from gpomap.errors import GpomapError
from gpomap.streaming import DEFAULT_TILE_SIZE as STREAM_TILE_SIZE

SRC = Path(__file__).resolve().parents[1] / "src" / "gpomap"

#: The arguments each subcommand is parsed with before one option is changed.
BASE: dict[str, list[str]] = {
    "map": ["map", "x.log", "-o", "out"],
    "demo": ["demo", "-o", "out"],
    "info": ["info", "x.log"],
    "evaluate": ["evaluate", "--demo"],
    "convert": ["convert", "map.yaml", "-o", "out"],
    "benchmark": ["benchmark", "--paper", "-o", "out"],
    "stream": ["stream", "x.log", "-o", "out"],
    "render": ["render", "map.gpom", "-o", "out"],
    "query": ["query", "map.gpom", "points.csv"],
    "update": ["update", "map.gpom", "x.log", "-o", "out"],
}

#: A value other than the default for each option that takes one (choices are picked from the
#: parser, flags are flipped). A new option needs an entry here, and so a check that it reaches.
VALUES: dict[str, str] = {
    "truth": "truth.yaml",
    "output": "elsewhere",
    "max_range": "20",
    "topic": "/scan",
    "fixed_frame": "map",
    "odom_topic": "/odom",
    "time_offset": "0.25",
    "scan_range": "2:9",
    "scans": "5",
    "beams": "9",
    "free_step": "0.37",
    "free_clearance": "0.11",
    "no_return_cap": "7.5",
    "min_cell": "0.25",
    "max_cell": "0.75",
    "length_scale": "0.8",
    "seed": "7",
    "evidence_resolution": "0.07",
    "resolution": "0.3",
    "extent": "0,4,0,3",
    "thresholds": "0.2,0.8",
    "memory_limit": "3",
    "max_cells": "1234",
    "tile_size": "6.5",
    "workers": "3",
    "threads": "2",
    "scheduler": "tcp://127.0.0.1:8786",
    "scheduler_timeout": "9",
    "chunk_scans": "10",
    "z_range": "0,2",
    "slices": "0.5,1",
    "poses": "poses.txt",
    "stride": "2",
    "depth_scale": "5000",
    "split": "blocks",
    "grid_resolution": "0.1",
    "scan_step": "2",
    "test_points": "500",
    "methods": "msk,ogm",
    "experiments": "synthetic",
    "rate": "2",
    "every": "3",
    "warmup": "12",
    "max_refits": "4",
    "timed_runs": "2",
    "figure": "scores.png",
    "save_state": "state.gpom",
    "resume": "state.gpom",
    "answers": "answers.npz",
    "occupied_fraction": "0.5",
    "pooling_factor": "3",
}

#: Options the command uses itself, not handed to the library as a setting: why, by dest.
COMMAND_OWN: dict[str, str] = {
    "output": "the output directory (checked, staged and written by gpomap.io.atomic)",
    "quiet": "progress messages",
    "json": "the report's format",
    "demo": "evaluate: the input (the built-in room instead of a file)",
    "compare": "evaluate: gpomap beside the standard grids (gpomap.comparison.compare) instead of one method",
    "truth": "evaluate: the true map scored against (Truth.from_rosmap), read before the log",
    "figure": "evaluate: the ROC curves and reliability diagrams drawn (gpomap.plot.plot_evaluation)",
    "paper": "benchmark: which benchmark",
    "chunk_scans": "map: the incremental loop (_map_in_chunks)",
    "resolution": "the written grid's cell side (model.grid)",
    "extent": "the written grid's region (model.grid)",
    "pgm_mode": "the written image (write_map_files)",
    "memory_limit": "the memory checks before any work",
    "z_range": "the written voxel map's heights",
    "slices": "the heights of map-slices.png (write_voxel_outputs)",
    "rate": "stream: the replay's pace (replay)",
    "every": "stream: how often the map is written (replay)",
    "debug": "tracebacks on errors (main)",
    "save_state": "stream: where the mapper's state is saved (gpomap.io.mapfile.save_streaming_state)",
    "resume": "stream: the saved state the replay goes on from (resumed_mapper)",
    "relearn": "update: everything fitted again instead of the scans absorbed (cmd_update)",
    "answers": "query: the file the answers are written to (cmd_query)",
    "values": "convert: how a grid's pixel values are read (convert_grid's values, beside the model options)",
}


@functools.cache
def _parser() -> argparse.ArgumentParser:
    """One parser for every parse here: argparse leaves a parser as it was (and the defaults are
    only read), and building it took most of this file's time, hundreds of times over."""
    return cli.build_parser()


def _parse(argv: list[str]) -> argparse.Namespace:
    args = _parser().parse_args(argv)
    resolve_library_defaults(args)
    return args


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _options(command: str) -> list[argparse.Action]:
    return [a for a in _subparsers()[command]._actions if a.option_strings and a.dest != "help"]


def _changed_argv(command: str, action: argparse.Action) -> list[str]:
    """The base arguments of `command` with `action` set to a value other than its default."""
    flag = action.option_strings[-1] if action.option_strings[-1].startswith("--") else action.option_strings[0]
    argv = list(BASE[command])
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        return argv if flag in argv else [*argv, flag]
    default = _parse(BASE[command]).__dict__.get(action.dest)
    if action.choices is not None:
        value = next(str(c) for c in action.choices if c != default and not (c == "none" and default is None))
    else:
        assert action.dest in VALUES, f"{command} {flag}: no test value in VALUES; add one, and see that it reaches"
        value = VALUES[action.dest]
    return [*argv, flag, value]


def _snapshot(value: Any) -> Any:
    """`value` as plain data: estimators by their parameters, other objects by their public attributes."""
    if isinstance(value, dict):
        return {str(k): _snapshot(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_snapshot(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _snapshot(dataclasses.asdict(value))
    if hasattr(value, "get_params"):
        return _snapshot(value.get_params())
    if hasattr(value, "__dict__") and not callable(value):
        return _snapshot({k: v for k, v in vars(value).items() if not k.startswith("_")})
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


@pytest.fixture
def fake_inputs(monkeypatch):
    """A scan reader that returns the paper's room (31 scans of 36 beams), whatever the path."""
    import gpomap.io
    from gpomap.simulate import paper_room_scans

    scans = paper_room_scans()
    monkeypatch.setattr(gpomap.io, "read_scans", lambda path, **options: list(scans))


def _reader_snapshot(args: argparse.Namespace, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """The keyword arguments each reader would get for `args`, by input format."""
    import gpomap.io

    out: dict[str, Any] = {}
    for fmt in ("carmen", "rosbag1"):
        monkeypatch.setattr(gpomap.io, "detect_format", lambda path, fmt=fmt: fmt)
        out[fmt] = reader_options(args, "input")
    if hasattr(args, "poses"):  # the 3-D readers of gpomap map
        for fmt in ("pcd", "depth-directory", "rosbag1"):
            monkeypatch.setattr(gpomap.io, "detect_format", lambda path, fmt=fmt: fmt)
            try:
                out["3d-" + fmt] = cloud_reader_options(args)
            except GpomapError as exc:  # an option that format refuses (by name), e.g. --stride on a PCD
                out["3d-" + fmt] = str(exc)
    return out


def _handed_to_library(command: str, args: argparse.Namespace, monkeypatch: pytest.MonkeyPatch) -> Any:
    """What `command` gives the library for `args` (unfitted models, keyword arguments), as plain data."""
    if command == "map":
        args.input = "input.log"
        return {
            "config": map_config(args),
            "tiling": tiling_config(args),
            "model": map_model(args),
            "readers": _reader_snapshot(args, monkeypatch),
            "scans": [(s.n_beams, s.time) for s in load_scans(args)],
        }
    if command == "demo":
        return {"config": map_config(args), "tiling": tiling_config(args), "model": map_model(args)}
    if command == "info":
        return _reader_snapshot(args, monkeypatch)
    if command == "evaluate":
        return {
            "arguments": evaluate_arguments(args),
            "model": _evaluated_model(args),
            "readers": _reader_snapshot(args, monkeypatch),
        }
    if command == "convert":
        return {"options": convert_options(args), "max_cells": args.max_cells}
    if command == "benchmark":
        return benchmark_arguments(args)
    if command == "stream":
        args.input = "input.log"
        return {
            "mapper": mapper_from_args(args),
            "readers": _reader_snapshot(args, monkeypatch),
            "scans": [(s.n_beams, s.time) for s in load_scans(args)],
        }
    if command in ("render", "query", "update"):
        # A saved map, loaded: the command's settings put on it (gpomap.cli.render.configure).
        from gpomap.mapping import AreaGPOM

        model = AreaGPOM()
        configure(args, model)
        if command != "update":
            return {"model": model}
        args.input = "input.log"
        return {
            "model": model,
            "readers": _reader_snapshot(args, monkeypatch),
            "scans": [(s.n_beams, s.time) for s in load_scans(args)],
        }
    raise AssertionError(f"no check for gpomap {command}: add one to _handed_to_library")


def _evaluated_model(args: argparse.Namespace) -> Any:
    """The unfitted model ``gpomap evaluate`` scores."""
    from gpomap.evaluation import make_model

    a = evaluate_arguments(args)
    return make_model(a["method"], a["kernel"], a["seed"], a["resolution"], a["n_workers"], **method_options(args))


def _evaluate_methods() -> list[str]:
    from gpomap.evaluation import METHODS

    return list(METHODS)


def _read_by_the_command(dest: str) -> bool:
    """Whether the command code (gpomap.cli, gpomap.apps) reads ``args.<dest>`` outside its parser."""
    pattern = re.compile(rf"args\.{dest}\b|getattr\(args, \"{dest}\"")
    return any(pattern.search(p.read_text()) for p in [*(SRC / "cli").glob("*.py"), *(SRC / "apps").glob("*.py")])


def test_every_subcommand_is_checked():
    assert set(_subparsers()) == set(BASE)


@pytest.mark.parametrize("command", sorted(BASE))
def test_every_option_reaches_the_library(command, fake_inputs, monkeypatch):
    """An option set to another value changes what the library gets, or is refused by --method, or
    is the command's own (COMMAND_OWN) and read by its code."""
    dropped, unread = [], []
    bases: dict[str | None, Any] = {}  # what the base arguments hand over, per method: the same each time
    for action in _options(command):
        argv = _changed_argv(command, action)
        methods = _evaluate_methods() if command == "evaluate" and action.dest != "method" else [None]
        for method in methods:
            extra = [] if method is None else ["--method", method]
            if method not in bases:
                bases[method] = _snapshot(_handed_to_library(command, _parse(BASE[command] + extra), monkeypatch))
            base = bases[method]
            try:
                changed = _snapshot(_handed_to_library(command, _parse(argv + extra), monkeypatch))
            except GpomapError as exc:
                # Refused, the option named, rather than ignored: an option --method does not take.
                assert method is not None and action.option_strings[-1] in str(exc), (argv, method, exc)
                continue
            if changed != base:
                continue
            if action.dest not in COMMAND_OWN:
                dropped.append(" ".join(argv + extra))
            elif not _read_by_the_command(action.dest):
                unread.append(action.dest)
    assert not unread, f"gpomap {command}: options parsed and never read: {unread}"
    assert not dropped, f"gpomap {command}: options parsed but not handed to the library: {dropped}"


def test_map_resolution_reaches_the_written_grid(monkeypatch):
    """``gpomap map --resolution``: the written grid's cells; left unset, the ray counts' (the config's)."""
    assert _parse(BASE["map"]).resolution == MapConfig().evidence_resolution
    assert _parse([*BASE["map"], "--resolution", "0.3"]).resolution == 0.3
    assert "resolution" in _parse(BASE["map"]).library_defaults  # so cmd_map follows --evidence-resolution


@pytest.mark.parametrize("command", ["map", "demo", "evaluate", "stream"])
def test_defaults_are_the_configs(command):
    """Left unset, the model options give the config's defaults: nothing is re-stated in the parser."""
    args = _parse(BASE[command])
    assert map_config(args) == MapConfig()
    if command == "map":
        assert tiling_config(args) == TilingConfig()
    own = {"tile_size": STREAM_TILE_SIZE} if command == "stream" else {}  # a streaming map's own tiles
    help_text = " ".join(_subparsers()[command].format_help().split())
    for action in _options(command):
        for config in (MapConfig(), TilingConfig()):
            if action.dest in {f.name for f in dataclasses.fields(config)} and action.default is not None:
                assert isinstance(action.default, Default), (command, action.dest)
                assert action.default.value == own.get(action.dest, getattr(config, action.dest)), (command, action.dest)
                if action.nargs == 0:  # a flag's help says what it does instead
                    continue
                if action.default.value is None and action.dest in {f.name for f in dataclasses.fields(MapProfile)}:
                    # Left to the data's profile: the help names each profile's value.
                    said = f"default: {getattr(PROFILES[2], action.dest):g} for scans, {getattr(PROFILES[3], action.dest):g} for point clouds"
                    assert said in help_text, (command, action.dest)
                else:
                    assert f"default: {action.default}" in help_text, (command, action.dest)


def test_library_signatures_are_the_configs():
    """The options' configs are the library's signatures, declared once: MapSettings' fields are
    MapConfig's, AreaGPOM's signature is EstimatorConfig's (MapConfig's fields, then TilingConfig's),
    derived rather than written out (tests/test_estimator_params.py), and TiledGPOM's is
    TiledConfig's (TilingConfig's fields, then MapConfig's), derived the same way."""
    from gpomap.config import EstimatorConfig, TiledConfig
    from gpomap.mapping import AreaGPOM
    from gpomap.settings import MapSettings
    from gpomap.tiles import TiledGPOM

    assert inspect.signature(MapSettings) == inspect.signature(MapConfig)
    assert inspect.signature(AreaGPOM) == inspect.signature(EstimatorConfig, eval_str=True)
    assert {n: p.default for n, p in inspect.signature(AreaGPOM).parameters.items()} == {
        **MapConfig().kwargs(),
        **TilingConfig().kwargs(),
        "n_workers": 1,  # the estimator runs its tiles in this process unless told (as scikit-learn's n_jobs)
    }
    assert inspect.signature(TiledGPOM) == inspect.signature(TiledConfig, eval_str=True)
    tiled = inspect.signature(TiledGPOM).parameters
    assert {n: p.default for n, p in tiled.items()} == {**TilingConfig().kwargs(), **MapConfig().kwargs()}


def test_importing_the_config_stays_light():
    import subprocess
    import sys

    probe = "import sys, gpomap.config; print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy'))"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


@pytest.mark.parametrize(
    ("method", "option", "value", "attribute"),
    [
        ("gpomik", "--no-return-cap", "7.5", ("no_return_cap", 7.5)),
        ("gpomik", "--normalisation", "sum", ("normalisation", "sum")),
        ("gpomik", "--length-scale", "0.8", ("length_scale", 0.8)),
        ("gpom", "--no-return-cap", "7.5", ("no_return_cap", 7.5)),
        ("gpom", "--length-scale", "0.8", ("length_scale", 0.8)),
        ("msk", "--normalisation", "sum", ("normalisation", "sum")),
        ("msk", "--no-return-cap", "7.5", ("no_return_cap", 7.5)),
        ("ogm", "--no-return-cap", "7.5", ("max_range_free", 7.5)),
    ],
)
def test_evaluate_hands_the_model_options_to_each_method(method, option, value, attribute):
    """The options ``gpomap evaluate`` used to drop for the baselines reach their constructors."""
    model = _evaluated_model(_parse(["evaluate", "--demo", "--method", method, option, value]))
    name, expected = attribute
    assert getattr(model, name) == expected
    if option == "--length-scale":
        assert model.optimise is False  # fixed, as for MSK-GPOM


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--method", "gpomik", "--free-clearance", "0.1"], "--free-clearance: not an option of --method gpomik"),
        (["--method", "gpom", "--normalisation", "sum"], "--normalisation: not an option of --method gpom"),
        (["--method", "ogm", "--kernel", "se"], "--kernel: not an option of --method ogm"),
        (["--method", "msk", "--resolution", "0.2"], "--resolution is for --method ogm"),
        (["--method", "ogm", "--grid-resolution", "0.1"], "--grid-resolution is for --method msk"),
        (["--method", "gpom", "--workers", "2"], "--workers is for --method msk"),
    ],
)
def test_evaluate_refuses_what_a_method_would_ignore(argv, message, capsys, monkeypatch):
    import functools

    import gpomap.evaluation

    @functools.wraps(gpomap.evaluation.evaluate)  # the same signature, whose defaults are the options'
    def evaluate(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("evaluate ran: the option was not refused")

    monkeypatch.setattr(gpomap.evaluation, "evaluate", evaluate)
    code = cli.main(["evaluate", "--demo", "-q", *argv])
    assert code == cli.EXIT_ERROR
    assert message in capsys.readouterr().err
