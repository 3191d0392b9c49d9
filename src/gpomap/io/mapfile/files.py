"""The map file itself: the archive, its header and version, saving and loading (:mod:`gpomap.io.mapfile`)."""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gpomap.errors import GpomapError, InputFormatError
from gpomap.io.atomic import atomic_write
from gpomap.io.checks import MAX_NPZ_ARRAY_BYTES, load_npz, regular_file
from gpomap.io.mapfile.encoding import _HEADER, _name, _Reader, _StateError, _Writer
from gpomap.io.members import write_member

FORMAT = "gpomap-fitted-map"
#: Raised whenever what a map file holds changes; a file of another version is refused.
VERSION = 4
#: The map file ``gpomap map`` writes beside its grids: ``.gpom``, not ``.npz``, so that it is never
#: taken for the written grid ``map.npz`` (though both are zip archives of NumPy arrays).
FILENAME = "map.gpom"
_WHAT = "gpomap map file (.gpom, written by gpomap map or save_fitted_map)"


def _summary(model: Any) -> dict[str, Any]:
    lo, hi = model.bounds_
    from gpomap.tiles import light_tiles

    cells = [s.n_cells for s in light_tiles(model.tiles_)]
    return {
        "class": _name(type(model)),
        "dim": int(model.dim_),
        "bounds": [[float(v) for v in lo], [float(v) for v in hi]],
        "n_scans": int(model._n_scans),
        "scans_kept": model._scans is not None,
        "n_tiles": len(cells),
        "largest_tile_cells": int(max(cells)) if cells else 0,
        "n_cells": int(model.n_inputs_),
        "hyperparameters": {k: float(v) for k, v in model.hyperparameters_.items()},
        "thresholds": [float(t) for t in model.thresholds_],
        "ray_evidence": model.evidence_ is not None,
        "no_return_cap": model.base.no_return_cap,
        "evidence_resolution": float(model.base.evidence_resolution_3d if model.dim_ == 3 else model.base.evidence_resolution),
    }


def _write(path: str | os.PathLike[str], obj: Any, where: str, header: Callable[[Any], dict[str, Any]]) -> Path:
    """The archive of `obj`: every array as the state is encoded, then the header (``header(state)``)."""
    target = Path(path)
    with atomic_write(target, "wb") as f, zipfile.ZipFile(f, "w", allowZip64=True) as zf:
        state = _Writer(lambda key, array: write_member(zf, key, array)).encode(obj, where)
        text = json.dumps(header(state), allow_nan=True, separators=(",", ":"))
        write_member(zf, _HEADER, np.array(text))
    return target


def save_fitted_map(model: Any, path: str | os.PathLike[str]) -> Path:
    """Write a fitted map to `path` (``map.gpom`` by convention), atomically.

    Parameters
    ----------
    model : TiledGPOM
        A fitted map (an :class:`~gpomap.mapping.AreaGPOM`, or a
        :class:`~gpomap.streaming.StreamingGPOM`'s ``model_``), 2-D or 3-D. Saved as it is,
        tiles waiting for a refresh included: the file predicts what the model predicts now.
        Not to be changed by another thread while it is saved.
    path : path-like
        Written exactly as given (no suffix is added).

    Returns
    -------
    Path

    Raises
    ------
    TypeError
        `model` is not a TiledGPOM, or holds something a map file cannot (see :func:`saved_classes`).
    NotFittedError
        `model` is not fitted.
    """
    from gpomap._version import __version__
    from gpomap.tiles import TiledGPOM

    if not isinstance(model, TiledGPOM):
        hint = (
            " (a StreamingGPOM: save its model_, or its whole state with save_streaming_state)"
            if hasattr(model, "model_")
            else ""
        )
        raise TypeError(f"save_fitted_map takes a fitted TiledGPOM or AreaGPOM, got {type(model).__name__}{hint}")
    model._check_fitted()
    summary = _summary(model)

    def header(state: Any) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "written_by": f"gpomap {__version__}",
            "kind": "map",
            "summary": summary,
            "state": state,
        }

    return _write(path, model, "map", header)


def save_streaming_state(mapper: Any, path: str | os.PathLike[str]) -> Path:
    """Write a :class:`~gpomap.streaming.StreamingGPOM`'s whole state to `path`, to resume it later.

    The file is a map file of kind ``"stream"``: :func:`load_streaming_state` gives the mapper
    back (scans absorbed, tiles waiting, statistics, the warm-up's scans if it is not over), and
    :func:`load_fitted_map` its map, once the warm-up is over.

    Parameters
    ----------
    mapper : StreamingGPOM
    path : path-like

    Returns
    -------
    Path
    """
    from gpomap._version import __version__
    from gpomap.streaming import StreamingGPOM

    if not isinstance(mapper, StreamingGPOM):
        raise TypeError(f"save_streaming_state takes a StreamingGPOM, got {type(mapper).__name__}")
    summary: dict[str, Any] = {"ready": mapper.model_ is not None, "n_scans_added": int(mapper.n_scans_)}
    if mapper.model_ is not None:
        summary.update(_summary(mapper.model_))
    else:
        summary["warmup"] = [len(mapper._buffer), mapper.warmup_scans]

    def header(state: Any) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "written_by": f"gpomap {__version__}",
            "kind": "stream",
            "summary": summary,
            "state": state,
        }

    return _write(path, mapper, "stream", header)


def _not_a_map(path: str, found: str) -> InputFormatError:
    return InputFormatError(f"not a gpomap map file: {found}; expected a {_WHAT}", path=path)


