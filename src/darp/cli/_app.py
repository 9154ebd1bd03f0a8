"""The root typer application and the error boundary shared by every command.

Every error reaches the user as one line on stderr, ``darp: error: <message>``, with exit code 2: a bad
argument (click's usage errors, and the ``typer.BadParameter`` a parser or a command raises) as well as a
library error (:class:`darp.errors.DarpError`) or a file that cannot be opened.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable
from typing import Any, Protocol, cast

import typer

from darp.errors import DarpError, DarpWarning


class _ClickError(Protocol):
    exit_code: int

    def format_message(self) -> str: ...

    def show(self, file: object = None) -> None: ...


def _click_error_types() -> tuple[type[BaseException], ...]:
    """Click's exception base, from click itself and from the copy recent typer versions vendor."""
    import click

    types: list[type[BaseException]] = [click.ClickException]
    try:
        from typer._click.exceptions import ClickException as VendoredClickException

        types.append(VendoredClickException)
    except ImportError:
        pass
    return tuple(types)


_CLICK_ERRORS = _click_error_types()

app = typer.Typer(
    name="darp",
    help="darp: calibrated dual-arm eye-in-hand RGB-D-IR perception (calibrate, acquire, process, simulate).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def error(message: str) -> None:
    """Print one ``darp: error:`` line on stderr."""
    typer.echo(f"darp: error: {message}", err=True)


def _warning_printer(fallback: Callable[..., Any]) -> Callable[..., None]:
    """A ``warnings.showwarning`` that prints each :class:`DarpWarning` once per file (or message) as one
    ``darp: warning: <file>: <message>`` line on stderr, and leaves other warnings to ``fallback``."""
    shown: set[tuple[type, str]] = set()

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: Any = None,
             line: str | None = None) -> None:
        if not issubclass(category, DarpWarning):
            fallback(message, category, filename, lineno, file, line)
            return
        path = getattr(message, "path", None)
        key = (category, str(path.resolve()) if path is not None else str(message))
        if key not in shown:
            shown.add(key)
            typer.echo(f"darp: warning: {message}", err=True)

    return show


def run(argv: list[str] | None = None) -> int:
    """Run the app, mapping every error to one line and exit code 2 (130 when interrupted), and each
    DarpWarning to one ``darp: warning:`` line."""
    import darp.cli  # noqa: F401  (registers the command modules)

    with warnings.catch_warnings():
        warnings.simplefilter("always", DarpWarning)  # every file's warning reaches the printer (once each)
        warnings.showwarning = _warning_printer(warnings.showwarning)
        return _run(argv)


def _run(argv: list[str] | None) -> int:
    try:
        # With standalone_mode=False click returns the exit code of typer.Exit instead of raising it.
        rc = app(args=argv, prog_name="darp", standalone_mode=False)
    except DarpError as err:
        error(str(err))
        return 2
    except typer.Exit as err:
        return int(err.exit_code or 0)
    except typer.Abort:
        typer.echo("darp: aborted", err=True)
        return 130
    except KeyboardInterrupt:
        typer.echo("darp: interrupted", err=True)
        return 130
    except (FileNotFoundError, IsADirectoryError, PermissionError) as err:
        error(f"{err.filename}: {err.strerror}")
        return 2
    except _CLICK_ERRORS as exc:  # bad arguments: unknown option, missing argument, bad value
        usage = cast(_ClickError, exc)
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group called alone: its help
            usage.show(file=sys.stderr)
        else:
            error(usage.format_message())
        return int(getattr(usage, "exit_code", 2))
    return int(rc or 0) if isinstance(rc, int) else 0
