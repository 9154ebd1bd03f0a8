"""The ``darp`` command. Each command group lives in its own module and registers itself here.

Library errors (:class:`darp.errors.DarpError`) become one line on stderr and exit code 2; no
traceback is shown for user errors.
"""

from __future__ import annotations

import sys

import typer

from darp.cli import calib as _calib  # noqa: F401,E402
from darp.cli import collect as _collect  # noqa: F401,E402
from darp.cli import demo as _demo  # noqa: F401,E402
from darp.cli import hardware as _hardware  # noqa: F401,E402
from darp.cli import inspect as _inspect  # noqa: F401,E402
from darp.cli import poses as _poses  # noqa: F401,E402
from darp.cli import process as _process  # noqa: F401,E402

# Command modules register themselves on ``app`` when imported.
from darp.cli import recording as _recording  # noqa: F401,E402
from darp.cli import rig as _rig  # noqa: F401,E402
from darp.cli import twin as _twin  # noqa: F401,E402
from darp.cli._app import app


def main() -> None:
    """Console entry point."""
    from darp.cli._app import run

    sys.exit(run())


__all__ = ["app", "main", "typer"]
