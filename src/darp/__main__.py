"""The ``darp`` command (``python -m darp``): a Ctrl-C, SIGTERM or SIGHUP while the command modules still load
(about a second) ends it like one later on: one ``darp:`` line and exit 130 / 143 / 129, no import traceback."""

from __future__ import annotations

import os
import signal
import sys

from darp.errors import Interrupted


def _interrupt(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def main() -> None:
    """Console entry point: load the command line, then run it (:func:`darp.cli.main`)."""
    for name in ("SIGTERM", "SIGHUP"):  # SIGINT already raises KeyboardInterrupt
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), _interrupt)
    try:
        from darp.cli import main as cli_main
    except KeyboardInterrupt as err:
        signum = err.signum if isinstance(err, Interrupted) else int(signal.SIGINT)
        sys.stderr.write("darp: interrupted\n" if signum == signal.SIGINT
                         else f"darp: stopped by {signal.Signals(signum).name}\n")
        sys.stderr.flush()
        # Not sys.exit: an interrupt that landed inside a native extension's own evaluation of Python code
        # (pybind11 runs some at import) leaves CPython marked "unhandled KeyboardInterrupt", and the interpreter
        # would then end by SIGINT (-2) instead of exit 130. Nothing needs cleaning up this early.
        os._exit(128 + signum)
    cli_main()


if __name__ == "__main__":
    main()
