"""One tile's fit and prediction, as plain functions of arrays that threads, process pools and Dask can ship.

:class:`TileFitTask` holds all a fit needs: the tile's cells, the settings, the hyperparameters
and the tile's last fit. :func:`fit_tile_task` factorises it as :class:`~gpomap.gp.SupportGP`
does, so that a one-tile map is one SupportGP over its cells to the last bits, and reuses the
covariances of the cells a refit keeps; :func:`predict_tile_task` gives the tile's latent moments
at points. :class:`TileState` is a fitted tile.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpomap.config import MapConfig
from gpomap.gp import GPPosterior, SupportGP, cholesky_solve, noisy_cholesky
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.point import make_point_kernel
from gpomap.squash import ProbitSquash
from gpomap.supports import Supports


@dataclass
class TileState:
    """A fitted tile: its GP's posterior and the hyperparameters it was fitted with.

    Attributes
    ----------
    key : (int, int)
        Tile index (ix, iy) on the tile grid.
    posterior : GPPosterior
        The tile's training cells (their member points only for the ``"summed"`` area kernel,
        which needs them), the Cholesky factor, the weights, the kernel and the squash.
    hyperparameters : dict
        variance, length_scale, noise, alpha, beta used by this tile.
    seconds : float
        Time the fit took on its worker.
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.tiles"

    key: tuple[int, int]
    posterior: GPPosterior
    hyperparameters: dict[str, float]
    seconds: float

    @property
    def n_cells(self) -> int:
        """Number of training cells."""
        return self.posterior.n_inputs


@dataclass(frozen=True)
class TileSettings:
    """What a tile's tasks need of the map's settings: the kernel and noise and, for per-tile
    hyperparameters, how to learn them (the fields of :class:`~gpomap.config.MapConfig` they come from).

    Attributes
    ----------
    area : str
        The area kernel's method, resolved ("exact", "quadrature" or "summed"; the map's
        ``area_method``).
    per_tile : bool
        Learn each tile's hyperparameters, starting from the map's; False: use the map's.
    """

    area: str
    kernel: str = MapConfig.kernel
    normalisation: str = MapConfig.normalisation
    quadrature_order: int = MapConfig.quadrature_order
    length_scale_bounds: tuple[float, float] = MapConfig.length_scale_bounds
    noise_bounds: tuple[float, float] = MapConfig.noise_bounds
    noise_model: str = MapConfig.noise_model
    objective: str = MapConfig.objective
    n_restarts: int = MapConfig.n_restarts
    seed: int = MapConfig.seed
    hyper_subset: int | None = MapConfig.hyper_subset
    prior_std: float | None = MapConfig.prior_std
    class_weight: str | None = MapConfig.class_weight
    per_tile: bool = False

    def search_gp(
        self,
        kernel: AreaKernel,
        noise: float,
        optimise: bool,
        hyper_subset: int | None,
        hyper_group: int | None = None,
        n_threads: int = 1,
    ) -> SupportGP:
        """The GP that learns hyperparameters with these settings: MSK-GPOM's search, its objective
        per input, its groups on `n_threads` threads."""
        return SupportGP(
            kernel,
            noise=noise,
            noise_bounds=self.noise_bounds,
            noise_model=self.noise_model,
            objective=self.objective,
            optimise=optimise,
            n_restarts=self.n_restarts,
            seed=self.seed,
            hyper_subset=hyper_subset,
            prior_std=self.prior_std,
            class_weight=self.class_weight,
            hyper_group=hyper_group,
            objective_per_input=True,
            n_threads=n_threads,
        )


