"""A fitted GP (:class:`GPPosterior`) and its prediction, dense or local.

Local prediction takes, for each block of queries, only the inputs within the kernel's reach
(:func:`local_blocks`): covariances below :data:`LOCAL_TOL` of the signal variance are left out
of the mean, below :data:`LOCAL_VARIANCE_TOL` of the variance's reduction.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

from gpomap import _compiled_local
from gpomap.config import MapConfig
from gpomap.gp.linalg import cholesky_inverse, lower_product, triangular_inverse_for
from gpomap.kernels.area import AreaKernel
from gpomap.kernels.box_points import BoxPointFactors
from gpomap.kernels.closed_form import POINT_WIDTH
from gpomap.lattice import column_bounds, stable_order
from gpomap.squash import ProbitSquash
from gpomap.supports import Supports

#: Local prediction treats covariances below this fraction of the signal variance as zero. The
#: latent mean then moves by at most LOCAL_TOL * variance * sum(|weights|) of the cells left out.
#: Tight enough that probabilities barely move against the dense prediction, loose enough that
#: most SE tiles predict locally (docs/choices.md, "Local prediction leaves out covariances").
LOCAL_TOL = 1e-6

#: The variance's reduction k_J^T (K^-1)_JJ k_J takes only the inputs whose covariance with the
#: block reaches this fraction of the signal variance (a subset of the mean's). An input left out
#: changes the reduction by its covariance with the query times its weight in the query's kriging
#: predictor (K^-1 k)_i, and both decay with distance, so the error is second order and a looser
#: tolerance than the mean's costs little. The product over |J|^2 inputs per query is most of the
#: local prediction's work, so fewer inputs pay (docs/choices.md, "Local prediction leaves out
#: covariances", the variance's own tolerance).
LOCAL_VARIANCE_TOL = 1e-4

#: Side of the local-prediction blocks, in cutoff distances r. A block's inputs lie within r of
#: it (a rounded square of area s^2 + 4 s r + pi r^2), and each query costs about their number
#: squared, so smaller blocks gather fewer inputs per query, down to where the per-block
#: overhead and the short matrix products take over.
LOCAL_BLOCK_SIDE: float = 0.25

#: Taking a block's (K^-1)_JJ costs about what this many of its queries' products with it do
#: (a gather of |J|^2 entries against |J|^2 fused multiply-adds per query; docs/choices.md,
#: "Measured for the code").
LOCAL_GATHER_QUERIES: int = 64

#: Local prediction is taken where its work (:func:`local_blocks`' estimate, plus n^3 for K^-1)
#: is at most this share of the dense n^2 m: half with numpy's block loop, whose products are the
#: dense path's own; twice with the compiled walk (:mod:`gpomap._compiled_local`), whose kernel
#: costs a small part of the dense path's numpy one (an erf per side end and point), so it wins
#: even on tiles whose every cell is within reach of every block (docs/choices.md, "Local
#: prediction leaves out covariances", the compiled walk).
LOCAL_WORK_SHARE: float = 0.5
COMPILED_LOCAL_WORK_SHARE: float = 2.0

#: Block-cell pairs tested at once when :func:`local_blocks` looks for each block's inputs.
_PAIRS_AT_ONCE: int = 1 << 15


class LocalBlock(NamedTuple):
    """A spatial block of queries and the training inputs near it (:func:`local_blocks`)."""

    #: Indices of the block's queries, ndarray of int, shape (q,).
    queries: NDArray[np.intp]
    #: Indices of the inputs within the radius, ndarray of int, shape (J,); those within the
    #: inner radius first.
    inputs: NDArray[np.intp]
    #: How many of `inputs` lie within the inner radius (the variance's).
    n_inner: int


@dataclass(frozen=True)
class LocalBlocks:
    """Every block of a local prediction, packed: block b's queries are
    ``query_index[query_start[b]:query_start[b + 1]]``, its inputs likewise, the first
    ``n_inner[b]`` of them within the inner radius. Iterating gives each :class:`LocalBlock`."""

    #: ndarray of int64, shape (m,): the queries, block after block.
    query_index: NDArray[np.int64]
    #: ndarray of int64, shape (blocks + 1,).
    query_start: NDArray[np.int64]
    #: ndarray of int64, shape (sum of |J|,): the inputs, block after block, inner ones first.
    input_index: NDArray[np.int64]
    #: ndarray of int64, shape (blocks + 1,).
    input_start: NDArray[np.int64]
    #: ndarray of int64, shape (blocks,).
    n_inner: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.n_inner.size)

    def __iter__(self) -> Iterator[LocalBlock]:
        qs, js = self.query_start, self.input_start
        for b in range(len(self)):
            yield LocalBlock(self.query_index[qs[b] : qs[b + 1]], self.input_index[js[b] : js[b + 1]], int(self.n_inner[b]))


def local_blocks(
    queries: Supports,
    train: Supports,
    radius: float,
    chunk_size: int,
    axes: int | None = None,
    side: float = LOCAL_BLOCK_SIDE,
    euclidean: bool = True,
    inner_radius: float | None = None,
) -> tuple[LocalBlocks, float]:
    """The queries in spatial blocks, each with the training inputs that come within `radius` of it.

    Queries are binned by centre on a grid of side ``LOCAL_BLOCK_SIDE * radius`` (bins of more
    than `chunk_size` queries are split); a block's inputs are those whose box is nearer than
    `radius` (Euclidean) to the bounding box of its queries. For an isotropic point kernel that
    decreases with distance and is below the tolerance beyond `radius`, a mean-normalised area
    kernel between two boxes is an average of point-kernel values (a Gauss-Legendre rule's
    weights are positive), none larger than at the boxes' nearest points, so every input left out
    covaries with every query of the block by less than the tolerance.

    Parameters
    ----------
    queries : Supports
        m query inputs.
    train : Supports
        n training inputs.
    radius : float
        Distance beyond which the point kernel is negligible.
    chunk_size : int
        Most queries per block.
    axes : int, optional
        Bin on the first `axes` coordinates only (3-D tile columns: x, y); default all.
    side : float
        Bin side, in units of `radius`.
    euclidean : bool
        Keep the inputs nearer than `radius` to a block; False: those whose box meets the block
        grown by `radius` along every axis (a superset: the corners too).
    inner_radius : float, optional
        A second, smaller distance (the variance's, :data:`LOCAL_VARIANCE_TOL`): each block's
        inputs within it come first; default `radius` (all of them).

    Returns
    -------
    blocks : LocalBlocks
        Query indices, training indices and how many of those are within `inner_radius`, per
        block; every query is in exactly one block.
    work : float
        Sum over blocks of ``|J_inner|^2 (|q| + LOCAL_GATHER_QUERIES)``: about the work of the
        local prediction's variance, in the units of the dense ``n^2 m``.
    """
    m = len(queries)
    if m == 0:
        empty = np.zeros(0, dtype=np.int64)
        return LocalBlocks(empty, np.zeros(1, dtype=np.int64), empty, np.zeros(1, dtype=np.int64), empty), 0.0
    centres = queries.centres
    a = centres.shape[1] if axes is None else axes
    low, _ = column_bounds(centres[:, :a])
    bins = np.floor((centres[:, :a] - low) / (side * radius)).astype(np.int64)
    # One integer per bin, the last axis fastest, sorted stably, and cut where it changes.
    key = np.zeros(m, dtype=np.int64)
    for k in range(a):
        key *= int(bins[:, k].max()) + 1
        key += bins[:, k]
    order = stable_order(key)
    sorted_key = key[order]
    starts = np.flatnonzero(np.concatenate([[True], sorted_key[1:] != sorted_key[:-1]]))
    ends = np.append(starts[1:], m)
    # Bins of more than chunk_size queries in pieces of at most that many.
    pieces = [np.arange(s, e, chunk_size) for s, e in zip(starts, ends)]
    cuts = np.concatenate(pieces) if pieces else starts
    lo_b = np.minimum.reduceat(queries.lower[order], cuts, axis=0)
    hi_b = np.maximum.reduceat(queries.upper[order], cuts, axis=0)
    n = len(train)
    inner = radius if inner_radius is None else min(inner_radius, radius)
    limit, inner_limit = (radius * radius, inner * inner) if euclidean else (radius, inner)
    rows: list[NDArray[np.intp]] = []
    cols: list[NDArray[np.intp]] = []
    outer: list[NDArray[np.bool_]] = []
    step = max(1, _PAIRS_AT_ONCE // max(n, 1))
    for b0 in range(0, cuts.size, step):
        b1 = min(cuts.size, b0 + step)
        # Squared distance between each block's box and each input's box, axis by axis.
        d2 = np.zeros((b1 - b0, n))
        for k in range(train.dim):
            gap = np.maximum(train.lower[None, :, k] - hi_b[b0:b1, k, None], lo_b[b0:b1, k, None] - train.upper[None, :, k])
            np.maximum(gap, 0.0, out=gap)
            if euclidean:
                gap *= gap
                d2 += gap
            else:
                np.maximum(d2, gap, out=d2)
        r, c = np.nonzero(d2 < limit)  # by block, then input
        rows.append(r + b0)
        cols.append(c)
        outer.append(d2[r, c] >= inner_limit)
    row, is_outer = np.concatenate(rows), np.concatenate(outer)
    # Each block's inner inputs first, each part in input order (a stable sort on small integers).
    order_in = np.argsort(2 * row + is_outer, kind="stable")
    counts = np.bincount(row, minlength=cuts.size)
    n_inner = counts - np.bincount(row, weights=is_outer, minlength=cuts.size).astype(np.int64)
    query_start = np.append(cuts, m).astype(np.int64)
    blocks = LocalBlocks(
        query_index=order.astype(np.int64),
        query_start=query_start,
        input_index=np.concatenate(cols)[order_in].astype(np.int64),
        input_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        n_inner=n_inner.astype(np.int64),
    )
    work = float(np.sum(n_inner.astype(np.float64) ** 2 * (np.diff(query_start) + LOCAL_GATHER_QUERIES)))
    return blocks, work


#: Most queries per kernel evaluation of a local block for the quadrature and summed kernels,
#: whose time per query grows past a few hundred (see :meth:`GPPosterior.latent`); the exact SE
#: kernel's tabled factors take a block in one piece.
LOCAL_KERNEL_POINTS: int = 256

#: Queries per local block aimed at, and the bounds of the block side (in cutoff distances r):
#: where queries are sparse the kernel call's fixed cost dominates, so sparse blocks grow.
LOCAL_BLOCK_QUERIES: int = 256
LOCAL_SIDE_RANGE: tuple[float, float] = (0.25, 1.0)

#: Query coordinates the local blocks bin on, per dimension (None: all). 3-D tiles are columns
#: and bin in x, y: several times faster than binning in z too (docs/choices.md, "Measured for
#: the code").
LOCAL_AXES: dict[int, int | None] = {2: None, 3: 2}


@dataclass
class GPPosterior:
    """A fitted GP: what predicting from it takes, and its prediction, dense or local.

    What :meth:`SupportGP.fit` and a tile's fit (:func:`gpomap.tiles.fit_tile_task`) return, and
    what pool and Dask workers send back: picklable, its cache of K^-1 left out.

    Attributes
    ----------
    inputs : Supports
        The n training inputs (or any inputs `kernel` takes, such as GPOMIK's segments).
    L : ndarray of shape (n, n)
        Lower Cholesky factor of K + noise (+ jitter).
    weights : ndarray of shape (n,)
        (K + noise)^-1 y.
    kernel : AreaKernel
        The kernel, with the hyperparameters the factor was formed with (for GPOMIK's segments,
        its line kernel).
    squash : ProbitSquash
        Latent moments to probabilities.
    jitter : float
        What was added to the diagonal for the factorisation to succeed (0 when nothing was).
    precision : ndarray of shape (n, n) or None
        (K + noise)^-1, formed by the first local prediction and kept for the next ones; a
        cache, left out of comparisons and pickles (a worker forms its own).
    """

    # The map file names this class by its package (gpomap.io.mapfile), where it is found by that name.
    __module__ = "gpomap.gp"

    inputs: Supports
    L: NDArray[np.float64]
    weights: NDArray[np.float64]
    kernel: AreaKernel
    squash: ProbitSquash
    jitter: float = 0.0
    precision: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)

    def __getstate__(self) -> dict[str, object]:
        # The cache would double what is shipped to a worker.
        return {**self.__dict__, "precision": None}

    @property
    def n_inputs(self) -> int:
        """Number of training inputs."""
        return int(self.weights.size)

    def latent(
        self, queries: Supports, variance: bool = True, local: bool = True, chunk_size: int = MapConfig.chunk_size
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Latent mean and (with `variance`) variance at the queries, each ndarray of shape (m,).

        Parameters
        ----------
        queries : Supports
            m query inputs (points are boxes of zero width).
        variance : bool
            Also the variance (the costly part); False gives None.
        local : bool
            Where the kernel falls below ``LOCAL_TOL`` of its variance within a small part of the
            inputs, predict block by block from the inputs near each block of queries (see
            :meth:`local_blocks`): equal to the dense prediction to that tolerance, and taken only
            where it saves at least half of the dense work. False: always dense (the reference).
        chunk_size : int
            Queries per block, bounding memory at ``n * chunk_size``.
        """
        if local:
            blocks = self.local_blocks(queries, chunk_size)
            if blocks is not None:
                return self._latent_local(queries, blocks, variance)
        return self._latent_dense(queries, variance, chunk_size)

    def local_blocks(self, queries: Supports, chunk_size: int) -> LocalBlocks | None:
        """Spatial blocks of queries with the inputs near each (:func:`local_blocks`), or None
        where the dense prediction is taken.

        A block's inputs are those within r of it, r the distance beyond which the point kernel
        is below ``LOCAL_TOL`` of its variance: every input left out covaries with every query
        of the block by less than that. Those within the distance of ``LOCAL_VARIANCE_TOL`` come
        first and make the variance. None for kernels without such a bound (member sums, the
        "sum" normalisation, other inputs than boxes) and where the blocks' work is more than
        ``LOCAL_WORK_SHARE`` of the dense one (``COMPILED_LOCAL_WORK_SHARE`` where the compiled
        walk takes them). The decision counts forming K^-1 (n^3) even when it is cached, so an
        answer never depends on what was predicted before.
        """
        kern, X = self.kernel, self.inputs
        if not (isinstance(kern, AreaKernel) and isinstance(X, Supports) and isinstance(queries, Supports)):
            return None
        if kern.method == "summed" or kern.normalisation != "mean" or len(queries) == 0:
            return None
        n, m = len(X), len(queries)
        share = COMPILED_LOCAL_WORK_SHARE if self._walks_compiled(queries) else LOCAL_WORK_SHARE
        if n**3 > share * n * n * m:
            return None  # dense whatever the blocks' work (below): not worth finding them
        r = kern.base.cutoff(LOCAL_TOL)
        axes = LOCAL_AXES.get(X.dim)
        # Blocks of about LOCAL_BLOCK_QUERIES queries where they are sparse (each kernel call and
        # gather of (K^-1)_JJ costs as much as a few dozen queries), else small, so their inputs
        # stay few: the side from the queries' mean density over their bounding box, within bounds.
        low, high = column_bounds(queries.centres[:, :axes])
        lo_side, hi_side = LOCAL_SIDE_RANGE
        extent = np.maximum(high - low, lo_side * r)
        side = (LOCAL_BLOCK_QUERIES * float(np.prod(extent)) / m) ** (1.0 / extent.size) / r
        blocks, work = local_blocks(
            queries,
            X,
            r,
            chunk_size,
            axes=axes,
            side=min(max(side, lo_side), hi_side),
            inner_radius=kern.base.cutoff(LOCAL_VARIANCE_TOL),
        )
        if work + n**3 > share * n * n * m:
            return None
        return blocks

    def _walks_compiled(self, queries: Supports) -> bool:
        """Whether local prediction at `queries` takes the compiled walk: the exact (SE) kernel at points."""
        kern = self.kernel
        return (
            _compiled_local.ENABLED
            and isinstance(kern, AreaKernel)
            and kern.method == "exact"
            and kern.normalisation == "mean"
            and bool(np.array_equal(queries.lower, queries.upper))
        )

    def _latent_local(
        self, queries: Supports, blocks: LocalBlocks, variance: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Mean k_J^T w_J and (with `variance`) variance k** - k_I^T (K^-1)_II k_I, block by block
        (J a block's inputs, I its inner ones).

        The exact SE kernel at points takes one compiled call over every block
        (:func:`gpomap._compiled_local.point_block_moments`) where numba is enabled; the loop
        below is the reference it is tested against, and the path of every other kernel.
        """
        kern, X = self.kernel, self.inputs
        mean = np.zeros(len(queries))
        var = kern.diag(queries) if variance else None  # the prior where no input is near
        if variance and self.precision is None:
            self.precision = cholesky_inverse(self.L)
        points = bool(np.array_equal(queries.lower, queries.upper))
        # Work common to every block done once (the exact kernel's tables of factors).
        cross = kern.point_blocks(X, queries.lower) if points else None
        if isinstance(cross, BoxPointFactors) and _compiled_local.ENABLED:
            reduction = np.zeros(len(queries))
            side_lo, side_hi, side_of = cross.packed_sides()
            _compiled_local.point_block_moments(
                self.precision if self.precision is not None else np.empty((0, 0)),
                self.weights,
                side_lo,
                side_hi,
                side_of,
                np.ascontiguousarray(queries.lower, dtype=np.float64),
                blocks.query_index,
                blocks.query_start,
                blocks.input_index,
                blocks.input_start,
                blocks.n_inner,
                float(cross.length_scale),
                float(cross.variance),
                POINT_WIDTH,
                var is not None,
                mean,
                reduction,
            )
            if var is not None:
                var = np.maximum(var - reduction, 0.0)
            return mean, var
        for q, near, n_inner in blocks:
            if near.size == 0:
                continue
            K_II = None
            if var is not None:
                K_inv = self.precision
                assert K_inv is not None  # formed above
                inner = near[:n_inner]
                # One gather of the |I|^2 entries (rows then columns would copy |I| whole rows first).
                K_II = np.take(K_inv, inner[:, None] * K_inv.shape[1] + inner[None, :])
            w_J = self.weights[near]
            step = q.size if kern.method == "exact" else LOCAL_KERNEL_POINTS
            for s in range(0, q.size, step):
                qs = q[s : s + step]
                # (|J|, |qs|)
                Ks = cross.block(near, qs) if cross is not None else kern(X.subset(near), queries.subset(qs))
                mean[qs] = w_J @ Ks
                if var is not None and K_II is not None:
                    K_I = Ks[:n_inner]
                    reduction = np.einsum("ij,ij->j", K_I, K_II @ K_I)
                    var[qs] = np.maximum(var[qs] - reduction, 0.0)
        return mean, var

    def _latent_dense(
        self, queries: Supports, variance: bool, chunk_size: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """Mean and variance from every input, in chunks of queries."""
        m = len(queries)
        mean = np.empty(m)
        var = np.empty(m) if variance else None
        # Whitening by a product where it pays (see triangular_inverse_for).
        L_inv = triangular_inverse_for(self.L, m, getattr(self.inputs, "dim", 2)) if variance else None
        for s in range(0, m, chunk_size):
            part = queries.subset(slice(s, min(m, s + chunk_size)))
            Ks = self.kernel(self.inputs, part)  # (n, c)
            mean[s : s + len(part)] = Ks.T @ self.weights
            if var is not None:
                v = solve_triangular(self.L, Ks, lower=True, check_finite=False) if L_inv is None else lower_product(L_inv, Ks)
                var[s : s + len(part)] = np.maximum(self.kernel.diag(part) - np.einsum("ij,ij->j", v, v), 0.0)
        return mean, var
