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
#: the paper's baselines and the grid conversion, other methods with defaults of their own.
OWN_DEFAULTS: frozenset[str] = frozenset({"config.py", "baselines/gpom.py", "baselines/gpomik.py", "convert.py", "convert3d.py"})

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
