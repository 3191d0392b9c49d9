"""From an occupancy grid to a continuous GP occupancy map.

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
  taken as :data:`OCCUPIED_FRACTION` occupied) unless its walls are broken as majority pooling
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
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Union

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from gpomap.cells import Cells
from gpomap.errors import EmptyDataError, InputFormatError
from gpomap.estimator import GPMapEstimator, as_points
from gpomap.gp import SupportGP, inverse_diagonal
from gpomap.grid import FREE, OCCUPIED, GridSpec, OccupancyMap, ternary
from gpomap.io.npz import load_map
from gpomap.io.rosmap import RosMap, read_rosmap
from gpomap.kernels.point import make_point_kernel
from gpomap.metrics import roc_auc
from gpomap.observations import Observations
from gpomap.settings import MapSettings
from gpomap.supports import Supports

__all__ = [
    "converter_for",
    "ConversionResult",
    "GridCells",
    "GridGPOM",
    "grid_cells",
    "grid_to_observations",
    "convert_grid",
    "output_grid",
    "load_grid",
    "model_defaults",
]

GridSource = Union[RosMap, OccupancyMap, str, "os.PathLike[str]"]

#: Cell-tree sizes in source pixels (see the module docstring for the measurements behind them).
MIN_CELL_PIXELS = 1.2
MAX_CELL_PIXELS = 4.0
#: Each cell box is widened by this many source pixels on every side: half a pixel turns the
#: bounding box of the cell's pixel centres into the union of its pixels' footprints.
FOOTPRINT_PIXELS = 0.5
#: Known pixels within this many pixels (chessboard distance) of an occupied one are cells of their
#: own; only free pixels farther away are merged into larger cells.
WALL_REACH_PIXELS = 3
#: Width, in source pixels, of the free strip put inside a free pixel along each edge it shares
#: with an occupied pixel: none by default, since a free pixel of a majority-pooled grid may be
#: up to half occupied (docs/convert.md).
EDGE_STRIP_PIXELS = 0.0
#: Noise of the point where an occupied pixel's obstacle most likely is, relative to a one-pixel cell's.
CENTRE_NOISE = 3.0
#: What an occupied pixel of a grid of 0s and 1s is taken to hold: any-pixel pooling marks pixels
#: a thin wall grazes, majority pooling pixels more than half filled (docs/convert.md).
OCCUPIED_FRACTION = 0.7
#: What a free pixel of a majority-pooled grid within :data:`MAJORITY_REACH` pixels (chessboard)
#: of an occupied one is taken to hold: up to half of it may be a wall that continues from its
#: neighbour, and such walls vanish from the grid (docs/convert.md).
MAJORITY_NEIGHBOUR_SHARE = 0.2
MAJORITY_REACH = 1
#: A grid of 0s and 1s more than this share of whose occupied pixels end a wall or touch another
#: only at a corner is read as majority-pooled (:func:`infer_pooling`).
BROKEN_SHARE = 0.1
#: How a grid of 0s and 1s was made from a finer one (:func:`read_pixels`); "auto": see
#: :func:`infer_pooling`.
POOLINGS = ("auto", "any", "majority", "mean")
#: What the map keeps of the GP's probability in a pixel the grid holds wholly free (and of its
#: complement in one it holds wholly occupied): nothing there is otherwise, and the GP's order is kept.
HELD_SCALE = 1e-3
#: Samples per pixel side over which a pixel's mean probability is measured (:class:`GridGPOM`).
SHARE_SAMPLES = 8
#: Length scale of a converted grid, in source pixels, not learnt: the maps with a learnt one
#: scored lower on most pooled plans (docs/convert.md).
GRID_LENGTH_SCALE_PIXELS = 1.0
#: Starting length scale and its search bounds, in source (octree) voxels, where they are learnt.
LENGTH_SCALE_PIXELS = 3.0
LENGTH_SCALE_BOUNDS_PIXELS = (1.0, 50.0)

# Beyond this many length scales from every cell the kernel is below ~1e-13 and the prediction is
# the prior's: predicting there is skipped (the large unknown margins of most saved maps).
_NEGLIGIBLE_LENGTH_SCALES = {"se": 8.0, "matern32": 20.0}
# Tolerance for "the resolution divides the extent": relative to one output cell.
_DIVIDES_TOLERANCE = 1e-6


@dataclass
class ConversionResult:
    """The continuous map made from a grid, the model behind it, and what the conversion measured.

    Attributes
    ----------
    map : OccupancyMap
        Probability and latent variance on the output grid, ndarrays of shape (ny, nx).
    model : GridGPOM
        The fitted estimator; ask it anywhere with ``predict_proba(points)``.
    report : dict
        ``pixels`` (``free``, ``occupied``, ``unknown`` counts of the source), ``cells`` (``n``,
        ``occupied``, ``ambiguous``, ``min_cell``, ``max_cell``), ``pooling`` (how the pixels were
        read, :func:`read_pixels`), ``hyperparameters``, ``timings``
        (seconds: ``read``, ``observations``, ``fit`` with its stages, ``prediction``,
        ``agreement``, ``total``), ``agreement`` (``ternary``: fraction of known source pixels
        whose ternary label in the continuous map equals theirs; ``free`` and ``occupied``: the
        same per class; ``auc``: ROC AUC of the probability at known pixel centres against their
        labels) and ``grid`` (``source`` and ``output`` origin, resolution, shape, extent, and
        ``edges_coincide``).
    """

    map: OccupancyMap
    model: GridGPOM
    report: dict[str, Any] = field(default_factory=dict)


def load_grid(source: GridSource) -> RosMap | OccupancyMap:
    """Read a grid from a ROS map YAML or a gpomap ``.npz``; pass maps already read through.

    Parameters
    ----------
    source : RosMap, OccupancyMap, or path to a ``.yaml`` / ``.yml`` or ``.npz`` file

    Returns
    -------
    RosMap or OccupancyMap

    Raises
    ------
    InputFormatError
        Unknown suffix, or whatever the reader rejects (for example a rotated map origin).
    """
    if isinstance(source, (RosMap, OccupancyMap)):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        suffix = path.suffix.lower()
        if suffix in (".yaml", ".yml"):
            return read_rosmap(path)
        if suffix == ".npz":
            return load_map(path)
        raise InputFormatError(
            "cannot tell the grid format from the file name: expected a ROS map YAML (.yaml, .yml) or a gpomap map (.npz)",
            path=str(path),
        )
    raise TypeError(f"source must be a RosMap, an OccupancyMap or a path, got {type(source).__name__}")


#: How a grid's pixel values are read (:func:`grid_fractions`).
VALUE_READINGS = ("auto", "fraction", "ternary")
#: Values this close to 0 or 1 are wholly free or occupied (an 8-bit image's grey step is 1/255).
FRACTION_TOLERANCE = 0.005


def _labels(grid_map: RosMap | OccupancyMap) -> NDArray[np.int8]:
    """FREE / OCCUPIED / UNKNOWN per source pixel, ndarray of int8, shape (ny, nx)."""
    # RosMap.ternary keeps map_server's own reading (thresholds, modes, transparency);
    # OccupancyMap.ternary applies the map's thresholds, NaN probabilities being unknown.
    return np.asarray(grid_map.ternary, dtype=np.int8)


def value_reading(grid_map: RosMap | OccupancyMap, values: str = "auto") -> str:
    """How :func:`grid_fractions` reads `grid_map` with ``values``: ``"fraction"`` or ``"ternary"``.

    ``"auto"`` reads a ROS map in trinary mode (its values are codes) and a map with a latent
    variance (a GP's belief, such as gpomap's own ``.npz``) as ``"ternary"``; any other grid (a
    scale or raw ROS map, an OccupancyMap of plain values) as ``"fraction"``.
    """
    if values not in VALUE_READINGS:
        raise ValueError(f"values must be one of {VALUE_READINGS}, got {values!r}")
    if values != "auto":
        return values
    if isinstance(grid_map, RosMap):
        return "ternary" if grid_map.mode == "trinary" else "fraction"
    return "ternary" if grid_map.variance is not None else "fraction"


def grid_fractions(grid_map: RosMap | OccupancyMap, values: str = "auto") -> NDArray[np.float64]:
    """The occupied fraction of every source pixel, NaN where it is unknown, shape (ny, nx).

    Read as ``"fraction"``, a pixel's value is the fraction of its area that is occupied: a grid
    made by averaging a finer one (a 0.05 m pixel holding a 2 cm wall is 0.4) keeps its thin
    walls, where thresholding called them free. Values within :data:`FRACTION_TOLERANCE` of 0 or
    1 are wholly free or occupied; pixels the grid marks unknown (NaN in an
    :class:`~gpomap.grid.OccupancyMap`, transparent pixels of a scale-mode ROS map, raw values
    above 100) are unknown. Read as ``"ternary"``, pixels below the free threshold are free (0),
    above the occupied threshold occupied (1), between them unknown, as map_server reads a
    trinary map. ``"auto"``: see :func:`value_reading`.

    Parameters
    ----------
    grid_map : RosMap or OccupancyMap
    values : {"auto", "fraction", "ternary"}

    Returns
    -------
    ndarray of float64, shape (ny, nx)
    """
    if value_reading(grid_map, values) == "ternary":
        labels = _labels(grid_map)
        return np.where(labels == OCCUPIED, 1.0, np.where(labels == FREE, 0.0, np.nan))
    p = np.array(grid_map.probability, dtype=float)
    if isinstance(grid_map, RosMap):
        p[grid_map.unknown] = np.nan
    p[~np.isfinite(p)] = np.nan
    p = np.clip(p, 0.0, 1.0)
    p[p <= FRACTION_TOLERANCE] = 0.0
    p[p >= 1.0 - FRACTION_TOLERANCE] = 1.0
    return p


@dataclass(frozen=True)
class GridObservations(Observations):
    """Known pixel centres with the occupied fraction of each pixel.

    Attributes
    ----------
    fraction : ndarray of shape (n,)
        The occupied fraction of each pixel, in [0, 1] (:func:`grid_fractions`); ``occupied`` is
        ``fraction > 0`` (something in the pixel is occupied).
    values : str
        How the values were read (:func:`value_reading`): ``"fraction"`` or ``"ternary"``.
    """

    fraction: NDArray[np.float64] | None = None
    values: str = "fraction"


def grid_to_observations(grid_map: RosMap | OccupancyMap, values: str = "auto") -> GridObservations:
    """Known pixels of a grid as labelled points at their centres, with their occupied fractions.

    Parameters
    ----------
    grid_map : RosMap or OccupancyMap
        Row 0 at the lowest y. Free, occupied and partly occupied pixels are evidence; unknown pixels are not and give no point.
    values : {"auto", "fraction", "ternary"}
        How the pixels' values are read (:func:`grid_fractions`).

    Returns
    -------
    GridObservations
        ``points`` of shape (n_known, 2) in row-major pixel order, ``fraction`` and ``occupied``
        (fraction > 0) of shape (n_known,), ``scan_index`` all 0 (a grid has no scans).

    Raises
    ------
    EmptyDataError
        No known pixel, or no wholly free one, or none with anything occupied (a GP occupancy map
        needs free and occupied evidence).
    """
    fraction = grid_fractions(grid_map, values)
    known = np.isfinite(fraction)
    n_free = int((fraction == 0.0).sum())
    n_occ = int((fraction == 1.0).sum())
    n_partial = int(known.sum()) - n_free - n_occ
    n_unknown = int(fraction.size - known.sum())
    shape = f"{fraction.shape[0]} x {fraction.shape[1]}"
    if not known.any():
        raise EmptyDataError(f"the {shape} grid has no known pixels (all {n_unknown} unknown): nothing to convert")
    if n_free == 0 or n_occ + n_partial == 0:
        only = "free" if n_free else "occupied"
        raise EmptyDataError(
            f"the {shape} grid has only {only} known pixels ({n_free} free, {n_occ} occupied, {n_partial} partly "
            f"occupied, {n_unknown} unknown): a GP occupancy map needs both free and occupied pixels"
        )
    rows, cols = np.nonzero(known)
    g = grid_map.grid
    points = np.column_stack([g.x_centres()[cols], g.y_centres()[rows]])
    f = fraction[rows, cols]
    return GridObservations(
        points=points,
        occupied=f > 0.0,
        scan_index=np.zeros(points.shape[0], dtype=np.intp),
        fraction=f,
        values=value_reading(grid_map, values),
    )


def _cells_along(length: float, resolution: float) -> tuple[int, bool]:
    """Whole cells of side `resolution` covering `length`, and whether they fit it exactly."""
    ratio = length / resolution
    nearest = round(ratio)
    if nearest >= 1 and abs(ratio - nearest) <= _DIVIDES_TOLERANCE * max(1.0, ratio):
        return int(nearest), True
    return max(1, math.ceil(ratio)), False


def output_grid(
    source: GridSpec, resolution: float | None = None, extent: tuple[float, float, float, float] | None = None
) -> GridSpec:
    """The grid a converted map is written on.

    Parameters
    ----------
    source : GridSpec
        The source grid.
    resolution : float, optional
        Output cell side, metres; default the source's.
    extent : (xmin, xmax, ymin, ymax), optional
        Region to cover; default the source's extent.

    Returns
    -------
    GridSpec
        Origin = ``(xmin, ymin)`` of the extent (the source's origin by default). When `resolution`
        divides the extent's width / height (to a relative 1e-6 of a cell, which forgives float
        noise such as 19.2 / 0.01), the grid ends exactly on its right / top edge; otherwise it has
        one more cell there, ending less than one cell beyond the edge.
    """
    res = source.resolution if resolution is None else float(resolution)
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"resolution must be a positive number, got {resolution}")
    xmin, xmax, ymin, ymax = source.extent if extent is None else (float(v) for v in extent)
    if not (xmax > xmin and ymax > ymin):
        raise ValueError(f"extent must have xmin < xmax and ymin < ymax, got {extent}")
    nx, _ = _cells_along(xmax - xmin, res)
    ny, _ = _cells_along(ymax - ymin, res)
    return GridSpec((xmin, ymin), res, (ny, nx))


@dataclass(frozen=True)
class GridCells(Cells):
    """:class:`~gpomap.cells.Cells` whose GP inputs carry a noise weight each.

    Attributes
    ----------
    weight : ndarray of shape (n,) or None
        Multiplies each input's member count in :meth:`to_supports`. With the ``"per_count"``
        noise model an input's noise is the noise level divided by that count, so a weight of w
        makes the input w times surer (counts below 1 are read as 1 there, so weights are >= 1).
        None: every weight 1.
    target : ndarray of shape (n,) or None
        Each input's target in [-1, 1]; None: +1 occupied, -1 free.
    reading : PixelReading or None
        What each pixel was read as (:func:`read_pixels`), when the inputs were made from one.
    """

    weight: NDArray[np.float64] | None = None
    target: NDArray[np.float64] | None = None
    reading: PixelReading | None = None

    @property
    def labels(self) -> NDArray[np.float64]:
        """GP targets, ndarray of shape (n,): :attr:`target` when given, else +1 occupied, -1 free."""
        return super().labels if self.target is None else self.target

    def to_supports(self) -> Supports:
        """The cells as GP inputs, their counts multiplied by :attr:`weight`."""
        supports = super().to_supports()
        if self.weight is None:
            return supports
        return replace(supports, counts=supports.counts * self.weight)


def _extra_inputs(
    cells: Cells, lower: NDArray[np.float64], upper: NDArray[np.float64], occupied: NDArray[np.bool_], members: NDArray[np.intp]
) -> Cells:
    """`cells` followed by one-member inputs with boxes (lower, upper), labels and member indices."""
    n = lower.shape[0]
    counts = np.concatenate([cells.counts, np.ones(n, dtype=np.intp)])
    return Cells(
        lower=np.vstack([cells.lower, lower]),
        upper=np.vstack([cells.upper, upper]),
        node_lower=np.vstack([cells.node_lower, lower]),
        node_upper=np.vstack([cells.node_upper, upper]),
        occupied=np.concatenate([cells.occupied, occupied]),
        ambiguous=np.concatenate([cells.ambiguous, np.zeros(n, dtype=bool)]),
        member_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.intp),
        member_order=np.concatenate([cells.member_order, members]).astype(np.intp),
        points=cells.points,
    )


def _core_centres(
    pts: NDArray[np.float64], frac: NDArray[np.float64], free: NDArray[np.bool_], ij: NDArray[np.intp], pixel: float
) -> NDArray[np.float64]:
    """Where the occupied part of each pixel holding anything occupied most likely is, shape (m, 2).

    A wholly occupied pixel's is its centre. A partly occupied one (fraction f) is taken to be
    occupied away from the sides it shares with wholly free pixels: a strip `delta` pixels deep
    along each such side is free, `delta` such that the rest, its core, has area f; the point is
    the core's centre (a pixel with no free side: its centre). A 2 cm wall in a 0.05 m pixel
    between free ones is at its centre; one straddling two pixels (0.2 each) at their shared edge.

    Parameters
    ----------
    pts : ndarray of shape (m, 2)
        The pixels' centres.
    frac : ndarray of shape (m,)
        Their occupied fractions, each > 0.
    free : ndarray of bool, shape (ny, nx)
        Wholly free known pixels, on the lattice of `ij`.
    ij : ndarray of int, shape (m, 2)
        (column, row) of each pixel on that lattice.
    pixel : float
        Pixel side, metres.
    """
    padded = np.pad(free, 1)
    c, r = ij[:, 0], ij[:, 1]
    left = padded[1 + r, c].astype(float)
    right = padded[1 + r, 2 + c].astype(float)
    down = padded[r, 1 + c].astype(float)
    up = padded[2 + r, 1 + c].astype(float)
    a, b = left + right, down + up
    # (1 - a delta)(1 - b delta) = f: the smaller root, or the linear one when a or b is 0.
    ab = a * b
    disc = np.sqrt(np.maximum((a + b) ** 2 - 4.0 * ab * (1.0 - frac), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(ab > 0, ((a + b) - disc) / (2.0 * ab), (1.0 - frac) / (a + b))
    delta = np.where(a + b > 0, np.clip(np.nan_to_num(delta), 0.0, 1.0 / np.maximum(np.maximum(a, b), 1.0)), 0.0)
    shift = 0.5 * delta * pixel  # the core's centre moves half a strip away from each free side
    return pts + np.column_stack([(left - right) * shift, (down - up) * shift])


@dataclass(frozen=True)
class PixelReading:
    """What each known pixel of a grid says about the fine occupancy within it (:func:`read_pixels`).

    Attributes
    ----------
    origin : ndarray of shape (2,)
        Centre of the lattice's pixel (column 0, row 0), metres.
    pixel : float
        Pixel side, metres.
    index : ndarray of int, shape (ny, nx)
        The observation (known pixel) at each lattice pixel, -1 where the grid has none.
    pooling : str
        How the grid was read: ``"any"``, ``"majority"`` or ``"mean"``.
    value : ndarray of shape (m,)
        Each known pixel's occupied fraction as the grid gives it (:func:`grid_fractions`).
    share : ndarray of shape (m,)
        The occupied share the GP is given for each pixel (its input's target is 2 share - 1);
        NaN: the pixel is not evidence (known, but its value bounds its share too loosely).
    lower, upper : ndarray of shape (m,)
        Bounds on each pixel's occupied share that the pooling rule implies; the map's mean
        probability over the pixel is kept within them (:class:`GridGPOM`).
    """

    origin: NDArray[np.float64]
    pixel: float
    index: NDArray[np.intp]
    pooling: str
    value: NDArray[np.float64]
    share: NDArray[np.float64]
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]

    @property
    def ij(self) -> NDArray[np.intp]:
        """(column, row) of every known pixel on the lattice, ndarray of shape (m, 2)."""
        rows, cols = np.nonzero(self.index >= 0)
        out = np.empty((self.value.size, 2), dtype=np.intp)
        out[self.index[rows, cols]] = np.column_stack([cols, rows])
        return out

    def locate(self, points: NDArray[np.float64]) -> NDArray[np.intp]:
        """The known pixel holding each of `points` (shape (n, 2)), -1 outside them; shape (n,)."""
        f = np.floor((np.asarray(points, dtype=float) - self.origin) / self.pixel + 0.5)
        ny, nx = self.index.shape
        inside = (f[:, 0] >= 0) & (f[:, 0] < nx) & (f[:, 1] >= 0) & (f[:, 1] < ny)
        out = np.full(f.shape[0], -1, dtype=np.intp)
        c, r = f[inside, 0].astype(np.intp), f[inside, 1].astype(np.intp)
        out[inside] = self.index[r, c]
        return out


def _lattice(points: NDArray[np.float64], pixel: float) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp]]:
    """The pixel lattice of known pixel centres: its origin (2,), each point's (column, row) (m, 2)
    and the point index at every lattice pixel (ny, nx), -1 where none."""
    origin = points.min(axis=0)
    f = (points - origin) / pixel
    ij = np.rint(f).astype(np.intp)  # (column, row)
    if np.abs(f - ij).max() > 1e-3:
        raise ValueError(f"the points are not the centres of a grid of {pixel} m pixels")
    nx, ny = ij.max(axis=0) + 1
    index = np.full((ny, nx), -1, dtype=np.intp)
    index[ij[:, 1], ij[:, 0]] = np.arange(points.shape[0])
    return origin, ij, index


def infer_pooling(values: NDArray[np.float64]) -> str:
    """The pooling ``"auto"`` reads a grid by, from its values (ndarray of shape (ny, nx), NaN unknown).

    A grid with values between 0 and 1 holds occupied shares: ``"mean"``. A grid of 0s and 1s is
    read as ``"any"`` (an occupancy grid marks the cell a beam ended in, wherever in it), unless
    its walls are broken: more than :data:`BROKEN_SHARE` of its occupied pixels end a wall (at
    most one occupied pixel among their eight neighbours) or touch an occupied pixel only at a
    corner. Any-pixel pooling keeps a wall's pixels edge to edge; majority pooling drops the
    stretches of a thin wall that fill less than half of a pixel, and what is left are ends and
    diagonal steps (docs/convert.md).
    """
    v = np.asarray(values, dtype=float)
    if np.any((v > 0.0) & (v < 1.0)):
        return "mean"
    occ = v == 1.0
    if not occ.any():
        return "any"
    padded = np.pad(occ, 1)
    ny, nx = occ.shape

    def shifted(dy: int, dx: int) -> NDArray[np.bool_]:
        return padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]

    neighbours = sum(shifted(dy, dx).astype(int) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx)
    corner_only = np.zeros_like(occ)
    for dy, dx in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        corner_only |= shifted(dy, dx) & ~shifted(dy, 0) & ~shifted(0, dx)
    broken = occ & ((neighbours <= 1) | corner_only)
    return "majority" if broken.sum() > BROKEN_SHARE * occ.sum() else "any"


def read_pixels(
    points: NDArray[np.float64],
    value: NDArray[np.float64],
    pixel: float,
    pooling: str = "auto",
    occupied_fraction: float | None = None,
) -> PixelReading:
    """What each known pixel says about its fine occupancy, given how the grid was made.

    A pixel value between 0 and 1 is its occupied share, whatever the pooling. A grid of 0s and 1s
    says less, and what it says depends on how it was made from a finer one:

    - ``"any"`` (a pixel occupied if any of its fine pixels is; an occupancy grid marking the cell
      a beam ended in): a 0 is wholly free; a 1 holds something, anywhere from a sliver to all of
      it: its share is taken as `occupied_fraction` (default :data:`OCCUPIED_FRACTION`), bounded
      only by (0, 1].
    - ``"majority"`` (occupied if more than half is): a 1 holds more than half (taken as
      `occupied_fraction`, default :data:`OCCUPIED_FRACTION`, bounded to [0.5, 1]); a 0 at most
      half. Walls thinner than half a pixel vanish from such a grid between the pixels where they
      cross or thicken, so a 0 within :data:`MAJORITY_REACH` of a 1 is not evidence (its share is
      left to the GP, within [0, 0.5]); farther 0s are free, bounded to [0, 0.5].
    - ``"mean"`` (the occupied share as the value): every value is exact, bounds included.

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        Known pixel centres on a lattice of pitch `pixel`.
    value : ndarray of shape (m,)
        Each pixel's occupied fraction in [0, 1] (:func:`grid_fractions`).
    pixel : float
        Pixel side, metres.
    pooling : {"auto", "any", "majority", "mean"}
        ``"auto"``: :func:`infer_pooling` on the grid's values.
    occupied_fraction : float, optional
        The share taken for a 1 of an any- or majority-pooled grid, in (0, 1].

    Returns
    -------
    PixelReading
    """
    if pooling not in POOLINGS:
        raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
    if occupied_fraction is not None and not 0.0 < occupied_fraction <= 1.0:
        raise ValueError(f"occupied_fraction must be in (0, 1], got {occupied_fraction}")
    pts = np.asarray(points, dtype=float)
    v = np.asarray(value, dtype=float)
    origin, ij, index = _lattice(pts, pixel)
    if pooling == "auto":
        grid = np.full(index.shape, np.nan)
        grid[ij[:, 1], ij[:, 0]] = v
        read = infer_pooling(grid)
    else:
        read = pooling
    share, lower, upper = v.copy(), v.copy(), v.copy()  # mean pooling, and any value between 0 and 1
    ones, zeros = v == 1.0, v == 0.0
    if read == "any":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.0
    elif read == "majority":
        share[ones] = OCCUPIED_FRACTION if occupied_fraction is None else occupied_fraction
        lower[ones] = 0.5
        upper[zeros] = 0.5
        ones_grid = np.zeros(index.shape, dtype=bool)
        ones_grid[ij[ones, 1], ij[ones, 0]] = True
        near = ndimage.binary_dilation(ones_grid, structure=np.ones((3, 3), dtype=bool), iterations=MAJORITY_REACH)
        share[zeros & near[ij[:, 1], ij[:, 0]]] = MAJORITY_NEIGHBOUR_SHARE
    return PixelReading(origin, float(pixel), index, read, v, share, lower, upper)


def grid_cells(
    points: NDArray[np.float64],
    occupied: NDArray[np.float64] | NDArray[np.bool_],
    pixel: float,
    max_cell: float,
    wall_reach: int = WALL_REACH_PIXELS,
    edge_strip: float = EDGE_STRIP_PIXELS,
    centre_noise: float | None = CENTRE_NOISE,
    occupied_fraction: float | None = None,
    pooling: str = "auto",
) -> GridCells:
    """Wall-aware GP inputs for the known pixels of a grid, each pixel read as an occupied share.

    - Each pixel is read by :func:`read_pixels` (`pooling`, `occupied_fraction`): the share of it
      taken as occupied, or none where its value says too little to be evidence.
    - Every known pixel within `wall_reach` pixels (chessboard distance) of one holding anything
      occupied is a cell of its own, covering its square, its target the mean of the +-1
      occupancy over it: 2 s - 1 for a pixel of occupied share s. Free pixels farther away are
      merged by a quadtree on the pixel lattice into square-ish blocks of at most `max_cell` whose
      pixels are all known and free. (Cells much larger than the length scale constrain only
      their average, and the map rang inside them: ghost walls beside real ones.)
    - Each pixel holding anything occupied also gets a point input, labelled occupied, where its
      obstacle most likely is (:func:`_core_centres`), with `centre_noise` times the noise of a
      one-pixel cell (every other input's count is multiplied by `centre_noise`, see
      :class:`GridCells`): the pixel's average says how much is occupied, the point where.
    - With `edge_strip` > 0, a wholly free pixel gets a free strip that many pixels wide along each
      edge it shares with a pixel holding anything occupied (a free pixel is free up to its edge).

    Parameters
    ----------
    points : ndarray of shape (m, 2)
        Known pixel centres, on a lattice of pitch `pixel` (as :func:`grid_to_observations` gives).
    occupied : ndarray of shape (m,)
        The occupied fraction of each pixel in [0, 1], or bool (wholly occupied or free).
    pixel : float
        Source pixel side, metres.
    max_cell : float
        Largest side of a merged free cell, metres (at least one pixel is used).
    wall_reach : int
        Pixels around occupied ones that stay single cells.
    edge_strip : float
        Strip width in pixels; 0: no strips.
    centre_noise : float or None
        Noise of the points relative to a one-pixel cell; None: no points.
    occupied_fraction : float, optional
        The share taken for a 1 of a grid of 0s and 1s (:func:`read_pixels`), in (0, 1].
    pooling : {"auto", "any", "majority", "mean"}
        How the grid was made (:func:`read_pixels`).

    Returns
    -------
    GridCells
        The pixel cells first, then the strips (free), then the points (occupied), each with its
        target (:attr:`GridCells.target`, None when every target is +-1), and the reading
        (:attr:`GridCells.reading`). Strips and points have their pixel as their single member.

    Raises
    ------
    ValueError
        The points are not on a lattice of pitch `pixel`, a fraction is outside [0, 1], or the
        pooling or `occupied_fraction` is not one of those allowed.
    """
    pts = np.asarray(points, dtype=float)
    frac = np.asarray(occupied, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or frac.shape != (pts.shape[0],) or pts.shape[0] == 0:
        raise ValueError(f"points must have shape (m, 2) with m > 0 and occupied (m,), got {pts.shape} and {frac.shape}")
    if not ((frac >= 0.0) & (frac <= 1.0)).all():
        raise ValueError("occupied fractions must lie in [0, 1]")
    reading = read_pixels(pts, frac, pixel, pooling, occupied_fraction)
    _, ij, all_index = _lattice(pts, pixel)
    evidence = np.isfinite(reading.share)
    some = frac > 0.0  # anything occupied
    ny, nx = all_index.shape
    # Pixels that are not evidence get no input: for the inputs they are unknown.
    index = np.where(evidence[np.maximum(all_index, 0)] & (all_index >= 0), all_index, -1)
    some_grid = np.zeros((ny, nx), dtype=bool)
    some_grid[ij[:, 1], ij[:, 0]] = some
    known = index >= 0
    free_grid = known & ~some_grid
    if some_grid.any():
        dist = ndimage.distance_transform_cdt(~some_grid, metric="chessboard")
        far_free = free_grid & (dist > wall_reach)
    else:
        far_free = known.copy()
    max_side = max(1, math.floor(max_cell / pixel + 1e-9))

    half = 0.5 * pixel
    lower: list[NDArray[np.float64]] = []
    upper: list[NDArray[np.float64]] = []
    members: list[NDArray[np.intp]] = []
    stack = [(0, int(ny), 0, int(nx))]
    while stack:
        r0, r1, c0, c1 = stack.pop()
        block = index[r0:r1, c0:c1]
        if not (block >= 0).any():
            continue  # unknown pixels are no evidence
        h, w = r1 - r0, c1 - c0
        if (h == 1 and w == 1) or (max(h, w) <= max_side and far_free[r0:r1, c0:c1].all()):
            idx = block.ravel()
            p = pts[idx]
            lower.append(p.min(axis=0) - half)
            upper.append(p.max(axis=0) + half)
            members.append(idx)
            continue
        if h >= w:
            m = r0 + h // 2
            stack += [(m, r1, c0, c1), (r0, m, c0, c1)]
        else:
            m = c0 + w // 2
            stack += [(r0, r1, m, c1), (r0, r1, c0, m)]
    counts = np.array([m.size for m in members], dtype=np.intp)
    first = np.array([m[0] for m in members], dtype=np.intp)
    lo_a, hi_a = np.array(lower), np.array(upper)
    cells = Cells(
        lower=lo_a,
        upper=hi_a,
        node_lower=lo_a.copy(),
        node_upper=hi_a.copy(),
        occupied=some[first],
        ambiguous=np.zeros(len(members), dtype=bool),
        member_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.intp),
        member_order=np.concatenate(members).astype(np.intp),
        points=pts,
    )
    # Merged cells are wholly free, and free pixels' shares 0.
    targets = [2.0 * reading.share[first] - 1.0]

    if edge_strip > 0:
        s_lo, s_hi, s_idx = [], [], []
        padded = np.pad(some_grid, 1)
        width = edge_strip * pixel
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            # Wholly free pixels whose neighbour at (row + dy, column + dx) holds something occupied.
            neighbour = padded[1 + dy : 1 + dy + ny, 1 + dx : 1 + dx + nx]
            rows, cols = np.nonzero(free_grid & neighbour)
            idx = index[rows, cols]
            c = pts[idx]
            lo, hi = c - half, c + half
            if dx:
                # The strip hugs the shared edge: x from the edge `width` into the free pixel.
                edge = c[:, 0] + dx * half
                lo[:, 0], hi[:, 0] = np.minimum(edge, edge - dx * width), np.maximum(edge, edge - dx * width)
            else:
                edge = c[:, 1] + dy * half
                lo[:, 1], hi[:, 1] = np.minimum(edge, edge - dy * width), np.maximum(edge, edge - dy * width)
            s_lo.append(lo)
            s_hi.append(hi)
            s_idx.append(idx)
        idx_all = np.concatenate(s_idx)
        cells = _extra_inputs(cells, np.vstack(s_lo), np.vstack(s_hi), np.zeros(idx_all.size, dtype=bool), idx_all)
        targets.append(np.full(idx_all.size, -1.0))

    n_inputs = len(cells)
    if centre_noise is not None:
        occ_idx = np.flatnonzero(some)
        # The share the pixel is read as, not its value: a 1 of a grid of 0s and 1s fills
        # `occupied_fraction` of it, away from its free sides.
        core = np.where(np.isfinite(reading.share) & (reading.share > 0.0), reading.share, frac)
        centres = _core_centres(pts[occ_idx], core[occ_idx], free_grid, ij[occ_idx], pixel)
        cells = _extra_inputs(cells, centres, centres.copy(), np.ones(occ_idx.size, dtype=bool), occ_idx)
        targets.append(np.ones(occ_idx.size))
    weight = np.ones(len(cells))
    if centre_noise is not None:
        weight[:n_inputs] = float(centre_noise)
    target = np.concatenate(targets)
    fields = {name: getattr(cells, name) for name in Cells.__dataclass_fields__}
    return GridCells(**fields, weight=weight, target=None if np.all(np.abs(target) == 1.0) else target, reading=reading)


def _fit_soft_squash(gp: SupportGP, y: NDArray[np.float64], class_weight: str | None) -> None:
    """Refit the fitted `gp`'s squash to soft targets `y` in [-1, 1] (shape (n,)).

    An input whose target is 2 f - 1 counts as occupied with weight f and free with weight
    1 - f in the leave-one-out log predictive probability (a cross-entropy with soft labels);
    with ``"balanced"`` class weights the occupied and the free weights each total half.
    """
    post = gp.posterior_
    d = inverse_diagonal(post.L)
    mu, var = y - post.weights / d, 1.0 / d
    f = 0.5 * (y + 1.0)
    w_occ, w_free = f, 1.0 - f
    if class_weight == "balanced" and w_occ.sum() > 0 and w_free.sum() > 0:
        n = y.size
        w_occ, w_free = w_occ * n / (2.0 * w_occ.sum()), w_free * n / (2.0 * w_free.sum())
    labels = np.concatenate([np.ones(y.size), -np.ones(y.size)])
    weights = np.concatenate([w_occ, w_free])
    keep = weights > 0
    gp.squash.fit(labels[keep], np.concatenate([mu, mu])[keep], np.concatenate([var, var])[keep], weights[keep])


class GridGPOM(MapSettings, GPMapEstimator):
    """One MSK-GPOM GP over a grid's pixels, with cells that know the pixels.

    Maps from scans are local GPs in tiles (:class:`~gpomap.mapping.AreaGPOM`); a converted grid
    is one GP over all its cells (at most ``--max-cells``), predicted on the output grid block by
    block from the cells near each block (:meth:`gpomap.gp.GPPosterior.latent`).

    A grid pixel is an area observation: a free pixel says its whole square is free, an occupied
    one that something within its square is occupied. With ``pixel_pad`` > 0 (half the source
    pixel) and ``wall_reach`` set, the inputs are :func:`grid_cells`: single-pixel cells near
    occupied pixels, merged free cells farther away, free strips along the edges free pixels share
    with occupied ones, and a point at every occupied pixel's centre. With ``wall_reach=None`` the
    project's cell tree runs on the pixel centres and each box is widened by ``pixel_pad`` (the
    union of its pixels' squares with ``cell_box="tight"``); ``pixel_pad=0`` is the plain cell tree.

    Parameters
    ----------
    pixel_pad : float
        Half the source pixel side, metres (0: plain cell tree, no footprints).
    wall_reach : int or None
        See :func:`grid_cells`; None: the cell tree widened by ``pixel_pad``.
    edge_strip : float
        See :func:`grid_cells`.
    centre_noise : float or None
        See :func:`grid_cells`. The weights go through the member counts, so they assume the
        ``"per_count"`` noise model and ``"mean"`` normalisation (the defaults).
    occupied_fraction : float, optional
        See :func:`read_pixels`.
    pooling : {"auto", "any", "majority", "mean"}
        How the grid was made from a finer one (:func:`read_pixels`). The map keeps what the
        pooling says of each pixel, measured on :data:`SHARE_SAMPLES` x :data:`SHARE_SAMPLES`
        points in it (:meth:`_share_scales`):

        - a pixel the grid holds wholly free (a 0 of an any- or mean-pooled grid) keeps
          :data:`HELD_SCALE` of the GP's probability, a wholly occupied one (a 1 of a mean-pooled
          grid) as much of its complement;
        - elsewhere the probability is scaled within each pixel so that its mean over the pixel
          is the pixel's share (a mean-pooled value) or within the pooling's bounds (at least
          half for a 1 of a majority-pooled grid, at most half for a 0);
        - the occupied region (p > 0.5) is the GP's (where its probability passes 0.5), except
          where that covers less of a pixel than the bounds allow (a mean-pooled value, half of a
          majority-pooled 1, some of a pixel holding anything) or more: there it is the part of
          the pixel where the GP's probability is highest, as much as the bound allows. A point
          the scaling would put on the other side of 0.5 is held beside it.

        So the map's occupied region, pooled again the way the grid was made, gives back the
        grid (to a sample's area).
    **options
        :class:`~gpomap.settings.MapSettings` arguments (``min_cell`` is used only by the cell tree).
    """

    method_name = "msk-gpom"
    # MSK-GPOM's search, as the maps from scans run it (see SupportGP's objective_per_input).
    objective_per_input = True

    def __init__(
        self,
        pixel_pad: float = 0.0,
        wall_reach: int | None = None,
        edge_strip: float = EDGE_STRIP_PIXELS,
        centre_noise: float | None = CENTRE_NOISE,
        occupied_fraction: float | None = None,
        pooling: str = "auto",
        **options: Any,
    ) -> None:
        super().__init__(**options)
        if pooling not in POOLINGS:
            raise ValueError(f"pooling must be one of {POOLINGS}, got {pooling!r}")
        self.pixel_pad = float(pixel_pad)
        self.wall_reach = wall_reach
        self.edge_strip = edge_strip
        self.centre_noise = centre_noise
        self.occupied_fraction = None if occupied_fraction is None else float(occupied_fraction)
        self.pooling = pooling

    def __repr__(self) -> str:
        return f"GridGPOM(pixel_pad={self.pixel_pad}, wall_reach={self.wall_reach}, {MapSettings.__repr__(self)})"

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor arguments, by name (the map settings and the grid ones)."""
        names = ("pixel_pad", "wall_reach", "edge_strip", "centre_noise", "occupied_fraction", "pooling")
        own = {n: getattr(self, n) for n in names}
        return {**own, **MapSettings.get_params(self)}

    def fit(self, data: Observations) -> GridGPOM:
        """Fit the GP on the pixels' labelled points (:func:`grid_to_observations`).

        Parameters
        ----------
        data : Observations
            One point per known pixel, at its centre.

        Returns
        -------
        self
        """
        timings: dict[str, float] = {}
        t = time.perf_counter()
        obs = self.make_observations(data)
        cells = self.make_cells(obs)
        timings["cells"] = time.perf_counter() - t
        gp = self._make_gp(self.make_kernel())
        y = cells.labels
        gp.fit(cells.to_supports(), y)
        if not np.all(np.abs(y) == 1.0):
            t = time.perf_counter()
            _fit_soft_squash(gp, y, self.class_weight)
            timings["soft_squash"] = time.perf_counter() - t
        timings.update(gp.timings_)
        self.observations_: Observations = obs
        self.cells_: Cells = cells
        self.gp_ = gp
        self.timings_ = timings
        self.extent_points_ = obs.points
        self.path_ = None
        # Pixels are not rays: no held-out stretches (the variance scale stays 1), no ray counts.
        self.extrapolation_: dict[str, Any] = {"kappa": 1.0, "reason": "labelled points given, not scans"}
        self.evidence_ = None
        self.reading_: PixelReading | None = getattr(cells, "reading", None)
        self.share_scale_: NDArray[np.float64] | None = None
        self.share_threshold_: NDArray[np.float64] | None = None
        self.pixel_variance_: float | None = None
        if self.reading_ is not None:
            t = time.perf_counter()
            self.pixel_variance_ = self._pixel_variance(cells, self.reading_.pixel)
            self.share_scale_, self.share_threshold_ = self._share_scales(self.reading_)
            timings["shares"] = time.perf_counter() - t
        return self

    def _pixel_variance(self, cells: Cells, pixel: float) -> float:
        """The median latent variance at the centres of the one-pixel cells of `cells`."""
        side = cells.upper - cells.lower
        single = np.all(np.abs(side - pixel) <= 1e-6 * pixel, axis=1)
        centres = 0.5 * (cells.lower[single] + cells.upper[single])
        if centres.shape[0] == 0:
            return 0.0
        # A sample is enough for a median.
        step = max(1, centres.shape[0] // 2000)
        _, var = self.predict(centres[::step], return_var=True)
        return float(np.median(var))

    def _pixel_proba(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
        """The probability at `points` (m, 2) before it is held to the pixels, the latent
        variance and the known pixel of each point (-1 outside them), each of shape (m,).

        Within a known pixel the latent mean is squashed at the variance of a one-pixel input
        (:attr:`pixel_variance_`): the free blocks merged far from walls save inputs, they are not
        weaker evidence, and the variance they leave inside would rank open space above the free
        pixels beside walls. Outside, at the GP's own variance.
        """
        mean, var = self.predict(points, return_var=True)
        reading, v_px = getattr(self, "reading_", None), getattr(self, "pixel_variance_", None)
        if reading is None or v_px is None:
            return self.gp_.squash(mean, var), var, np.full(mean.shape, -1, dtype=np.intp)
        k = reading.locate(points)
        return self.gp_.squash(mean, np.where(k >= 0, v_px, var)), var, k

    def _share_scales(self, reading: PixelReading) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The factor on the GP's probability and the occupied threshold in each known pixel, each
        of shape (m,) (see the class docstring).

        The factor is 1 where the GP's mean probability over the pixel is within the pixel's
        bounds, else the factor s that brings the mean of min(s p, 1) to the nearer bound. The
        threshold is 0.5 where the share of the pixel with p > 0.5 is within the bounds, else the
        probability that cuts the pixel's samples at the nearer bound.
        """
        lo, hi = reading.lower, reading.upper
        scale, threshold = np.ones(lo.size), np.full(lo.size, 0.5)
        some = reading.value > 0.0
        bounded = ((lo > 0.0) | (hi < 1.0) | some) & (hi > 0.0) & (lo < 1.0)
        some_grid = np.zeros(reading.index.shape, dtype=bool)
        ij = reading.ij
        some_grid[ij[:, 1], ij[:, 0]] = reading.value > 0.0
        if some_grid.any() and self.wall_reach is not None:
            # A pixel far from everything occupied holds the prior's free mean, far below any bound.
            near = ndimage.distance_transform_cdt(~some_grid, metric="chessboard") <= self.wall_reach
            bounded &= near[ij[:, 1], ij[:, 0]] | (lo > 0.0)
        idx = np.flatnonzero(bounded)
        if idx.size == 0:
            return scale, threshold
        n = SHARE_SAMPLES
        offsets = ((np.arange(n) + 0.5) / n - 0.5) * reading.pixel
        ox, oy = np.meshgrid(offsets, offsets)
        centres = reading.origin + ij[idx] * reading.pixel
        samples = (centres[:, None, :] + np.column_stack([ox.ravel(), oy.ravel()])[None, :, :]).reshape(-1, 2)
        p = self._pixel_proba(samples)[0].reshape(idx.size, n * n)
        mean = p.mean(axis=1)
        low, high = mean < lo[idx], mean > hi[idx]
        s = np.ones(idx.size)
        s[high] = hi[idx][high] / mean[high]
        if low.any():
            # mean(min(s p, 1)) grows with s: bisection on log s, every low pixel at once.
            pl, target = p[low], lo[idx][low]
            a, b = np.zeros(pl.shape[0]), np.full(pl.shape[0], math.log(1e12))
            for _ in range(60):
                mid = 0.5 * (a + b)
                below = np.minimum(pl * np.exp(mid)[:, None], 1.0).mean(axis=1) < target
                a, b = np.where(below, mid, a), np.where(below, b, mid)
            s[low] = np.exp(b)
        scale[idx] = s
        # The occupied region: the samples above 0.5, unless they fill less of the pixel than its
        # lower bound or more than its upper one; then the samples ranked highest, as many as the
        # bound allows.
        ranked = -np.sort(-p, axis=1)
        m = n * n
        area = (p > 0.5).mean(axis=1)
        t = np.full(idx.size, 0.5)
        # A pixel holding anything holds some of the occupied region.
        need = np.maximum(np.ceil(lo[idx] * m - 1e-9).astype(np.intp), some[idx].astype(np.intp))
        few = area < need / m
        # Just below the need-th highest sample: it and those above it are in.
        t[few] = np.nextafter(ranked[few, need[few] - 1], -np.inf)
        allow = np.floor(hi[idx] * m + 1e-9).astype(np.intp)
        many = area > hi[idx]
        t[many] = ranked[many, np.minimum(allow[many], m - 1)]
        threshold[idx] = t
        return scale, threshold

    def predict_proba(self, points: NDArray[np.float64], return_var: bool = False):
        """Occupancy probability at points: the GP's, held to what each pixel's value says.

        Parameters
        ----------
        points : ndarray of shape (m, 2)
        return_var : bool
            Also return the GP's latent variance.

        Returns
        -------
        probability : ndarray of shape (m,)
        var : ndarray of shape (m,), only with `return_var`
        """
        pts = as_points(points, self.dim_)
        p, var, k = self._pixel_proba(pts)
        p = self._held(p, k)
        return (p, var) if return_var else p

    def _held(self, p: NDArray[np.float64], k: NDArray[np.intp]) -> NDArray[np.float64]:
        """Probabilities `p` (shape (m,)) in known pixels `k` (shape (m,), -1: none) held to the pixels.

        In a pixel the grid holds wholly free, :data:`HELD_SCALE` p; wholly occupied,
        1 - :data:`HELD_SCALE` (1 - p); elsewhere min(s p, 1) with the pixel's share scale s,
        held beside 0.5 on the side of the pixel's occupied threshold t (p > t: occupied; both
        from :meth:`_share_scales`) where it would cross it. Outside the known pixels, p.
        """
        reading, scale = getattr(self, "reading_", None), getattr(self, "share_scale_", None)
        threshold = getattr(self, "share_threshold_", None)
        if reading is None or scale is None or threshold is None:
            return p
        inside = k >= 0
        kk, pi = k[inside], p[inside]
        q = np.minimum(pi * scale[kk], 1.0)
        # The occupied region is where p passes the pixel's threshold: a point the scaling puts
        # on the other side of 0.5 stays beside it.
        occupied = pi > threshold[kk]
        up, down = occupied & (q <= 0.5), ~occupied & (q > 0.5)
        q[up] = 0.5 + HELD_SCALE * np.maximum(q[up], 1e-12)
        q[down] = 0.5 - HELD_SCALE * np.maximum(1.0 - q[down], 1e-12)
        free, full = reading.upper[kk] == 0.0, reading.lower[kk] == 1.0
        q[free] = HELD_SCALE * pi[free]
        q[full] = 1.0 - HELD_SCALE * (1.0 - pi[full])
        out = p.copy()
        out[inside] = q
        return out

    @property
    def n_inputs_(self) -> int:
        """Number of GP inputs (cells)."""
        self._check_fitted()
        return len(self.cells_)

    def _queries(self, points: NDArray[np.float64]) -> Supports:
        return Supports.from_points(points)

    def _summary_extra(self) -> dict[str, Any]:
        return {"area": self.area_method, "n_cells": len(self.cells_), "n_ambiguous_cells": int(self.cells_.ambiguous.sum())}

    def make_cells(self, obs: Observations) -> Cells:
        """The GP inputs over the pixel centres `obs` (see the class docstring)."""
        if self.pixel_pad > 0 and self.wall_reach is not None:
            frac = getattr(obs, "fraction", None)
            # A grid read by its thresholds is an occupancy grid: its occupied cells are where
            # beams ended, anywhere in them.
            pooling = "any" if self.pooling == "auto" and getattr(obs, "values", "fraction") == "ternary" else self.pooling
            return grid_cells(
                obs.points,
                obs.occupied if frac is None else frac,
                2.0 * self.pixel_pad,
                self.cell_sides(2)[1],
                self.wall_reach,
                self.edge_strip,
                self.centre_noise,
                self.occupied_fraction,
                pooling,
            )
        cells = MapSettings.make_cells(self, obs)
        if self.pixel_pad > 0:
            cells = replace(cells, lower=cells.lower - self.pixel_pad, upper=cells.upper + self.pixel_pad)
        return cells


def model_defaults(resolution: float) -> dict[str, Any]:
    """Map settings for a grid of pixel side `resolution` (see the module docstring).

    Parameters
    ----------
    resolution : float
        Source pixel side, metres.

    Returns
    -------
    dict
        Constructor arguments of :class:`GridGPOM` (``convert_grid`` adds
        ``pixel_pad`` = :data:`FOOTPRINT_PIXELS` pixels for :class:`GridGPOM`).
    """
    r = float(resolution)
    return {
        "kernel": "se",
        "cell_box": "tight",
        "min_cell": MIN_CELL_PIXELS * r,
        "max_cell": MAX_CELL_PIXELS * r,
        "length_scale": LENGTH_SCALE_PIXELS * r,
        "length_scale_bounds": (LENGTH_SCALE_BOUNDS_PIXELS[0] * r, LENGTH_SCALE_BOUNDS_PIXELS[1] * r),
        "n_restarts": 0,
    }


def _predict_on(
    model: GridGPOM, spec: GridSpec, support_box: tuple[NDArray[np.float64], NDArray[np.float64]]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Probability and latent variance at every cell centre of `spec`, each of shape (ny, nx).

    Rows and columns farther than the kernel's negligible distance from `support_box` (lower,
    upper corners of shape (2,) round every GP input) get the prior's prediction, computed once.
    """
    name = make_point_kernel(model.kernel).name
    reach = _NEGLIGIBLE_LENGTH_SCALES.get(name, math.inf) * model.hyperparameters_["length_scale"]
    lo, hi = support_box[0] - reach, support_box[1] + reach
    xs, ys = spec.x_centres(), spec.y_centres()
    near_x = (xs >= lo[0]) & (xs <= hi[0])
    near_y = (ys >= lo[1]) & (ys <= hi[1])
    prob = np.empty(spec.shape)
    var = np.empty(spec.shape)
    if not (near_x.all() and near_y.all()):
        # One point well outside the reach stands for all of them: there the mean is 0 and the
        # variance the prior's, whatever the data. (reach is finite here: an infinite one keeps
        # every row and column.)
        far = np.array([[hi[0] + reach + 1.0, hi[1] + reach + 1.0]])
        p_far, v_far = model.predict_proba(far, return_var=True)
        prob[:] = p_far[0]
        var[:] = v_far[0]
    ix, iy = np.flatnonzero(near_x), np.flatnonzero(near_y)
    if ix.size and iy.size:
        # The local prediction's blocks of the exact SE kernel table its factors once per grid
        # row and column (gpomap.kernels.closed_form.BoxPointFactors).
        xx, yy = np.meshgrid(xs[ix], ys[iy])
        p, v = model.predict_proba(np.column_stack([xx.ravel(), yy.ravel()]), return_var=True)
        prob[np.ix_(iy, ix)] = p.reshape(iy.size, ix.size)
        var[np.ix_(iy, ix)] = v.reshape(iy.size, ix.size)
    return prob, var


def _grid_dict(spec: GridSpec) -> dict[str, Any]:
    return {"origin": spec.origin, "resolution": spec.resolution, "shape": spec.shape, "extent": spec.extent}


def converter_for(resolution: float, **model_options: Any) -> GridGPOM:
    """The unfitted :class:`GridGPOM` that :func:`convert_grid` fits on a grid of pixel side `resolution`.

    Its :meth:`GridGPOM.make_cells` gives the GP inputs, so their number (what a fit's memory
    grows with) can be known before fitting.

    Parameters
    ----------
    resolution : float
        Source pixel side, metres.
    **model_options
        Override :func:`model_defaults`, the pixel footprint and wall-aware inputs, and the
        fixed length scale (:data:`GRID_LENGTH_SCALE_PIXELS`; ``optimise=True`` learns it).
    """
    options = model_defaults(resolution)
    options["pixel_pad"] = FOOTPRINT_PIXELS * resolution
    options["wall_reach"] = WALL_REACH_PIXELS
    # The length scale is the pixel's and the noise the map settings' own: only the squash is
    # fitted (GRID_LENGTH_SCALE_PIXELS).
    options["length_scale"] = GRID_LENGTH_SCALE_PIXELS * resolution
    options["optimise"] = False
    options.update(model_options)
    return GridGPOM(**options)


def convert_grid(
    source: GridSource,
    resolution: float | None = None,
    extent: tuple[float, float, float, float] | None = None,
    values: str = "auto",
    **model_options: Any,
) -> ConversionResult:
    """Turn an occupancy grid into a continuous GP occupancy map, sampled on a grid.

    Parameters
    ----------
    source : RosMap, OccupancyMap, or path to a ROS map ``.yaml`` or gpomap ``.npz``
        The grid; its free and occupied pixels are the training data (:func:`grid_to_observations`).
    resolution : float, optional
        Output cell side, metres; default the source's.
    extent : (xmin, xmax, ymin, ymax), optional
        Output region; default the source's extent, with its origin. See :func:`output_grid` for
        when the outer edges coincide with the source's.
    **model_options
        :class:`GridGPOM` arguments (those of :class:`~gpomap.settings.MapSettings`, and
        ``pixel_pad``, default half a source pixel; ``pooling``, how the grid was made from a
        finer one, default inferred), overriding :func:`model_defaults` (which are relative to
        the source's pixel size).

    Returns
    -------
    ConversionResult
        ``map`` (probability and variance of shape (ny, nx) on the output grid, the model's
        thresholds), ``model`` and ``report``.

    Raises
    ------
    EmptyDataError
        The source has no known pixels, or only free or only occupied ones.
    InputFormatError
        The source file cannot be read (missing, malformed, rotated origin, ...).
    """
    t_start = time.perf_counter()
    grid_map = load_grid(source)
    t_read = time.perf_counter() - t_start

    t = time.perf_counter()
    obs = grid_to_observations(grid_map, values)
    t_obs = time.perf_counter() - t
    src = grid_map.grid

    model = converter_for(src.resolution, **model_options)
    t = time.perf_counter()
    model.fit(obs)
    t_fit = time.perf_counter() - t
    fit_stages = dict(model.timings_)

    spec = output_grid(src, resolution, extent)
    t = time.perf_counter()
    # Every cell box lies within the known pixel centres' bounding box ("node" and "tight" alike),
    # widened by the footprint padding.
    pad = model.pixel_pad
    support_box = (obs.points.min(axis=0) - pad, obs.points.max(axis=0) + pad)
    prob, var = _predict_on(model, spec, support_box)
    t_pred = time.perf_counter() - t

    t = time.perf_counter()
    # Wholly free or occupied pixels are scored (a partly occupied one has no single label);
    # on the source grid itself they are in the observations' row-major order.
    assert obs.fraction is not None
    hard = (obs.fraction == 0.0) | (obs.fraction == 1.0)
    p_known = prob[np.isfinite(grid_fractions(grid_map, values))] if spec == src else model.predict_proba(obs.points)
    agreement = _agreement(p_known[hard], obs.fraction[hard] == 1.0, model.thresholds_)
    t_agree = time.perf_counter() - t

    cells = model.cells_
    tol = 1e-6 * spec.resolution
    edges = all(math.isclose(a, b, rel_tol=0.0, abs_tol=tol) for a, b in zip(spec.extent, src.extent))
    report: dict[str, Any] = {
        "pixels": {
            "free": int((obs.fraction == 0.0).sum()),
            "occupied": int((obs.fraction == 1.0).sum()),
            "partial": int((~hard).sum()),
            "unknown": int(src.shape[0] * src.shape[1] - obs.points.shape[0]),
        },
        "cells": {
            "n": len(cells),
            "occupied": int(cells.occupied.sum()),
            "ambiguous": int(cells.ambiguous.sum()),
            "min_cell": model.cell_sides(2)[0],
            "max_cell": model.cell_sides(2)[1],
        },
        "pooling": model.reading_.pooling if model.reading_ is not None else None,
        "hyperparameters": dict(model.hyperparameters_),
        "agreement": agreement,
        "grid": {
            "source": _grid_dict(src),
            "output": _grid_dict(spec),
            "edges_coincide": edges,
        },
    }
    report["timings"] = {
        "read": t_read,
        "observations": t_obs,
        "fit": t_fit,
        "fit_stages": fit_stages,
        "prediction": t_pred,
        "agreement": t_agree,
        "total": time.perf_counter() - t_start,
    }
    info = dict(model.summary())
    info["source"] = "grid conversion"
    info["conversion"] = {k: report[k] for k in ("pixels", "cells", "pooling", "agreement", "grid")}
    occupancy_map = OccupancyMap(spec, prob, variance=var, thresholds=model.thresholds_, info=info)
    return ConversionResult(map=occupancy_map, model=model, report=report)


def _agreement(
    probability: NDArray[np.float64], occupied: NDArray[np.bool_], thresholds: tuple[float, float]
) -> dict[str, float]:
    """How well probabilities at known pixels reproduce their labels.

    Parameters
    ----------
    probability : ndarray of shape (n,)
    occupied : ndarray of bool, shape (n,)
        Known labels (a class absent gives NaN for it and for the AUC).
    thresholds : (float, float)
        Ternary thresholds; a pixel agrees when its ternary label equals its known label (an
        "unknown" answer never agrees).

    Returns
    -------
    dict
        ``ternary``, ``free``, ``occupied`` (fractions) and ``auc``.
    """
    lab = ternary(probability, thresholds)
    truth = np.where(occupied, OCCUPIED, FREE)
    match = lab == truth
    both = bool(occupied.any() and not occupied.all())
    return {
        "ternary": float(match.mean()) if match.size else math.nan,
        "free": float(match[~occupied].mean()) if (~occupied).any() else math.nan,
        "occupied": float(match[occupied].mean()) if occupied.any() else math.nan,
        "auc": float(roc_auc(occupied, probability)) if both else math.nan,
    }
