"""Atomic output: write to a temporary file beside the target, then rename over it.

An interrupted run therefore never leaves a file that looks complete: either the old file (or none)
is there, or the new one, whole. Temporary names end in ``.partial`` so that they are easy to spot.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

PARTIAL_SUFFIX = ".partial"
# Written into an output folder before a multi-file run starts and removed when it ends: every reader of
# such a folder (report, export, view, dataset) treats a folder holding it as not there.
UNFINISHED_FILE = "UNFINISHED.txt"


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success it is renamed to ``target``.

    On an exception the temporary file is removed and ``target`` is left untouched.
    """
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=PARTIAL_SUFFIX, dir=target.parent)
    except OSError as err:
        raise _naming(err, target) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        os.chmod(tmp, 0o666 & ~_current_umask())  # mkstemp creates 0600; give outputs normal permissions
        yield tmp
        os.replace(tmp, target)
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(err, OSError) and (err.filename is None or Path(os.fsdecode(err.filename)) == tmp):
            raise _naming(err, target) from None  # the user knows the output, not the temporary name
        raise


def _naming(err: OSError, target: Path) -> OSError:
    """The same OS error, naming ``target`` (full disk, read-only file system, permission denied)."""
    return type(err)(err.errno, err.strerror or str(err), str(target))


@contextlib.contextmanager
def atomic_open(target: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file for writing; it replaces ``target`` only if the block succeeds."""
    with atomic_path(target) as tmp, open(tmp, mode, **kwargs) as handle:
        yield handle
        handle.flush()
        os.fsync(handle.fileno())


def write_json_atomic(target: str | Path, payload: Any, *, indent: int = 2) -> None:
    """Write ``payload`` as JSON to ``target`` atomically."""
    with atomic_open(target, "w", encoding="utf-8") as handle:
        json.dump(payload, handle, indent=indent, sort_keys=False)
        handle.write("\n")


def write_text_atomic(target: str | Path, text: str) -> None:
    """Write ``text`` to ``target`` atomically."""
    with atomic_open(target, "w", encoding="utf-8") as handle:
        handle.write(text)