@dataclass
class TileCells:
    """The cells a tile's GP is fitted on (those meeting its grown square, in canonical order).

    Attributes
    ----------
    lower, upper : ndarray of shape (n, d)
        Boxes.
    counts : ndarray of shape (n,)
        Member points per cell.
    labels : ndarray of shape (n,)
        +1 occupied, -1 free.
    member_points : ndarray of shape (m, d) or None
        Only for the ``"summed"`` area kernel.
    member_offsets : ndarray of int, shape (n + 1,) or None
    """

    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    counts: NDArray[np.float64]
    labels: NDArray[np.float64]
    member_points: NDArray[np.float64] | None = None
    member_offsets: NDArray[np.intp] | None = None

    def supports(self) -> Supports:
        """The cells as GP inputs."""
        return Supports(self.lower, self.upper, self.counts, self.member_points, self.member_offsets)

    def signature(self) -> tuple[bytes, ...]:
        """A digest of the cells' bytes (SHA-256 of their boxes, counts and labels; the bytes
        themselves would be the cells again): equal signatures, the same GP (an update refits a
        tile only when it changes)."""
        digest = hashlib.sha256()
        for a in (self.lower, self.upper, self.counts, self.labels):
            digest.update(np.ascontiguousarray(a).tobytes())
            digest.update(str(a.shape).encode())
        return (digest.digest(),)


@dataclass
class TileFitTask:
    """One tile's fit, as it is shipped to a worker (:func:`fit_tile_task`).

    Attributes
    ----------
    key : (int, int)
        Tile index (ix, iy).
    cells : TileCells
    settings : TileSettings
    hyperparameters : dict
        variance, length_scale, noise, alpha, beta: used as they are, or as the start with
        ``settings.per_tile``.
    previous : TileState or None
        This tile's last fit, whose covariances of the cells still there are reused (same
        hyperparameters only); None: every entry computed afresh.
    """

    key: tuple[int, int]
    cells: TileCells
    settings: TileSettings
    hyperparameters: dict[str, float]
    previous: TileState | None = None


def _area_kernel(settings: TileSettings, variance: float, length_scale: float) -> AreaKernel:
    base = make_point_kernel(
        settings.kernel, variance=variance, length_scale=length_scale, length_scale_bounds=settings.length_scale_bounds
    )
    kern = AreaKernel(base, settings.area, settings.normalisation, settings.quadrature_order)
    # Same path as SupportGP's factorisation (clone from log theta), so a one-tile map matches
    # one SupportGP over its cells to the last bits.
    return kern.clone_with_theta(kern.theta)


def _noise_vector(settings: TileSettings, noise: float, counts: NDArray[np.float64]) -> NDArray[np.float64]:
    scale = 1.0 / np.maximum(counts, 1.0) if settings.noise_model == "per_count" else np.ones(counts.size)
    return np.exp(np.log(noise)) * scale


def _box_keys(lower: NDArray[np.float64], upper: NDArray[np.float64]) -> list[bytes]:
    return [row.tobytes() for row in np.ascontiguousarray(np.concatenate([lower, upper], axis=1))]


def _gram_reusing(kern: AreaKernel, X: Supports, previous: TileState, settings: TileSettings) -> NDArray[np.float64] | None:
    """K(X, X), with the entries of cells the previous fit of this tile had copied from it.

    The previous covariance is recovered from its factor (``L L^T`` less its noise and jitter):
    a few matrix products instead of the kernel's quadrature, which is most of a tile fit. The
    copied entries carry rounding of about 1e-15 relative; :meth:`TiledGPOM.refresh` with
    ``exact=True`` refits without them. The caller checks that the hyperparameters are the same.
    None when too little can be reused: a kernel whose entries depend on more than the boxes
    (member points, counts), or fewer than half the cells in common.
    """
    if settings.area == "summed" or settings.normalisation == "sum":
        return None
    old_index = {k: i for i, k in enumerate(_box_keys(previous.posterior.inputs.lower, previous.posterior.inputs.upper))}
    new_keys = _box_keys(X.lower, X.upper)
    pairs = [(j, old_index[k]) for j, k in enumerate(new_keys) if k in old_index]
    if len(pairs) < 0.5 * len(new_keys):
        return None
    keep_new = np.array([j for j, _ in pairs], dtype=np.intp)
    keep_old = np.array([i for _, i in pairs], dtype=np.intp)
    before = previous.posterior
    Lk = before.L[keep_old]
    K = np.empty((len(X), len(X)))
    old_diag = _noise_vector(settings, previous.hyperparameters["noise"], before.inputs.counts[keep_old]) + before.jitter
    K_old = Lk @ Lk.T
    K_old[np.diag_indices_from(K_old)] -= old_diag
    K[np.ix_(keep_new, keep_new)] = K_old
    fresh = np.setdiff1d(np.arange(len(X)), keep_new)
    if fresh.size:
        rows = kern(X.subset(fresh), X)
        K[fresh, :] = rows
        K[:, fresh] = rows.T
        # The fresh-fresh block as the full Gram would give it (symmetrised).
        K[np.ix_(fresh, fresh)] = kern(X.subset(fresh))
    return K


