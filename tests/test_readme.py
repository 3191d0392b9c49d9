"""The README's promises hold: its Python runs as printed, and docs/cli.md documents every option of every command."""

import argparse
import re
import runpy
from pathlib import Path

import pytest

from gpomap.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
CLI_DOC = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
INTEL = ROOT.parent / "shared" / "data" / "intel" / "intel-corrected.log.gz"


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, flags=re.S)


def test_there_is_a_python_example():
    blocks = python_blocks()
    assert blocks and all("points" not in b or "points =" in b for b in blocks)


@pytest.mark.skipif(not INTEL.exists(), reason="shared Intel log not present")
@pytest.mark.parametrize("index", range(len(python_blocks())))
def test_python_blocks_run_as_printed(index, tmp_path, monkeypatch):
    # From the repository's root, as the README says (its paths are relative to it); run as a
    # script (__main__) in this process: a fresh interpreter would only add its start-up and imports.
    script = tmp_path / "block.py"
    script.write_text(python_blocks()[index])
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(script), run_name="__main__")


def _section(command: str) -> str:
    start = CLI_DOC.index(f"## Options of `gpomap {command}`")
    end = CLI_DOC.find("\n#", start + 1)
    return CLI_DOC[start : end if end != -1 else None]


def test_every_option_of_every_command_is_documented():
    parser = build_parser()
    missing = []
    for action in parser._subparsers._group_actions:
        for name, sub in action.choices.items():
            text = _section(name)
            for act in sub._actions:
                if act.help == argparse.SUPPRESS:  # hidden: a global option repeated after the command
                    continue
                for option in act.option_strings:
                    if option.startswith("--") and option != "--help" and not re.search(f"`{re.escape(option)}[`\\s]", text):
                        missing.append(f"{name} {option}")
    assert missing == []
