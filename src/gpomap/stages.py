"""The map's probability as a chain of fitted stages, each of one interface.

A fitted map's probability at a point is made in three fitted stages, in this order::

    the GP's calibrated moments  (alpha mu + beta, alpha^2 v: the tiles' blended, or one GP's)
        -> squash    gpomap.extrapolation.VarianceScale     -> the GP's probability, and for unseen space
        -> fusion    gpomap.fusion.EvidenceCalibration      -> with the cell's ray counts: the cell's probability
        -> revisit   gpomap.revisit.RevisitCalibration      -> the map's probability for a later visit

Each stage is a frozen dataclass of its fitted values, in a module of its own, and each answers
to :class:`Stage`: ``apply`` maps what the stage before gives to what the next takes. Each is
fitted by a classmethod ``fit`` on points at their natural frequencies, its inputs declared in
its signature: :meth:`VarianceScale.fit <gpomap.extrapolation.VarianceScale.fit>` on held-out
stretches' points where no kept beam went (the held-in GP's moments there),
:meth:`EvidenceCalibration.fit <gpomap.fusion.EvidenceCalibration.fit>` on the map's own scans'
points held out one at a time (the other scans' counts there),
:meth:`RevisitCalibration.fit <gpomap.revisit.RevisitCalibration.fit>` on a held-out stretch's
points and the calibration's own. Where those points come from is each module's other work
(``fit_variance_scale``, ``fit_calibration``, ``later_visit_points``).

:class:`StageChain` names the sequence and applies it (:attr:`gpomap.fitted.FittedMap.stages`).
The map's answers run it in two places: the field squashes its moments (the tiles through
:class:`~gpomap.extrapolation.VarianceScale`), and the evidence layer applies the stages after the
squash (:meth:`StageChain.after_squash`) at points, or at a written grid's cells, whose GP
probabilities are interpolated from coarser samples between the squash and the fusion.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

In = TypeVar("In", contravariant=True)
Out = TypeVar("Out", covariant=True)


class Stage(Protocol[In, Out]):
    """A fitted stage of the map: its values fitted once, then applied to what the stage before gives."""

    def apply(self, given: In, /) -> Out:
        """What the next stage takes, from what the stage before gives."""
        ...


class CalibratedMoments(NamedTuple):
    """What the squash takes at each point (matching shapes): the GP's latent moments under the
    squash's alpha and beta. A tiled map blends these over its tiles, so that each tile's alpha
    and beta blend too.

    Attributes
    ----------
    mean : ndarray
        ``alpha mu + beta``, mu the latent mean.
    variance : ndarray
        ``alpha^2 v``, v the latent variance.
    """

    mean: NDArray[np.float64]
    variance: NDArray[np.float64]


class GPProbability(NamedTuple):
    """What the squash gives at each point (matching shapes).

    Attributes
    ----------
    probability : ndarray
        The GP's probability.
    unseen : ndarray
        The GP's probability for unseen space (its variance scaled, :mod:`gpomap.extrapolation`).
    """

    probability: NDArray[np.float64]
    unseen: NDArray[np.float64]


class Counted(NamedTuple):
    """What the ray-count fusion takes at each point or cell (matching shapes): the GP's
    probability and the cell's counts, weighed by the fusion's own weights
    (:meth:`gpomap.fusion.EvidenceCalibration.hits` and ``misses``).

    Attributes
    ----------
    probability : ndarray
        The GP's probability.
    unseen : ndarray or None
        The GP's probability for unseen space, taken where the cell has no count; None: the
        fusion's value from `probability` there too.
    hits, misses : ndarray
        The weighted hits and misses.
    silent : ndarray of bool or None
        Cells that only beams that returned nothing reached
        (:func:`gpomap.fusion.calibration.only_silent`); None: none are.
    """

    probability: NDArray[np.float64]
    unseen: NDArray[np.float64] | None
    hits: NDArray[np.float64]
    misses: NDArray[np.float64]
    silent: NDArray[np.bool_] | None = None


@dataclass(frozen=True)
class StageChain:
    """The map's fitted stages in the order they apply: squash, ray-count fusion, later-visit recalibration.

    Parameters
    ----------
    squash : Stage
        Calibrated moments to the GP's probabilities (:class:`gpomap.extrapolation.VarianceScale`).
    fusion : Stage or None
        The GP's probability and the cell's counts to the cell's probability
        (:class:`gpomap.fusion.EvidenceCalibration`); None for a map of the GP alone, whose chain
        ends at the squash.
    revisit : Stage or None
        Probabilities to the map's for a later visit (:class:`gpomap.revisit.RevisitCalibration`);
        None where there is no fusion.
    """

    squash: Stage[CalibratedMoments, GPProbability]
    fusion: Stage[Counted, NDArray[np.float64]] | None = None
    revisit: Stage[NDArray[np.float64], NDArray[np.float64]] | None = None

    def apply(self, moments: CalibratedMoments, counts: tuple[NDArray[Any], ...] | None = None) -> NDArray[np.float64]:
        """The map's probability from the GP's calibrated moments and the cells' weighted counts.

        Parameters
        ----------
        moments : CalibratedMoments
            At m points, each of shape (m,).
        counts : (hits, misses) or (hits, misses, silent), optional
            The weighted counts of each point's cell and whether only beams that returned nothing
            reached it, each (m,) (:meth:`gpomap.fusion.EvidenceLayer.counts_at`); needed when the
            chain has a fusion.

        Returns
        -------
        ndarray of shape (m,)
        """
        gp = self.squash.apply(moments)
        if self.fusion is None:
            return gp.probability
        if counts is None:
            raise ValueError("a chain with ray-count fusion needs the cells' counts")
        return self.after_squash(self.fusion, self.revisit, Counted(gp.probability, gp.unseen, *counts))

    @staticmethod
    def after_squash(
        fusion: Stage[Counted, NDArray[np.float64]],
        revisit: Stage[NDArray[np.float64], NDArray[np.float64]] | None,
        counted: Counted,
    ) -> NDArray[np.float64]:
        """The stages after the squash, in order: the fusion, then the recalibration (when there is one).

        Parameters
        ----------
        fusion, revisit : Stage
            As the chain's.
        counted : Counted
            At points or cells, any shape.

        Returns
        -------
        ndarray
            The map's probability, the shape of ``counted.probability``.
        """
        p = fusion.apply(counted)
        return p if revisit is None else revisit.apply(p)
