"""Layers import one way, and no module imports itself round a loop.

Each module of ``src/gpomap`` belongs to one layer; every ``gpomap`` import it makes (at the top
or inside a function) must name a module of its own layer or a lower one. Readers and writers
(``gpomap.io``) and the figures (``gpomap.plot``) sit beside the engine, not on it: they may use
the foundation and the data layer only, so a file format never depends on how maps are fitted;
and between them one way: the writers draw their figures with ``gpomap.plot``, which knows no
reader or writer (it writes a figure on its own through the foundation's ``gpomap.atomic_files``). The command line
(``gpomap.cli``) is the top: no other module imports it. And the imports, function-level ones
included, form no cycle, inside a layer or across layers: each module can be read knowing only
what it imports.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
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
            "gpomap.signature",
            "gpomap.progress",
            "gpomap.atomic_files",
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
            "gpomap._compiled_raycast",
            "gpomap._compiled_bounds",
            "gpomap._compiled_clouds",
            "gpomap.compiled",
            "gpomap.lapack",
        ),
    ),
    (
        "data",
        (
            "gpomap.observations",
            "gpomap.cells",
            "gpomap.robot_path",
            "gpomap.evidence",
            "gpomap.counted_cells",
            "gpomap.heldout",
            "gpomap.unseen",
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
        (
            "gpomap.fitted",
            "gpomap.field",
            "gpomap.estimator",
            "gpomap.fusion",
            "gpomap.extrapolation",
            "gpomap.revisit",
            "gpomap.stages",
            "gpomap.settings",
            "gpomap.baselines",
        ),
    ),
    ("tiling", ("gpomap.tiles", "gpomap._compiled_squares", "gpomap.mapping", "gpomap.streaming")),
    ("figures", ("gpomap.plot",)),
    ("io", ("gpomap.io",)),
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
            # The jobs only a command does, with typed arguments; their options are parsed in gpomap.cli.
            "gpomap.apps",
        ),
    ),
    ("cli", ("gpomap.cli",)),
    # The package's face (its __init__) gives the user-facing names of every layer.
    ("public", ("gpomap",)),
]
RANK = {name: i for i, (name, _) in enumerate(LAYERS)}
#: What each layer may import besides itself; by default every lower layer.
ALLOWED: dict[str, set[str]] = {name: {n for n, _ in LAYERS[: i + 1]} for i, (name, _) in enumerate(LAYERS)}
ALLOWED["figures"] = {"foundation", "data", "figures"}
ALLOWED["io"] = {"foundation", "data", "figures", "io"}


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


def import_graph(sources: Mapping[str, tuple[str, bool]]) -> dict[str, set[str]]:
    """Module -> the modules of `sources` it imports; `sources` maps a module to its text and whether it is a package.

    An import of a name inside a module (``from gpomap.io.carmen import read_carmen``) is an
    import of that module; one naming no module of `sources` goes to its longest prefix that is one.
    """
    graph: dict[str, set[str]] = {}
    for module, (source, is_package) in sources.items():
        targets = set()
        for target in gpomap_imports(source, module, is_package):
            while target not in sources and "." in target:
                target = target.rpartition(".")[0]
            if target in sources:
                targets.add(target)
        graph[module] = targets
    return graph


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """One import cycle for each group of modules that reach one another, as ``[a, b, ..., a]``."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[set[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                group.add(w)
                if w == v:
                    break
            if len(group) > 1 or v in graph.get(v, ()):
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for group in groups:
        start = min(group)
        # The shortest way back to `start` inside its group.
        came_from: dict[str, str] = {}
        frontier = [start]
        while start not in came_from:
            reached = []
            for v in frontier:
                for w in sorted(graph[v] & group):
                    if w not in came_from:
                        came_from[w] = v
                        reached.append(w)
            frontier = reached
        path = [start]
        while True:
            path.append(came_from[path[-1]])
            if path[-1] == start:
                break
        out.append(path[::-1])
    return sorted(out)


def _sources() -> dict[str, tuple[str, bool]]:
    return {name: (path.read_text(encoding="utf-8"), path.name == "__init__.py") for name, path in _modules()}


def test_every_module_has_a_layer():
    for name, _ in _modules():
        layer_of(name)
    with pytest.raises(LookupError, match="in no layer"):
        layer_of("gpomap.newmodule")


def test_imports_go_one_way():
    bad = []
    for name, (source, is_package) in _sources().items():
        bad += violations(source, name, is_package)
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_import_cycles():
    found = cycles(import_graph(_sources()))
    assert not found, "import cycles (each module reached again through the others):\n" + "\n".join(" -> ".join(c) for c in found)


@pytest.mark.parametrize(
    ("sources", "expected"),
    [
        # Inside a layer, through a function-level import and `from gpomap import X`.
        (
            {
                "gpomap.fusion": ("from gpomap import revisit", False),
                "gpomap.revisit": ("def f():\n    from gpomap.extrapolation import g\n", False),
                "gpomap.extrapolation": ("def g():\n    import gpomap.fusion\n", False),
            },
            [["gpomap.extrapolation", "gpomap.fusion", "gpomap.revisit", "gpomap.extrapolation"]],
        ),
        # Across layers: the CLI's package and a module of the apps that imports it back.
        (
            {
                "gpomap.cli": ("from gpomap.cli import render", True),
                "gpomap.cli.render": ("from gpomap.apps.render import map_header", False),
                "gpomap.apps.render": ("def f():\n    from gpomap import cli\n", False),
            },
            [["gpomap.apps.render", "gpomap.cli", "gpomap.cli.render", "gpomap.apps.render"]],
        ),
        # A module importing its own package's name, a name of the package (not a module of it).
        (
            {
                "gpomap.io": ("from gpomap.io.carmen import read_carmen", True),
                "gpomap.io.carmen": ("from gpomap.io import x", False),
            },
            [["gpomap.io", "gpomap.io.carmen", "gpomap.io"]],
        ),
        # One way only: no cycle.
        (
            {
                "gpomap.cli": ("from gpomap.cli import render", True),
                "gpomap.cli.render": ("from gpomap.apps.render import map_header", False),
                "gpomap.apps.render": ("from gpomap.io.mapfile import read_map_header", False),
                "gpomap.io.mapfile": ("import json", False),
            },
            [],
        ),
    ],
)
def test_the_cycle_check_itself(sources, expected):
    assert cycles(import_graph(sources)) == expected


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
        ("def f():\n    from gpomap import cli\n", "gpomap.apps.render", False),
        ("from gpomap.cli.options import positive", "gpomap.apps.stream", False),
        ("from gpomap.apps.render import map_header", "gpomap.cli.render", True),
        # The writers draw their figures; the figures know no writer, and no engine knows either.
        ("def f():\n    from gpomap.plot import plot_map\n", "gpomap.io.export", True),
        ("from gpomap.io.atomic import atomic_write", "gpomap.plot", False),
        ("def f():\n    from gpomap.io import export\n", "gpomap.plot", False),
        ("from gpomap.atomic_files import atomic_write", "gpomap.plot", True),
        ("from gpomap.tiles import TiledGPOM", "gpomap.plot", False),
        ("from gpomap.plot import plot_map", "gpomap.fitted", False),
        ("from gpomap.plot import plot_map", "gpomap.benchmark", True),
    ],
)
def test_the_check_itself(source, module, ok):
    assert (violations(source, module) == []) is ok
