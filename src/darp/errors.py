"""The exception hierarchy: one root, one subclass per layer; and darp's warnings.

Library code raises these; only the command-line layer turns them into a one-line message and exit
code 2. Messages name the file (when there is one) and the problem, so that they can be shown as is.
Warnings (:class:`DarpWarning`) are issued with :func:`warnings.warn` and printed by the command line
as ``darp: warning: <file>: <message>``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path


class DarpError(Exception):
    """Root of every error darp raises on purpose (bad input, impossible request)."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self.message = message
        super().__init__(f"{path}: {message}" if path is not None else message)


class FormatError(DarpError):
    """A file does not follow its format: corrupt, truncated, wrong columns, bad values."""


class RecordingError(FormatError):
    """A RealSense recording (.bag / .db3) cannot be read or written as asked."""


class SurveyError(FormatError):
    """A survey folder is missing a file or holds inconsistent files."""


class KinematicsError(DarpError):
    """A kinematic request is impossible (bad joint vector, unknown frame, unknown arm)."""


class ConfigError(DarpError):
    """A configuration file (rig, twin settings) is invalid."""


class CalibrationError(DarpError):
    """Calibration cannot be computed from the given captures."""


class AcquisitionError(DarpError):
    """A survey cannot be planned or executed."""


class TwinError(DarpError):
    """The digital twin cannot build or run the requested scene."""


class HardwareError(DarpError):
    """Real hardware (Z1 SDK, RealSense) is unavailable or misbehaves."""


class ReconstructionError(DarpError):
    """Keyframes, fusion or meshing cannot proceed."""


class EvaluationError(DarpError):
    """Evaluation inputs are missing or inconsistent."""


class ProcessingError(DarpError):
    """A processing run (``darp process``) cannot go on: a survey failed in one of its stages."""


class DecodeError(ValueError):
    """Low level: bytes or values that do not decode, raised deep inside a reader that does not know the file's
    name. The reader that does catches it (with the ``ValueError`` of :mod:`struct` and numpy) and raises its
    layer's :class:`FormatError` naming the file, so it never reaches a user as it is. A ``ValueError`` for that
    reason; darp raises no bare ``ValueError``."""


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread by the command line's handler so that the same cleanup
    as for Ctrl-C runs; the command exits with 128 + ``signum``."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(f"signal {self.signum}")


_deferral: dict[str, int | None] = {"depth": 0, "pending": None}


def raise_interrupted(signum: int) -> None:
    """Raise :class:`Interrupted` now, or, inside :func:`interrupts_deferred`, when that block ends."""
    if (_deferral["depth"] or 0) > 0:
        if _deferral["pending"] is None:
            _deferral["pending"] = int(signum)
        return
    raise Interrupted(signum)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold the command line's SIGTERM/SIGHUP interrupt until the block ends, then raise it.

    For steps that must not be cut in half: a spawned child process whose start is interrupted reads a
    truncated pickle from its parent and prints a traceback of its own."""
    _deferral["depth"] = (_deferral["depth"] or 0) + 1
    try:
        yield
    finally:
        _deferral["depth"] = (_deferral["depth"] or 1) - 1
        pending = _deferral["pending"]
        if not _deferral["depth"] and pending is not None:
            _deferral["pending"] = None
            raise Interrupted(pending)


class DarpWarning(UserWarning):
    """Root of darp's warnings: the input was used, but something about it needs saying. Library code
    issues them with :func:`warnings.warn`; the command line prints each once as a ``darp: warning:`` line."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else None
        self.message = message
        super().__init__(f"{path}: {message}" if path is not None else message)


class SalvagedRecordingWarning(DarpWarning):
    """A damaged recording (no usable index, cut short) was opened by salvaging what is readable;
    ``Recording.salvage`` says what is missing and what was recovered."""
