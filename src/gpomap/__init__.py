"""gpomap: continuous occupancy maps with multi-support Gaussian processes."""

from __future__ import annotations

import os
from typing import Any

from gpomap._version import __version__
from gpomap.errors import GpomapError
from gpomap.scans import Scan

__all__ = ["GpomapError", "Scan", "load_map", "__version__"]


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
