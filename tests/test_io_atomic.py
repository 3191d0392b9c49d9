import os

import pytest

from gpomap.io import atomic
from gpomap.io.atomic import atomic_write, atomic_write_group


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_writes_new_file_binary_and_text(tmp_path):
    with atomic_write(tmp_path / "a.bin") as f:
        f.write(b"\x00\x01\x02")
    with atomic_write(tmp_path / "b.txt", "w") as f:
        f.write("héllo\n")
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01\x02"
    assert (tmp_path / "b.txt").read_text(encoding="utf-8") == "héllo\n"
    assert _leftovers(tmp_path) == []


def test_replaces_existing_file(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with atomic_write(target) as f:
        f.write(b"new content")
    assert target.read_bytes() == b"new content"
    assert _leftovers(tmp_path) == []


def test_exception_leaves_old_file_and_no_temp(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"previous good file")
    with pytest.raises(RuntimeError, match="boom"), atomic_write(target) as f:
        f.write(b"half of the new")
        raise RuntimeError("boom")
    assert target.read_bytes() == b"previous good file"
    assert _leftovers(tmp_path) == []


def test_exception_when_target_absent_creates_nothing(tmp_path):
    with pytest.raises(KeyError), atomic_write(tmp_path / "never.bin") as f:
        f.write(b"x")
        raise KeyError("x")
    assert list(tmp_path.iterdir()) == []


def test_failing_fsync_keeps_old_file(tmp_path, monkeypatch):
    # The failure happens after the content was written, during the commit step.
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"), atomic_write(target) as f:
        f.write(b"new")
    assert target.read_bytes() == b"old"
    assert _leftovers(tmp_path) == []


def test_group_failure_in_second_file_leaves_all_old(tmp_path):
    a, b = tmp_path / "map.pgm", tmp_path / "map.yaml"
    a.write_bytes(b"old image")
    b.write_text("old yaml")
    with pytest.raises(ValueError, match="midway"), atomic_write_group([a, b], mode=["wb", "w"]) as (fa, fb):
        fa.write(b"new image, complete")
        fb.write("new yaml, half")
        raise ValueError("midway")
    assert a.read_bytes() == b"old image"
    assert b.read_text() == "old yaml"
    assert _leftovers(tmp_path) == []


def test_group_success_replaces_all(tmp_path):
    a, b = tmp_path / "one", tmp_path / "two"
    a.write_bytes(b"1")
    with atomic_write_group([a, b]) as (fa, fb):
        fa.write(b"new 1")
        fb.write(b"new 2")
    assert (a.read_bytes(), b.read_bytes()) == (b"new 1", b"new 2")
    assert _leftovers(tmp_path) == []


def test_group_rename_failure_cleans_temps(tmp_path, monkeypatch):
    a, b = tmp_path / "one", tmp_path / "two"
    real_replace = os.replace
    calls = []

    def replace_once(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError("rename failed")
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", replace_once)
    with pytest.raises(OSError, match="rename failed"), atomic_write_group([a, b]) as (fa, fb):
        fa.write(b"1")
        fb.write(b"2")
    assert _leftovers(tmp_path) == []


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="modes"), atomic_write(tmp_path / "x", mode="ab"):
        pass
    with pytest.raises(ValueError, match="same file twice"), atomic_write_group([tmp_path / "x", tmp_path / "x"]):
        pass
    with pytest.raises(IsADirectoryError), atomic_write(tmp_path):
        pass
    assert _leftovers(tmp_path) == []


def test_new_file_gets_default_permissions(tmp_path):
    # Not the 0o600 of mkstemp: what a plain open() would give under the current umask.
    umask = os.umask(0)
    os.umask(umask)
    with atomic_write(tmp_path / "p") as f:
        f.write(b"x")
    if os.name == "posix":
        assert (tmp_path / "p").stat().st_mode & 0o777 == 0o666 & ~umask
