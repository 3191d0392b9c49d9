"""The estimators' parameters are declared once, as the fields of their configs: AreaGPOM's those of
:class:`gpomap.config.EstimatorConfig` (:class:`~gpomap.config.MapConfig`'s, then
:class:`~gpomap.config.TilingConfig`'s), TiledGPOM's those of :class:`gpomap.config.TiledConfig`
(TilingConfig's, then MapConfig's). What their users rely on holds: the signature ``inspect``,
``help`` and a type checker read, scikit-learn's conventions (``get_params`` / ``set_params``, a
clone that hands the same objects back, a ``repr`` of the arguments that differ from their
defaults), pickling and map files."""

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

import numpy as np
import pytest

from gpomap.config import EstimatorConfig, MapConfig, TiledConfig, TilingConfig
from gpomap.mapping import AreaGPOM
from gpomap.settings import MapSettings
from gpomap.tiles import TiledGPOM

ROOT = Path(__file__).resolve().parents[1]
NAMES = [f.name for f in dataclasses.fields(EstimatorConfig)]
#: Each estimator and the config whose fields are its parameters.
ESTIMATORS = [(AreaGPOM, EstimatorConfig), (TiledGPOM, TiledConfig)]
BOTH = pytest.mark.parametrize(("cls", "config"), ESTIMATORS, ids=["AreaGPOM", "TiledGPOM"])


def test_the_estimator_config_is_the_map_settings_then_the_tiling():
    assert [*MapConfig.__dataclass_fields__, *TilingConfig.__dataclass_fields__] == NAMES
    assert [f.name for f in dataclasses.fields(MapSettings)] == [f.name for f in dataclasses.fields(MapConfig)]
    estimator, tiling = EstimatorConfig(), TilingConfig()
    assert {n: getattr(estimator, n) for n in MapConfig.__dataclass_fields__} == MapConfig().kwargs()
    # Its one default of its own: the tiles run in this process unless told (scikit-learn's n_jobs).
    assert {n: getattr(estimator, n) for n in TilingConfig.__dataclass_fields__} == {**tiling.kwargs(), "n_workers": 1}


def test_the_tiled_config_is_the_tiling_then_the_map_settings():
    """TiledGPOM's parameters: TilingConfig's fields first (its positional arguments, the tile side
    first, as before the map settings were named), then MapConfig's, with both configs' defaults."""
    names = [f.name for f in dataclasses.fields(TiledConfig)]
    assert names == [*TilingConfig.__dataclass_fields__, *MapConfig.__dataclass_fields__]
    assert TiledConfig().kwargs() == {**TilingConfig().kwargs(), **MapConfig().kwargs()}


@BOTH
def test_the_signature_is_the_configs_fields(cls, config):
    """Names, order, kinds, defaults and types: the config's, for the class, its __init__ and get_params."""
    fields = inspect.signature(config, eval_str=True)
    assert inspect.signature(cls) == fields
    init = inspect.signature(cls.__init__)
    self, *parameters = init.parameters.values()
    assert self.name == "self" and self.kind is self.POSITIONAL_ONLY
    assert parameters == list(fields.parameters.values())
    assert list(cls().get_params()) == [f.name for f in dataclasses.fields(config)]
    assert cls().get_params() == config().kwargs()
    assert cls.__init__.__qualname__ == f"{cls.__name__}.__init__"


def test_tiled_gpom_takes_the_tiling_first():
    """A TiledGPOM made positionally, as gpomap.apps.update makes one, gets the same arguments."""
    model = TiledGPOM(4.0, 1.0, 0.5, (0.0, 0.0), n_workers=1, kernel="se")
    assert (model.tile_size, model.overlap, model.blend, model.origin, model.n_workers) == (4.0, 1.0, 0.5, (0.0, 0.0), 1)
    assert model.kernel == "se" and model.base == MapSettings(kernel="se")
    # The map settings it holds (what its refits, updates and map file take) are every setting.
    assert model.options == {**MapConfig().kwargs(), "kernel": "se"}
    assert MapSettings(**model.options) == model.base


