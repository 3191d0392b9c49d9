"""Honest reports: what a fitted map's numbers say about how far it can be trusted.

A fit can finish without error and still be poor: a hyperparameter that ran to the edge of its
search (the data did not pin it down, or wanted a value the search does not allow), a probit
slope at its cap (the classes separate perfectly and a map of the GP alone turns hard 0 / 1;
not a warning for a map of ray counts, whose GP is only their prior), a map whose
probability away from the data is far from 0.5 (unexplored space then looks free or occupied
instead of unknown), or a written map with hardly a wall, or more wall than free space. The command line prints these as
``warning: ...`` lines after a fit; :func:`fit_warnings` is the one entry point.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BOUND_TOLERANCE",
    "OCCUPIED_SHARE_BAND",
    "PRIOR_BAND",
    "at_bounds",
    "fit_warnings",
    "hyperparameter_source",
    "hyperparameter_warnings",
    "map_warnings",
    "prior_probability",
    "search_bounds",
]

#: A value within this fraction of a bound counts as at the bound (5 %: L-BFGS-B stops a little
#: inside a bound it is pushing against).
BOUND_TOLERANCE = 0.05
#: The probability far from the data should be within this band (0.5 +- 0.1): "unknown".
PRIOR_BAND = (0.4, 0.6)
#: The share of a written map's known cells that are occupied, outside of which the map is
#: reported. A map of range data is mostly free space, the beams' way to the walls: the shared
#: logs' maps at 0.05 m hold 2-10 % wall cells. Below the band the walls the scans hit are
#: missing; above it the space the beams crossed is not free in the map.
OCCUPIED_SHARE_BAND = (0.001, 0.5)

_WHY = {
    "length_scale": "the data did not pin the length scale down; give --length-scale (metres) to fix it, or a --min-cell "
    "nearer the scene's detail",
    "noise": "the data did not pin the noise down; check the poses (a mislocalised log mixes the cells' classes) and "
    "--free-clearance",
    "variance": "the data did not pin the signal variance down; give the hyperparameters of a map of similar data",
    "alpha": "the classes separate so cleanly that the probit slope is capped and the map turns hard 0 / 1 where no "
    "beam went; read those parts as unknown, or add scans that see them",
    "shift": "the free/occupied boundary of the probit (beta / alpha) ran to its limit; check that the data hold both "
    "free space and surfaces",
}


def _base_estimator(model: Any) -> Any:
    """What holds the settings: a map's ``base`` (:class:`~gpomap.settings.MapSettings`), or the model itself (GridGPOM)."""
    return getattr(model, "base", model)


def search_bounds(model: Any) -> dict[str, tuple[float, float]]:
    """Bounds of the hyperparameter search of a (fitted or not) AreaGPOM, TiledGPOM or GridGPOM.

    Parameters
    ----------
    model : AreaGPOM, TiledGPOM or GridGPOM

    Returns
    -------
    dict
        ``name -> (low, high)`` for the hyperparameters the fit searched: length scale and noise
        when they are learnt (the signal variance too with the marginal-likelihood objective),
        always the probit's alpha and shift = beta / alpha, and the variance scale for unseen
        space when the fit searched it.
    """
    from gpomap.squash import SQUASH_BOUNDS

    base = _base_estimator(model)
    bounds: dict[str, tuple[float, float]] = {}
    if getattr(base, "optimise", True):
        kernel = base.make_kernel().base
        bounds["length_scale"] = tuple(float(v) for v in kernel.length_scale_bounds)  # type: ignore[assignment]
        bounds["noise"] = tuple(float(v) for v in base.noise_bounds)  # type: ignore[assignment]
        if getattr(base, "objective", "loo") == "lml":
            bounds["variance"] = tuple(float(v) for v in kernel.variance_bounds)  # type: ignore[assignment]
    (log_alpha_lo, log_alpha_hi), shift = SQUASH_BOUNDS
    bounds["alpha"] = (float(math.exp(log_alpha_lo)), float(math.exp(log_alpha_hi)))
    bounds["shift"] = (float(shift[0]), float(shift[1]))
    # The variance scale's search, where the fit made one (it reports its bounds).
    variance_scale = (getattr(model, "extrapolation_", None) or {}).get("bounds")
    if variance_scale is not None:
        bounds["variance_scale"] = (float(variance_scale[0]), float(variance_scale[1]))
    return bounds


