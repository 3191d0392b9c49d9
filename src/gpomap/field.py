"""The GP under a fitted map, as the map asks it, and the values it hands over.

A fitted map (:class:`gpomap.fitted.FittedMap`) asks its GP through one protocol,
:class:`LatentField` (a tiled map's tiles blended, one dense GP, the octree conversion's columns),
and a field that makes a voxel grid in a pass of its own through :class:`VoxelPass`. The field's
hyperparameters are typed (:class:`GPHyperparameters`), its probabilities and variances come as
:data:`Moments`, and every point it is asked about is of shape (m, d) (:func:`as_points`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from gpomap.squash import ProbitSquash

if TYPE_CHECKING:
    from gpomap.fusion import BlendedMoments
    from gpomap.voxels import VoxelSpec

#: The GP's probability, latent variance and probability for unseen space at points, each (m,).
Moments = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def as_points(points: NDArray[np.float64], dim: int = 2) -> NDArray[np.float64]:
    """`points` as a float ndarray of shape (m, dim), or a ValueError saying what was wrong."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != dim:
        raise ValueError(f"points must have shape (m, {dim}) for this {dim}-D map, got {p.shape}")
    return p


@dataclass(frozen=True)
class GPHyperparameters:
    """The GP's learnt (or given) hyperparameters.

    Parameters
    ----------
    variance : float
        Signal variance of the kernel.
    length_scale : float
        Length scale of the kernel, metres.
    noise : float
        Observation noise variance.
    """

    variance: float
    length_scale: float
    noise: float

    @classmethod
    def from_mapping(cls, values: dict[str, float]) -> GPHyperparameters:
        """The three GP values of a hyperparameter report (``hyperparameters_``), which also
        holds the squash's calibration."""
        return cls(float(values["variance"]), float(values["length_scale"]), float(values["noise"]))


class LatentField(Protocol):
    """The GP under a fitted map, as :class:`~gpomap.fitted.FittedMap` asks it.

    Points given to its methods are already of shape (m, d), d its :attr:`dim`.
    """

    @property
    def dim(self) -> int:
        """2 for a planar map, 3 for a voxel map."""
        ...

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """The GP's hyperparameters."""
        ...

    @property
    def squash(self) -> ProbitSquash:
        """The calibrated probit from latent moments to probabilities (alpha, beta, variance scale)."""
        ...

    @property
    def blended(self) -> BlendedMoments | None:
        """The field's calibrated moments, when a written grid can take its variance more coarsely
        than its mean (:meth:`gpomap.fusion.EvidenceLayer.written_grid`); else None."""
        ...

    def latent(self, points: NDArray[np.float64], return_var: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Latent mean at points, shape (m,), and the latent variance (m,) when asked (else None)."""
        ...

    def gp_probabilities(self, points: NDArray[np.float64]) -> Moments:
        """The GP's probability, latent variance and probability for unseen space at points, each (m,)."""
        ...

    def limited(self) -> contextlib.AbstractContextManager[Any]:
        """A context in which the field computes within its share of the cores."""
        ...

    def forget_below(self, y: float) -> None:
        """Let go of what predicting below height `y` formed (a planar grid is built upwards in bands)."""
        ...

    def grid_done(self) -> None:
        """Called once a grid is made: the field may give back what the grid needed."""
        ...


@runtime_checkable
class VoxelPass(Protocol):
    """A field that makes a voxel grid in a pass of its own, as :meth:`FittedMap.voxels <gpomap.fitted.FittedMap.voxels>` asks it:
    one fitted in pieces that are let go once they have answered (the octree conversion's columns,
    :class:`gpomap.convert.octree_tiles.ColumnsField`), which answers points beside the grid in
    the same pass, each piece fitted once."""

    def voxel_probabilities(
        self, spec: VoxelSpec, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The GP's probability and latent variance at every voxel of `spec`, each of shape
        ``spec.shape``, and at `points` (m, 3), each (m,)."""
        ...