def _functions_naming(source: str, names: set[str]) -> list[tuple[int, list[str]]]:
    """(line, parameters) of every function in `source` with parameters named as some of `names`."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            args = node.args
            named = [a.arg for a in [*args.posonlyargs, *args.args, *args.kwonlyargs] if a.arg in names]
            if named:
                found.append((node.lineno, named))
    return found


def _parameters_named(source: str, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every parameter of a function in `source` named as one of `names`."""
    return [(line, name) for line, named in _functions_naming(source, names) for name in named]


def test_the_check_finds_a_parameter_written_out():
    source = "class A:\n    def __init__(self, params, kernel: str = MapConfig.kernel, *, tile_size=None):\n        pass\n"
    assert _parameters_named(source, set(NAMES)) == [(2, "kernel"), (2, "tile_size")]
    # TiledGPOM's signature as it was written before it was derived: its tiling, one per line.
    source = (
        "class TiledGPOM:\n    def __init__(\n        self,\n        tile_size: float | None = None,\n"
        "        overlap=None,\n        blend=None,\n        origin=None,\n        **options,\n    ):\n        pass\n"
    )
    assert _functions_naming(source, set(TilingConfig.__dataclass_fields__)) == [(2, ["tile_size", "overlap", "blend", "origin"])]


@pytest.mark.parametrize("module", ["mapping.py", "tiles/tiled.py", "signature.py"])
def test_the_estimators_write_no_parameter_out_again(module):
    """The estimators' modules name no parameter of theirs in a signature: it is derived, not restated."""
    found = _parameters_named((ROOT / "src" / "gpomap" / module).read_text(encoding="utf-8"), set(NAMES))
    assert not found, f"src/gpomap/{module} restates the config's fields: {found}"


def test_no_signature_in_src_restates_the_tiling():
    """No function of gpomap takes the tiling arguments as a list of its own (more than three of
    TilingConfig's fields): the tile side, overlap and origin of a geometry helper are not a restated
    list, the estimators' whole tiling is."""
    tiling = set(TilingConfig.__dataclass_fields__)
    found = {
        f"{path.relative_to(ROOT)}:{line}": named
        for path in sorted((ROOT / "src" / "gpomap").rglob("*.py"))
        for line, named in _functions_naming(path.read_text(encoding="utf-8"), tiling)
        if len(named) > 3
    }
    assert not found, f"signatures restating TilingConfig's fields: {found}"


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


def test_tiled_gpom_binds_its_arguments_as_a_plain_init_binds_them():
    model = TiledGPOM(4.0, None, None, None, 2, None, 100, True, 1, 5.0, True, 2.0, "se", None, "sum")
    tiling = [getattr(model, n) for n in TilingConfig.__dataclass_fields__]
    assert tiling == [4.0, None, None, None, 2, None, 100, True, 1, 5.0, True, 2.0]
    assert (model.kernel, model.area, model.normalisation) == ("se", None, "sum")
    with pytest.raises(TypeError, match=r"TiledGPOM\.__init__\(\) got an unexpected keyword argument 'lenght_scale'"):
        TiledGPOM(lenght_scale=0.5)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match=r"TiledGPOM\.__init__\(\) multiple values for argument 'tile_size'"):
        TiledGPOM(4.0, tile_size=4.0)  # type: ignore[misc]
    for bad, message in [
        ({"tile_size": 0.0}, "tile_size must be positive"),
        ({"scheduler_timeout": 0.0}, "scheduler_timeout must be positive"),
        ({"memory_limit": -1.0}, "memory_limit must be positive"),
    ]:
        with pytest.raises(ValueError, match=message):
            TiledGPOM(**bad)


@BOTH
def test_parameters_are_kept_as_given_and_a_clone_hands_them_back(cls, config):
    """scikit-learn's clone: the parameters read back are deep-copied into a new estimator, and each
    must come back as the very object it was given (a parameter changed by __init__ fails there)."""
    origin = (0.5, -1.0)
    model = cls(kernel="se", length_scale=0.7, length_scale_bounds=(0.1, 5.0), origin=origin, tile_size=4.0)
    assert model.origin is origin and model.kernel == "se" and model.length_scale == 0.7
    params = model.get_params(deep=False)
    copies = {name: copy.deepcopy(value) for name, value in params.items()}
    clone = type(model)(**copies)
    returned = clone.get_params(deep=False)
    assert [n for n in params if returned[n] is not copies[n]] == []
    assert returned == params
    # A value TiledGPOM converts is stored converted (as before), the given object only when equal in type.
    assert cls(origin=(1, 2)).origin == (1.0, 2.0) and type(cls(origin=(1, 2)).origin[0]) is float
    assert cls(origin=[1.0, 2.0]).origin == (1.0, 2.0)
    assert type(cls(tile_size=4).tile_size) is float


