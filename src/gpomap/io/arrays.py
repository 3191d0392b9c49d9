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
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import InputFormatError
from gpomap.observations import Observations

__all__ = ["read_points", "write_points"]

_REQUIRED = ("x", "y", "occupied")
_TRUE = {"1", "true", "t", "yes", "1.0"}
_FALSE = {"0", "false", "f", "no", "0.0"}


def _observations(points: NDArray[np.float64], occupied: NDArray[np.bool_]) -> Observations:
    return Observations(points=points, occupied=occupied, scan_index=np.zeros(len(points), dtype=np.intp))


def _read_csv(path: Path) -> Observations:
    spath = str(path)
    with path.open(newline="") as f:
        rows = csv.reader(f)
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
                raise InputFormatError(
                    f"{len(row)} fields, expected {len(names)} as in the header", path=spath, line=line
                )
            try:
                x, y = float(row[ix]), float(row[iy])
            except ValueError:
                bad = row[ix] if not _is_float(row[ix]) else row[iy]
                raise InputFormatError(
                    f"non-numeric coordinate {bad.strip()!r}; expected a number", path=spath, line=line
                ) from None
            if not (np.isfinite(x) and np.isfinite(y)):
                raise InputFormatError(
                    f"non-finite coordinate ({x}, {y}); expected finite numbers", path=spath, line=line
                )
            label = row[io].strip().lower()
            if label in _TRUE:
                occ.append(True)
            elif label in _FALSE:
                occ.append(False)
            else:
                raise InputFormatError(
                    f"occupied value {row[io].strip()!r}; expected 0/1 or true/false", path=spath, line=line
                )
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
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputFormatError(f"not a readable .npz file ({exc})", path=spath) from None
    with data:
        missing = [k for k in ("points", "occupied") if k not in data.files]
        if missing:
            raise InputFormatError(
                f"missing array(s) {', '.join(missing)} (has {sorted(data.files)}); expected 'points' and 'occupied'",
                path=spath,
            )
        points, occupied = data["points"], data["occupied"]
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputFormatError(f"'points' has shape {points.shape}; expected (n, 2)", path=spath)
    if occupied.shape != (points.shape[0],):
        raise InputFormatError(
            f"'occupied' has shape {occupied.shape}; expected ({points.shape[0]},) to match 'points'", path=spath
        )
    if not (np.issubdtype(points.dtype, np.number) and np.isfinite(points).all()):
        raise InputFormatError("'points' must hold finite numbers", path=spath)
    if occupied.dtype != bool:
        if not np.issubdtype(occupied.dtype, np.number) or not np.isin(occupied, (0, 1)).all():
            raise InputFormatError("'occupied' must be boolean or 0/1", path=spath)
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
    p = Path(path)
    if not p.is_file():
        raise InputFormatError("no such file", path=str(p))
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
