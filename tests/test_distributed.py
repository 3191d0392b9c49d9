"""Tiles on a real Dask cluster: a scheduler and workers started as separate processes.

Nothing here makes a default ``distributed.Client`` in the test process: gpomap must pass its own
client everywhere (the bug this file guards against failed with "No clients found" exactly
then). The tests start ``dask scheduler`` and ``--no-nanny`` workers from this venv (no nanny, so
killing the process we started really kills the worker and nothing restarts it), and the fixture
kills every process it started, whatever happens. Starting a process costs seconds of imports
on a busy machine, so one scheduler serves every test; each test first starts the workers it
needs (none when the tests run in file order: the previous test left them).
"""

from __future__ import annotations

import inspect
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

pytest.importorskip("distributed", reason="dask[distributed] is not installed: pip install 'gpomap[distributed]'")

import gpomap.tiles as tiles
import gpomap.tiles.executors as tile_executors
from gpomap.cli import EXIT_ERROR, EXIT_OK, main

LOG = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "intel" / "intel-corrected.log.gz"
# 20 Intel scans in 4 m tiles: 25 tiles of 29-339 cells, half a second of tile fits; the
# hyperparameters are fixed (--length-scale) so the runs stay short and exactly comparable.
MAP_ARGS = [
    "--range",
    "0:20",
    "--beams",
    "90",
    "--kernel",
    "se",
    "--length-scale",
    "1.0",
    "--free-step",
    "0.5",
    "--tile-size",
    "4",
    "--resolution",
    "0.5",
]
STARTUP_SECONDS = 60.0  # most a process may take to come up on a busy 2-core machine


