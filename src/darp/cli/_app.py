"""The root typer application and the error boundary shared by every command.

Every error reaches the user as one line on stderr, ``darp: error: <message>``, with exit code 2: a bad
argument (click's usage errors, and the ``typer.BadParameter`` a parser or a command raises) as well as a
library error (:class:`darp.errors.DarpError`) or a file that cannot be opened.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, Protocol, cast

import typer

from darp.errors import DarpError, DarpWarning, Interrupted, raise_interrupted


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
    """Print one ``darp: error:`` line on stderr (a message over several lines is joined into one)."""
    typer.echo(f"darp: error: {' '.join(message.split())}", err=True)


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


# Signals that end a command like Ctrl-C does (the same cleanup runs), with the shell's exit code 128 + signal.
_ENDING_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
_ERRNO_WORDS = {errno.ENOSPC: "no space left on device", errno.EROFS: "read-only file system",
                errno.EDQUOT: "disk quota exceeded", errno.EFBIG: "file too large",
                errno.EACCES: "permission denied", errno.EPERM: "operation not permitted"}
_received: list[int] = []  # signals received during this run (typer turns the interrupt into exit 130)
_state = {"redeliver": False, "done": True, "announced": False}
REDELIVER_S = 2.0  # a first interrupt swallowed by a library (trimesh's ``except BaseException`` around its
HARD_EXIT_S = 8.0  # imports) is raised again after this long; a run still alive after HARD_EXIT_S just exits


def _raise_interrupted(signum: int, frame: object) -> None:
    """Raise :class:`Interrupted` in the main thread on the first signal (the cleanup runs as for Ctrl-C);
    ignore repeats during the cleanup, except the watchdog's one re-delivery."""
    if _state["redeliver"]:
        _state["redeliver"] = False
        raise_interrupted(_received[0] if _received else signum)
        return
    _received.append(signum)
    if len(_received) == 1:
        threading.Thread(target=_watchdog, args=(signum,), name="darp-signal-watchdog", daemon=True).start()
        raise_interrupted(signum)  # held while a child process starts (darp.errors.interrupts_deferred)


def _watchdog(signum: int) -> None:
    """Make sure a signal ends the run: re-deliver it once, then exit without cleanup."""
    time.sleep(REDELIVER_S)
    if _state["done"]:
        return
    _state["redeliver"] = True
    import _thread

    _thread.interrupt_main(signal.Signals(signum))
    time.sleep(HARD_EXIT_S - REDELIVER_S)
    if not _state["done"]:
        with contextlib.suppress(OSError, ValueError):
            sys.stderr.write(f"darp: stopped by {_signal_name(signum)} (cleanup cut short)\n")
            sys.stderr.flush()
        os._exit(128 + signum)


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)


def _output_hint(argv: list[str] | None) -> str | None:
    """The ``-o/--out`` value of the command line, to name the output when an OS error names no file."""
    args = list(sys.argv[1:] if argv is None else argv)
    for i, arg in enumerate(args):
        if arg in ("-o", "--out") and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--out="):
            return arg.split("=", 1)[1]
    return None


def os_error_message(err: OSError, argv: list[str] | None = None) -> str:
    """One line for an OS error: the file it concerns (or the command's output) and what went wrong."""
    words = _ERRNO_WORDS.get(err.errno or 0) or (err.strerror or str(err)).lower()
    name = err.filename
    if name is None:
        hint = _output_hint(argv)
        return f"{hint}: {words} (while writing the output)" if hint else words
    return f"{os.fsdecode(name)}: {words}"


def run(argv: list[str] | None = None) -> int:
    """Run the app, mapping every error to one line and exit code 2 (130 on SIGINT, 143 on SIGTERM, 129 on
    SIGHUP: each runs the same cleanup as Ctrl-C), and each DarpWarning to one ``darp: warning:`` line."""
    import logging

    import darp.cli  # noqa: F401  (registers the command modules)

    # matplotlib's notes about its cache folder (an unwritable HOME) are not the user's business: darp draws
    # into files it names itself
    logging.getLogger("matplotlib").setLevel(logging.ERROR)

    in_main = threading.current_thread() is threading.main_thread()
    _received.clear()
    _state.update(redeliver=False, done=False, announced=False)
    previous = {s: signal.signal(s, _raise_interrupted) for s in _ENDING_SIGNALS} if in_main else {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", DarpWarning)  # every file's warning reaches the printer (once each)
            warnings.showwarning = _warning_printer(warnings.showwarning)
            try:
                rc = _run_app(argv)
            except KeyboardInterrupt as err:  # a signal during the cleanup of the first one
                rc = _interrupted(err)
            if _received and not _state["announced"]:
                rc = _interrupted(Interrupted(_received[0]))
            return rc
    finally:
        _state["done"] = True
        for s, handler in previous.items():
            signal.signal(s, handler)


def _interrupted(err: BaseException) -> int:
    signum = err.signum if isinstance(err, Interrupted) else (_received[0] if _received else int(signal.SIGINT))
    if not _state["announced"]:
        _state["announced"] = True
        with contextlib.suppress(OSError, ValueError):  # stderr gone with the terminal (SIGHUP)
            typer.echo("darp: interrupted" if signum == signal.SIGINT else f"darp: stopped by {_signal_name(signum)}",
                       err=True)
    return 128 + signum


def _run_app(argv: list[str] | None) -> int:
    try:
        # With standalone_mode=False click returns the exit code of typer.Exit instead of raising it.
        from darp.cli._outputs import guard_commands  # every command's outputs checked and locked

        command = guard_commands(typer.main.get_command(app))
        rc = command.main(args=argv, prog_name="darp", standalone_mode=False)
    except DarpError as err:
        error(str(err))
        return 2
    except typer.Exit as err:
        return int(err.exit_code or 0)
    except typer.Abort:
        if _received:
            return _interrupted(Interrupted(_received[0]))
        typer.echo("darp: aborted", err=True)
        return 130
    except KeyboardInterrupt as err:  # SIGINT, or SIGTERM / SIGHUP as darp.errors.Interrupted
        return _interrupted(err)
    except OSError as err:  # a full disk, a read-only file system, a file that cannot be opened
        error(os_error_message(err, argv))
        return 2
    except RecursionError:
        error("an input file is nested too deeply to read")
        return 2
    except _CLICK_ERRORS as exc:  # bad arguments: unknown option, missing argument, bad value
        usage = cast(_ClickError, exc)
        if type(exc).__name__ == "NoArgsIsHelpError":  # a group called alone: its help
            usage.show(file=sys.stderr)
        else:
            error(usage.format_message())
        return int(getattr(usage, "exit_code", 2))
    except Exception:
        if _received:  # the interrupt surfaced wrapped in another error (ctypes' ArgumentError, an ImportError)
            return _interrupted(Interrupted(_received[0]))
        raise
    return int(rc or 0) if isinstance(rc, int) else 0
