"""Atomic output: a file is either the old one or the complete new one, never half-written, and a
run's files replace the previous run's together.

Every writer in gpomap goes through :func:`atomic_write` (one file) or :func:`atomic_write_group`
(several files that belong together, such as a ROS ``map.yaml`` and its ``map.pgm``), both of
:mod:`gpomap.atomic_files` and named here too. A run's whole set of outputs (map.yaml, map.pgm,
map.npz, map.png, ...) goes through :func:`output_set`: written into a staging directory, then put
in place of the previous set together (see :class:`OutputSet`).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from gpomap.atomic_files import _fsync_dir, _remove_quietly, atomic_write, atomic_write_group

__all__ = ["OutputSet", "atomic_write", "atomic_write_group", "check_output_dir", "output_set", "recover_output_dir"]


# --------------------------------------------------------------------------- sets of outputs
#: The list of files gpomap wrote into an output directory last time (so the next run can tell
#: its own previous outputs, replaced as a set, from files the user put there, never touched).
MANIFEST = ".gpomap-outputs.json"
#: Present in a staging directory once every file in it is complete and the renames have begun:
#: a run killed during them is finished ("rolled forward") by the next run on the same OUTDIR.
JOURNAL = ".gpomap-commit.json"
_STAGING_TAG = ".gpomap-staging-"
#: Test hooks (documented in the README): seconds to sleep after each file a writer finishes in a
#: staging directory, and between the renames of a commit, so tests can signal a run mid-write.
WRITE_DELAY_ENV = "GPOMAP_TEST_WRITE_DELAY"
COMMIT_DELAY_ENV = "GPOMAP_TEST_COMMIT_DELAY"


def _test_delay(variable: str) -> None:
    value = os.environ.get(variable)
    if value:
        import time

        time.sleep(float(value))


def file_written() -> None:
    """Writers of an output set call this after each file (a no-op unless the test hook is set)."""
    _test_delay(WRITE_DELAY_ENV)


def check_output_dir(outdir: str | os.PathLike[str], option: str = "-o") -> Path:
    """Cheap check, before any work, that `outdir` can receive a set of outputs.

    Parameters
    ----------
    outdir : path-like
        The output directory: an existing writable directory, or a path that can be created.
    option : str
        The option that named it, for the message.

    Returns
    -------
    Path
        `outdir`.

    Raises
    ------
    GpomapError
        `outdir` is a file, or it (or the directory it would be created in) is not writable.
    """
    from gpomap.errors import GpomapError

    out = Path(outdir)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise GpomapError(f"{option} {out}: exists and is not a directory (expected a directory for the outputs)")
        if not os.access(out, os.W_OK | os.X_OK):
            raise GpomapError(f"{option} {out}: directory is not writable")
        return out
    # The nearest existing ancestor is where the directory (and its parents) would be created.
    ancestor = out.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise GpomapError(f"{option} {out}: cannot be created, {ancestor} is not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise GpomapError(f"{option} {out}: cannot be created, {ancestor} is not writable")
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return True
    return True


def _host() -> str:
    import socket

    return "".join(c if c.isalnum() else "_" for c in socket.gethostname())[:40] or "host"


def _staging_places(out: Path) -> list[Path]:
    """Directories a staging directory of `out` may be in: beside it, or (fallback) inside it."""
    places = [out.absolute().parent]
    if out.is_dir():
        places.append(out)
    return places


def _staging_prefix(out: Path, inside: bool) -> str:
    return f"{_STAGING_TAG}" if inside else f".{out.name}{_STAGING_TAG}"


def _read_json(path: Path) -> Any:
    import json

    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _write_json(path: Path, value: Any) -> None:
    import json

    with atomic_write(path, "w") as f:
        json.dump(value, f, indent=1)
        f.write("\n")


def _remove_tree(path: Path) -> None:
    import shutil

    shutil.rmtree(path, ignore_errors=True)


def _roll_forward(staging: Path, out: Path) -> None:
    """Finish the renames a journal describes (idempotent: a file already moved is skipped)."""
    journal = _read_json(staging / JOURNAL)
    replaced = staging / ".replaced"
    for name in journal["files"]:
        src, dst = staging / name, out / name
        if not (src.exists() or src.is_symlink()):
            continue  # renamed before the interruption
        if dst.is_dir() and not dst.is_symlink():
            # A directory cannot be renamed over a non-empty one: move the old one aside first.
            replaced.mkdir(exist_ok=True)
            os.replace(dst, replaced / f"{name}.{secrets.token_hex(4)}")
        os.replace(src, dst)
        _test_delay(COMMIT_DELAY_ENV)
    for name in journal["remove"]:
        stale = out / name
        if stale.is_dir() and not stale.is_symlink():
            _remove_tree(stale)
        else:
            _remove_quietly(stale)
    _fsync_dir(out)


def recover_output_dir(outdir: str | os.PathLike[str]) -> list[str]:
    """Clean up after runs on `outdir` that were killed (SIGKILL, power loss) before they finished.

    A staging directory whose commit had begun is finished, so `outdir` holds that run's complete
    set; one whose run died while still writing is removed (its previous set was never touched).
    Staging directories of runs still alive (same host, live process) are left alone.

    Parameters
    ----------
    outdir : path-like

    Returns
    -------
    list of str
        What was done, one sentence per staging directory.
    """
    out = Path(outdir)
    done: list[str] = []
    host = _host()
    for place in _staging_places(out):
        inside = place == out
        prefix = _staging_prefix(out, inside)
        try:
            entries = [p for p in place.iterdir() if p.name.startswith(prefix) and p.is_dir()]
        except OSError:
            continue
        for staging in entries:
            # NAME.gpomap-staging-HOST-PID-HEX
            parts = staging.name[len(prefix) :].rsplit("-", 2)
            if len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
                continue  # another machine's run (shared file system), or not ours
            if _pid_alive(int(parts[1])) and int(parts[1]) != os.getpid():
                continue
            if (staging / JOURNAL).exists():
                out.mkdir(parents=True, exist_ok=True)
                _roll_forward(staging, out)
                done.append(f"completed the interrupted update of {out} from {staging.name}")
            else:
                done.append(f"removed {staging.name}, left by an interrupted run (the outputs in {out} were not touched)")
            _remove_tree(staging)
    return done


class OutputSet:
    """The files of one run, written into a private staging directory and then put in place together.

    Use :func:`output_set`. Writers put their files into :attr:`path` (under the final names);
    :meth:`commit` then replaces the previous set in the output directory: every file of the new
    set is renamed into place, and the files of the previous set (named in its manifest,
    :data:`MANIFEST`) that this run did not write are removed. Files the user put in the output
    directory are never touched. Until the commit, the output directory is not touched at all.

    Parameters
    ----------
    outdir : path-like
        The output directory (created if missing).

    Notes
    -----
    The staging directory is a hidden sibling of `outdir` (``.OUTDIR.gpomap-staging-HOST-PID-X``),
    on the same file system so the renames are cheap and atomic; when the parent is not writable
    or is another file system, it is a hidden directory inside `outdir` instead. The commit takes
    a few renames; SIGINT and SIGTERM are held back during it, so a signal leaves either the whole
    previous set or the whole new one. A SIGKILL (or power loss) during the renames leaves a
    journal in the staging directory: the next run on `outdir` (:func:`recover_output_dir`)
    finishes them, so the directory never stays a mix of two runs.
    """

    def __init__(self, outdir: str | os.PathLike[str]) -> None:
        self.outdir = Path(outdir)
        self.committed = False
        self.files: list[Path] = []
        recover_output_dir(self.outdir)
        inside = not self._can_stage_beside()
        if inside:
            self.outdir.mkdir(parents=True, exist_ok=True)
        # Otherwise the output directory is created only by the commit: a run that fails leaves
        # no empty directory behind.
        place = self.outdir if inside else self.outdir.absolute().parent
        prefix = _staging_prefix(self.outdir, inside)
        for _ in range(100):
            path = place / f"{prefix}{_host()}-{os.getpid()}-{secrets.token_hex(4)}"
            try:
                path.mkdir()
            except FileExistsError:
                continue
            self.path = path
            break
        else:  # pragma: no cover - 100 collisions of 32 random bits
            raise FileExistsError(f"could not create a staging directory in {place}")

    def _can_stage_beside(self) -> bool:
        parent = self.outdir.absolute().parent
        if not parent.is_dir():
            parent.mkdir(parents=True, exist_ok=True)
        if not os.access(parent, os.W_OK | os.X_OK):
            return False
        if self.outdir.exists():
            try:
                return os.stat(parent).st_dev == os.stat(self.outdir).st_dev
            except OSError:
                return False
        return True

    def final(self, path: str | os.PathLike[str]) -> Path:
        """Where a file written into the staging directory ends up after the commit."""
        return self.outdir / Path(path).relative_to(self.path)

    def commit(self) -> list[Path]:
        """Put the staged set in place of the previous one; returns the final paths of the new files."""
        names = sorted(p.name for p in self.path.iterdir() if p.name not in (MANIFEST, JOURNAL))
        # Files that refer to others go last (a map YAML names its image); the manifest after all.
        names.sort(key=lambda n: n.endswith((".yaml", ".yml")))
        previous: list[str] = []
        manifest = self.outdir / MANIFEST
        if manifest.exists():
            try:
                previous = [str(n) for n in _read_json(manifest).get("files", [])]
            except (OSError, ValueError, AttributeError):
                previous = []
        # Never let a manifest name reach outside the directory.
        stale = [n for n in previous if n not in names and n == Path(n).name and n not in (MANIFEST, JOURNAL)]
        _write_json(self.path / MANIFEST, {"files": names})
        with _signals_held():
            _write_json(self.path / JOURNAL, {"files": [*names, MANIFEST], "remove": stale})
            # From here on the staging directory is needed to finish (by the next run if this one
            # dies): discard() keeps it.
            self._journaled = True
            self.outdir.mkdir(parents=True, exist_ok=True)
            _roll_forward(self.path, self.outdir)
            self.committed = True
            _remove_tree(self.path)
        self.files = [self.outdir / n for n in names]
        return self.files

    def discard(self) -> None:
        """Remove the staging directory; the output directory keeps its previous set.

        A staging directory whose commit had begun is kept for :func:`recover_output_dir`.
        """
        if not getattr(self, "_journaled", False):
            _remove_tree(self.path)


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for the block; deliver them (to the previous handlers) after it.

    Python runs signal handlers between bytecodes, so a signal during the renames of a commit
    would otherwise stop it half-way. Outside the main thread handlers cannot be changed: nothing
    is held.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum: int, frame: Any) -> None:
        caught.append(signum)

    previous: dict[int, Any] = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
        for s in dict.fromkeys(caught):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), s)


@contextmanager
def output_set(outdir: str | os.PathLike[str]) -> Iterator[OutputSet]:
    """Write a run's outputs as one set: all replace the previous ones, or none does.

    Parameters
    ----------
    outdir : path-like
        The output directory.

    Yields
    ------
    OutputSet
        Write files into its ``path``; after the block, ``files`` lists their final paths.

    Notes
    -----
    On leaving the block normally the set is committed (see :class:`OutputSet`); on any exception,
    KeyboardInterrupt included, the staging directory is removed and `outdir` is left as it was.

    Examples
    --------
    >>> with output_set("out") as outputs:  # doctest: +SKIP
    ...     (outputs.path / "a.txt").write_text("new")
    """
    outputs = OutputSet(outdir)
    try:
        yield outputs
        outputs.commit()
    except BaseException:
        if not outputs.committed:
            outputs.discard()
        raise