class Cluster:
    """A ``dask scheduler`` and ``dask worker`` processes on localhost, started from this venv."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.procs: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.address = ""
        # One BLAS thread per process: the machine's two cores are shared.
        self.env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

    def start_scheduler(self) -> None:
        """Start the scheduler on a free port and wait for its address."""
        file = self.folder / "scheduler.json"
        self._start(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--dashboard-address",
                "127.0.0.1:0",
                "--scheduler-file",
                str(file),
                # Safety net should the test process itself be killed before its clean-up.
                "--idle-timeout",
                "300",
            ],
            "scheduler",
        )
        self.address = self._wait(lambda: file.exists() and json.loads(file.read_text() or "{}").get("address"), "scheduler")

    def _start(self, cmd: list[str], name: str) -> subprocess.Popen:
        with open(self.folder / f"{name}.log", "w") as log:  # the child keeps its own copy
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=self.folder, env=self.env)
        proc.log = self.folder / f"{name}.log"  # type: ignore[attr-defined]
        self.procs.append(proc)
        return proc

    def _wait(self, ready, what: str, proc: subprocess.Popen | None = None):
        deadline = time.monotonic() + STARTUP_SECONDS
        while time.monotonic() < deadline:
            try:
                value = ready()
            except (OSError, ValueError):  # the file is being written
                value = None
            if value:
                return value
            p = proc or self.procs[0]
            if p.poll() is not None:
                pytest.fail(f"{what} exited with {p.returncode}:\n{p.log.read_text()}")
            time.sleep(0.1)
        pytest.fail(f"{what} did not start within {STARTUP_SECONDS:g} s")

    def add_workers(self, n: int) -> None:
        """Start `n` single-threaded workers together and wait until each has registered."""
        started = []
        for _ in range(n):
            name = f"worker{len(self.workers)}"
            proc = self._start(
                [
                    sys.executable,
                    "-m",
                    "distributed.cli.dask_worker",
                    self.address,
                    "--nthreads",
                    "1",
                    "--nworkers",
                    "1",
                    "--no-nanny",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                    "--name",
                    name,
                    "--death-timeout",
                    "60",
                ],
                name,
            )
            self.workers.append(proc)
            started.append((name, proc))
        for name, proc in started:
            self._wait(lambda proc=proc: "Registered to" in proc.log.read_text(), name, proc)

    def alive(self) -> list[subprocess.Popen]:
        """The workers still running."""
        return [w for w in self.workers if w.poll() is None]

    def ensure_workers(self, n: int) -> list[subprocess.Popen]:
        """At least `n` workers running (starting the missing ones); returns the running ones."""
        self.add_workers(max(0, n - len(self.alive())))
        return self.alive()

    @staticmethod
    def kill(worker: subprocess.Popen) -> None:
        """SIGKILL a worker (no goodbye to the scheduler, as when a machine dies)."""
        worker.send_signal(signal.SIGKILL)
        worker.wait(10)

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.kill()
        for p in self.procs:
            with suppress(subprocess.TimeoutExpired):  # kill -9 does not fail; never hang here
                p.wait(10)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[Cluster]:
    """A scheduler (workers are started by the tests); every process is killed at the end."""
    c = Cluster(tmp_path_factory.mktemp("cluster"))
    try:
        c.start_scheduler()
        yield c
    finally:
        c.close()  # also when starting failed half-way


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict[str, np.ndarray]:
    """The same map built in this process (no pool, no cluster)."""
    out = tmp_path_factory.mktemp("reference")
    # One BLAS thread as in the workers: the same arithmetic, so the same map to the last bit
    # (other thread counts move the ray-evidence calibration on top of the GP by ~1e-7).
    with threadpool_limits(1):
        assert main(["map", str(LOG), "-o", str(out), "--workers", "1", "-q", *MAP_ARGS]) == EXIT_OK
    return dict(np.load(out / "map.npz"))


# The library on the built-in simulator: 35 tiles of 4 m (8-107 cells), fixed hyperparameters.
ROOM_OPTS = dict(
    tile_size=4.0,
    overlap=2.0,
    kernel="se",
    free_step=0.5,
    min_cell=0.5,
    max_cell=3.0,
    optimise=False,
    length_scale=1.0,
    noise=0.1,
)


@pytest.fixture(scope="module")
def room() -> list:
    from gpomap.simulate import paper_room_scans

    return paper_room_scans()


@pytest.fixture(scope="module")
def room_reference(room):
    """Hyperparameters and map of the room, tiles fitted in this process."""
    with threadpool_limits(1):  # as in the workers (see `reference`)
        model = tiles.TiledGPOM(n_workers=1, **ROOM_OPTS).fit(room)
        return model.hyperparameters_, model.grid(0.25), len(model.tiles_)


def _assert_same_map(out: Path, reference: dict[str, np.ndarray]) -> None:
    got = np.load(out / "map.npz")
    assert got["probability"].shape == reference["probability"].shape
    np.testing.assert_allclose(got["probability"], reference["probability"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(got["variance"], reference["variance"], rtol=0, atol=1e-9)
    assert not np.isnan(got["probability"]).any()  # no tile missing


@contextmanager
def _on_first_tile_done(monkeypatch, action) -> Iterator[list[str]]:
    """Call `action()` once, when the first tile fit of the map itself has come back (through the
    progress hook); the variance scale's held-in maps, fitted before it, fit tiles too."""
    real = tile_executors.progress
    fired: list[str] = []

    @contextmanager
    def hooked(total, desc, unit="item"):
        with real(total, desc, unit) as bar:
            update = bar.update

            def update_then_act(n: int = 1) -> None:
                update(n)
                held_in = any(f.function == "_fit_variance_scale" for f in inspect.stack(0))
                if desc == "fitting tiles" and not fired and not held_in:
                    fired.append(f"{bar.n}/{total}")
                    action()

            bar.update = update_then_act
            yield bar

    monkeypatch.setattr(tile_executors, "progress", hooked)
    yield fired


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def progress_lines(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Progress as plain lines for one test (the mode is global to the process), from the first step."""
    from gpomap import progress
    from gpomap.progress import get_progress_mode, set_progress_mode

    monkeypatch.setattr(progress, "LINES_AFTER_SECONDS", 0.0)
    before = get_progress_mode()
    set_progress_mode("lines")
    try:
        yield
    finally:
        set_progress_mode(before)


def test_cli_map_on_scheduler_matches_in_process(cluster, reference, tmp_path, capsys, progress_lines):
    cluster.ensure_workers(2)
    out = tmp_path / "dask"
    with threadpool_limits(1):  # this process fits alpha and beta and the evidence: as for `reference`
        code = main(["map", str(LOG), "-o", str(out), "--scheduler", cluster.address, *MAP_ARGS])
    printed = capsys.readouterr()
    assert code == EXIT_OK, printed.err
    assert "dask" in printed.out  # the summary names the executor
    assert re.search(r"fitting tiles: \d+/\d+ tiles", printed.err)  # progress reported
    _assert_same_map(out, reference)


def test_dead_worker_tiles_are_recomputed(cluster, room, room_reference, monkeypatch):
    hyp, ref, n_tiles = room_reference
    victim, survivor, *_ = cluster.ensure_workers(2)
    model = tiles.TiledGPOM(scheduler=cluster.address, scheduler_timeout=30.0, **ROOM_OPTS)
    with _on_first_tile_done(monkeypatch, lambda: cluster.kill(victim)) as fired:
        model.fit(room, hyperparameters=hyp)
    assert fired and fired[0] != f"{n_tiles}/{n_tiles}"  # killed while tiles were left
    assert victim.poll() is not None and survivor.poll() is None
    assert sorted(model.tiles_) == sorted(model.last_refit_) and len(model.tiles_) == n_tiles
    got = model.grid(0.25)  # on the one worker left
    np.testing.assert_allclose(got.probability, ref.probability, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.variance, ref.variance, rtol=0, atol=1e-9)


def test_no_workers_left_is_a_clear_error(cluster, room, tmp_path, monkeypatch, capsys):
    from gpomap.errors import DistributedError

    workers = cluster.ensure_workers(1)
    out = tmp_path / "dask"
    with _on_first_tile_done(monkeypatch, lambda: [cluster.kill(w) for w in workers]) as fired:
        code = main(
            ["map", str(LOG), "-o", str(out), "--scheduler", cluster.address, "--scheduler-timeout", "2", "-q", *MAP_ARGS]
        )
    err = capsys.readouterr().err
    assert fired
    assert code == EXIT_ERROR
    m = re.search(r"no Dask worker .* for 2 s, with (\d+) of (\d+) tile\(s\) left", err)
    assert m, err
    assert 0 < int(m.group(1)) < int(m.group(2))
    assert cluster.address in err and "--scheduler-timeout" in err
    assert not (out / "map.npz").exists()  # no map with tiles missing
    # The same scheduler, now without any worker from the start: the library raises the same.
    model = tiles.TiledGPOM(scheduler=cluster.address, scheduler_timeout=1.0, **ROOM_OPTS)
    with pytest.raises(DistributedError, match=r"no Dask worker .* with (\d+) of \1 tile\(s\) left"):
        model.fit(room[:8])


def test_unreachable_scheduler_fails_before_local_work(tmp_path, monkeypatch, capsys):
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    built: list[bool] = []
    real_build = tiles.TiledGPOM._build_blocks
    monkeypatch.setattr(tiles.TiledGPOM, "_build_blocks", lambda self, *a: built.append(True) or real_build(self, *a))
    out = tmp_path / "never"
    code = main(["map", str(LOG), "-o", str(out), "--scheduler", address, "--scheduler-timeout", "1", "-q", *MAP_ARGS])
    err = capsys.readouterr().err
    assert code == EXIT_ERROR
    assert f"could not connect to the Dask scheduler at {address} within 1 s" in err
    assert "--scheduler-timeout" in err
    assert not built  # the cells were never built: the address was checked first
    assert not (out / "map.npz").exists()


def test_a_scheduler_address_of_no_known_scheme_is_refused_before_a_client_is_made(tmp_path, monkeypatch, capsys):
    # A client made on such an address fails half-built and its clean-up waits minutes at exit.
    import distributed

    made: list[str] = []

    class Recording(distributed.Client):
        def __init__(self, *a, **k):
            made.append(str(a))
            super().__init__(*a, **k)

    monkeypatch.setattr(distributed, "Client", Recording)
    out = tmp_path / "never"
    code = main(["map", str(LOG), "-o", str(out), "--scheduler", "garbage://foo", "-q", *MAP_ARGS])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_ERROR and err[-1].startswith(
        "gpomap: error: Dask scheduler address 'garbage://foo': unknown address scheme"
    )
    assert made == [] and not (out / "map.npz").exists()
