"""The ``darp`` command. Each command group lives in its own module and registers itself here: :mod:`.demo`,
:mod:`.collect`, :mod:`.calib`, :mod:`.process` (with ``keyframes`` and ``report``), :mod:`.poses`, :mod:`.inspect`,
:mod:`.imports`, :mod:`.export`, :mod:`.view`, :mod:`.twin`, :mod:`.generate` (``twin generate``), :mod:`.hardware`,
:mod:`.recording` and :mod:`.rig`.

Every error (a bad argument, a library :class:`darp.errors.DarpError`) becomes one ``darp: error:`` line on
stderr and exit code 2; no traceback is shown for user errors. The option convention every command follows
is in :mod:`darp.cli._options` and docs/DEVELOPING.md.
"""

from __future__ import annotations

import sys
from typing import Any

import typer

# Command modules register themselves on ``app`` when imported.
from darp.cli import calib as _calib  # noqa: F401
from darp.cli import collect as _collect  # noqa: F401
from darp.cli import demo as _demo  # noqa: F401
from darp.cli import export as _export  # noqa: F401
from darp.cli import generate as _generate  # noqa: F401
from darp.cli import hardware as _hardware  # noqa: F401
from darp.cli import imports as _imports  # noqa: F401
from darp.cli import inspect as _inspect  # noqa: F401
from darp.cli import poses as _poses  # noqa: F401
from darp.cli import process as _process  # noqa: F401
from darp.cli import recording as _recording  # noqa: F401
from darp.cli import rig as _rig  # noqa: F401
from darp.cli import twin as _twin  # noqa: F401
from darp.cli import view as _view  # noqa: F401
from darp.cli._app import app


class _QuietStdout:
    """``sys.stdout`` for the console command: when the reader goes away (``| head``: a broken pipe) or stdout is
    closed, the rest of what darp prints is dropped and the command still finishes its real outputs (files), with
    its own exit code; it is never cut short with a silent exit 1 (click's way) or a traceback."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self._gone = False

    def _drop(self) -> None:
        import contextlib
        import os

        self._gone = True
        with contextlib.suppress(OSError, ValueError):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())  # native writers to fd 1 are quiet too
            os.close(null)

    def write(self, text: str) -> int:
        if not self._gone:
            try:
                return int(self._stream.write(text))
            except TypeError:
                raise
            except (BrokenPipeError, OSError, ValueError):
                self._drop()
        return len(text)

    def flush(self) -> None:
        if not self._gone:
            try:
                self._stream.flush()
            except (BrokenPipeError, OSError, ValueError):
                self._drop()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _exit_handler(signum: int, frame: object) -> None:
    """A signal while the interpreter shuts down, after the command completed: one line, not a silent death."""
    import contextlib
    import os
    import signal as signals

    with contextlib.suppress(OSError, ValueError):
        sys.stderr.write(f"darp: stopped by {signals.Signals(signum).name} while exiting (the command had "
                         "completed and written its outputs)\n")
        sys.stderr.flush()
    os._exit(128 + signum)


def main() -> None:
    """Console entry point. After a signal (exit 129/130/143) darp's own cleanup has run; the process then ends
    at once, so that no library's exit hook (thread joins, a native ``exit(1)``) delays it or changes its code.
    A signal during the normal exit (library exit hooks) still ends with one line; a closed stdout never cuts the
    command short."""
    import contextlib
    import os
    import signal

    from darp.cli._app import run

    if sys.stdout is None:  # started with stdout closed (>&-): what darp prints goes nowhere, quietly
        sys.stdout = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 (for the life of the process)
    sys.stdout = _QuietStdout(sys.stdout)
    rc = run()
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    if rc > 128:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.flush()
        os._exit(rc)
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _exit_handler)
    sys.exit(rc)


__all__ = ["app", "main", "typer"]
