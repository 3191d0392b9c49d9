"""The hyperparameters a map uses: given and checked, or learnt once on a compact sample of cells round a dense, typical block."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from gpomap.config import PROFILES
from gpomap.lapack import available_cores
from gpomap.supports import Supports
from gpomap.tiles.fits import TileFits

HYPER_NAMES = ("variance", "length_scale", "noise", "alpha", "beta")
#: What a fit learns of unseen space besides, taken as given when passed with the hyperparameters:
#: the variance scale (:mod:`gpomap.extrapolation`).
UNSEEN_NAMES = ("variance_scale",)

#: Of the hyperparameters, those that must be positive; beta is any number.
_POSITIVE_HYPER = ("variance", "length_scale", "noise", "alpha", "variance_scale")


def given_hyperparameters(hyperparameters: dict[str, float]) -> dict[str, float]:
    """The hyperparameters a fit is given (:data:`HYPER_NAMES`, and any of :data:`UNSEEN_NAMES`), as floats.

    Raises
    ------
    ValueError
        Naming the hyperparameter missing, not a finite number, or out of its range.
    """
    missing = [n for n in HYPER_NAMES if n not in hyperparameters]
    if missing:
        raise ValueError(f"hyperparameters must give {HYPER_NAMES}; missing {missing}")
    out: dict[str, float] = {}
    for n in (*HYPER_NAMES, *UNSEEN_NAMES):
        if n not in hyperparameters:
            continue
        try:
            v = float(hyperparameters[n])
        except (TypeError, ValueError):
            raise ValueError(f"hyperparameter {n} must be a number, got {hyperparameters[n]!r}") from None
        if not np.isfinite(v) or (n in _POSITIVE_HYPER and v <= 0):
            need = "positive" if n in _POSITIVE_HYPER else "finite"
            raise ValueError(f"hyperparameter {n} must be {need}, got {v}")
        out[n] = v
    return out


#: Most cells of the compact sample the hyperparameters are learnt on, by the map's dimension:
#: a larger sample pinned planar maps' hyperparameters better, while in 3-D each step of the cuboid
#: kernel is dearer and 300 scored as well (the measurements: docs/choices.md, "The hyperparameter
#: search in groups of 200 cells").
DEFAULT_HYPER_SAMPLE: dict[int, int] = {d: p.hyper_sample for d, p in PROFILES.items()}

#: Most cells of each compact group the hyperparameter sample is cut into for the search, each
#: group its own GP (:class:`gpomap.gp.SupportGP`'s ``hyper_group``), by the map's dimension;
#: None: one GP over the sample. Planar maps: 200, so the 800 cells are four groups and each
#: evaluation of the objective is 16 times cheaper, while the written maps score as with one GP.
#: Voxel maps: one GP; their 300-cell search costs mostly kernel evaluations, which groups do not
#: make fewer, and smaller groups cost log loss (docs/choices.md, "The hyperparameter search in
#: groups of 200 cells").
HYPER_GROUP_CELLS: dict[int, int | None] = {d: p.hyper_group_cells for d, p in PROFILES.items()}

#: The hyperparameter sample is anchored only in a block whose share of occupied cells is at
#: least this fraction of the whole map's (when any block is): a sample of one class says nothing
#: of how occupied and free cells differ: the objective is flat there, the squash takes its lowest
#: alpha and the GP adds nothing to the map (docs/choices.md, "The hyperparameter sample").
MIN_SAMPLE_OCCUPIED_SHARE: float = 0.5


def hyper_anchor_block(sizes: ArrayLike, occupied_fractions: ArrayLike, map_occupied_fraction: float) -> int:
    """Index of the block the hyperparameter sample is anchored in: a dense, typical, mixed block.

    Among the blocks whose occupied fraction is at least :data:`MIN_SAMPLE_OCCUPIED_SHARE` of
    the map's (all blocks when none is), the one whose cell count is nearest the upper quartile
    of every block's (the first such in order on ties).

    Parameters
    ----------
    sizes : array_like of shape (b,)
        Cells per block.
    occupied_fractions : array_like of shape (b,)
        Fraction of each block's cells that are occupied.
    map_occupied_fraction : float
        Fraction of the map's cells that are occupied.

    Returns
    -------
    int
    """
    sizes = np.asarray(sizes, dtype=float)
    mixed = np.asarray(occupied_fractions, dtype=float) >= MIN_SAMPLE_OCCUPIED_SHARE * map_occupied_fraction
    candidates = np.flatnonzero(mixed) if mixed.any() else np.arange(sizes.size)
    # Dense but typical: the densest block can be one spot where the robot lingered, many tiny
    # cells whose squash comes out flat (docs/choices.md, "The hyperparameter sample").
    return int(candidates[np.argmin(np.abs(sizes[candidates] - np.quantile(sizes, 0.75)))])


class HyperparameterSearch(TileFits):
    """Learns a map's hyperparameters on its cells (a part of :class:`~gpomap.tiles.TiledGPOM`)."""

    def _learn_hyperparameters(self) -> dict[str, float]:
        """Learn all five hyperparameters once, on a compact sample round a dense, typical block."""
        b = self.base
        keys = sorted(self._blocks)
        lo, hi, cnt, lab, _ = self._all_cells()
        sizes = np.array([len(self._blocks[k].counts) for k in keys])
        shares = np.array([float(np.mean(self._blocks[k].occupied)) if n else 0.0 for k, n in zip(keys, sizes, strict=True)])
        bc = self._blocks[keys[hyper_anchor_block(sizes, shares, float(np.mean(lab > 0)))]]
        anchor = 0.5 * (bc.lower + bc.upper).mean(axis=0)
        n = lab.size
        k = self.hyper_sample if self.hyper_sample is not None else DEFAULT_HYPER_SAMPLE[self._dim]
        if n <= k:
            idx = np.arange(n)
        else:
            d = np.sum((0.5 * (lo + hi) - anchor) ** 2, axis=1)
            idx = np.sort(np.argpartition(d, k - 1)[:k])
        if b.area_method == "summed":
            blocks = [self._blocks[k] for k in keys]
            from gpomap.supports import concatenate

            X = concatenate([Supports(c.lower, c.upper, c.counts, c.member_points, c.member_offsets) for c in blocks]).subset(idx)
        else:
            X = Supports(lo[idx], hi[idx], cnt[idx])
        # The search runs in this process, its groups on the local workers' cores.
        gp = self._settings().search_gp(
            b.make_kernel(),
            b.noise,
            optimise=b.optimise,
            hyper_subset=None,
            hyper_group=HYPER_GROUP_CELLS[self._dim],
            n_threads=min(self.n_workers_, available_cores()),
        )
        gp.fit(X, lab[idx])
        hyp = {
            "variance": float(gp.kernel.base.variance),
            "length_scale": float(gp.kernel.base.length_scale),
            "noise": float(gp.noise),
            "alpha": float(gp.squash.alpha),
            "beta": float(gp.squash.beta),
        }
        r = np.sqrt(np.max(np.sum((0.5 * (lo[idx] + hi[idx]) - anchor) ** 2, axis=1)))
        self.hyper_source_ = {
            "how": "learnt" if b.optimise else "given (alpha, beta fitted)",
            "sample_cells": int(idx.size),
            "sample_centre": [round(float(anchor[0]), 2), round(float(anchor[1]), 2)],
            "sample_radius_m": round(float(r), 2),
            "sample_occupied_fraction": round(float(np.mean(lab[idx] > 0)), 4),
            "evaluations": gp.fit_report_.n_evaluations if gp.fit_report_ is not None else 0,
            "sample_groups": gp.fit_report_.groups if gp.fit_report_ is not None else 1,
        }
        return hyp
