"""GPOMIK (O'Callaghan & Ramos, AAAI 2011): beams as line segments, hits as points.

Each beam that returned becomes two GP inputs: the segment from the sensor to a margin short of
its end point (free space, target -1) and the end point (a hit, target +1). A no-return beam
becomes a free segment only, up to a cap. The covariance is the point kernel integrated along
the segments (:class:`gpomap.kernels.line.LineKernel`); the GP core (hyperparameter objective,
noise, probit squash) is :class:`gpomap.gp.SupportGP`, the same as MSK-GPOM's. The original
pre-selects "relevant" readings per kernel; here ``n_beams_per_scan`` thins each scan to evenly
spaced beams instead, as MSK-GPOM does.

The Gram matrices are compiled (:class:`CompiledLineKernel`, :mod:`gpomap._compiled_line`) where
numba is enabled; :class:`~gpomap.kernels.line.LineKernel`'s numpy passes are the reference, the
same numbers to round-off.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpomap import _compiled_line
from gpomap.errors import EmptyDataError
from gpomap.estimator import GPMapEstimator
from gpomap.grid import DEFAULT_THRESHOLDS
from gpomap.kernels._compiled import MATERN32, profile_id
from gpomap.kernels.line import PARALLEL_SIN, POINT_LENGTH, LineKernel, Segments, as_segments, concatenate_segments
from gpomap.kernels.point import make_point_kernel
from gpomap.scans import Scan, evenly_spaced

#: Default quadrature per kernel: (nodes per panel, longest panel in metres). The SE needs GL
#: along one segment only (the other is closed form); Matern along both, so fewer nodes.
DEFAULT_RULES: dict[str, tuple[int, float]] = {"se": (4, 1.0), "matern32": (3, 2.0)}


def beam_segments(
    scans: Sequence[Scan],
    hit_margin: float = 0.1,
    no_return_cap: float | None = 10.0,
    n_beams_per_scan: int | None = None,
) -> tuple[Segments, Segments, dict[str, int]]:
    """Free segments and hit points of a set of scans.

    Parameters
    ----------
    scans : sequence of Scan
    hit_margin : float
        A free segment stops this short of its hit; beams shorter than the margin give a hit only.
    no_return_cap : float, optional
        A no-return beam is free up to this distance (10 m by default, as MSK-GPOM; None: the
        scan's max range); 0 drops them.
    n_beams_per_scan : int, optional
        Keep this many evenly spaced beams per scan (all by default).

    Returns
    -------
    free : Segments
        b free segments (sensor to end, less the margin).
    hits : Segments
        h zero-length segments at the hits.
    counts : dict
        ``n_beams``, ``n_invalid``, ``n_no_return`` over the beams used.
    """
    starts, ends, hits = [], [], []
    n_beams = n_invalid = n_no_return = 0
    for scan in scans:
        if n_beams_per_scan is not None:
            scan = scan.select_beams(evenly_spaced(scan.n_beams, n_beams_per_scan))
        valid, no_ret = scan.valid(), scan.no_return()
        hit = valid & ~no_ret
        n_beams += scan.n_beams
        n_invalid += int((~valid).sum())
        n_no_return += int(no_ret.sum())
        cap = scan.max_range if no_return_cap is None else float(no_return_cap)
        length = np.where(hit, scan.ranges - hit_margin, np.minimum(cap, scan.max_range))
        use = valid & (length > 0)
        a = scan.world_angles()[use]
        o = np.broadcast_to(scan.pose[:2], (a.size, 2))
        starts.append(o)
        ends.append(o + length[use, None] * np.column_stack([np.cos(a), np.sin(a)]))
        hits.append(scan.endpoints()[hit])
    free = Segments(np.concatenate(starts), np.concatenate(ends)) if starts else Segments(np.zeros((0, 2)), np.zeros((0, 2)))
    hit_pts = Segments.from_points(np.concatenate(hits) if hits else np.zeros((0, 2)))
    return free, hit_pts, {"n_beams": n_beams, "n_invalid": n_invalid, "n_no_return": n_no_return}


class CompiledLineKernel(LineKernel):
    """:class:`~gpomap.kernels.line.LineKernel` with its Gram matrices compiled (:mod:`gpomap._compiled_line`).

    The same parameters and the same numbers to round-off: Matern 3/2's node sums (an input set
    against itself with or without the length-scale gradient, or against another without it) and
    the squared exponential's closed forms and quadrature (every case) are compiled; other base
    kernels, and whenever ``gpomap._compiled_line.ENABLED`` is off, take LineKernel's numpy path.
    """

    def _takes_compiled(self, same: bool, eval_gradient: bool) -> bool:
        if not _compiled_line.ENABLED:
            return False
        if self.closed_form:
            return True
        return profile_id(self.base) == MATERN32 and (same or not eval_gradient)

    def _se_arrays(self, X: Segments) -> _compiled_line.SegmentArrays:
        nodes = self.nodes(X)
        return X.starts, X.ends, X.lengths, nodes.nodes, nodes.weights, np.asarray(nodes.offsets, dtype=np.intp)

    def _compiled_gram(
        self, A: Segments, B: Segments | None, eval_gradient: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """K(A, B) (B None: A against itself) and d K / d log l with `eval_gradient`, normalisation applied."""
        var, l = self.base.variance, self.base.length_scale
        dL: NDArray[np.float64] | None
        if self.closed_form:
            F, dF = _compiled_line.se_gram(
                self._se_arrays(A), None if B is None else self._se_arrays(B), l, POINT_LENGTH, PARALLEL_SIN, eval_gradient
            )
            K = var * F
            dL = None if dF is None else var * dF
        else:
            na = self.nodes(A)
            if B is None:
                K, dL = _compiled_line.matern32_gram(na.nodes, na.weights, na.offsets, var, l, eval_gradient)
            else:
                nb = self.nodes(B)
                K, dL = (
                    _compiled_line.matern32_cross(na.nodes, na.weights, na.offsets, nb.nodes, nb.weights, nb.offsets, var, l),
                    None,
                )
        if self.normalisation == "sum":
            scale = np.outer(self._weights(A), self._weights(A if B is None else B))
            K = K * scale
            if dL is not None:
                dL = dL * scale
        return K, dL

    def __call__(self, A: Any, B: Any = None, eval_gradient: bool = False) -> Any:
        """Covariances between two sets of segments (or points), as :meth:`LineKernel.__call__`.

        Parameters
        ----------
        A : Segments
            n inputs (an (n, 2) array or point Supports are taken as points).
        B : Segments, optional
            m inputs; defaults to `A`.
        eval_gradient : bool
            Also return dK/dtheta.

        Returns
        -------
        K : ndarray of shape (n, m)
        dK : ndarray of shape (n, m, 2), only with `eval_gradient`
        """
        if not self._takes_compiled(B is None, eval_gradient):
            return super().__call__(A, B, eval_gradient)
        A = as_segments(A)
        K, dL = self._compiled_gram(A, None if B is None else as_segments(B), eval_gradient)
        if not eval_gradient:
            return K
        assert dL is not None  # asked for
        return K, np.stack([K, dL], axis=-1)

    def gram_and_length_scale_gradient(self, X: Any, prepared: Any = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """K(X, X) and d K / d log(length_scale), both exactly symmetric (what :class:`gpomap.gp.SupportGP`'s search asks).

        Parameters
        ----------
        X : Segments
            n inputs.
        prepared : None
            Nothing is prepared (the protocol of :meth:`gpomap.kernels.area.AreaKernel.gram_and_length_scale_gradient`).

        Returns
        -------
        K, dL : ndarray of shape (n, n)
        """
        X = as_segments(X)
        if not self._takes_compiled(True, True):
            K, dK = super().__call__(X, eval_gradient=True)
            return K, np.ascontiguousarray(dK[:, :, 1])
        K, dL = self._compiled_gram(X, None, True)
        assert dL is not None  # asked for
        return K, dL


class GPOMIK(GPMapEstimator):
    """GP occupancy map with integral kernels over beams (GPOMIK).

    Parameters
    ----------
    kernel : {"se", "matern32"}
        Point kernel integrated along the beams.
    n_beams_per_scan : int, optional
        Evenly spaced beams kept per scan; all by default. GPOMIK has one input per beam plus one
        per hit, so this sets the GP's size.
    hit_margin : float
        Free segments stop this short of the hit, metres.
    no_return_cap : float, optional
        Length of the free segment of a no-return beam (default the sensor's max range).
    normalisation : {"mean", "sum"}
        Average the kernel along segments or integrate it (see :mod:`gpomap.kernels.line`).
    order, max_panel : int, float, optional
        Gauss-Legendre rule along segments: nodes per panel and longest panel (metres);
        defaults per kernel in ``DEFAULT_RULES``.
    variance, length_scale, noise, length_scale_bounds, noise_bounds, noise_model, objective,
    optimise, n_restarts, seed, thresholds, chunk_size
        As in :class:`gpomap.settings.MapSettings`.
    """

    method_name = "gpomik"

    hit_margin: float

    def __init__(
        self,
        kernel: str = "matern32",
        n_beams_per_scan: int | None = None,
        hit_margin: float = 0.1,
        no_return_cap: float | None = 10.0,
        normalisation: str = "mean",
        order: int | None = None,
        max_panel: float | None = None,
        variance: float = 1.0,
        length_scale: float = 1.0,
        noise: float = 0.1,
        length_scale_bounds: tuple[float, float] = (0.05, 20.0),
        noise_bounds: tuple[float, float] = (1e-4, 10.0),
        noise_model: str = "constant",
        objective: str = "loo",
        optimise: bool = True,
        n_restarts: int = 2,
        seed: int = 0,
        thresholds: tuple[float, float] = DEFAULT_THRESHOLDS,
        chunk_size: int = 4096,
    ) -> None:
        self.kernel = kernel
        self.n_beams_per_scan = n_beams_per_scan
        self.hit_margin = hit_margin
        self.no_return_cap = no_return_cap
        self.normalisation = normalisation
        self.order = order
        self.max_panel = max_panel
        self.variance = variance
        self.length_scale = length_scale
        self.noise = noise
        self.length_scale_bounds = length_scale_bounds
        self.noise_bounds = noise_bounds
        self.noise_model = noise_model
        self.objective = objective
        self.optimise = optimise
        self.n_restarts = n_restarts
        self.seed = seed
        self.thresholds = thresholds
        self.chunk_size = chunk_size

    def __repr__(self) -> str:
        return f"GPOMIK(kernel={self.kernel!r}, n_beams_per_scan={self.n_beams_per_scan})"

    def rule(self) -> tuple[int, float | None]:
        """The quadrature rule in use: (nodes per panel, longest panel)."""
        order, panel = DEFAULT_RULES.get(make_point_kernel(self.kernel).name, (4, 1.0))
        return (order if self.order is None else int(self.order), panel if self.max_panel is None else self.max_panel)

    def make_kernel(self) -> LineKernel:
        """The line kernel these settings describe, at the starting hyperparameters (compiled where numba is)."""
        base = make_point_kernel(
            self.kernel, variance=self.variance, length_scale=self.length_scale, length_scale_bounds=self.length_scale_bounds
        )
        order, panel = self.rule()
        return CompiledLineKernel(base, self.normalisation, order, panel)

    def fit(self, scans: Sequence[Scan]) -> GPOMIK:
        """Build the map from scans.

        Parameters
        ----------
        scans : sequence of Scan

        Returns
        -------
        self
        """
        timings: dict[str, float] = {}
        t = time.perf_counter()
        free, hits, counts = beam_segments(scans, self.hit_margin, self.no_return_cap, self.n_beams_per_scan)
        if len(free) == 0 or len(hits) == 0:
            raise EmptyDataError(
                f"need both free beams and hits, got {len(free)} beams and {len(hits)} hits from {len(scans)} scan(s)"
            )
        X = concatenate_segments([free, hits])
        y = np.concatenate([-np.ones(len(free)), np.ones(len(hits))])
        timings["observations"] = time.perf_counter() - t
        gp = self._make_gp(self.make_kernel())
        # Segments offer what SupportGP uses of its inputs (len, counts, subset); GPOMIK never
        # samples inputs for its hyperparameters, which would need cell centres.
        self._fit_gp(gp, X, y)
        timings.update(gp.timings_)
        self.segments_ = free
        self.hits_ = hits
        self.counts_ = counts
        self.gp_ = gp
        self.timings_ = timings
        self.extent_points_ = np.concatenate([free.starts, free.ends, hits.starts])
        self.path_ = np.array([s.pose[:2] for s in scans])
        return self

    @property
    def n_inputs_(self) -> int:
        """Number of GP inputs: free segments plus hits."""
        self._check_fitted()
        return len(self.segments_) + len(self.hits_)

    def _queries(self, points: NDArray[np.float64]) -> Segments:
        return Segments.from_points(points)

    def _summary_extra(self) -> dict[str, Any]:
        order, panel = self.rule()
        return {
            "normalisation": self.normalisation,
            "quadrature_order": order,
            "max_panel": panel,
            "n_beams_per_scan": self.n_beams_per_scan,
            "n_segments": len(self.segments_),
            "n_hits": len(self.hits_),
            "n_invalid_readings": self.counts_["n_invalid"],
            "n_no_return_readings": self.counts_["n_no_return"],
        }
