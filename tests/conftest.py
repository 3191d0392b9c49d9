"""Test order for the two pytest-xdist workers: the longest files first.

``make test`` hands whole files to the workers (``--dist loadfile``) in collection order
(``--no-loadscope-reorder``; xdist would otherwise order them by their number of tests, which sends
files of a few long tests, such as the CLI's or the ROS node's, last). Starting with the longest
files and filling in with the short ones leaves the two workers finishing close together.
"""

from __future__ import annotations

from pathlib import Path

import pytest

#: Files taking more than about 10 s, longest first (measured with --durations on 2 cores). A file
#: not listed runs after these, in its usual order.
LONGEST_FIRST = [
    "test_cli.py",
    "test_mapping.py",
    "test_distributed.py",
    "test_convert.py",
    "test_tiles.py",
    "test_ros_node.py",
    "test_streaming.py",
    "test_outputs_atomic.py",
    "test_stream_cli.py",
    "test_ros_messages.py",
    "test_benchmark.py",
    "test_protocol.py",
    "test_fusion.py",
    "test_extrapolation.py",
    "test_ogm.py",
]
_RANK = {name: i for i, name in enumerate(LONGEST_FIRST)}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    # A stable sort: tests keep their order within a file, and the other files theirs.
    items.sort(key=lambda item: _RANK.get(Path(str(item.path)).name, len(LONGEST_FIRST)))
