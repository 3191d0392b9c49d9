"""OctoMap trees to continuous maps: the names of :mod:`gpomap.convert.octree` and
:mod:`gpomap.convert.octree_tiles`, importable here as they were before the conversion became a
package (:mod:`gpomap.convert` gives them too)."""

from __future__ import annotations

from gpomap.convert.octree import (
    DEFAULT_MAX_CELLS,
    MARGIN_VOXELS,
    OctreeConversion,
    convert_octree,
    octree_to_observations,
    region,
)
from gpomap.convert.octree_tiles import TILE_SIDES, VARIANCE_STEP_SOURCE_VOXELS, TiledOctreeModel

__all__ = [
    "OctreeConversion",
    "TiledOctreeModel",
    "octree_to_observations",
    "convert_octree",
    "region",
    "MARGIN_VOXELS",
    "DEFAULT_MAX_CELLS",
    "TILE_SIDES",
    "VARIANCE_STEP_SOURCE_VOXELS",
]
