"""What gpomap's own files hold, for ``gpomap info``: a fitted map (``map.gpom``, or a streaming
state), a written grid (``map.npz``) or a written voxel map (a 3-D map's ``map.npz``).

A fitted map is described from its header alone (:func:`gpomap.io.mapfile.read_map_header`), so a
building's map of a gigabyte answers at once; a written grid is read whole, as it is the cells.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.grid import FREE, OCCUPIED, UNKNOWN

__all__ = ["describe_own_file", "own_format"]

#: The names :func:`own_format` gives gpomap's files.
FITTED_MAP, GRID, VOXELS = "gpomap-fitted-map", "gpomap-occupancy-map", "gpomap-voxel-map"


def own_format(path: str | os.PathLike[str]) -> str | None:
    """Which of gpomap's own files `path` is: :data:`FITTED_MAP`, :data:`GRID` or :data:`VOXELS`;
    None for anything else (range data, labelled points, a directory, a file that cannot be read).

    Only the archive's member names and its ``format`` member are read; a ``.gpom`` file is a
    fitted map whatever it holds (its reader names what is wrong with it).
    """
    p = Path(path)
    if p.suffix == ".gpom" and p.is_file():
        return FITTED_MAP  # read as one, so that a damaged map file is named as such
    if not p.is_file() or not zipfile.is_zipfile(p):
        return None
    try:
        with zipfile.ZipFile(p) as zf:
            names = set(zf.namelist())
            if "header.npy" in names:
                return FITTED_MAP
            if "format.npy" not in names:
                return None
            with zf.open("format.npy") as member:
                fmt = np.lib.format.read_array(member, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return None
    found = str(fmt) if fmt.shape == () and fmt.dtype.kind == "U" else None
    return found if found in (GRID, VOXELS) else None


def describe_own_file(path: str | os.PathLike[str], fmt: str) -> dict[str, Any]:
    """Summary of one of gpomap's own files (`fmt` as :func:`own_format` names it), for ``gpomap info``.

    Returns
    -------
    dict
        ``path``, ``format``, ``file_size``; for a fitted map its header's summary (``kind``,
        ``written_by``, ``model``, ``extent``, ``n_scans``, ``scans_kept``, ``n_tiles``,
        ``n_cells``, ``largest_tile_cells``, ``hyperparameters``, ``thresholds``,
        ``ray_counts``, ``no_return_cap``, and a stream's ``ready`` and ``n_scans_added``); for a
        written grid or voxel map ``cells`` (its shape), ``resolution``, ``extent``,
        ``thresholds``, ``free``, ``occupied`` and ``unknown`` (counts and shares),
        ``probability`` (its range), ``variance`` (whether it holds one) and, for a grid,
        ``robot_path``.

    Raises
    ------
    InputFormatError
        One line naming the file, as the file's own reader says it (another format version, a
        truncated file, arrays of the wrong shape).
    """
    from gpomap.resources import format_bytes

    info: dict[str, Any] = {"path": str(path)}
    size = format_bytes(Path(path).stat().st_size)
    if fmt == FITTED_MAP:
        info.update(_fitted_map(path))
    elif fmt == GRID:
        from gpomap.io.npz import load_map

        grid = load_map(path)
        info["format"] = "gpomap written grid (map.npz)"
        info.update(_cells(grid, grid.grid.resolution, np.asarray(grid.grid.origin)))
        info["robot_path"] = "none" if grid.path is None else f"{len(grid.path)} poses"
    elif fmt == VOXELS:
        from gpomap.io.voxel_outputs import load_voxels

        voxels = load_voxels(path)
        info["format"] = "gpomap written voxel map (map.npz)"
        info.update(_cells(voxels, voxels.spec.resolution, np.asarray(voxels.spec.origin)))
    else:
        raise ValueError(f"not one of gpomap's own formats: {fmt!r}")
    info["file_size"] = size
    return info


def _fitted_map(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The header of a map file, as :func:`describe_own_file` gives it."""
    from gpomap.io.mapfile import read_map_header

    header = read_map_header(path)
    summary = dict(header["summary"])
    lo, hi = summary.pop("bounds")
    hyper = summary.pop("hyperparameters")
    dim = int(summary.pop("dim"))
    evidence = summary.pop("ray_evidence")
    resolution = summary.pop("evidence_resolution")
    out: dict[str, Any] = {
        "format": f"gpomap fitted map (map.gpom, version {header['version']})",
        "kind": "streaming state" if header["kind"] == "stream" else "map",
        "written_by": header.get("written_by", "unknown"),
        "model": f"{str(summary.pop('class')).rsplit('.', 1)[-1]}, {dim}-D",
        "extent": tuple(float(v) for pair in zip(lo, hi, strict=True) for v in pair),
        "n_scans": summary.pop("n_scans"),
        "scans_kept": summary.pop("scans_kept"),
        "n_tiles": summary.pop("n_tiles"),
        "n_cells": summary.pop("n_cells"),
        "largest_tile_cells": summary.pop("largest_tile_cells"),
        "hyperparameters": ", ".join(f"{k} {float(v):.4g}" for k, v in hyper.items()),
        "thresholds": tuple(float(t) for t in summary.pop("thresholds")),
        "ray_counts": f"on {float(resolution):g} m cells" if evidence else "off",
        "no_return_cap": summary.pop("no_return_cap"),
    }
    out.update(summary)  # a stream's readiness and scans added
    return out


def _cells(written: Any, resolution: float, origin: NDArray[np.float64]) -> dict[str, Any]:
    """A written map's (:class:`~gpomap.grid.OccupancyMap` or :class:`~gpomap.voxels.VoxelMap`)
    cells: shape, resolution, extent, classes, probability range, thresholds and whether it holds
    a variance."""
    probability, ternary = written.probability, written.ternary
    shape = probability.shape  # (ny, nx) or (nz, ny, nx)
    upper = origin + resolution * np.array(shape[::-1], dtype=float)
    n = max(int(ternary.size), 1)
    out: dict[str, Any] = {
        "cells": " x ".join(str(s) for s in shape[::-1]),
        "resolution": float(resolution),
        "extent": tuple(float(v) for pair in zip(origin, upper, strict=True) for v in pair),
    }
    for name, label in (("free", FREE), ("occupied", OCCUPIED), ("unknown", UNKNOWN)):
        count = int(np.count_nonzero(ternary == label))
        out[name] = f"{count} ({100 * count / n:.1f} %)"
    finite = probability[np.isfinite(probability)]
    out["probability"] = (float(finite.min()), float(finite.max())) if finite.size else None
    out["thresholds"] = tuple(float(t) for t in written.thresholds)
    out["variance"] = written.variance is not None
    return out
