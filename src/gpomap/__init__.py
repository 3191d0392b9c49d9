"""gpomap: continuous occupancy maps with multi-support Gaussian processes.

The names a user needs are here: the estimator (:class:`AreaGPOM`) and its streaming form
(:class:`StreamingGPOM`), the readers (:func:`read_scans`, :func:`read_clouds`), the fitted map
every answer comes from (:class:`FittedMap`, an estimator's ``map_``), the maps it writes
(:class:`OccupancyMap`, :class:`VoxelMap`), the writers (:func:`write_map_outputs`,
:func:`write_voxel_outputs`) and the map file (:func:`save_map`, :func:`load_map`). Each is
imported when first asked for, so ``import gpomap`` stays light.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

from gpomap._version import __version__
from gpomap.errors import GpomapError
from gpomap.scans import Scan

if TYPE_CHECKING:
    from gpomap.clouds import CloudScan
    from gpomap.fitted import FittedMap
    from gpomap.grid import OccupancyMap
    from gpomap.io import read_clouds, read_scans
    from gpomap.io.export import write_map_outputs
    from gpomap.io.mapfile import save_fitted_map as save_map
    from gpomap.io.voxel_outputs import write_voxel_outputs
    from gpomap.mapping import AreaGPOM
    from gpomap.scans import select_scans
    from gpomap.streaming import StreamingGPOM
    from gpomap.voxels import VoxelMap

#: Public name: (module, attribute), imported on first use (:func:`__getattr__`).
_LAZY: dict[str, tuple[str, str]] = {
    "AreaGPOM": ("gpomap.mapping", "AreaGPOM"),
    "StreamingGPOM": ("gpomap.streaming", "StreamingGPOM"),
    "CloudScan": ("gpomap.clouds", "CloudScan"),
    "FittedMap": ("gpomap.fitted", "FittedMap"),
    "OccupancyMap": ("gpomap.grid", "OccupancyMap"),
    "VoxelMap": ("gpomap.voxels", "VoxelMap"),
    "read_scans": ("gpomap.io", "read_scans"),
    "read_clouds": ("gpomap.io", "read_clouds"),
    "select_scans": ("gpomap.scans", "select_scans"),
    "write_map_outputs": ("gpomap.io.export", "write_map_outputs"),
    "write_voxel_outputs": ("gpomap.io.voxel_outputs", "write_voxel_outputs"),
    "save_map": ("gpomap.io.mapfile", "save_fitted_map"),
}

__all__ = [
    "AreaGPOM",
    "CloudScan",
    "FittedMap",
    "GpomapError",
    "OccupancyMap",
    "Scan",
    "StreamingGPOM",
    "VoxelMap",
    "__version__",
    "load_map",
    "read_clouds",
    "read_scans",
    "save_map",
    "select_scans",
    "write_map_outputs",
    "write_voxel_outputs",
]


def __getattr__(name: str) -> Any:
    """The public names of :data:`_LAZY`, imported when first asked for (PEP 562)."""
    if name in _LAZY:
        module, attribute = _LAZY[name]
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gpomap' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


def load_map(path: str | os.PathLike[str]) -> Any:
    """The fitted map saved in a map file (``map.gpom``, written by ``gpomap map``): the model itself.

    Its ``predict_proba(points, return_var=False)`` and ``grid(resolution, extent=None)`` (an
    :class:`~gpomap.grid.OccupancyMap`, a :class:`~gpomap.voxels.VoxelMap` in 3-D) answer as the
    model that was saved, to the bit, at any points and any resolution; ``update(scans)`` adds
    scans. See :func:`gpomap.io.mapfile.load_fitted_map`. A written grid (``map.npz``, numbers on
    the cells of one resolution) is read by :func:`gpomap.io.npz.load_map` instead.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    TiledGPOM
        (an :class:`~gpomap.mapping.AreaGPOM` for a map of ``gpomap map``).

    Raises
    ------
    InputFormatError
        One line naming the file and what was expected: not a map file, truncated, another
        format version.
    """
    from gpomap.io.mapfile import load_fitted_map

    return load_fitted_map(path)
