"""The ``darp`` command (``python -m darp``): a Ctrl-C while the command modules still load (about a second)
ends it like one later on, with ``darp: interrupted`` and exit 130 instead of an import traceback."""

from __future__ import annotations

import sys


def main() -> None:
    """Console entry point: load the command line, then run it (:func:`darp.cli.main`)."""
    try:
        from darp.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("darp: interrupted\n")
        sys.exit(130)
    cli_main()


if __name__ == "__main__":
    main()