def fit_tile_task(task: TileFitTask) -> TileState:
    """Fit one tile's GP (a top-level function so process pools and Dask can ship it).

    Parameters
    ----------
    task : TileFitTask

    Returns
    -------
    TileState
    """
    t0 = time.perf_counter()
    st = task.settings
    hyp = dict(task.hyperparameters)
    X = task.cells.supports()
    y = np.asarray(task.cells.labels, dtype=float)
    kern = _area_kernel(st, hyp["variance"], hyp["length_scale"])
    if st.per_tile:
        gp = st.search_gp(kern, hyp["noise"], optimise=True, hyper_subset=st.hyper_subset)
        gp.squash = ProbitSquash(hyp["alpha"], hyp["beta"])
        gp.fit(X, y)
        kern, L, weights, jitter = gp.kernel, gp.posterior_.L, gp.posterior_.weights, gp.posterior_.jitter
        hyp = {
            "variance": gp.kernel.base.variance,
            "length_scale": gp.kernel.base.length_scale,
            "noise": gp.noise,
            "alpha": gp.squash.alpha,
            "beta": gp.squash.beta,
        }
    else:
        # Fixed hyperparameters: one factorisation, no leave-one-out pass (alpha and beta are
        # global), which halves the work of SupportGP.fit.
        previous = task.previous
        same_hyp = previous is not None and all(
            previous.hyperparameters.get(n) == hyp[n] for n in ("variance", "length_scale", "noise")
        )
        K = _gram_reusing(kern, X, previous, st) if previous is not None and same_hyp else None
        if K is None:
            K = kern(X)
        L, jitter = noisy_cholesky(K, _noise_vector(st, hyp["noise"], X.counts), lambda: kern(X))
        weights = cholesky_solve(L, y)
    # Member points only where the kernel reads them.
    kept = X if st.area == "summed" else Supports(X.lower, X.upper, X.counts)
    hyp = {k: float(v) for k, v in hyp.items()}
    posterior = GPPosterior(kept, L, weights, kern, ProbitSquash(hyp["alpha"], hyp["beta"]), jitter)
    return TileState((int(task.key[0]), int(task.key[1])), posterior, hyp, time.perf_counter() - t0)


def predict_tile_task(
    state: TileState,
    points: NDArray[np.float64],
    chunk_size: int = MapConfig.chunk_size,
    variance: bool = True,
    local: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Latent mean and variance of one tile's GP at points (top-level, picklable):
    :meth:`~gpomap.gp.GPPosterior.latent` of its posterior.

    Parameters
    ----------
    state : TileState
    points : ndarray of shape (m, d)
    chunk_size : int
        Query points per block, bounding memory at ``n * chunk_size``.
    variance : bool
        Also the variance (the costly part); False gives None.
    local : bool
        Local prediction where it pays (equal to the dense one to :data:`gpomap.gp.LOCAL_TOL` and
        :data:`gpomap.gp.LOCAL_VARIANCE_TOL`); False: always dense (the reference).

    Returns
    -------
    mean, var : ndarray of shape (m,)
    """
    pts = np.asarray(points, dtype=float).reshape(-1, state.posterior.inputs.dim)
    return state.posterior.latent(Supports.from_points(pts), variance, local, chunk_size)
