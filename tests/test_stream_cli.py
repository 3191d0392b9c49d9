"""``gpomap stream``: a recorded log replayed through the streaming mapper, as fast as possible or as recorded."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from gpomap.cli import main
from gpomap.io.npz import load_map
from gpomap.io.rosbag import STAGE_TIME_OFFSET, read_rosbag
from gpomap.io.rosmap import read_rosmap
from gpomap.streaming import StreamingGPOM
from tests.processes import as_from_a_terminal

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BAG = DATA / "stage-arena" / "robot1.bag"
BELGIOIOSO = DATA / "belgioioso" / "belgioioso-corrected.log.gz"
needs_bag = pytest.mark.skipif(not BAG.exists(), reason="shared Stage arena bag not present")
ARENA = [str(BAG), "--topic", "/base_scan", "--time-offset", str(STAGE_TIME_OFFSET), "--resolution", "0.1"]


def _set_is_complete(outdir: Path) -> None:
    """OUTDIR holds one whole map set: the manifest's four files, readable, and no staging left beside it."""
    names = json.loads((outdir / ".gpomap-outputs.json").read_text())["files"]
    assert sorted(names) == ["map.npz", "map.pgm", "map.png", "map.yaml"]
    occupancy_map = load_map(outdir / "map.npz")
    rosmap = read_rosmap(outdir / "map.yaml")
    assert rosmap.grid.shape == occupancy_map.grid.shape
    assert not [p for p in outdir.parent.iterdir() if "gpomap-staging" in p.name]


@needs_bag
def test_stream_as_fast_as_possible_ends_with_the_batch_map_of_every_scan(tmp_path, capsys):
    # The first 40 scans: a warm-up of 20 and 20 streamed one by one after it (a map written after
    # each), as the whole bag's would be; when the log ends, the map of all 40 as gpomap map fits it.
    out = tmp_path / "live"
    args = ["--range", "0:40", "--warmup", "20", "--rate", "0", "--every", "1", "-q"]
    assert main(["stream", *ARENA, "-o", str(out), *args]) == 0
    text = capsys.readouterr().out
    assert "scans        40 of 40\n" in text and "as fast as possible" in text
    assert "latency      add_scan median" in text and "p95" in text and "scans/s" in text
    _set_is_complete(out)
    # gpomap map on the same scans: the same map, to the bit, with the same ternary thresholds.
    batch = tmp_path / "batch"
    assert main(["map", *ARENA, "-o", str(batch), "--range", "0:40", "-q"]) == 0
    streamed, mapped = load_map(out / "map.npz"), load_map(batch / "map.npz")
    assert streamed.grid == mapped.grid and streamed.thresholds == mapped.thresholds
    np.testing.assert_array_equal(streamed.probability, mapped.probability)
    np.testing.assert_array_equal(streamed.ternary, mapped.ternary)
    # Before the end, the maps written were the streaming mapper's: its hyperparameters from the warm-up.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scans = read_rosbag(BAG, topic="/base_scan", time_offset=STAGE_TIME_OFFSET)
    reference = StreamingGPOM(warmup_scans=20, n_workers=1)
    for s in scans[:40]:
        reference.add_scan(s)
    assert reference.grid(0.1).grid == streamed.grid


@needs_bag
def test_stream_at_rate_one_takes_the_recorded_time(tmp_path, capsys):
    # Scans 0..19 of the arena: 1.9 s of recording at 10 Hz (10 of warm-up, 10 paced after it).
    # The length scale fixed: the pacing is the point, not what the warm-up learns.
    out = tmp_path / "live"
    t = time.monotonic()
    fixed = ["--length-scale", "0.5"]
    assert main(["stream", *ARENA, "-o", str(out), "--range", "0:20", "--warmup", "10", "--rate", "1", "-q", *fixed]) == 0
    elapsed = time.monotonic() - t
    text = capsys.readouterr().out
    wall = float(text.split("replay       at rate 1: ")[1].split(" s wall")[0])
    assert 1.9 <= wall <= elapsed and "behind the recording" in text
    # Twice as fast: never ahead of half the recording. (How much longer it takes depends on how
    # busy the machine is, so only the pacing's lower bound is checked.)
    assert main(["stream", *ARENA, "-o", str(out), "--range", "0:20", "--warmup", "10", "--rate", "2", "-q", *fixed]) == 0
    wall2 = float(capsys.readouterr().out.split("replay       at rate 2: ")[1].split(" s wall")[0])
    assert wall2 >= 0.95
    _set_is_complete(out)


@needs_bag
def test_ctrl_c_stops_the_replay_and_keeps_the_last_complete_map(tmp_path):
    out = tmp_path / "live"
    # Twice as fast as recorded: a warm-up of 10 scans in 0.5 s, the whole log in 22 s. The length
    # scale fixed: the interruption is the point, not what the warm-up learns.
    fixed = ["--warmup", "10", "--length-scale", "0.5"]
    cmd = [sys.executable, "-m", "gpomap.cli", "stream", *ARENA, "-o", str(out), "--rate", "2", "--every", "0.5", *fixed]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=as_from_a_terminal
    )
    try:
        deadline = time.monotonic() + 120
        while not (out / "map.npz").exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no map written"
            time.sleep(0.1)

        # Past the first write, inside another one: a staging directory other than the first's is there.
        def staging() -> set[str]:
            return {p.name for p in tmp_path.iterdir() if "gpomap-staging" in p.name}

        first = staging()
        while not staging() - first:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no second write"
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGINT, stderr
    assert "(interrupted)" in stdout and "latency      add_scan median" in stdout
    assert f"gpomap: interrupted; {out} holds the last complete set of outputs this run wrote" in stderr
    _set_is_complete(out)
    n_done = int(stdout.split("scans        ")[1].split(" of 432")[0])
    assert 10 <= n_done < 432


def test_a_log_without_time_stamps_needs_rate_zero(tmp_path, capsys):
    if not BELGIOIOSO.exists():
        pytest.skip("shared Belgioioso log not present")
    assert main(["stream", str(BELGIOIOSO), "-o", str(tmp_path / "o"), "--rate", "1", "-q"]) == 1
    err = capsys.readouterr().err
    assert f"gpomap: error: {BELGIOIOSO}: 395 of 395 scans have no time stamp (first: scan 0)" in err
    assert "use --rate 0" in err and not (tmp_path / "o").exists()


@needs_bag
def test_too_few_scans_for_the_warm_up_is_an_error_leaving_nothing(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["stream", *ARENA, "-o", str(out), "--range", "0:5", "--warmup", "10", "--rate", "0", "-q"]) == 1
    err = capsys.readouterr().err
    assert "5 scans were not enough to learn the hyperparameters; use a smaller --warmup" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--rate", "-1"], "argument --rate: expected a number >= 0, got '-1'"),
        (["--every", "nan"], "argument --every: expected a number >= 0, got 'nan'"),
        (["--warmup", "0"], "argument --warmup: expected a positive integer, got '0'"),
    ],
)
def test_bad_options_are_usage_errors(tmp_path, capsys, args, match):
    with pytest.raises(SystemExit) as exc:
        main(["stream", "in.log", "-o", str(tmp_path / "o"), *args])
    assert exc.value.code == 2 and match in capsys.readouterr().err


def test_a_missing_input_is_one_line_and_exit_one(tmp_path, capsys):
    assert main(["stream", str(tmp_path / "nope.log"), "-o", str(tmp_path / "o"), "--rate", "0", "-q"]) == 1
    err = capsys.readouterr().err
    assert err == f"gpomap: error: {tmp_path / 'nope.log'}: no such file or directory\n"