@BOTH
def test_set_params_changes_the_settings_the_fit_reads(cls, config):
    model = cls(kernel="se")
    assert model.set_params(length_scale=0.4, tile_size=3.0, n_workers=2) is model
    assert (model.length_scale, model.base.length_scale, model.tile_size, model.n_workers) == (0.4, 0.4, 3.0, 2)
    assert model.get_params() == {
        **config().kwargs(),
        "kernel": "se",
        "length_scale": 0.4,
        "tile_size": 3.0,
        "n_workers": 2,
    }
    assert model.options["length_scale"] == 0.4 and model.options["kernel"] == "se"
    assert model.base == MapSettings(kernel="se", length_scale=0.4)
    with pytest.raises(ValueError, match=f"unknown parameter 'bogus' for {cls.__name__}"):
        model.set_params(bogus=1)
    with pytest.raises(ValueError, match="tile_size must be positive"):
        model.set_params(tile_size=0.0)


def test_repr_shows_the_arguments_that_differ_from_their_defaults():
    assert repr(AreaGPOM()) == "AreaGPOM()"
    model = AreaGPOM(kernel="se", length_scale=0.5, origin=(0.0, 1.0), n_workers=None)
    assert repr(model) == "AreaGPOM(kernel='se', length_scale=0.5, origin=(0.0, 1.0), n_workers=None)"
    assert eval(repr(model), {"AreaGPOM": AreaGPOM}).get_params() == model.get_params()
    # TiledGPOM's defaults are its own config's: every core unless told, the tiling first.
    assert repr(TiledGPOM()) == "TiledGPOM()"
    tiled = TiledGPOM(6.0, kernel="se", origin=(0.0, 1.0), n_workers=1)
    assert repr(tiled) == "TiledGPOM(tile_size=6.0, origin=(0.0, 1.0), n_workers=1, kernel='se')"
    assert eval(repr(tiled), {"TiledGPOM": TiledGPOM}).get_params() == tiled.get_params()


@BOTH
def test_help_shows_the_parameters(cls, config):
    """help(cls) shows the parameters, their types and defaults (an IDE reads the same signature)."""
    text = pydoc.render_doc(cls, renderer=pydoc.plaintext)
    fields = ", ".join(f"{f.name}: {f.type} = {getattr(config(), f.name)!r}" for f in dataclasses.fields(config))
    assert f"{cls.__name__}({fields}) -> None" in text
    assert f"__init__(self, /, {fields}) -> None" in text


@BOTH
def test_an_unfitted_estimator_pickles_with_its_arguments(cls, config):
    model = cls(kernel="se", free_step=0.1, tile_size=4.0, origin=(0.0, 0.0))
    again = pickle.loads(pickle.dumps(model))
    assert type(again) is cls and again.get_params() == model.get_params()
    assert vars(again).keys() == vars(model).keys()


def test_a_map_file_of_a_tiled_gpom_holding_only_its_given_settings_loads_with_its_arguments(tmp_path):
    """A TiledGPOM kept the map settings it was given (only those) as ``options`` before its
    signature named them all: its map files hold that. Such a file loads, its settings read from
    ``base`` as every map's are, and it refits as it was fitted."""
    from gpomap.io.mapfile import load_fitted_map, save_fitted_map
    from gpomap.simulate import paper_room_scans

    given = {"free_step": 0.5, "max_cell": 1.0, "optimise": False, "ray_evidence": False}
    scans = paper_room_scans()[:6]
    model = TiledGPOM(6.0, n_workers=1, **given).fit(scans)
    model.options = dict(given)  # as a TiledGPOM made before kept them
    loaded = load_fitted_map(save_fitted_map(model, tmp_path / "map.gpom"))
    assert type(loaded) is TiledGPOM and loaded.options == given
    assert loaded.get_params() == {**TiledConfig().kwargs(), "tile_size": 6.0, "n_workers": 1, **given}
    assert repr(loaded) == repr(TiledGPOM(6.0, n_workers=1, **given))
    points = np.array([[1.0, 1.0], [2.5, -0.5], [0.0, 3.0]])
    again = loaded._refit().unfitted().fit(scans, hyperparameters=loaded.hyperparameters_)
    assert np.array_equal(again.predict_proba(points), model.predict_proba(points))


