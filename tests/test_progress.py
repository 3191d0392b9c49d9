"""Progress lines: none for a quick stage, then one per tenth of the work once it has run a while."""

import pytest

from gpomap import progress
from gpomap.progress import get_progress_mode, set_progress_mode


@pytest.fixture
def clock(monkeypatch):
    """A settable clock for gpomap.progress, and line mode for one test."""
    now = [100.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    before = get_progress_mode()
    set_progress_mode("lines")
    yield now
    set_progress_mode(before)


def test_a_quick_stage_prints_nothing(clock, capsys):
    with progress.progress(10, "fitting tiles", unit="tile") as bar:
        for _ in range(10):
            clock[0] += 0.05  # half a second in all
            bar.update()
    assert capsys.readouterr().err == ""


def test_a_slow_stage_prints_once_past_the_delay_then_every_tenth(clock, capsys):
    with progress.progress(20, "fitting tiles", unit="tile") as bar:
        for _ in range(20):
            clock[0] += 0.25  # 5 s in all; the delay (1 s) passes at the 4th tile
            bar.update()
    lines = capsys.readouterr().err.splitlines()
    # The 4th tile (1.0 s) is the first past the delay and prints; then each 10 % step (6th, 8th, ... tile),
    # and no line for the last: the stage's end says the rest.
    assert [line.split(":")[1].split(",")[0].strip() for line in lines] == [
        f"{k}/20 tiles" for k in (4, 6, 8, 10, 12, 14, 16, 18)
    ]
    assert lines[0] == "  fitting tiles: 4/20 tiles, 1 s elapsed, ~4 s left"


def test_quiet_and_nested_stages_print_nothing(clock, capsys):
    with progress.progress(4, "outer") as outer:
        with progress.progress(4, "inner") as inner:
            for _ in range(4):
                clock[0] += 1.0
                inner.update()
        clock[0] += 1.0
        outer.update()
    err = capsys.readouterr().err
    assert "inner" not in err and "outer: 1/4" in err
    set_progress_mode("quiet")
    with progress.progress(4, "hushed") as bar:
        clock[0] += 2.0
        bar.update()
    assert capsys.readouterr().err == ""
