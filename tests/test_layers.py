"""Layers import one way: the core never reaches up into maps, tiling, file formats, apps or the CLI.

Each module of ``src/gpomap`` belongs to one layer; every ``gpomap`` import it makes (at the top
or inside a function) must name a module of its own layer or a lower one. Readers and writers
(``gpomap.io`` and the figures) sit beside the engine, not on it: they may use the foundation and
the data layer only, so a file format never depends on how maps are fitted.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: Lowest first. A module is matched by its longest listed prefix.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "foundation",
        (
            "gpomap._version",
            "gpomap.errors",
            "gpomap.extras",
            "gpomap.config",
            "gpomap.progress",
            "gpomap.protocol",
            "gpomap.resources",
            "gpomap.clouds",
            "gpomap.scans",
            "gpomap.grid",
            "gpomap.voxels",
            "gpomap.lattice",
            "gpomap.supports",
            "gpomap.squash",
            "gpomap.metrics",
            "gpomap.diagnostics",
            "gpomap.raycast",
            "gpomap.compiled",
            "gpomap.lapack",
        ),
    ),
    (
        "data",
        (
            "gpomap.observations",
            "gpomap.cells",
            "gpomap.evidence",
            "gpomap.heldout",
            "gpomap._compiled_counts",
            "gpomap._compiled_clearance",
            "gpomap._compiled_cells",
            "gpomap.simulate",
        ),
    ),
    ("kernels", ("gpomap.kernels",)),
    ("gp", ("gpomap.gp", "gpomap._compiled_local", "gpomap._compiled_line")),
    (
        "maps",
        ("gpomap.estimator", "gpomap.fusion", "gpomap.extrapolation", "gpomap.revisit", "gpomap.settings", "gpomap.baselines"),
    ),
    ("tiling", ("gpomap.tiles", "gpomap.mapping", "gpomap.streaming")),
    ("io", ("gpomap.io", "gpomap.plot")),
    (
        "apps",
        (
            "gpomap.convert",
            "gpomap.convert3d",
            "gpomap.evaluation",
            "gpomap.truth",
            # The fitted map's file knows the model's classes, so it sits above them.
            "gpomap.io.mapfile",
            "gpomap.simulate3d",
            "gpomap.comparison",
            "gpomap.benchmark",
            "gpomap.ros",
            "gpomap.ros2",
        ),
    ),
    # The commands' modules (gpomap.apps) import the CLI's option helpers: one layer with it.
    ("cli", ("gpomap.cli", "gpomap.apps")),
    # The package's face (its __init__) gives the user-facing names of every layer.
    ("public", ("gpomap",)),
]
RANK = {name: i for i, (name, _) in enumerate(LAYERS)}
#: What each layer may import besides itself; by default every lower layer.
ALLOWED: dict[str, set[str]] = {name: {n for n, _ in LAYERS[: i + 1]} for i, (name, _) in enumerate(LAYERS)}
ALLOWED["io"] = {"foundation", "data", "io"}


def layer_of(module: str) -> str:
    """The layer of a dotted module name (its longest listed prefix)."""
    best, depth = None, -1
    for name, prefixes in LAYERS:
        for p in prefixes:
            # The package itself ("gpomap", its __init__) is no prefix: a new module needs a layer.
            if (module == p or (p != "gpomap" and module.startswith(p + "."))) and p.count(".") > depth:
                best, depth = name, p.count(".")
    if best is None:
        raise LookupError(f"module {module} is in no layer: add it to LAYERS in {__file__}")
    return best


def gpomap_imports(source: str, module: str, is_package: bool) -> set[str]:
    """Every gpomap module `source` imports, absolute or relative, anywhere in the file."""
    package = module if is_package else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "gpomap"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.split(".")[0] == "gpomap":
                # `from gpomap import cli` imports the module gpomap.cli, not the package's namespace.
                submodules = {f"{name}.{a.name}" for a in node.names if _is_module(f"{name}.{a.name}")}
                out |= submodules or {name}
    return out


def _is_module(name: str) -> bool:
    path = SRC.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """Imports of `source` (as `module`) that reach a layer it may not use."""
    mine = layer_of(module)
    bad = []
    for target in sorted(gpomap_imports(source, module, is_package)):
        theirs = layer_of(target)
        if theirs not in ALLOWED[mine]:
            bad.append(f"{module} ({mine}) imports {target} ({theirs})")
    return bad


def _modules() -> list[tuple[str, Path]]:
    out = []
    for f in sorted((SRC / "gpomap").rglob("*.py")):
        parts = f.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out.append((name, f))
    return out


def test_every_module_has_a_layer():
    for name, _ in _modules():
        layer_of(name)
    with pytest.raises(LookupError, match="in no layer"):
        layer_of("gpomap.newmodule")


def test_imports_go_one_way():
    bad = []
    for name, path in _modules():
        bad += violations(path.read_text(encoding="utf-8"), name, path.name == "__init__.py")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("source", "module", "ok"),
    [
        ("from gpomap.tiles import TiledGPOM", "gpomap.cells", False),
        ("def f():\n    import gpomap.cli\n", "gpomap.gp", False),
        ("from gpomap.mapping import AreaGPOM", "gpomap.io.npz", False),
        ("from ..tiles import TiledGPOM", "gpomap.io.carmen", False),
        ("from .checks import regular_file", "gpomap.io.carmen", True),
        ("from gpomap.cells import build_cells", "gpomap.tiles", True),
        ("import numpy as np", "gpomap.errors", True),
        ("from gpomap import cli", "gpomap.truth", False),
        ("from gpomap import tiles, errors", "gpomap.fusion", False),
        ("from gpomap import errors, scans", "gpomap.fusion", True),
        ("from gpomap import GpomapError", "gpomap.fusion", False),
        ("from gpomap.tiles import TiledGPOM", "gpomap", True),
    ],
)
def test_the_check_itself(source, module, ok):
    assert (violations(source, module) == []) is ok
