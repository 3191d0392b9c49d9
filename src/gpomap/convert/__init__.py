"""From an occupancy grid, or an OctoMap octree, to a continuous GP occupancy map.

A grid (a ROS map_server map, or an :class:`~gpomap.grid.OccupancyMap` such as one read from an
``.npz``) already says how much of each pixel is occupied. Each known pixel's value is read as the
fraction of its area that is occupied (:func:`grid_fractions`): 0 free, 1 occupied, between them
partly occupied, as a grid made by averaging a finer one has it; unknown pixels are not evidence.
The pixels become GP inputs over their squares (:func:`grid_cells`), the MSK-GPOM model is fitted
on them, and the continuous map is sampled back onto a grid at any resolution.

    >>> result = convert_grid("map.yaml", resolution=0.01)      # doctest: +SKIP
    >>> write_rosmap(result.map, "map_fine.yaml")               # doctest: +SKIP

Output grid geometry
--------------------
By default the output covers the source's extent with the source's origin convention (origin = the
lower-left corner of the lower-left cell). The origin is always kept, so the output sits exactly on
the source in ROS tools. When the new resolution divides the source's width and height (0.05 m
written at 0.01 m, 0.025 m or 0.1 m, 0.2 m for a 384-pixel map, ...) the outer edges coincide too.
Otherwise the grid gets as many whole cells as are needed to cover the source, so its top and right
edges lie up to one output cell beyond the source's (they are never cropped short of it).

Defaults (measured with benchmarks/convert_maps.py; see docs/convert.md)
-------------------------------------------------------------------------
- values read as fractions (``values="auto"``): a ROS map in trinary mode, whose values are codes,
  and a map with a latent variance (a GP's belief, such as gpomap's own ``.npz``) are read as
  free / occupied / unknown by their thresholds instead;
- each pixel read by how the grid was made from a finer one (``pooling="auto"``,
  :func:`read_pixels`, :func:`infer_pooling`): values between 0 and 1 are occupied shares (mean
  pooling); a grid of 0s and 1s is any-pixel pooled (a 0 wholly free, a 1 holding something,
  taken as :data:`OCCUPIED_FRACTION` occupied, or, told the grid's ``pooling_factor``, a 1 beside
  unknown space as the front of a wall whose back no sensor saw) unless its walls are broken as majority pooling
  breaks thin walls (a 1 more than half occupied, a 0 at most half, and a 0 beside a 1 taken as
  :data:`MAJORITY_NEIGHBOUR_SHARE` occupied); a grid read by its thresholds is any-pixel pooled;
- wall-aware GP inputs (:func:`grid_cells`): pixels within 3 pixels of one holding anything
  occupied are cells of their own (each its pixel's square, its target 2 s - 1, the mean of the
  +-1 occupancy over it for a share s), free pixels farther away are merged into blocks of at
  most ``max_cell`` = 4 pixels; each pixel holding anything occupied also gets a point where its
  obstacle most likely is (its centre, or the centre of the part away from its free sides that
  its share fills), 3 times noisier than a pixel cell;
- the map keeps what each pixel says (:class:`GridGPOM`): nothing occupied in a pixel the grid
  holds wholly free, each pixel's mean probability its share or within the pooling's bounds,
  and an occupied region (p > 0.5) that, pooled again the same way, gives back the grid; within
  the known pixels the latent mean is squashed at a one-pixel input's variance;
- squared-exponential kernel with the exact closed-form area kernel; on a grid it is a product of
  per-axis factors, which the prediction on the output grid tables once per row and column;
- length scale one source pixel and noise 0.1, not learnt (``optimise=False``); the squash's
  alpha and beta are fitted, to the soft targets where there are any (an input of target
  2 f - 1 counts as occupied with weight f and free with weight 1 - f).

Any of these can be overridden through ``**model_options`` (the :class:`GridGPOM` constructor
arguments: those of :class:`~gpomap.settings.MapSettings`, ``pixel_pad``, ``wall_reach``,
``edge_strip``, ``centre_noise``, ``occupied_fraction`` and ``pooling``; ``optimise=True`` learns the length
scale and noise; ``wall_reach=None`` gives the cell tree over footprints of before,
``pixel_pad=0`` the centre boxes of before that). ``free_step``, ``hit_margin`` and
``no_return_cap`` concern laser beams and have no effect here.

Where each part lives
---------------------
- :mod:`~gpomap.convert.grids`: reading a grid (files, pixel values, known pixels as labelled
  points) and the output grid's geometry;
- :mod:`~gpomap.convert.pooling`: how the grid was made from a finer one, and what each pixel
  then says (:func:`read_pixels`, :func:`infer_pooling`);
- :mod:`~gpomap.convert.inputs`: the GP inputs over the pixels (:func:`grid_cells`);
- :mod:`~gpomap.convert.estimator`: the estimator, its map held to the pixels (:class:`GridGPOM`),
  and its settings for a pixel size (:func:`model_defaults`);
- :mod:`~gpomap.convert.grid_conversion`: a grid converted and sampled (:func:`convert_grid`);
- :mod:`~gpomap.convert.agreement`: how well a map keeps the source's labels;
- :mod:`~gpomap.convert.octree`, :mod:`~gpomap.convert.octree_tiles` and
  :mod:`~gpomap.convert.octree_tiling`: an octree in 3-D (:func:`convert_octree`), in tiles when
  one GP cannot hold it (:class:`TiledOctreeModel`, whose fitted map's field is :class:`ColumnsField`).

Every public name of these modules is importable from :mod:`gpomap.convert`.
"""

