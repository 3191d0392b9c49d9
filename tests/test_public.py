"""The public face: ``import gpomap`` gives the user-facing names, each the object its module
defines, without importing the heavy modules until one is asked for."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import gpomap


def test_every_public_name_is_its_modules_object() -> None:
    for name in gpomap.__all__:
        value = getattr(gpomap, name)
        if name in gpomap._LAZY:
            module, attribute = gpomap._LAZY[name]
            assert value is getattr(importlib.import_module(module), attribute), name
    assert gpomap.save_map is importlib.import_module("gpomap.io.mapfile").save_fitted_map
    assert set(gpomap._LAZY) <= set(gpomap.__all__) and set(gpomap._LAZY) <= set(dir(gpomap))


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no attribute 'fit_everything'"):
        _ = gpomap.fit_everything  # type: ignore[attr-defined]


def test_importing_gpomap_imports_no_heavy_module_until_asked() -> None:
    code = (
        "import sys, gpomap\n"
        "print(sorted(m for m in ('numba', 'scipy', 'matplotlib', 'gpomap.mapping') if m in sys.modules))\n"
        "gpomap.AreaGPOM\n"
        "print('gpomap.mapping' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.split("\n")[:2] == ["[]", "True"], out.stdout