USER_CODE = """\
from gpomap import AreaGPOM
from gpomap.config import EstimatorConfig, TiledConfig
from gpomap.tiles import TiledGPOM

model: AreaGPOM = AreaGPOM(length_scale=0.5)
AreaGPOM("se", tile_size=3.0, origin=(0.0, 1.0), n_workers=None, scheduler="tcp://127.0.0.1:8786")
AreaGPOM(**EstimatorConfig(noise=0.2).kwargs())
AreaGPOM(lenght_scale=0.5)
AreaGPOM(length_scale="0.5")
AreaGPOM(tile_size="4")
AreaGPOM(1.0)
tiled: TiledGPOM = TiledGPOM(4.0, 1.0, kernel="se", origin=(0.0, 1.0), n_workers=1)
TiledGPOM(**TiledConfig(noise=0.2).kwargs())
same: TiledGPOM = tiled.set_params(noise=0.3)
area: AreaGPOM = AreaGPOM().set_params(noise=0.3)
TiledGPOM(lenght_scale=0.5)
TiledGPOM(length_scale="0.5")
TiledGPOM("se")
TiledGPOM(origin=(0.0, 1.0, 2.0))
"""


def test_a_type_checker_reads_the_signature(tmp_path):
    """mypy --strict on a user's code: the right calls pass, each wrong one is an error on its line."""
    pytest.importorskip("mypy")
    path = tmp_path / "user.py"
    path.write_text(textwrap.dedent(USER_CODE), encoding="utf-8")
    # The libraries gpomap imports are not read (their types Any): the calls checked pass only
    # builtins, and reading numpy's and scipy's stubs took 4 of mypy's 6.5 s (the same output).
    config = tmp_path / "mypy.ini"
    skipped = "numpy.*,scipy.*,numba.*,matplotlib.*,dask.*,distributed.*,PIL.*,yaml.*,threadpoolctl.*"
    config.write_text(f"[mypy]\n[mypy-{skipped}]\nfollow_imports = skip\n", encoding="utf-8")
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "--strict",
            "--follow-imports=silent",
            "--no-incremental",
            "--config-file",
            str(config),
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
    assert lines == [8, 9, 10, 11, 16, 17, 18, 19], out.stdout + out.stderr
    assert 'Unexpected keyword argument "lenght_scale" for "AreaGPOM"' in out.stdout
    assert 'Argument "length_scale" to "AreaGPOM" has incompatible type "str"; expected "float"' in out.stdout
    assert 'Argument "tile_size" to "AreaGPOM" has incompatible type "str"; expected "float | None"' in out.stdout
    assert 'Argument 1 to "AreaGPOM" has incompatible type "float"; expected "str"' in out.stdout
    assert 'Unexpected keyword argument "lenght_scale" for "TiledGPOM"' in out.stdout
    assert 'Argument "length_scale" to "TiledGPOM" has incompatible type "str"; expected "float"' in out.stdout
    assert 'Argument 1 to "TiledGPOM" has incompatible type "str"; expected "float | None"' in out.stdout
    assert 'Argument "origin" to "TiledGPOM" has incompatible type "tuple[float, float, float]"' in out.stdout


def test_the_package_ships_its_types():
    """PEP 561: the wheel holds gpomap/py.typed (pyproject's package-data), so a user's type checker
    reads the signatures above from an installed gpomap, not only from the source tree."""
    import tomllib

    import gpomap

    assert (Path(gpomap.__file__).parent / "py.typed").is_file()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert "py.typed" in project["tool"]["setuptools"]["package-data"]["gpomap"]