from __future__ import annotations

from gpomap.convert.agreement import label_agreement
from gpomap.convert.estimator import (
    FOOTPRINT_PIXELS,
    HELD_SCALE,
    LENGTH_SCALE_BOUNDS_PIXELS,
    LENGTH_SCALE_PIXELS,
    MAX_CELL_PIXELS,
    MIN_CELL_PIXELS,
    SHARE_SAMPLES,
    GridGPOM,
    model_defaults,
)
from gpomap.convert.grid_conversion import GRID_LENGTH_SCALE_PIXELS, ConversionResult, convert_grid, converter_for
from gpomap.convert.grids import (
    FRACTION_TOLERANCE,
    VALUE_READINGS,
    GridObservations,
    GridSource,
    grid_fractions,
    grid_to_observations,
    load_grid,
    output_grid,
    value_reading,
)
from gpomap.convert.inputs import CENTRE_NOISE, EDGE_STRIP_PIXELS, WALL_REACH_PIXELS, GridCells, grid_cells
from gpomap.convert.octree import (
    DEFAULT_MAX_CELLS,
    MARGIN_VOXELS,
    MAX_CHECK,
    OctreeConversion,
    OctreeSource,
    convert_octree,
    octree_to_observations,
    region,
)
from gpomap.convert.octree_tiles import BAND_LAYERS, TILE_SIDES, VARIANCE_STEP_SOURCE_VOXELS, ColumnsField, TiledOctreeModel
from gpomap.convert.pooling import (
    BROKEN_SHARE,
    MAJORITY_NEIGHBOUR_SHARE,
    MAJORITY_REACH,
    OCCUPIED_FRACTION,
    POOLINGS,
    PixelReading,
    boundary_wall_thickness,
    infer_pooling,
    occluded_share,
    pixel_lattice,
    read_pixels,
)

__all__ = [
    # grids
    "GridSource",
    "GridObservations",
    "VALUE_READINGS",
    "FRACTION_TOLERANCE",
    "load_grid",
    "value_reading",
    "grid_fractions",
    "grid_to_observations",
    "output_grid",
    # pooling
    "POOLINGS",
    "OCCUPIED_FRACTION",
    "MAJORITY_NEIGHBOUR_SHARE",
    "MAJORITY_REACH",
    "BROKEN_SHARE",
    "PixelReading",
    "boundary_wall_thickness",
    "occluded_share",
    "infer_pooling",
    "pixel_lattice",
    "read_pixels",
    # inputs
    "WALL_REACH_PIXELS",
    "EDGE_STRIP_PIXELS",
    "CENTRE_NOISE",
    "GridCells",
    "grid_cells",
    # estimator
    "MIN_CELL_PIXELS",
    "MAX_CELL_PIXELS",
    "FOOTPRINT_PIXELS",
    "HELD_SCALE",
    "SHARE_SAMPLES",
    "LENGTH_SCALE_PIXELS",
    "LENGTH_SCALE_BOUNDS_PIXELS",
    "GridGPOM",
    "model_defaults",
    # grid conversion
    "GRID_LENGTH_SCALE_PIXELS",
    "ConversionResult",
    "converter_for",
    "convert_grid",
    "label_agreement",
    # octrees
    "OctreeSource",
    "OctreeConversion",
    "TiledOctreeModel",
    "ColumnsField",
    "octree_to_observations",
    "convert_octree",
    "region",
    "MARGIN_VOXELS",
    "MAX_CHECK",
    "DEFAULT_MAX_CELLS",
    "TILE_SIDES",
    "VARIANCE_STEP_SOURCE_VOXELS",
    "BAND_LAYERS",
]
