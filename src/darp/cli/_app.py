"""The root typer application and the error boundary shared by every command."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable
from typing import Any

import typer

from darp.errors import DarpError, DarpWarning


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


def fail(message: str) -> typer.Exit:
    """Print one error line and return the exit exception (code 2) for the caller to raise."""
    typer.echo(f"darp: error: {message}", err=True)
    return typer.Exit(code=2)


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
    """Run the app, mapping DarpError (and bad files) to one line and exit code 2, and DarpWarnings to one
    ``darp: warning:`` line each."""
    import darp.cli  # noqa: F401  (registers the command modules)

    with warnings.catch_warnings():
        warnings.simplefilter("always", DarpWarning)  # every file's warning reaches the printer (once each)
        warnings.showwarning = _warning_printer(warnings.showwarning)
        return _run(argv)


def _run(argv: list[str] | None) -> int:
    try:
        # With standalone_mode=False click returns the exit code of typer.Exit instead of raising it.
        rc = app(args=argv, standalone_mode=False)
    except DarpError as err:
        typer.echo(f"darp: error: {err}", err=True)
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
        typer.echo(f"darp: error: {err.filename}: {err.strerror}", err=True)
        return 2
    except _CLICK_ERRORS as err:  # usage errors: unknown option, missing argument, bad value
        err.show(file=sys.stderr)
        return int(getattr(err, "exit_code", 2))
    return int(rc or 0) if isinstance(rc, int) else 0
