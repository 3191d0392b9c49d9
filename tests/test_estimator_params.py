"""The estimator's parameters are declared once, as the fields of :class:`gpomap.config.EstimatorConfig`
(:class:`~gpomap.config.MapConfig`'s, then :class:`~gpomap.config.TilingConfig`'s), and what its
users rely on holds: the signature ``inspect``, ``help`` and a type checker read, scikit-learn's
conventions (``get_params`` / ``set_params``, a clone that hands the same objects back, a ``repr``
of the arguments that differ from their defaults) and pickling."""

from __future__ import annotations

import ast
import copy
import dataclasses
import inspect
import pickle
import pydoc
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gpomap.config import EstimatorConfig, MapConfig, TilingConfig
from gpomap.mapping import AreaGPOM
from gpomap.settings import MapSettings
from gpomap.tiles import TiledGPOM

ROOT = Path(__file__).resolve().parents[1]
NAMES = [f.name for f in dataclasses.fields(EstimatorConfig)]


def test_the_estimator_config_is_the_map_settings_then_the_tiling():
    assert [*MapConfig.__dataclass_fields__, *TilingConfig.__dataclass_fields__] == NAMES
    assert [f.name for f in dataclasses.fields(MapSettings)] == [f.name for f in dataclasses.fields(MapConfig)]
    estimator, tiling = EstimatorConfig(), TilingConfig()
    assert {n: getattr(estimator, n) for n in MapConfig.__dataclass_fields__} == MapConfig().kwargs()
    # Its one default of its own: the tiles run in this process unless told (scikit-learn's n_jobs).
    assert {n: getattr(estimator, n) for n in TilingConfig.__dataclass_fields__} == {**tiling.kwargs(), "n_workers": 1}


def test_the_signature_is_the_configs_fields():
    """Names, order, kinds, defaults and types: the config's, for the class, its __init__ and get_params."""
    config = inspect.signature(EstimatorConfig, eval_str=True)
    assert inspect.signature(AreaGPOM) == config
    init = inspect.signature(AreaGPOM.__init__)
    self, *parameters = init.parameters.values()
    assert self.name == "self" and self.kind is self.POSITIONAL_ONLY
    assert parameters == list(config.parameters.values())
    assert list(AreaGPOM().get_params()) == NAMES
    assert AreaGPOM().get_params() == EstimatorConfig().kwargs()
    assert AreaGPOM.__init__.__qualname__ == "AreaGPOM.__init__"


def test_the_tiling_fields_are_tiled_gpoms_arguments():
    """TiledGPOM's own signature (besides the map settings, its **options) has TilingConfig's names,
    order and defaults: what AreaGPOM hands it by those names is what it takes."""
    tiled = inspect.signature(TiledGPOM.__init__).parameters
    named = {n: p.default for n, p in tiled.items() if n != "self" and p.kind is not p.VAR_KEYWORD}
    assert list(named) == list(TilingConfig.__dataclass_fields__)
    assert named == TilingConfig().kwargs()


def _parameters_named(source: str, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every parameter of a function in `source` named as one of `names`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            args = node.args
            for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs]:
                if arg.arg in names:
                    found.append((arg.lineno, arg.arg))
    return found


def test_the_check_finds_a_parameter_written_out():
    source = "class A:\n    def __init__(self, params, kernel: str = MapConfig.kernel, *, tile_size=None):\n        pass\n"
    assert _parameters_named(source, set(NAMES)) == [(2, "kernel"), (2, "tile_size")]


def test_the_estimator_writes_no_parameter_out_again():
    """gpomap.mapping names no parameter of the estimator in a signature: it is derived, not restated."""
    found = _parameters_named((ROOT / "src" / "gpomap" / "mapping.py").read_text(encoding="utf-8"), set(NAMES))
    assert not found, f"src/gpomap/mapping.py restates the config's fields: {found}"


def test_arguments_are_bound_as_a_plain_init_binds_them():
    assert AreaGPOM("se").kernel == "se"  # positional, in the signature's order (the kernel first)
    model = AreaGPOM("se", None, "sum", 0.1, tile_size=4.0, n_workers=None)
    assert (model.kernel, model.area, model.normalisation, model.free_step, model.tile_size, model.n_workers) == (
        "se",
        None,
        "sum",
        0.1,
        4.0,
        None,
    )
    with pytest.raises(TypeError, match=r"AreaGPOM\.__init__\(\) got an unexpected keyword argument 'lenght_scale'"):
        AreaGPOM(lenght_scale=0.5)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match=r"AreaGPOM\.__init__\(\) multiple values for argument 'kernel'"):
        AreaGPOM("se", kernel="se")  # type: ignore[misc]
    # TiledGPOM's own checks still run.
    with pytest.raises(ValueError, match="tile_size must be positive"):
        AreaGPOM(tile_size=-1.0)


