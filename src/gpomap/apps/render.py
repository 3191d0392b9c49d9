"""A saved map read again: its header, the region it is written over, and the output directory it may not replace.

The map file (``map.gpom``, :mod:`gpomap.io.mapfile`) holds the fitted model; these are the jobs
``gpomap render``, ``query`` and ``update`` (:mod:`gpomap.cli.render`) share before the map is
loaded: what its header says, and which region a written grid covers (the data's box grown as
``TiledGPOM.grid`` grows it, unless given).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap.errors import GpomapError

__all__ = ["map_header", "padded_bounds", "written_extent", "check_not_replaced"]


def map_header(path: str) -> dict[str, Any]:
    """The header of the map file `path` (:func:`gpomap.io.mapfile.read_map_header`).

    Raises
    ------
    GpomapError
        A streaming state still in its warm-up (it holds no map).
    """
    from gpomap.io.mapfile import read_map_header

    header = read_map_header(path)
    summary = header["summary"]
    if header["kind"] == "stream" and not summary.get("ready", False):
        warm = summary.get("warmup", ["?", "?"])
        raise GpomapError(f"{path}: a streaming state still warming up ({warm[0]} of {warm[1]} scans): it holds no map yet")
    return header


def padded_bounds(summary: dict[str, Any], resolution: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The default written extent's corners, shape (dim,) each: the data's box grown as ``TiledGPOM.grid`` grows it."""
    from gpomap.lattice import EXTENT_MARGIN_CELLS

    lo, hi = (np.asarray(b, dtype=float) for b in summary["bounds"])
    pad = EXTENT_MARGIN_CELLS * resolution
    return lo - pad, hi + pad


def written_extent(
    summary: dict[str, Any],
    resolution: float,
    extent: Sequence[float] | None = None,
    z_range: Sequence[float] | None = None,
) -> tuple[float, ...] | None:
    """The extent to pass to a saved map's ``grid``.

    Parameters
    ----------
    summary : dict
        The map's ``dim`` and ``bounds`` (its header's summary).
    resolution : float
        The written grid's cell side, metres.
    extent : (xmin, xmax, ymin, ymax), optional
        The region asked for in x and y.
    z_range : (zmin, zmax), optional
        The heights asked for (3-D maps).

    Returns
    -------
    tuple of float or None
        None for the map's default; else `extent` (2-D), or the data's box grown as the default
        grows it, with x, y from `extent` and z from `z_range` (3-D: xmin, xmax, ymin, ymax, zmin, zmax).
    """
    if summary["dim"] == 2:
        return None if extent is None else tuple(extent)
    if extent is None and z_range is None:
        return None
    lo, hi = padded_bounds(summary, resolution)
    if extent is not None:
        lo[:2], hi[:2] = (extent[0], extent[2]), (extent[1], extent[3])
    if z_range is not None:
        lo[2], hi[2] = z_range
    from gpomap.lattice import bounds_extent

    return tuple(float(v) for v in bounds_extent(lo, hi))


def check_not_replaced(mapfile: str, outdir: str) -> None:
    """Refuse an `outdir` whose output set holds `mapfile`: a new set there would remove it.

    Raises
    ------
    GpomapError
        Naming the directory and the map file.
    """
    from gpomap.io.atomic import MANIFEST

    m, out = Path(mapfile).resolve(), Path(outdir).resolve()
    if m.parent != out:
        return
    try:
        files = json.loads((out / MANIFEST).read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        return
    if m.name in files:
        raise GpomapError(
            f"-o {outdir}: its output set holds {m.name}, the map being rendered, which the new set would remove; "
            "write the render to another directory"
        )
