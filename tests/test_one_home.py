"""One home for each model default: a parameter named as a field of :class:`gpomap.config.MapConfig`
whose default is the config's takes it from there, never from the literal written again in another
signature. (A part's own default that differs, say a lone GP's constant noise model, is its own.)"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from gpomap.config import MapConfig

SRC = Path(__file__).resolve().parents[1] / "src" / "gpomap"

#: Modules whose signatures may state these names with their own values: the config itself, and
#: the paper's baselines, another method with defaults of its own.
OWN_DEFAULTS: frozenset[str] = frozenset({"config.py", "baselines/gpom.py", "baselines/gpomik.py"})

#: A random seed is every sampler's argument, not a setting of the map alone.
FIELDS = frozenset(f.name for f in dataclasses.fields(MapConfig)) - {"seed"}
DEFAULTS = MapConfig()


def literal_defaults(source: str) -> list[tuple[int, str, object]]:
    """(line, parameter, value) of every parameter named as a MapConfig field whose default is the
    config's, written as a literal (of the same type: a flag named ``variance`` is not the variance)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        args = node.args
        positional = [*args.posonlyargs, *args.args]
        pairs = list(zip(positional[len(positional) - len(args.defaults) :], args.defaults, strict=True))
        pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is not None]
        for arg, default in pairs:
            if arg.arg not in FIELDS or not isinstance(default, ast.Constant) or default.value is None:
                continue
            config = getattr(DEFAULTS, arg.arg)
            if type(default.value) is type(config) and default.value == config:
                found.append((default.lineno, arg.arg, default.value))
    return found


def test_the_check_finds_a_literal_default() -> None:
    source = (
        "def f(x, free_step: float = 0.2, *, noise=MapConfig.noise, kernel='matern32', area=None, variance=True):\n    pass\n"
    )
    assert literal_defaults(source) == [(1, "free_step", 0.2), (1, "kernel", "matern32")]
    assert literal_defaults("def g(free_step=0.1, kernel='se'):\n    pass\n") == []  # defaults of its own


@pytest.mark.parametrize("path", sorted(p.relative_to(SRC).as_posix() for p in SRC.rglob("*.py")))
def test_no_model_default_is_written_twice(path: str) -> None:
    if path in OWN_DEFAULTS:
        pytest.skip("defaults of its own")
    found = literal_defaults((SRC / path).read_text(encoding="utf-8"))
    assert not found, f"src/gpomap/{path}: " + "; ".join(
        f"line {line}: {name} = {value!r} (use MapConfig.{name})" for line, name, value in found
    )


#: Tables by dimension that are how the code computes, not defaults of the map (a traversal's
#: subdivisions, the axes a local prediction sorts on).
COMPUTATIONAL_TABLES: frozenset[str] = frozenset({"CLEARANCE_SUBDIVISIONS", "LOCAL_AXES"})


def dimension_tables(source: str) -> list[tuple[int, str]]:
    """(line, name) of every module-level table written as a literal keyed by the dimensions 2 and 3."""
    found = []
    for node in ast.parse(source).body:
        target, value = (node.target, node.value) if isinstance(node, ast.AnnAssign) else (None, None)
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target, value = node.targets[0], node.value
        if not isinstance(target, ast.Name) or not isinstance(value, ast.Dict):
            continue
        keys = {k.value for k in value.keys if isinstance(k, ast.Constant)}
        if keys == {2, 3} and target.id not in COMPUTATIONAL_TABLES:
            found.append((node.lineno, target.id))
    return found


def test_the_check_finds_a_table_by_dimension() -> None:
    source = "A: dict[int, float] = {2: 5.0, 3: 3.0}\nB = {2: True, 3: False}\nC = {d: p for d, p in X.items()}\nD = {1: 2}\n"
    assert dimension_tables(source) == [(1, "A"), (2, "B")]


@pytest.mark.parametrize("path", sorted(p.relative_to(SRC).as_posix() for p in SRC.rglob("*.py")))
def test_every_default_by_dimension_lives_in_the_profiles(path: str) -> None:
    """What differs between planar and voxel maps is written once, in :data:`gpomap.config.PROFILES`;
    a stage's table by dimension is read from it."""
    if path == "config.py":
        return
    found = dimension_tables((SRC / path).read_text(encoding="utf-8"))
    assert not found, f"src/gpomap/{path}: " + "; ".join(
        f"line {line}: {name} (a field of config.MapProfile)" for line, name in found
    )
