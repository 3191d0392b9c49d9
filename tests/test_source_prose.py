"""Comments and docstrings of src/ say why; measured figures, log names and commit hashes live in docs/.

Every ``src/gpomap/**/*.py`` file's comments (:mod:`tokenize`) and string statements, docstrings
among them (:mod:`ast`), are scanned for

- a commit hash: a word of 7 to 40 lower-case hex digits holding both a digit and a letter a-f;
- the name of a log or data set used as evidence (:data:`LOG_NAMES`), outside code spans
  (````...```` or ```...```: a path or an identifier) and doctest lines.

A line that fails names its file and line. Where the number behind a comment lives:
docs/choices.md ("Measured for the code" for engineering figures), docs/3d.md, docs/streaming.md.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "gpomap"

#: Names of the logs and data sets the project measures on, as prose cites them (case-sensitive,
#: whole words). A format named after a data set (the 3DMatch depth layout) is a format, not
#: evidence, and is not listed.
LOG_NAMES: tuple[str, ...] = (
    "Intel",
    "FR079",
    "fr079",
    "Freiburg",
    "CSAIL",
    "csail",
    "MIT",
    "Killian",
    "Belgioioso",
    "belgioioso",
    "Orebro",
    "Örebro",
    "Seattle",
    "Acapulco",
    "ACES",
    "Edmonton",
    "FHW",
    "Stage arena",
    "stage arena",
    "hospital",
    "cave",
    "la3dm",
    "sim_structured",
    "sim_unstructured",
    "geb079",
    "TurtleBot3",
)

#: Files whose comments and docstrings are being rewritten by other work now; each is expected to
#: fail this test until then. Whoever cleans one removes it from here (strict: a file listed that
#: passes fails the suite, so the list cannot go stale).
BEING_REWRITTEN: frozenset[str] = frozenset()

HASH = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
NAMES = re.compile(r"(?<![\w-])(?:" + "|".join(re.escape(n) for n in LOG_NAMES) + r")(?![\w-])")
CODE_SPAN = re.compile(r"``.*?``|`[^`]*`")


def prose_lines(source: str) -> list[tuple[int, str]]:
    """The comment and string-statement lines of a module's `source`, as (line number, text), in order."""
    lines: list[tuple[int, str]] = []
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            lines.append((token.start[0], token.string))
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            # The string's own lines: its first line is the node's, each later one the next.
            lines.extend((node.value.lineno + i, text) for i, text in enumerate(node.value.value.splitlines()))
    return sorted(lines)


def problems(source: str) -> list[str]:
    """What `source`'s comments and docstrings carry that belongs in docs/, one ``line N: ...`` each."""
    found = []
    for number, text in prose_lines(source):
        for match in HASH.finditer(text):
            found.append(f"line {number}: commit hash {match.group()!r}: {text.strip()}")
        stripped = text.strip().lstrip("#:").strip()
        if stripped.startswith((">>>", "...")):
            continue  # a doctest: code, whose paths name the data they read
        for match in NAMES.finditer(CODE_SPAN.sub("", text)):
            found.append(f"line {number}: log name {match.group()!r}: {text.strip()}")
    return found


def _source_files() -> list[Path]:
    return sorted(SRC.rglob("*.py"))


def _case(path: Path) -> object:
    name = path.relative_to(SRC).as_posix()
    marks = [pytest.mark.xfail(strict=True, reason="being rewritten")] if name in BEING_REWRITTEN else []
    return pytest.param(path, id=name, marks=marks)


@pytest.mark.parametrize("path", [_case(p) for p in _source_files()])
def test_comments_and_docstrings_hold_no_figures_of_record(path: Path) -> None:
    found = problems(path.read_text(encoding="utf-8"))
    assert not found, f"{path.relative_to(SRC.parents[1])}:\n  " + "\n  ".join(found)


def test_being_rewritten_lists_existing_files() -> None:
    names = {p.relative_to(SRC).as_posix() for p in _source_files()}
    assert names >= BEING_REWRITTEN, sorted(BEING_REWRITTEN - names)


@pytest.mark.parametrize(
    "source, expected",
    [
        ("x = 1  # measured at 4d1639b\n", "commit hash '4d1639b'"),
        ('"""Fast.\n\nOn Belgioioso the fit took 0.3 s."""\n', "log name 'Belgioioso'"),
        ("def f():\n    '''Doc.\n\n    Intel's map.\n    '''\n", "line 4: log name 'Intel'"),
        ("# the Stage arena's plan\n", "log name 'Stage arena'"),
    ],
)
def test_problems_found(source: str, expected: str) -> None:
    assert any(expected in p for p in problems(source)), problems(source)


@pytest.mark.parametrize(
    "source",
    [
        '"""Read ``../shared/data/intel/intel-corrected.log.gz`` or `belgioioso`."""\n',
        '"""Example.\n\n>>> read_clouds("../shared/data/la3dm-sim/sim_structured")\n"""\n',
        "x = 1  # see docs/choices.md, 'Measured for the code'\n",
        "x = 'Intel 4d1639b'  # a string value, not prose\n",
        "# 1234567 scans, deadbeef, an intelligent caveat, belgioioso_path\n",
        "# a SHA-256 of the cells' bytes, 1e-15 relative, 2^16 pairs\n",
    ],
)
def test_clean_prose_passes(source: str) -> None:
    assert problems(source) == []
