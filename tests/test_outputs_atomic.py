"""A run's outputs are one set: replaced together, or left as they were (errors, SIGINT, SIGTERM, SIGKILL)."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gpomap.io import atomic
from gpomap.io.atomic import JOURNAL, MANIFEST, output_set, recover_output_dir
from tests.processes import as_from_a_terminal

SET = ["map.npz", "map.pgm", "map.png", "map.yaml"]


def snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


def staging_dirs(out: Path) -> list[str]:
    """Staging directories of `out`: beside it, or inside it."""
    beside = [p.name for p in out.parent.glob(f".{out.name}.gpomap-staging-*")]
    inside = [p.name for p in out.glob(".gpomap-staging-*")] if out.is_dir() else []
    return sorted(beside + inside)


def write(o, **files):
    for name, text in files.items():
        (o.path / name).write_text(text)


def test_set_replaces_gpomap_files_and_keeps_the_users(tmp_path):
    out = tmp_path / "out"
    with output_set(out) as o:
        write(o, **{"map.yaml": "1", "map.png": "1", "cells.png": "1"})
    (out / "notes.txt").write_text("mine")
    with output_set(out) as o:
        write(o, **{"map.yaml": "2", "map.png": "2"})
    # cells.png belonged to the previous set: removed; the user's notes stay.
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "map.png", "map.yaml", "notes.txt"]
    assert (out / "map.yaml").read_text() == "2" and (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / MANIFEST).read_text())["files"] == ["map.png", "map.yaml"]
    assert o.files == [out / "map.png", out / "map.yaml"]
    assert staging_dirs(out) == []


def test_an_error_leaves_the_previous_set_and_no_staging(tmp_path):
    out = tmp_path / "out"
    with output_set(out) as o:
        write(o, **{"map.yaml": "old", "map.pgm": "old"})
    before = snapshot(out)
    with pytest.raises(KeyboardInterrupt), output_set(out) as o:
        write(o, **{"map.yaml": "new"})
        raise KeyboardInterrupt
    assert snapshot(out) == before
    assert staging_dirs(out) == []


def test_a_failed_first_run_creates_no_directory(tmp_path):
    with pytest.raises(ValueError), output_set(tmp_path / "never"):
        raise ValueError("bad input")
    assert list(tmp_path.iterdir()) == []


def test_recovery_finishes_a_commit_that_was_cut_short(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with output_set(out) as o:
        write(o, **{"a.txt": "old", "b.yaml": "old", "stale.txt": "old"})
    # A commit that dies after its first rename (as SIGKILL would) leaves a journal behind.
    real = atomic._roll_forward
    calls = []

    def first_rename_only(staging, target):
        journal = json.loads((staging / JOURNAL).read_text())
        name = journal["files"][0]
        os.replace(staging / name, target / name)
        calls.append(name)
        raise OSError("killed")

    monkeypatch.setattr(atomic, "_roll_forward", first_rename_only)
    monkeypatch.setattr(atomic, "_pid_alive", lambda pid: False)
    with pytest.raises(OSError, match="killed"), output_set(out) as o:
        write(o, **{"a.txt": "new", "b.yaml": "new"})
    assert calls == ["a.txt"] and (out / "b.yaml").read_text() == "old"  # a mix, for now
    monkeypatch.setattr(atomic, "_roll_forward", real)
    notes = recover_output_dir(out)
    assert len(notes) == 1 and "completed" in notes[0]
    assert snapshot(out) == {MANIFEST: (out / MANIFEST).read_bytes(), "a.txt": b"new", "b.yaml": b"new"}
    assert staging_dirs(out) == []


def test_recovery_removes_a_dead_runs_staging_and_keeps_a_live_ones(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    host = atomic._host()
    dead = tmp_path / f".out.gpomap-staging-{host}-999999999-abcd"
    live = tmp_path / f".out.gpomap-staging-{host}-{os.getppid()}-abcd"
    for d in (dead, live):
        d.mkdir()
        (d / "map.yaml").write_text("half")
    recover_output_dir(out)
    assert not dead.exists() and live.exists()
    assert list(out.iterdir()) == []


# --------------------------------------------------------------------------- real signals
HELPER = """
import sys
import numpy as np
from gpomap.grid import GridSpec, OccupancyMap
from gpomap.io.export import write_map_outputs

