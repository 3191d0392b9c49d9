"""The points a saved map is asked about, from files or the command line, and its answers as CSV (``gpomap query``).

Each POINTS argument is a CSV file of ``x,y`` (``x,y,z`` for a 3-D map) per line, a header line
optional, an NPZ holding one array of shape (m, 2) or (m, 3) (named ``points`` when it holds
several), or one point written out, ``x,y`` or ``x,y,z``. The answer,
per point, is the loaded map's ``predict_proba(points, return_var=True)``: the occupancy probability
and the GP's latent variance, the live model's to the bit, and its ``predict_ternary(points)``:
free (0), unknown (-1) or occupied (1), the written map's rule (never occupied where no beam
ended, in 3-D where no ray went: the GP's guess behind a wall is unknown, whatever its
probability). A point far from the data gets what the map says there, the prior: the probability
the squash gives the prior mean (1/2 unless it has an offset) and the kernel's variance.
``gpomap query`` prints the answers as CSV (``x,y[,z],probability,variance,ternary``, each number
the shortest decimal that reads back to it exactly), or writes them with ``-o`` to a CSV or an NPZ
(``points``, ``probability``, ``variance``, ``ternary``), atomically.

:func:`query_points` reads the POINTS arguments (:func:`read_query_points` a file);
:func:`answers_csv` writes the answers; the command is :mod:`gpomap.cli.query`.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError

__all__ = ["answers_csv", "query_points", "read_query_points"]

_AXES = "xyz"


def _columns(dim: int) -> str:
    return ",".join(_AXES[:dim])


def query_points(arguments: Sequence[str], dim: int, mapfile: str = "the map") -> NDArray[np.float64]:
    """The points asked, shape (m, `dim`), in the order given: each argument a points file
    (:func:`read_query_points`) or one point written out, ``x,y[,z]``.

    An argument that names an existing file is read as one, whatever it looks like.

    Raises
    ------
    InputFormatError
        One line: a file's (see :func:`read_query_points`), or a point written out with the wrong
        number of coordinates or a non-finite one.
    """
    parts = []
    for text in arguments:
        values = None if Path(text).exists() else _written_point(text)
        if values is None:
            parts.append(read_query_points(text, dim, mapfile))
            continue
        if len(values) != dim:
            raise InputFormatError(
                f"point {text!r} has {len(values)} coordinates; {mapfile} is a {dim}-D map: expected {_columns(dim)}"
            )
        if not np.isfinite(values).all():
            raise InputFormatError(f"point {text!r} is not finite; expected {_columns(dim)} as real numbers")
        parts.append(np.array([values], dtype=float))
    return np.concatenate(parts)


def _numbers(text: str) -> list[float] | None:
    """The numbers of `text`, separated by commas (spaces round them allowed); None when one is not a number."""
    try:
        return [float(f) for f in text.split(",")]
    except ValueError:
        return None


def _written_point(text: str) -> list[float] | None:
    """The coordinates of `text` when it is numbers separated by commas, at least two; else None."""
    values = _numbers(text)
    return values if values is not None and len(values) >= 2 else None


def read_query_points(path: str, dim: int, mapfile: str = "the map") -> NDArray[np.float64]:
    """The points of a CSV (``x,y[,z]``, a header line optional) or NPZ file, shape (m, `dim`).

    Raises
    ------
    InputFormatError
        One line naming the file (and line): not numbers, rows of unequal length, non-finite
        values, no point, or not `dim` columns (the map's dimension).
    """
    from gpomap.io.checks import load_npz, regular_file

    p = regular_file(path, f"points file (CSV of {_columns(dim)}, or NPZ), or a point written out as {_columns(dim)}")
    if p.suffix.lower() == ".npz":
        arrays = load_npz(p, "NumPy .npz of points")
        if "points" in arrays:
            points = arrays["points"]
        elif len(arrays) == 1:
            points = next(iter(arrays.values()))
        else:
            raise InputFormatError(f"holds {sorted(arrays)}; expected one array, or one named 'points'", path=path)
        if not (np.issubdtype(points.dtype, np.floating) or np.issubdtype(points.dtype, np.integer)):
            raise InputFormatError(f"points have dtype {points.dtype}; expected real numbers", path=path)
        points = np.asarray(points, dtype=float)
        if points.ndim != 2:
            raise InputFormatError(f"points have shape {points.shape}; expected (m, {dim}): {_columns(dim)} per row", path=path)
    else:
        points = _read_csv(p, path)
    if points.shape[1] != dim:
        raise InputFormatError(
            f"points have {points.shape[1]} coordinates per row; {mapfile} is a {dim}-D map: expected {_columns(dim)}", path=path
        )
    if points.shape[0] == 0:
        raise InputFormatError(f"holds no points; expected {_columns(dim)} per row", path=path)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputFormatError(f"point {int(np.argmax(bad))} is not finite: {points[int(np.argmax(bad))].tolist()}", path=path)
    return points


def _read_csv(p: Path, path: str) -> NDArray[np.float64]:
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputFormatError("not a text file; expected a CSV of coordinates or an .npz", path=path) from None
    rows: list[list[float]] = []
    width = None
    header = False
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        values = _numbers(stripped)
        if values is None:
            if not rows and not header:  # the header line
                header = True
                continue
            raise InputFormatError(f"expected numbers separated by commas, got {stripped[:80]!r}", path=path, line=number)
        if width is not None and len(values) != width:
            raise InputFormatError(f"{len(values)} values; the rows above have {width}", path=path, line=number)
        width = len(values)
        rows.append(values)
    return np.array(rows, dtype=float).reshape(-1, width or 0)


def answers_csv(
    points: NDArray[np.float64], probability: NDArray[np.float64], variance: NDArray[np.float64], ternary: NDArray[np.int8]
) -> str:
    """The answers as CSV text: a header, then ``x,y[,z],probability,variance,ternary`` per point
    (points of shape (m, dim), the rest (m,))."""
    dim = points.shape[1]
    out = io.StringIO()
    out.write(f"{_columns(dim)},probability,variance,ternary\n")
    # Each number as its shortest decimal that reads back to the same float; the label as an integer.
    for row, label in zip(np.column_stack([points, probability, variance]).tolist(), ternary.tolist(), strict=True):
        out.write(",".join(map(repr, row)) + f",{label}\n")
    return out.getvalue()
