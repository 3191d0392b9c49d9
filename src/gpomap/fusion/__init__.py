"""The GP map as the prior of a fine grid: the GP's probability updated by each cell's ray counts.

The GP is smooth and carries the map across gaps; the counts of :mod:`gpomap.evidence` are what
make walls as sharp as the cells where beams went. Each fine cell's probability is the posterior
mean of a Beta prior centred on the GP's probability p_gp, with n0 the prior's weight, updated by
its weighted hits and misses (:class:`EvidenceCalibration`):

    p = (hit_weight * hits + near_hit_weight * near misses + n0 * p_gp)
        / (hit_weight * hits + near_hit_weight * near misses + far misses
           + surface_weight * surface misses + near_weight * near misses + n0),

the far misses here those that are not surface misses (:func:`surface_misses`); each step of the
robot's path through a cell adds :data:`PATH_HITS` hits' worth of misses. Where no beam went, p
is the GP's probability for unseen space (:mod:`gpomap.extrapolation`); far from all data, 0.5.
Every probability is then mixed with a surprise rate (:func:`with_surprises`), in cells that only
beams without a return reached with a rate of their own (:func:`only_silent`,
:func:`fit_silent_rate`, fitted on the later visit's held-out stretch), and mapped through a later
visit's recalibration (:mod:`gpomap.revisit`).

The weights are fitted on the map's own scans, a sample of them held out in turn from the
counts (exact: counts add over scans), never on a test set (:func:`fit_calibration`). The GP's
own probability is not re-tempered there, as its points were the GP's training data, and its
variance scale for unseen space is kept to the cells it was fitted for. :class:`EvidenceLayer`
keeps the counts on a growing lattice, adds scans and writes grids.

The package's rooms:

- :mod:`~gpomap.fusion.calibration`: :class:`EvidenceCalibration` (the weights and the surprise
  rate), :func:`fit_calibration` on the map's own scans held out, :func:`fit_surprise_rate`.
- :mod:`~gpomap.fusion.layer`: :class:`EvidenceLayer`, the counts on their lattice and the
  calibration applied to points; :func:`ternary_thresholds`.
- :mod:`~gpomap.fusion.grids`: the layer per cell of a grid (``LayerGrids``, a part of
  :class:`EvidenceLayer`): the cells' counts, the map on them, the cells beams saw through
  (:data:`SEEN_THROUGH_NOT_OCCUPIED`) and the written grid.
- :mod:`~gpomap.fusion.written`: the written grid's GP sampled coarsely
  (:func:`gp_sampling_factor`) and a large planar grid built in bands of rows
  (:func:`~gpomap.fusion.written.in_bands`, over :class:`BlendedMoments`).

Every name is importable from ``gpomap.fusion``; the classes a map file names
(:mod:`gpomap.io.mapfile`) give this package as their module. A module constant is read where it
is used, so a test or benchmark that sets one sets it there (``gpomap.fusion.calibration.PATH_HITS``).

Why each part, and what it was measured to be worth: docs/choices.md, "The map is the GP as the
prior of a fine grid" and the sections after it ("Shared updates", "Near misses", "A near miss is
part of a hit too", "A far miss beside a hit is weighed apart", "The robot's body round its
path"), "One observation in a hundred is a surprise" and "The map's probabilities for a later
visit"; for point clouds, docs/3d.md.
"""

from __future__ import annotations

from gpomap.evidence import NARROW_COUNT_SCANS, path_dtype
from gpomap.fusion.calibration import (
    CALIBRATION_BOUNDS,
    CALIBRATION_POINTS,
    FIT_SURFACE_WEIGHT,
    FIT_SURPRISE_RATE,
    MAX_SURPRISE_RATE,
    PATH_HITS,
    SILENT_FIT_POINTS,
    SURPRISE_RATE,
    CalibrationSample,
    EvidenceCalibration,
    GPApart,
    _other_scans_counts,
    fit_calibration,
    fit_silent_rate,
    fit_surprise_rate,
    only_silent,
    surface_misses,
    with_surprises,
)
from gpomap.fusion.grids import COUNT_DTYPE, SEEN_THROUGH_NOT_OCCUPIED, without_hits
from gpomap.fusion.layer import (
    LATTICE_GROWTH,
    EvidenceLayer,
    _unseen_where_empty,
    ternary_thresholds,
)
from gpomap.fusion.written import (
    GP_SAMPLES_PER_LENGTH_SCALE,
    MAX_GP_STEP_CELLS,
    VARIANCE_STEP_SAMPLES,
    BlendedMoments,
    gp_sampling_factor,
    variance_step,
)

__all__ = [
    "CALIBRATION_BOUNDS",
    "CALIBRATION_POINTS",
    "COUNT_DTYPE",
    "FIT_SURFACE_WEIGHT",
    "FIT_SURPRISE_RATE",
    "GP_SAMPLES_PER_LENGTH_SCALE",
    "LATTICE_GROWTH",
    "MAX_GP_STEP_CELLS",
    "MAX_SURPRISE_RATE",
    "NARROW_COUNT_SCANS",
    "PATH_HITS",
    "SEEN_THROUGH_NOT_OCCUPIED",
    "SILENT_FIT_POINTS",
    "SURPRISE_RATE",
    "VARIANCE_STEP_SAMPLES",
    "BlendedMoments",
    "CalibrationSample",
    "EvidenceCalibration",
    "EvidenceLayer",
    "GPApart",
    "_other_scans_counts",
    "_unseen_where_empty",
    "fit_calibration",
    "fit_silent_rate",
    "fit_surprise_rate",
    "gp_sampling_factor",
    "only_silent",
    "path_dtype",
    "surface_misses",
    "ternary_thresholds",
    "variance_step",
    "with_surprises",
    "without_hits",
]