def test_parameters_are_kept_as_given_and_a_clone_hands_them_back():
    """scikit-learn's clone: the parameters read back are deep-copied into a new estimator, and each
    must come back as the very object it was given (a parameter changed by __init__ fails there)."""
    origin = (0.5, -1.0)
    model = AreaGPOM(kernel="se", length_scale=0.7, length_scale_bounds=(0.1, 5.0), origin=origin, tile_size=4.0)
    assert model.origin is origin and model.kernel == "se" and model.length_scale == 0.7
    params = model.get_params(deep=False)
    copies = {name: copy.deepcopy(value) for name, value in params.items()}
    clone = type(model)(**copies)
    returned = clone.get_params(deep=False)
    assert [n for n in params if returned[n] is not copies[n]] == []
    assert returned == params
    # A value TiledGPOM converts is stored converted (as before), the given object only when equal in type.
    assert AreaGPOM(origin=(1, 2)).origin == (1.0, 2.0) and type(AreaGPOM(origin=(1, 2)).origin[0]) is float
    assert AreaGPOM(origin=[1.0, 2.0]).origin == (1.0, 2.0)  # type: ignore[arg-type]


def test_set_params_changes_the_settings_the_fit_reads():
    model = AreaGPOM(kernel="se")
    assert model.set_params(length_scale=0.4, tile_size=3.0, n_workers=2) is model
    assert (model.length_scale, model.base.length_scale, model.tile_size, model.n_workers) == (0.4, 0.4, 3.0, 2)
    assert model.get_params() == {
        **EstimatorConfig().kwargs(),
        "kernel": "se",
        "length_scale": 0.4,
        "tile_size": 3.0,
        "n_workers": 2,
    }
    assert model.options["length_scale"] == 0.4 and model.options["kernel"] == "se"


def test_repr_shows_the_arguments_that_differ_from_their_defaults():
    assert repr(AreaGPOM()) == "AreaGPOM()"
    model = AreaGPOM(kernel="se", length_scale=0.5, origin=(0.0, 1.0), n_workers=None)
    assert repr(model) == "AreaGPOM(kernel='se', length_scale=0.5, origin=(0.0, 1.0), n_workers=None)"
    assert eval(repr(model), {"AreaGPOM": AreaGPOM}).get_params() == model.get_params()


def test_help_shows_the_parameters():
    """help(AreaGPOM) shows the parameters, their types and defaults (an IDE reads the same signature)."""
    text = pydoc.render_doc(AreaGPOM, renderer=pydoc.plaintext)
    fields = ", ".join(
        f"{f.name}: {f.type} = {getattr(EstimatorConfig(), f.name)!r}" for f in dataclasses.fields(EstimatorConfig)
    )
    assert f"AreaGPOM({fields}) -> None" in text
    assert f"__init__(self, /, {fields}) -> None" in text


def test_an_unfitted_estimator_pickles_with_its_arguments():
    model = AreaGPOM(kernel="se", free_step=0.1, tile_size=4.0, origin=(0.0, 0.0))
    again = pickle.loads(pickle.dumps(model))
    assert type(again) is AreaGPOM and again.get_params() == model.get_params()
    assert vars(again).keys() == vars(model).keys()


USER_CODE = """\
from gpomap import AreaGPOM
from gpomap.config import EstimatorConfig

model: AreaGPOM = AreaGPOM(length_scale=0.5)
AreaGPOM("se", tile_size=3.0, origin=(0.0, 1.0), n_workers=None, scheduler="tcp://127.0.0.1:8786")
AreaGPOM(**EstimatorConfig(noise=0.2).kwargs())
AreaGPOM(lenght_scale=0.5)
AreaGPOM(length_scale="0.5")
AreaGPOM(tile_size="4")
AreaGPOM(1.0)
"""


def test_a_type_checker_reads_the_signature(tmp_path):
    """mypy --strict on a user's code: the right calls pass, each wrong one is an error on its line."""
    pytest.importorskip("mypy")
    path = tmp_path / "user.py"
    path.write_text(textwrap.dedent(USER_CODE), encoding="utf-8")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "--strict",
            "--follow-imports=silent",
            "--no-incremental",
            "--cache-dir",
            str(tmp_path / "cache"),
            str(path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env={"MYPYPATH": str(ROOT / "src"), "PATH": "/usr/bin:/bin"},
    )
    # gpomap's own modules are read for their types, their errors left to the lint (follow-imports=silent).
    errors = [line for line in out.stdout.splitlines() if ": error: " in line]
    lines = sorted({int(line.split(":")[1]) for line in errors})
    assert lines == [7, 8, 9, 10], out.stdout + out.stderr
    assert 'Unexpected keyword argument "lenght_scale" for "AreaGPOM"' in out.stdout
    assert 'Argument "length_scale" to "AreaGPOM" has incompatible type "str"; expected "float"' in out.stdout
    assert 'Argument "tile_size" to "AreaGPOM" has incompatible type "str"; expected "float | None"' in out.stdout
    assert 'Argument 1 to "AreaGPOM" has incompatible type "float"; expected "str"' in out.stdout
