"""Gaussian process regression over multi-support inputs, with two ways to learn hyperparameters.

The model is zero-mean GP regression on +-1 targets (Rasmussen & Williams, algorithm 2.1) over
:class:`~gpomap.supports.Supports`, with noise variance ``noise * noise_scale_i`` per input.
Hyperparameters live in log space and are found with L-BFGS-B from a few seeded starts, with
analytic gradients, by one of two objectives:

- ``"lml"``: the log marginal likelihood (R&W eq. 5.8, gradient eq. 5.9); the probit squash is
  then fitted to the leave-one-out moments afterwards.
- ``"loo"``: the leave-one-out probit predictive probability (probabilistic least-squares
  classification, R&W sections 5.4.2 and 6.5), fitted jointly with the squash's alpha and beta.
  The signal variance is held fixed: scaling signal and noise together leaves the LOO means
  unchanged and alpha absorbs the scale, so it is not identifiable there.

The package's rooms:

- :mod:`~gpomap.gp.linalg`: Cholesky factors with jitter, their solves, inverses and diagonals,
  the whitening products.
- :mod:`~gpomap.gp.objective`: the two objectives with their gradients, summed over compact
  groups of the inputs (:class:`~gpomap.gp.objective.HyperparameterObjective`,
  :func:`compact_groups`).
- :mod:`~gpomap.gp.support`: :class:`SupportGP`, the search over the objective, the factor and the
  squash; what it makes is
- :mod:`~gpomap.gp.posterior`: :class:`GPPosterior`, the fitted GP and its prediction, dense or
  local (:func:`local_blocks`, :data:`LOCAL_TOL`).

Every name is importable from ``gpomap.gp``; :class:`GPPosterior`, which a map file names
(:mod:`gpomap.io.mapfile`), gives this package as its module. A module constant is read where it
is used: set it there (``gpomap.gp.posterior.LOCAL_TOL``).
"""

from __future__ import annotations

from gpomap.gp.linalg import (
    FILL_BLOCK,
    LOWER_PRODUCT_BLOCKS,
    WHITEN_BY_PRODUCT_DIMS,
    _clear_strict_upper,
    _fill_lower,
    _inverse_in_place,
    _trace_product_upper,
    _triangular_inverse,
    _weighted_outer_upper,
    cholesky_in_place,
    cholesky_inverse,
    cholesky_solve,
    inverse_diagonal,
    lower_product,
    noisy_cholesky,
    robust_cholesky,
    triangular_inverse_for,
)
from gpomap.gp.objective import (
    NOISE_MODELS,
    OBJECTIVES,
    GroupMap,
    ObjectivePart,
    _in_turn,
    compact_groups,
)
from gpomap.gp.posterior import (
    _PAIRS_AT_ONCE,
    COMPILED_LOCAL_WORK_SHARE,
    LOCAL_AXES,
    LOCAL_BLOCK_QUERIES,
    LOCAL_BLOCK_SIDE,
    LOCAL_GATHER_QUERIES,
    LOCAL_KERNEL_POINTS,
    LOCAL_SIDE_RANGE,
    LOCAL_TOL,
    LOCAL_VARIANCE_TOL,
    LOCAL_WORK_SHARE,
    GPPosterior,
    LocalBlock,
    LocalBlocks,
    local_blocks,
)
from gpomap.gp.support import (
    FitReport,
    SupportGP,
)

__all__ = [
    "COMPILED_LOCAL_WORK_SHARE",
    "FILL_BLOCK",
    "FitReport",
    "GPPosterior",
    "GroupMap",
    "LOCAL_AXES",
    "LOCAL_BLOCK_QUERIES",
    "LOCAL_BLOCK_SIDE",
    "LOCAL_GATHER_QUERIES",
    "LOCAL_KERNEL_POINTS",
    "LOCAL_SIDE_RANGE",
    "LOCAL_TOL",
    "LOCAL_VARIANCE_TOL",
    "LOCAL_WORK_SHARE",
    "LOWER_PRODUCT_BLOCKS",
    "LocalBlock",
    "LocalBlocks",
    "NOISE_MODELS",
    "OBJECTIVES",
    "ObjectivePart",
    "SupportGP",
    "WHITEN_BY_PRODUCT_DIMS",
    "_PAIRS_AT_ONCE",
    "_clear_strict_upper",
    "_fill_lower",
    "_in_turn",
    "_inverse_in_place",
    "_trace_product_upper",
    "_triangular_inverse",
    "_weighted_outer_upper",
    "cholesky_in_place",
    "cholesky_inverse",
    "cholesky_solve",
    "compact_groups",
    "inverse_diagonal",
    "local_blocks",
    "lower_product",
    "noisy_cholesky",
    "robust_cholesky",
    "triangular_inverse_for",
]