res = float(sys.argv[2])
spec = GridSpec((0.0, 0.0), res, (int(8 / res), int(10 / res)))
p = np.linspace(0, 1, spec.shape[0] * spec.shape[1]).reshape(spec.shape)
write_map_outputs(OccupancyMap(spec, p, variance=np.ones(spec.shape)), sys.argv[1], title="r" + sys.argv[2])
print("done", flush=True)
"""


def previous_set(out: Path) -> dict[str, bytes]:
    from gpomap.grid import GridSpec, OccupancyMap
    from gpomap.io.export import write_map_outputs

    spec = GridSpec((0.0, 0.0), 1.0, (8, 10))
    write_map_outputs(OccupancyMap(spec, np.full(spec.shape, 0.2), variance=np.ones(spec.shape)), out, title="previous")
    (out / "notes.txt").write_text("the user's")
    return snapshot(out)


def start(args, env_extra):
    env = {**os.environ, **env_extra}
    return subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=as_from_a_terminal
    )


def wait_for_each(moments, procs, sig, timeout=60.0):
    """Send ``sig[name]`` to ``procs[name]`` once ``moments[name]()`` is true, polling all the runs at once."""
    t0 = time.monotonic()
    waiting = dict(procs)
    while waiting:
        for name, proc in list(waiting.items()):
            if moments[name]():
                proc.send_signal(sig[name])
                del waiting[name]
            elif proc.poll() is not None:
                raise AssertionError(f"the {name} run ended before the moment to signal it: {proc.communicate()}")
        if waiting and time.monotonic() - t0 > timeout:
            for proc in waiting.values():
                proc.kill()
            raise AssertionError(f"timed out waiting for the {', '.join(waiting)} runs to reach the moment to signal them")
        time.sleep(0.02)


def staged_file(out: Path, name: str):
    return lambda: any((d / name).exists() for d in out.parent.glob(f".{out.name}.gpomap-staging-*"))


def test_signals_mid_write_leave_the_previous_set_byte_for_byte(tmp_path):
    """SIGINT and SIGTERM to ``gpomap map`` while it writes; SIGKILL to a writer, mid-write and mid-commit."""
    points = tmp_path / "pts.csv"
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 6, size=(300, 2))
    occ = (xy[:, 0] > 4.5).astype(int)
    points.write_text("x,y,occupied\n" + "".join(f"{x:.3f},{y:.3f},{o}\n" for (x, y), o in zip(xy, occ)))
    # One previous set, written by gpomap, copied byte for byte to each run's directory.
    first = tmp_path / "previous"
    previous_set(first)
    runs = {}
    for name in ["sigint", "sigterm", "sigkill", "commit"]:
        out = tmp_path / name
        shutil.copytree(first, out)
        runs[name] = [out, snapshot(out)]
    # Half a second after each file (and between the commit's renames): each run is signalled within
    # the test's 20 ms poll of reaching its moment, and its next step is at least that far away.
    slow = {atomic.WRITE_DELAY_ENV: "0.5"}
    cli = [
        "-m",
        "gpomap.cli",
        "map",
        str(points),
        "--length-scale",
        "1",
        "--resolution",
        "0.5",
        "--min-cell",
        "1",
        "--max-cell",
        "2",
        # The tiles in the run's own process: no pool to start before the moment to signal it.
        "--workers",
        "1",
        "-o",
    ]
    procs = {
        "sigint": start([*cli, str(runs["sigint"][0])], slow),
        "sigterm": start([*cli, str(runs["sigterm"][0])], slow),
        "sigkill": start(["-c", HELPER, str(runs["sigkill"][0]), "0.5"], slow),
        "commit": start(["-c", HELPER, str(runs["commit"][0]), "0.5"], {atomic.COMMIT_DELAY_ENV: "0.5"}),
    }
    sig = {"sigint": signal.SIGINT, "sigterm": signal.SIGTERM, "sigkill": signal.SIGKILL, "commit": signal.SIGKILL}
    # map.yaml and map.pgm written, the rest not.
    moments = {name: staged_file(runs[name][0], "map.npz") for name in ["sigint", "sigterm", "sigkill"]}
    # Killed between the renames of the commit: map.npz (first in order) is already new.
    out, old_npz = runs["commit"][0], runs["commit"][1]["map.npz"]
    moments["commit"] = lambda: (out / "map.npz").read_bytes() != old_npz
    # Each run is signalled as soon as it reaches its moment, whichever comes first.
    wait_for_each(moments, procs, sig)
    results = {name: (proc.wait(timeout=60), *proc.communicate()) for name, proc in procs.items()}

    for name in ["sigint", "sigterm"]:
        code, _stdout, stderr = results[name]
        out, before = runs[name]
        assert code == 128 + sig[name], (name, stderr)
        assert f"interrupted{' (SIGTERM)' if name == 'sigterm' else ''}; the previous outputs in {out} are unchanged" in stderr
        assert "Traceback" not in stderr
        assert snapshot(out) == before, name
        assert staging_dirs(out) == [], name

    # SIGKILL mid-write: the directory itself was never touched; the next run clears the leftover.
    out, before = runs["sigkill"]
    assert results["sigkill"][0] == -signal.SIGKILL
    assert snapshot(out) == before
    assert len(staging_dirs(out)) == 1
    recover_output_dir(out)
    assert snapshot(out) == before and staging_dirs(out) == []

    # SIGKILL mid-commit: a mix for now, completed by the next run into the new set, whole.
    out, before = runs["commit"]
    assert results["commit"][0] == -signal.SIGKILL
    recover_output_dir(out)
    after = snapshot(out)
    assert sorted(after) == sorted([MANIFEST, "notes.txt", *SET])
    assert after["notes.txt"] == before["notes.txt"]
    assert all(after[n] != before[n] for n in SET)
    from gpomap.io.npz import load_map
    from gpomap.io.rosmap import read_rosmap

    assert load_map(out / "map.npz").grid.resolution == 0.5 and read_rosmap(out / "map.yaml").grid.resolution == 0.5
    assert staging_dirs(out) == []


# A run that has finished and said so, then a Ctrl-C while the interpreter waits for a thread at exit.
_CTRL_C_AT_EXIT = """
import os, signal, threading, time
import gpomap.cli as cli

def finished(argv=None):
    threading.Thread(target=time.sleep, args=(1.5,)).start()
    threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
    print("wrote outputs")
    return 0

cli.main = finished
cli.console()
"""


def test_ctrl_c_after_a_finished_run_keeps_its_exit_code() -> None:
    r = subprocess.run([sys.executable, "-c", _CTRL_C_AT_EXIT], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, (r.returncode, r.stderr)
    assert r.stdout == "wrote outputs\n" and "Traceback" not in r.stderr
