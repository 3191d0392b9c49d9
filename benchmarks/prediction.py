"""GP prediction rate of the tiled engine: local (the default) against dense (the reference), points per second per core.

Per dataset and kernel, a map is fitted with ``AreaGPOM(kernel=k, n_workers=1)`` (defaults
otherwise) and predicted

- at `--points` uniform random points in the map's box (``model.bounds_``) by
  ``predict_proba_gp``,
- at the cell centres of the written grid at `--resolution` (the grid ``model.grid`` writes) by
  ``_predict_blended`` directly,
- and the whole ``model.grid(resolution)`` (the evidence layer samples the GP coarsely and
  interpolates, so it predicts far fewer points).

Each is timed with the local prediction (:func:`gpomap.tiles.predict_tile_task`'s default): the
first call (which forms each tile's K^-1) and the best of `--repeat` (K^-1 cached; wall clock,
and this process's CPU time, steadier on a shared machine); the best of `--repeat` again with the
blocks walked by numpy instead of the compiled loop (:mod:`gpomap._compiled_local`, the exact SE
kernel at points only; the same numbers to round-off); and once with
``local=False``, the dense solve it replaces; the table gives both rates, their ratio, and the
largest absolute differences of probability and latent variance between the two. One process,
one BLAS thread (set here before numpy loads).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/prediction.py [--datasets room,intel] [--kernels se,matern32]
"""

from __future__ import annotations

import argparse
import os
import time
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


@contextmanager
def dense_prediction() -> Any:
    """Every tile predicted by the dense path (``predict_tile_task(..., local=False)``) inside the block."""
    from gpomap.tiles import blending

    original = blending.predict_tile_task
    blending.predict_tile_task = partial(original, local=False)  # type: ignore[assignment]
    try:
        yield
    finally:
        blending.predict_tile_task = original


def timed(fn: Any, repeat: int) -> tuple[float, float, float, Any]:
    """First wall time, best wall time and best CPU time of `repeat` calls, and the last result."""
    wall, cpu = [], []
    out = None
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return wall[0], min(wall), min(cpu), out


def blended(model: Any, points: Any) -> tuple[Any, Any]:
    """Probability and latent variance of ``model._predict_blended`` at points."""
    p, _, var, _ = model._predict_blended(points)
    return p, var


def written_grid(model: Any, resolution: float) -> tuple[Any, Any]:
    """Probability and latent variance of ``model.grid(resolution)``."""
    g = model.grid(resolution)
    return g.probability, g.variance


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--datasets", default="room,intel")
    parser.add_argument("--kernels", default="se,matern32")
    parser.add_argument("--points", type=int, default=200_000, help="uniform random query points")
    parser.add_argument("--resolution", type=float, default=0.05, help="written grid cell, metres")
    parser.add_argument("--intel-scans", type=int, default=300, help="first scans of the Intel log")
    parser.add_argument("--repeat", type=int, default=3, help="local runs per case; first and best reported")
    parser.add_argument("--no-dense", action="store_true", help="skip the dense reference")
    args = parser.parse_args()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"

    import numpy as np

    from gpomap import _compiled_local
    from gpomap.grid import GridSpec
    from gpomap.io import read_scans
    from gpomap.mapping import AreaGPOM
    from gpomap.progress import set_progress_mode
    from gpomap.simulate import paper_room_scans

    set_progress_mode("quiet")
    loaders = {
        "room": paper_room_scans,
        "intel": lambda: read_scans(DATA / "intel" / "intel-corrected.log.gz")[: args.intel_scans],
    }
    head = (
        f"{'dataset':<8}{'kernel':<10}{'cells/tile':>11} {'case':<9}{'points':>9}{'first s':>9}{'best s':>8}"
        f"{'pts/s':>10}{'cpu pts/s':>10}{'numpy pts/s':>12}{'dense s':>9}{'dense pts/s':>12}{'speed-up':>9}{'max |dp|':>10}{'max |dvar|':>11}"
    )
    print(head, flush=True)
    for name in args.datasets.split(","):
        scans = loaders[name]()
        for kernel in args.kernels.split(","):
            model = AreaGPOM(kernel=kernel, n_workers=1).fit(scans)
            cells = np.array([s.n_cells for s in model.tiles_.values()])
            lo, hi = model.bounds_
            random_points = np.random.default_rng(0).uniform(lo, hi, size=(args.points, lo.size))
            spec = GridSpec.from_extent((lo[0], hi[0], lo[1], hi[1]), args.resolution, align=True)
            centres = spec.centres()
            cases = {
                "random": (random_points.shape[0], partial(model.predict_proba_gp, random_points, return_var=True)),
                "centres": (centres.shape[0], partial(blended, model, centres)),
                "grid": (spec.shape[0] * spec.shape[1], partial(written_grid, model, args.resolution)),
            }
            for case, (n_points, fn) in cases.items():
                # Each fit starts without K^-1: the first local call of each case forms it.
                for state in model.tiles_.values():
                    state.posterior.precision = None
                first, best, cpu, (p, v) = timed(fn, args.repeat)
                compiled = _compiled_local.ENABLED
                _compiled_local.ENABLED = False
                try:
                    _, numpy_best, _, _ = timed(fn, args.repeat)
                finally:
                    _compiled_local.ENABLED = compiled
                row = (
                    f"{name:<8}{kernel:<10}{f'{np.median(cells):.0f}/{cells.max()}':>11} {case:<9}{n_points:>9}"
                    f"{first:>9.3f}{best:>8.3f}{n_points / best:>10.0f}{n_points / cpu:>10.0f}{n_points / numpy_best:>12.0f}"
                )
                if args.no_dense:
                    print(row, flush=True)
                    continue
                with dense_prediction():
                    _, dense, _, (p_ref, v_ref) = timed(fn, 1)
                dp = float(np.max(np.abs(np.asarray(p) - np.asarray(p_ref))))
                dv = float(np.max(np.abs(np.asarray(v) - np.asarray(v_ref))))
                print(f"{row}{dense:>9.3f}{n_points / dense:>12.0f}{dense / best:>9.1f}{dp:>10.1e}{dv:>11.1e}", flush=True)


if __name__ == "__main__":
    main()