def _values(hyperparameters: Mapping[str, float]) -> dict[str, float]:
    values = {k: float(v) for k, v in hyperparameters.items()}
    if "alpha" in values and "beta" in values and values["alpha"] > 0:
        values["shift"] = values["beta"] / values["alpha"]
    return values


def at_bounds(
    hyperparameters: Mapping[str, float],
    bounds: Mapping[str, tuple[float, float]],
    tolerance: float = BOUND_TOLERANCE,
) -> dict[str, tuple[float, str, float]]:
    """The hyperparameters that sit at (within `tolerance` of) a bound of their search.

    Parameters
    ----------
    hyperparameters : mapping
        ``variance``, ``length_scale``, ``noise``, ``alpha``, ``beta`` (as ``hyperparameters_``).
    bounds : mapping
        ``name -> (low, high)`` (see :func:`search_bounds`); ``shift`` is beta / alpha.
    tolerance : float
        Positive bounds (scales) compare by ratio: at the upper bound when ``value >= high /
        (1 + tolerance)``; the shift, which may be negative, when within ``tolerance * |bound|``.

    Returns
    -------
    dict
        ``name -> (value, "lower" or "upper", bound)``.
    """
    values = _values(hyperparameters)
    found: dict[str, tuple[float, str, float]] = {}
    for name, (lo, hi) in bounds.items():
        if name not in values or not hi > lo:
            continue  # not searched (a bound pair that pins the value, or no value)
        v = values[name]
        if name != "shift" and lo > 0:
            if v <= lo * (1 + tolerance):
                found[name] = (v, "lower", lo)
            elif v >= hi / (1 + tolerance):
                found[name] = (v, "upper", hi)
        else:
            if v <= lo + tolerance * abs(lo):
                found[name] = (v, "lower", lo)
            elif v >= hi - tolerance * abs(hi):
                found[name] = (v, "upper", hi)
    return found


def prior_probability(hyperparameters: Mapping[str, float]) -> float:
    """The map's probability far from every observation: ``Phi(beta / sqrt(1 + alpha^2 variance))``.

    There the latent GP has mean 0 and its prior variance (the signal variance), and the probit
    squash turns that into this probability; 0.5 means "unknown".
    """
    alpha, beta = float(hyperparameters["alpha"]), float(hyperparameters["beta"])
    variance = float(hyperparameters.get("variance", 1.0))
    z = beta / math.sqrt(1.0 + alpha * alpha * variance)
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


def hyperparameter_warnings(
    hyperparameters: Mapping[str, float],
    bounds: Mapping[str, tuple[float, float]],
    tolerance: float = BOUND_TOLERANCE,
    counted: bool = False,
    tempered: bool = True,
) -> list[str]:
    """Warnings about hyperparameters at their bounds, with what to do, and about the probability far from data.

    Parameters
    ----------
    hyperparameters : mapping
        As ``hyperparameters_``.
    bounds : mapping
        As :func:`search_bounds` returns.
    tolerance : float
        See :func:`at_bounds`.
    counted : bool
        The map's probabilities come from ray counts with the GP as their prior
        (:mod:`gpomap.fusion`, the default of maps made from scans): then alpha at its cap is
        no warning. Where beams went, the counts decide and the GP weighs a few observations;
        where none went, the variance scale fitted on held-out stretches tempers the squash; so
        the map does not turn hard 0 / 1 (it is what most real logs fit: the cells are pure).
    tempered : bool
        The variance scale for unseen space was fitted (it tempers the squash where no beam went);
        when it was not, alpha at its cap is a warning even with counts.

    Returns
    -------
    list of str
        One sentence per finding (no "warning:" prefix); empty when all is well.
    """
    out = []
    for name, (v, side, bound) in at_bounds(hyperparameters, bounds, tolerance).items():
        if counted and tempered and name == "alpha" and side == "upper":
            continue
        if name == "variance_scale":
            # Either end is a map the held-out stretches asked for (as sure as the GP's mean, or
            # 1/2 where no beam went), nothing to act on: the summary's source line names it.
            continue
        label = "beta / alpha" if name == "shift" else name
        cap = " (its cap)" if name == "alpha" and side == "upper" else ""
        out.append(f"{label} {v:.4g} is at the {side} bound {bound:.4g} of its search{cap}: {_WHY.get(name, 'check the fit')}")
    if "alpha" in hyperparameters and "beta" in hyperparameters:
        p0 = prior_probability(hyperparameters)
        if not PRIOR_BAND[0] <= p0 <= PRIOR_BAND[1]:
            looks = "occupied" if p0 > 0.5 else "free"
            out.append(
                f"far from the data the map's probability is {p0:.2f}, not about 0.5 (alpha {float(hyperparameters['alpha']):.4g}, "
                f"beta {float(hyperparameters['beta']):.4g}): unexplored space will look {looks} rather than unknown"
            )
    return out


