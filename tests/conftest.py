"""Test order for the two pytest-xdist workers: numba's compilation once, then the longest files first.

``make test`` hands whole files to the workers (``--dist loadfile``) in collection order
(``--no-loadscope-reorder``; xdist would otherwise order them by their number of tests, which sends
files of a few long tests, such as the CLI's or the ROS node's, last). The first file goes to one
worker and the next ones to the other as it asks for more. On a fresh checkout the first map fitted
in a process compiles most of gpomap's numba code (about 30 s of one core), and numba caches it on
disk for every later process: so test_cli (its demo compiles it) comes first, and the other worker
meanwhile runs files that call no compiled code, instead of compiling the same functions at the same
time. Then the longest files, and the short ones fill in, which leaves the two workers finishing
close together.

Each xdist worker gets its share of the cores for BLAS (the cores divided by the workers, as
TiledGPOM shares them among its tile workers): with one worker per core, two BLAS threads in each
of two workers on two cores only wait for each other (measured under -n 2 on
test_streaming::test_stream_then_finish_equals_the_batch_map: 15.1 CPU seconds with numpy's and
scipy's OpenBLAS at their default two threads, 3.0 with one; 23.5 s wall against 4.9).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

#: The file whose first map compiles most of numba's code (test_cli's demo).
COMPILES_FIRST = ["test_cli.py"]

#: Files that call no numba-compiled code (none compiled in a run of them alone with an empty
#: NUMBA_CACHE_DIR; test_compiled_cache compiles in child processes of its own cache), longest
#: first: the other worker's start while the first compiles. A file here that comes to call compiled
#: code only compiles it once more, as both workers did before.
WITHOUT_COMPILING = [
    "test_plot.py",
    "test_io_carmen.py",
    "test_compiled_cache.py",
    "test_fuzz_readers.py",
    "test_io_rosbag.py",
    "test_io_octomap.py",
    "test_source_prose.py",
    "test_public.py",
    "test_line_kernel.py",
    "test_layers.py",
    "test_noreturn.py",
    "test_one_home.py",
    "test_cli_options.py",
    "test_members.py",
    "test_io_pointcloud2.py",
    "test_memory_use.py",
    "test_io_depth_ply.py",
    "test_io_rosmap.py",
    "test_io_pcd.py",
    "test_io_arrays.py",
    "test_io_npz.py",
    "test_io_atomic.py",
    "test_io_scangraph.py",
    "test_extras.py",
    "test_lapack.py",
    "test_metrics.py",
    "test_simulate.py",
    "test_replay.py",
    "test_baselines_octomap.py",
    "test_progress.py",
]

#: Files taking more than about 2.5 s, longest first (measured per file, in the whole suite under
#: -n 2 and alone), after those above: the two files that run ROS processes first (the ROS 1 node's
#: starts by installing gpomap in a venv of its own on a fresh checkout, and their nodes load
#: numba's code from the cache by the time they map); then by seconds. A file not listed runs after
#: these, in its usual order.
LONGEST_FIRST = [
    "test_ros_node.py",
    "test_ros2_node.py",
    "test_tiles.py",
    "test_comparison.py",
    "test_cli_writing.py",
    "test_mapfile.py",
    "test_distributed.py",
    "test_mapfile_cli.py",
    "test_fusion.py",
    "test_stream_cli.py",
    "test_outputs_atomic.py",
    "test_mapping.py",
    "test_convert.py",
    "test_revisit.py",
    "test_streaming.py",
    "test_stages.py",
    "test_cli_convert.py",
    "test_map3d_cli.py",
    "test_cli_checks.py",
    "test_local_prediction.py",
    "test_truth_map.py",
    "test_ros_messages.py",
    "test_estimator_params.py",
    "test_tensor_kernel.py",
    "test_voxels_map3d.py",
    "test_benchmark.py",
    "test_extrapolation.py",
    "test_clearance.py",
    "test_fitted.py",
    "test_convert3d.py",
    "test_protocol.py",
    "test_compiled_raycast.py",
    "test_kernels.py",
    "test_tensor_compiled.py",
]
_ORDER = [*COMPILES_FIRST, *WITHOUT_COMPILING, *LONGEST_FIRST]
_RANK = {name: i for i, name in enumerate(_ORDER)}
_BLAS_LIMIT = []


def pytest_configure(config: pytest.Config) -> None:
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if os.environ.get("PYTEST_XDIST_WORKER") and workers:
        # numpy and scipy each bring their own OpenBLAS: both loaded, so that the limit applies to both.
        import numpy  # noqa: F401
        import scipy.linalg  # noqa: F401
        from threadpoolctl import threadpool_limits

        # Kept for the whole session (not a context); tests that set their own limits restore this one.
        _BLAS_LIMIT.append(threadpool_limits(limits=max(1, (os.cpu_count() or 1) // int(workers))))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    # A stable sort: tests keep their order within a file, and the other files theirs.
    items.sort(key=lambda item: _RANK.get(Path(str(item.path)).name, len(_ORDER)))
