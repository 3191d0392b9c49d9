"""numba's compile cache across processes: a second run loads what the first compiled, and a machine
where nothing can be cached still runs (compiling each time) instead of failing at import."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from gpomap import compiled

pytestmark = pytest.mark.skipif(not compiled.NUMBA_AVAILABLE, reason="numba is not installed")

# One scan of two beams on a row of four 1 m cells: beam 0 from x = 0.5 crosses cell 0, then cell 1
# (its centre 1 m from the end, within the near distance of 1.5 m), and returns in cell 2; beam 1
# returned nothing and runs from x = 1.5 through cells 1, 2 and 3. By hand, the scan's one update
# per cell shared among its beams there: cell 2 half a hit (beam 0) and half a miss (beam 1); cells
# 0, 1 and 3 a whole miss, half of cell 1's near (beam 0's, not beam 1's); cell 3 silent, the only
# one beam 1 had to itself.
CHILD = textwrap.dedent(
    """
    import json
    import numpy as np
    from gpomap import _compiled_counts
    from gpomap.lattice import make_grid

    grid = make_grid((0.0, 0.0), 1.0, (4, 1))
    counts = tuple(np.zeros(4) for _ in range(4))
    _compiled_counts.count_beams(
        grid, np.array([[0.5, 0.5], [1.5, 0.5]]), np.array([[2.5, 0.5], [3.5, 0.5]]), np.array([True, False]),
        np.array([0, 0]), np.array([2, -1]), 1.5, 3, counts, np.full(4, -1, dtype=np.int32),
    )
    stats = _compiled_counts._count_beams.stats
    print(json.dumps({
        "hits": sum(stats.cache_hits.values()),
        "misses": sum(stats.cache_misses.values()),
        "cache_path": stats.cache_path,
        "counts": [c.tolist() for c in counts],
    }))
    """
)
EXPECTED = [[0, 0, 0.5, 0], [1, 1, 0.5, 1], [0, 0.5, 0, 0], [0, 0, 0, 1]]


def _run(env: dict[str, str]) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _env(**changes: str | None) -> dict[str, str]:
    env = {
        k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "NUMBA_CACHE_LOCATOR_CLASSES", "NUMBA_DISABLE_JIT")
    }
    env.update({k: v for k, v in changes.items() if v is not None})
    return env


def test_second_process_loads_from_the_cache(tmp_path):
    cache = tmp_path / "numba-cache"
    first = _run(_env(NUMBA_CACHE_DIR=str(cache)))
    second = _run(_env(NUMBA_CACHE_DIR=str(cache)))
    assert (first["misses"], first["hits"]) == (1, 0)  # compiled, and written
    assert (second["misses"], second["hits"]) == (0, 1)  # loaded, nothing compiled
    assert first["cache_path"].startswith(str(cache)) and list(cache.rglob("*.nbi"))
    assert first["counts"] == second["counts"] == EXPECTED


def test_nowhere_to_cache_compiles_each_time():
    """numba finds no cache location (as for a read-only install run without a writable home)."""
    result = _run(_env(NUMBA_CACHE_LOCATOR_CLASSES="numba.core.caching.IPythonCacheLocator"))
    assert result["cache_path"] is None and result["misses"] == 1
    assert result["counts"] == EXPECTED