def map_warnings(
    ternary: NDArray[np.integer], band: tuple[float, float] = OCCUPIED_SHARE_BAND, observed: NDArray[np.bool_] | None = None
) -> list[str]:
    """Warnings about the written map's classes.

    Parameters
    ----------
    ternary : ndarray of int
        0 free, 1 occupied, -1 unknown.
    band : (float, float)
        An occupied share of the known cells outside [low, high] is reported.
    observed : ndarray of bool, optional
        Same shape: the cells rays went to (a voxel map's), where the classes are counted, as its
        OctoMap file holds them. Elsewhere a voxel map's classes are the GP's guess, which reaches
        far into the space round a few depth frames.

    Returns
    -------
    list of str
    """
    t = np.asarray(ternary)
    cells = "cells"
    if observed is not None:
        t, cells = t[np.asarray(observed, dtype=bool)], "cells rays went to"
    known = int(np.count_nonzero(t >= 0))
    if t.size == 0:
        return []
    if known == 0:
        return [f"no cell of the {t.size}-cell map is known (all between the thresholds): the map says nothing"]
    n_occ = int(np.count_nonzero(t == 1))
    share = n_occ / known
    if share < band[0]:
        return [
            f"the map is almost all free: {n_occ} of its {known} known {cells} ({100 * share:.2g} %) are occupied; "
            "the walls the scans hit are mostly missing"
        ]
    if share > band[1]:
        return [
            f"the map is mostly occupied: {100 * share:.1f} % of its {known} known {cells}; "
            "the space the beams crossed is not free in it"
        ]
    return []


def hyperparameter_source(model: Any, tolerance: float = BOUND_TOLERANCE) -> str:
    """How the model's hyperparameters came about, for the summary line.

    Returns
    -------
    str
        ``"learnt"``, ``"at bound: length_scale, alpha"`` (learnt, but some sit at a bound), or
        ``"given (alpha, beta fitted)"``.
    """
    found = at_bounds(model.hyperparameters_, search_bounds(model), tolerance)
    names = ["beta / alpha" if n == "shift" else n for n in found]
    if names:
        return "at bound: " + ", ".join(names)
    return "learnt" if getattr(_base_estimator(model), "optimise", True) else "given (alpha, beta fitted)"


def fit_warnings(model: Any, occupancy_map: Any = None, tolerance: float = BOUND_TOLERANCE) -> list[str]:
    """Every warning about a fitted AreaGPOM, TiledGPOM or GridGPOM (and the map it wrote, if given).

    Parameters
    ----------
    model : AreaGPOM, TiledGPOM or GridGPOM
        Fitted.
    occupancy_map : OccupancyMap, optional
        The map written from it; checked for its share of occupied cells (:func:`map_warnings`).
    tolerance : float
        See :func:`at_bounds`.

    Returns
    -------
    list of str
        One sentence per finding, without a prefix.
    """
    out = model_warnings(model, tolerance)
    if occupancy_map is not None:
        out += map_warnings(occupancy_map.ternary, observed=getattr(occupancy_map, "observed", None))
    return out


def model_warnings(model: Any, tolerance: float = BOUND_TOLERANCE) -> list[str]:
    """:func:`fit_warnings` about the fitted model alone (its learnt values at their bounds), one sentence each."""
    counted = getattr(model, "evidence_", None) is not None
    # A variance scale left at 1 (too few held-out points where no beam went) tempers nothing.
    tempered = "reason" not in (getattr(model, "extrapolation_", None) or {})
    return hyperparameter_warnings(model.hyperparameters_, search_bounds(model), tolerance, counted=counted, tempered=tempered)
