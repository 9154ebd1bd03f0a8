"""The ``darp`` command. Each command group lives in its own module and registers itself here.

Every error (a bad argument, a library :class:`darp.errors.DarpError`) becomes one ``darp: error:`` line on
stderr and exit code 2; no traceback is shown for user errors. The option convention every command follows
is in :mod:`darp.cli._options` and docs/DEVELOPING.md.
"""

from __future__ import annotations

import sys

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


def main() -> None:
    """Console entry point. After a signal (exit 129/130/143) darp's own cleanup has run; the process then ends
    at once, so that no library's exit hook (thread joins, a native ``exit(1)``) delays it or changes its code."""
    import contextlib
    import os

    from darp.cli._app import run

    rc = run()
    if rc > 128:
        with contextlib.suppress(OSError, ValueError):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


__all__ = ["app", "main", "typer"]
