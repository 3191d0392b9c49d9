"""The memory a run reports using (``gpomap.resources.rss_mb``, ``peak_rss_mb``) and hands back
(``release_freed_memory``)."""

from __future__ import annotations

import builtins
import math
import sys
import types

import numpy as np
import pytest

from gpomap import resources


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/statm is Linux's")
def test_peak_counts_an_array_just_touched() -> None:
    # Two independent records of the same memory: /proc's resident pages now, getrusage's peak.
    # A unit slip (KiB read as bytes, or as MiB) would miss by a factor of 1024.
    before = resources.rss_mb()
    assert before is not None
    block = np.ones(64 * 2**20 // 8)  # 64 MiB, every page written
    now = resources.rss_mb()
    assert now is not None and now >= before + 60
    peak = resources.peak_rss_mb()
    assert now - 1 <= peak["self"] < 100 * now
    assert block.sum() == block.size


@pytest.mark.skipif(resources._malloc_trim() is None, reason="glibc's malloc_trim is not there")
def test_freed_heap_blocks_are_handed_back() -> None:
    # 384 MiB in 64 KiB arrays (above TRIM_FREE_BYTES): below glibc's mmap threshold, so they come
    # from the heap; one array allocated after them keeps the heap's top in use, so freeing them
    # returns nothing.
    blocks = [np.ones(8192) for _ in range(6144)]
    top = np.ones(8192)
    del blocks
    before = resources.rss_mb()
    assert before is not None
    assert resources.release_freed_memory()
    after = resources.rss_mb()
    assert after is not None and after < before - 256
    assert top.sum() == top.size


@pytest.mark.skipif(resources._mallinfo2() is None, reason="glibc's mallinfo2 is not there")
def test_heap_free_bytes_counts_arrays_just_freed() -> None:
    # 64 MiB in 64 KiB arrays from the heap, kept in use by one allocated after them: freed, the
    # allocator's free chunks grow by their size (each array's 64 KiB and its chunk header).
    blocks = [np.ones(8192) for _ in range(1024)]
    top = np.ones(8192)
    before = resources._heap_free_bytes()
    del blocks
    after = resources._heap_free_bytes()
    assert before is not None and after is not None
    assert 64 * 2**20 <= after - before < 66 * 2**20
    assert top.sum() == top.size


class _Trim:
    """A stand-in for ``malloc_trim`` that records its calls."""

    def __init__(self) -> None:
        self.calls: list[int] = []

    def __call__(self, pad: int) -> int:
        self.calls.append(pad)
        return 1


@pytest.mark.parametrize(
    ("free", "asked"), [(resources.TRIM_FREE_BYTES - 1, False), (resources.TRIM_FREE_BYTES, True), (None, True)]
)
def test_system_asked_only_when_enough_is_free(monkeypatch: pytest.MonkeyPatch, free: int | None, asked: bool) -> None:
    # Below the threshold the pages would be faulted in again by the next stage; where the C
    # library cannot say how much is free (None), it is asked as before.
    trim = _Trim()
    monkeypatch.setattr(resources, "_malloc_trim", lambda: trim)
    monkeypatch.setattr(resources, "_heap_free_bytes", lambda: free)
    assert resources.release_freed_memory() is asked
    assert trim.calls == ([0] if asked else [])


def test_release_is_a_no_op_without_malloc_trim(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(resources, "_malloc_trim", lambda: None)
    assert resources.release_freed_memory() is False


def _fake_resource(maxrss: int) -> types.SimpleNamespace:
    usage = types.SimpleNamespace(ru_maxrss=maxrss)
    return types.SimpleNamespace(RUSAGE_SELF=0, RUSAGE_CHILDREN=-1, getrusage=lambda who: usage)


@pytest.mark.parametrize(("platform", "maxrss"), [("linux", 2**20), ("darwin", 2**30)])
def test_peak_units_per_platform(monkeypatch: pytest.MonkeyPatch, platform: str, maxrss: int) -> None:
    # 1 GiB either way: Linux reports KiB, macOS bytes.
    monkeypatch.setitem(sys.modules, "resource", _fake_resource(maxrss))
    monkeypatch.setattr(resources.sys, "platform", platform)
    assert resources.peak_rss_mb() == {"self": 1024.0, "children": 1024.0}


def test_peak_unknown_without_resource_module(monkeypatch: pytest.MonkeyPatch) -> None:
    # Windows has no `resource` module: the peak is unknown (NaN), not an ImportError at import time.
    real_import = builtins.__import__

    def no_resource(name: str, *args: object, **kwargs: object) -> object:
        if name == "resource":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.delitem(sys.modules, "resource", raising=False)
    monkeypatch.setattr(builtins, "__import__", no_resource)
    peak = resources.peak_rss_mb()
    assert set(peak) == {"self", "children"} and all(math.isnan(v) for v in peak.values())


def test_cli_line_says_unknown_rather_than_nan() -> None:
    from gpomap.cli.common import peak_memory as _peak_memory

    assert _peak_memory({"self": 663.4, "children": 0.0}) == "self 663 MB, children 0 MB"
    assert _peak_memory({"self": math.nan, "children": math.nan}) == "unknown on this system"
