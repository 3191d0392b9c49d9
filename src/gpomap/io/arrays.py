"""Labelled points from files, for users who build free / occupied points themselves.

Two formats, chosen by suffix:

- CSV (``.csv``, ``.txt``): a header naming ``x``, ``y`` and ``occupied`` (any order, other
  columns ignored), then one point a line; ``occupied`` is ``0``/``1`` or ``true``/``false``.
- NPZ (``.npz``): arrays ``points`` of shape (n, 2) and ``occupied`` of shape (n,).

Both give :class:`gpomap.observations.Observations` with ``scan_index`` all zeros.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.io.checks import load_npz, regular_file
from gpomap.observations import Observations

__all__ = ["read_points", "write_points"]

_REQUIRED = ("x", "y", "occupied")
_TRUE = {"1", "true", "t", "yes", "1.0"}
_FALSE = {"0", "false", "f", "no", "0.0"}


def _observations(points: NDArray[np.float64], occupied: NDArray[np.bool_]) -> Observations:
    return Observations(points=points, occupied=occupied, scan_index=np.zeros(len(points), dtype=np.intp))


def _read_csv(path: Path) -> Observations:
    spath = str(path)
    state: dict[str, Any] = {}
    try:
        return _read_csv_rows(path, spath, state)
    except UnicodeDecodeError:
        raise InputFormatError(
            "not UTF-8 text; expected a CSV file with a header x,y,occupied", path=spath, line=_first_non_utf8_line(path)
        ) from None
    except csv.Error as exc:
        # NUL bytes, a field above the csv module's size limit, an unclosed quote.
        reader = state.get("reader")
        line = reader.line_num if reader is not None else None
        raise InputFormatError(f"malformed CSV ({exc}); expected x,y,occupied rows", path=spath, line=line) from None


def _first_non_utf8_line(path: Path) -> int | None:
    """1-based number of the first line that is not UTF-8, read line by line."""
    with path.open("rb") as f:
        for number, raw in enumerate(f, start=1):
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError:
                return number
    return None


def _read_csv_rows(path: Path, spath: str, state: dict[str, Any]) -> Observations:
    """The CSV reader proper; `state["reader"]` is the csv reader, for csv.Error messages."""
    with path.open(newline="", encoding="utf-8") as f:
        rows = csv.reader(f)
        state["reader"] = rows
        header = next(rows, None)
        while header is not None and not any(h.strip() for h in header):
            header = next(rows, None)
        if header is None:
            raise InputFormatError("empty file; expected a header line 'x,y,occupied'", path=spath, line=1)
        names = [h.strip().lower() for h in header]
        missing = [c for c in _REQUIRED if c not in names]
        if missing:
            raise InputFormatError(
                f"missing column(s) {', '.join(missing)} in header {header!r}; expected x, y and occupied",
                path=spath,
                line=rows.line_num,
            )
        ix, iy, io = (names.index(c) for c in _REQUIRED)
        xy: list[tuple[float, float]] = []
        occ: list[bool] = []
        for row in rows:
            line = rows.line_num
            if not any(v.strip() for v in row):
                continue
            if len(row) != len(names):
                raise InputFormatError(f"{len(row)} fields, expected {len(names)} as in the header", path=spath, line=line)
            try:
                x, y = float(row[ix]), float(row[iy])
            except ValueError:
                bad = row[ix] if not _is_float(row[ix]) else row[iy]
                raise InputFormatError(
                    f"non-numeric coordinate {bad.strip()!r}; expected a number", path=spath, line=line
                ) from None
            if not (np.isfinite(x) and np.isfinite(y)):
                raise InputFormatError(f"non-finite coordinate ({x}, {y}); expected finite numbers", path=spath, line=line)
            label = row[io].strip().lower()
            if label in _TRUE:
                occ.append(True)
            elif label in _FALSE:
                occ.append(False)
            else:
                raise InputFormatError(f"occupied value {row[io].strip()!r}; expected 0/1 or true/false", path=spath, line=line)
            xy.append((x, y))
    if not xy:
        raise InputFormatError("no data rows after the header; expected at least one point", path=spath)
    return _observations(np.array(xy, dtype=float).reshape(-1, 2), np.array(occ, dtype=bool))


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_npz(path: Path) -> Observations:
    spath = str(path)
    data = load_npz(path, "points .npz file")
    missing = [k for k in ("points", "occupied") if k not in data]
    if missing:
        raise InputFormatError(
            f"missing array(s) {', '.join(missing)} (has {sorted(data)}); expected 'points' and 'occupied'",
            path=spath,
        )
    points, occupied = data["points"], data["occupied"]
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputFormatError(f"'points' has shape {points.shape}; expected (n, 2)", path=spath)
    if occupied.shape != (points.shape[0],):
        raise InputFormatError(
            f"'occupied' has shape {occupied.shape}; expected ({points.shape[0]},) to match 'points'", path=spath
        )
    real = np.issubdtype(points.dtype, np.integer) or np.issubdtype(points.dtype, np.floating)
    if not real:
        raise InputFormatError(f"'points' has dtype {points.dtype}; expected real numbers (float or int)", path=spath)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise InputFormatError(
            f"'points' row {bad} is {points[bad].tolist()}; expected finite numbers ({int((~finite).sum())} rows are not)",
            path=spath,
        )
    if occupied.dtype != bool:
        real = np.issubdtype(occupied.dtype, np.integer) or np.issubdtype(occupied.dtype, np.floating)
        if not real or not np.isin(occupied, (0, 1)).all():
            raise InputFormatError(f"'occupied' (dtype {occupied.dtype}) must be boolean or 0/1", path=spath)
    return _observations(points.astype(float), occupied.astype(bool))


def read_points(path: str | os.PathLike[str]) -> Observations:
    """Read labelled points from a CSV or NPZ file.

    Parameters
    ----------
    path : path-like
        ``.npz`` is read as NPZ, anything else as CSV.

    Returns
    -------
    Observations
        ``points`` of shape (n, 2), ``occupied`` of shape (n,), ``scan_index`` zeros.

    Raises
    ------
    InputFormatError
        Missing file or column / array, non-numeric value (CSV: with its line), bad shape.
    """
    p = regular_file(path, "points file (CSV or NPZ)")
    if p.suffix.lower() == ".npz":
        return _read_npz(p)
    return _read_csv(p)


def write_points(path: str | os.PathLike[str], observations: Observations) -> None:
    """Write labelled points as CSV (``x,y,occupied`` with 0/1) or NPZ, by the suffix of `path`.

    Parameters
    ----------
    path : path-like
        ``.npz`` writes NPZ (arrays ``points`` (n, 2) and ``occupied`` (n,)); anything else CSV.
    observations : Observations
    """
    p = Path(path)
    pts = np.asarray(observations.points, dtype=float).reshape(-1, 2)
    occ = np.asarray(observations.occupied, dtype=bool)
    if p.suffix.lower() == ".npz":
        # Write through a file object so numpy does not append a second ".npz".
        with p.open("wb") as f:
            np.savez(f, points=pts, occupied=occ)
        return
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(_REQUIRED)
        # repr-precision floats so a round trip is exact.
        w.writerows((repr(float(x)), repr(float(y)), int(o)) for (x, y), o in zip(pts, occ))
