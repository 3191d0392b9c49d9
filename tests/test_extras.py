"""A missing optional dependency is one line naming the extra that brings it."""

import sys
from pathlib import Path

import pytest

from gpomap.cli import main
from gpomap.errors import MissingExtraError
from gpomap.extras import EXTRA_OF, require

LA3DM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "la3dm-sim" / "sim_structured"


def test_every_optional_module_names_an_extra_of_the_project():
    import tomllib

    extras = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    assert set(EXTRA_OF.values()) <= set(extras)


def test_a_missing_module_is_an_error_naming_its_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pypcd4", None)  # import pypcd4 now raises ImportError
    with pytest.raises(
        MissingExtraError, match=r"reading PCD files needs pypcd4, from gpomap's \[3d\] extra: pip install \"gpomap\[3d\]\""
    ):
        require("pypcd4", "reading PCD files")


@pytest.mark.skipif(not LA3DM.exists(), reason="shared la3dm data not present")
def test_point_clouds_without_the_3d_extra_are_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "pypcd4", None)
    code = main(["map", str(LA3DM), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and "Traceback" not in "\n".join(err)
    assert err[-1].startswith("gpomap: error: ") and 'pip install "gpomap[3d]"' in err[-1]
    assert not (tmp_path / "out").exists()
