"""The one way darp claims an output: a lock, so that two runs never write one output at the same time, and
unique temporary names beside it, so that two writers never share a temporary file.

The lock is ``fcntl.flock`` on a small file ``.<name>.darp-lock`` beside the output (an output that does not
exist yet can be locked too); it is held for the whole command and removed when the command ends. A second run
asking for the same output is refused at once (:class:`OutputBusy`), never made to wait or to collide. A lock
file left by a killed run is harmless: the kernel released its lock with the process.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from darp.errors import DarpError
from darp.formats.atomic import UNFINISHED_FILE, write_text_atomic

LOCK_SUFFIX = ".darp-lock"


class OutputBusy(DarpError):
    """Another darp run holds the lock of this output."""


def lock_path(out: str | Path) -> Path:
    """The lock file of ``out``: ``.<name>.darp-lock`` in its folder."""
    out = Path(out).expanduser().absolute()
    return out.parent / f".{out.name}{LOCK_SUFFIX}"


@contextlib.contextmanager
def output_lock(out: str | Path) -> Iterator[Path | None]:
    """Hold the lock of ``out`` for the block (yields the lock file); :class:`OutputBusy` when another process
    holds it. Where no lock file can be made (a read-only or missing folder) the block runs unlocked: the write
    itself then fails with its own one-line error."""
    path = lock_path(out)
    created = _make_parents(path.parent)  # the lock lives in the output's own folder, made now if need be
    fd = _acquire(path, Path(out))
    try:
        yield path if fd is not None else None
    finally:
        if fd is not None:
            with contextlib.suppress(OSError):
                path.unlink()  # while still held: a run that opened the old file sees a stale inode, below
            os.close(fd)
        for folder in created:  # folders made for the lock alone (the run was refused or wrote elsewhere)
            with contextlib.suppress(OSError):
                folder.rmdir()


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones created, deepest first (empty ones are removed at the
    end). Where they cannot be made, nothing is (the run goes on unlocked; its writes fail in their own words)."""
    missing = []
    probe = folder
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    made = []
    for p in reversed(missing):
        try:
            p.mkdir()
        except FileExistsError:
            continue
        except OSError:
            break
        made.append(p)
    return made[::-1]


def _acquire(path: Path, out: Path) -> int | None:
    for _ in range(3):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise OutputBusy(f"another darp run is writing it (pid {_holder(path)}); wait for it to end or "
                                 "choose another output", out) from None
            return None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except OSError:
            same = False
        if same:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)  # the holder removed the file between our open and our lock: take the new one
    return None


def _holder(path: Path) -> str:
    try:
        return path.read_text(encoding="ascii").strip() or "?"
    except (OSError, UnicodeDecodeError):
        return "?"


@contextlib.contextmanager
def unfinished_folder(folder: str | Path, command: str) -> Iterator[Path]:
    """Build a multi-file output folder marked unfinished: ``UNFINISHED.txt`` is its first file and is removed
    last, only when the block succeeds. A run that fails (a full or read-only disk, an error, a signal) leaves the
    marker, so a half folder is never taken for a whole one; where even the marker cannot be written, nothing is
    written (a folder this call created is removed again)."""
    folder = Path(folder)
    created = not folder.exists()
    marker = folder / UNFINISHED_FILE
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(marker, f"unfinished: {command} did not complete this folder (interrupted, failed or out "
                          "of space); its files are not a result: run it again\n")
    except OSError:
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    yield folder
    marker.unlink(missing_ok=True)


def unique_partial(target: str | Path, suffix: str = ".partial") -> Path:
    """A fresh, unused temporary path beside ``target`` (``.<name>.<random><suffix>``), created empty so that
    no other writer can take it; never a fixed name that two runs would share."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    os.close(fd)
    return Path(name)


__all__ = ["LOCK_SUFFIX", "OutputBusy", "lock_path", "output_lock", "unfinished_folder", "unique_partial"]
