"""The replay loop of ``gpomap stream``: a Ctrl-C is raised between two scans, never inside one."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from gpomap.apps.stream import ReplayResult, deferred_signals, replay
from gpomap.scans import Scan


@pytest.fixture(autouse=True)
def _python_sigint_handler():
    """Ctrl-C as a fresh Python process has it: a test worker may have been left with another handler."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _scans(n: int) -> list[Scan]:
    return [
        Scan(pose=np.zeros(3), angles=np.array([0.0]), ranges=np.array([1.0]), max_range=10.0, time=float(i)) for i in range(n)
    ]


class _Mapper:
    """A mapper whose `interrupt_at`-th scan gets a Ctrl-C, delivered where a callback would swallow it."""

    def __init__(self, interrupt_at: int) -> None:
        self.interrupt_at = interrupt_at
        self.added = 0
        self.ready_ = True

    def add_scan(self, scan: Scan) -> None:
        self.added += 1
        if self.added == self.interrupt_at:
            try:
                os.kill(os.getpid(), signal.SIGINT)
                sum(range(1000))  # the handler runs here, inside the scan's own code
            except KeyboardInterrupt:
                pass  # as a weakref callback being torn down reports and drops it


def test_a_ctrl_c_inside_a_scan_stops_the_replay_after_that_scan():
    mapper = _Mapper(interrupt_at=3)
    written: list[int] = []

    def write(n: int) -> list[Path]:
        written.append(n)
        return []

    result = ReplayResult()
    with pytest.raises(KeyboardInterrupt):
        replay(_scans(10), mapper, 0, 1e9, write, result=result)
    # Without the deferral the interrupt is lost inside the scan and all 10 scans are replayed.
    assert mapper.added == 3 and result.n_scans == 3 and result.interrupted
    assert written == []  # stopped before the end's write
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_deferred_signals_raise_at_the_check_and_a_second_one_at_once():
    with deferred_signals() as check:
        os.kill(os.getpid(), signal.SIGINT)
        sum(range(1000))  # nothing raised yet
        with pytest.raises(KeyboardInterrupt):
            check()
        check()  # the signal was taken once
        os.kill(os.getpid(), signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(1000))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_keeps_its_own_handler_s_exception():
    class Terminated(KeyboardInterrupt):
        pass

    def on_sigterm(signum: int, frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        with deferred_signals() as check:
            os.kill(os.getpid(), signal.SIGTERM)
            sum(range(1000))
            with pytest.raises(Terminated):
                check()
        assert signal.getsignal(signal.SIGTERM) is on_sigterm
    finally:
        signal.signal(signal.SIGTERM, previous)