def read_map_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The header of a map file (format, version, kind, summary, state), read alone: cheap, whatever the map's size.

    Raises
    ------
    InputFormatError
        One line naming the file: not a file, not a zip archive, truncated or corrupt, not a
        gpomap map file (a written grid ``map.npz`` is named as such), another format version.
    """
    name = str(path)
    p = regular_file(path, _WHAT)
    try:
        with p.open("rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise InputFormatError(f"cannot read the file ({exc}); expected a {_WHAT}", path=name) from None
    if not head.startswith(b"PK"):
        found = "a single NumPy array (.npy)" if head.startswith(b"\x93NUM") else f"a file starting with {head!r}"
        raise _not_a_map(name, found)
    try:
        with zipfile.ZipFile(p) as zf:
            names = zf.namelist()
            if f"{_HEADER}.npy" not in names:
                if "format.npy" in names:
                    with zf.open("format.npy") as m:
                        fmt = str(np.lib.format.read_array(m, allow_pickle=False))
                    grid = " (a written grid: gpomap.io.npz.load_map reads it)" if fmt == "gpomap-occupancy-map" else ""
                    raise _not_a_map(name, f"a file of format {fmt!r}{grid}")
                raise _not_a_map(name, "a zip archive without a 'header' array")
            info = zf.getinfo(f"{_HEADER}.npy")
            if info.file_size > MAX_NPZ_ARRAY_BYTES:
                raise _not_a_map(name, f"a header of {info.file_size:,} bytes")
            with zf.open(info) as m:
                header_array = np.lib.format.read_array(m, allow_pickle=False)
    except InputFormatError:
        raise
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        OSError,
        ValueError,
        KeyError,
        NotImplementedError,
        RuntimeError,
    ) as exc:
        raise InputFormatError(
            f"truncated or corrupt ({type(exc).__name__}: {str(exc)[:120]}); expected a {_WHAT}", path=name
        ) from None
    if header_array.shape != () or header_array.dtype.kind != "U":
        raise _not_a_map(name, f"a 'header' array of {header_array.dtype} with shape {header_array.shape}, not one JSON string")
    try:
        header = json.loads(str(header_array))
    except (ValueError, RecursionError):
        raise _not_a_map(name, "a 'header' that is not JSON") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        kind = header.get("format") if isinstance(header, dict) else None
        raise _not_a_map(name, f"a header of format {kind!r}, not {FORMAT!r}")
    version = header.get("version")
    if version != VERSION:
        raise InputFormatError(
            f"map file format version {version!r} (written by {header.get('written_by', 'an unknown gpomap')}); "
            f"this gpomap reads version {VERSION}: refit the map from its log, or use the gpomap that wrote it",
            path=name,
        )
    if header.get("kind") not in ("map", "stream") or not isinstance(header.get("summary"), dict):
        raise _not_a_map(name, f"a header of unknown kind {header.get('kind')!r}")
    return header


def _load_state(path: str | os.PathLike[str], header: dict[str, Any]) -> Any:
    arrays = load_npz(path, _WHAT)
    arrays.pop(_HEADER, None)
    try:
        return _Reader(arrays, str(path)).decode(header["state"])
    except _StateError as exc:
        raise InputFormatError(f"map file state: {exc}", path=str(path)) from None
    except (GpomapError, KeyError, TypeError, ValueError, AttributeError, IndexError, ArithmeticError, RecursionError) as exc:
        raise InputFormatError(
            f"map file state is not what gpomap writes ({type(exc).__name__}: {str(exc)[:160]}): an altered file", path=str(path)
        ) from None


def load_fitted_map(path: str | os.PathLike[str]) -> Any:
    """Read the fitted map of a map file (``gpomap.load_map``).

    Parameters
    ----------
    path : path-like
        A file written by :func:`save_fitted_map` (``gpomap map``'s ``map.gpom``), or by
        :func:`save_streaming_state` once its warm-up was over (its map, as it stood).

    Returns
    -------
    TiledGPOM
        The model that was saved (an :class:`~gpomap.mapping.AreaGPOM` from ``gpomap map``):
        ``predict_proba(points, return_var=False)``, ``predict``, ``grid(resolution, extent=None)``
        (an :class:`~gpomap.grid.OccupancyMap`, or a :class:`~gpomap.voxels.VoxelMap` in 3-D),
        ``summary()``, and ``update(scans)`` to add scans. Its tiles run in this process or on
        local workers, as its ``n_workers`` says.

    Raises
    ------
    InputFormatError
        One line naming the file and what was expected (see :func:`read_map_header`), or a
        streaming state still in its warm-up (no map yet).
    """
    header = read_map_header(path)
    obj = _load_state(path, header)
    if header["kind"] == "stream":
        if obj.model_ is None:
            warm = header["summary"].get("warmup", ["?", "?"])
            raise InputFormatError(
                f"a streaming state still warming up ({warm[0]} of {warm[1]} scans): it holds no map yet", path=str(path)
            )
        return obj.model_
    return obj


def load_streaming_state(path: str | os.PathLike[str]) -> Any:
    """Read a :class:`~gpomap.streaming.StreamingGPOM` written by :func:`save_streaming_state`, to add scans to it.

    Raises
    ------
    InputFormatError
        As :func:`read_map_header`, or a map file of kind ``"map"`` (not a streaming state).
    """
    header = read_map_header(path)
    if header["kind"] != "stream":
        raise InputFormatError(
            "holds a fitted map, not a streaming state (written by gpomap stream --save-state or save_streaming_state)",
            path=str(path),
        )
    return _load_state(path, header)
