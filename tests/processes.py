"""Starting the command as a terminal would, for the tests that signal it."""

from __future__ import annotations

import signal


def as_from_a_terminal() -> None:
    """``preexec_fn`` for a child that is to be signalled: SIGINT and SIGTERM at their defaults, unblocked.

    A child inherits ignored signals and the signal mask, and Python leaves SIGINT ignored when it
    starts ignored. A test worker's own state (what earlier tests in the same process did) must not
    decide whether Ctrl-C reaches the command under test.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
