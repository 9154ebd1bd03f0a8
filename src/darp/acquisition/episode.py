"""The episode folder of one survey: built in place, then accepted, rejected or left marked partial.

::

    <out>/<NAME>.partial/     while the survey runs (and after an interruption: PARTIAL.txt says why)
    <out>/<NAME>/             accepted: the DARP survey folder
    <out>/<NAME>.rejected/    rejected or terminated: REJECTED.txt says why (verification report beside it)

Every folder holds ``events.jsonl``: one JSON object per line for every decision, with ``kind``,
``rig_time_s`` (the rig's clock: simulated on the twin, the host clock on hardware) and
``wall_time_s`` (the host's wall clock), flushed line by line so that an interrupted run keeps them,
and ``outcome.json`` once the run ends (status, reason, message).

An existing ``NAME``, ``NAME.partial`` or ``NAME.rejected`` is never silently overwritten: creating
the episode is an error unless ``overwrite`` is given; even then a previous episode is only removed
when the new one is finalised (a stale ``NAME.partial`` at once), so an interrupted re-run never
destroys an accepted survey.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from darp.backend import Clock
from darp.errors import AcquisitionError
from darp.formats.atomic import write_json_atomic, write_text_atomic
from darp.formats.io_input import LIMITS
from darp.formats.schema import to_jsonable
from darp.formats.text import read_utf8_text

EVENTS_FILE = "events.jsonl"
OUTCOME_FILE = "outcome.json"
REJECTED_FILE = "REJECTED.txt"
PARTIAL_FILE = "PARTIAL.txt"
VERIFICATION_FILE = "verification.json"
PARTIAL_SUFFIX = ".partial"
REJECTED_SUFFIX = ".rejected"


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


class EventLog:
    """Append-only JSON-lines log of decisions; call it as ``events(kind, **fields)``."""

    def __init__(self, path: Path, clock: Clock | None = None) -> None:
        self.path = Path(path)
        self.clock = clock
        self._handle: TextIO | None = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 (kept open)
        self.count = 0

    def __call__(self, kind: str, **fields: Any) -> None:
        if self._handle is None:
            return
        record: dict[str, Any] = {"kind": kind}
        if self.clock is not None:
            record["rig_time_s"] = round(self.clock.now(), 6)
        record["wall_time_s"] = round(time.time(), 6)
        record.update(fields)
        self._handle.write(json.dumps(to_jsonable(record), default=_plain, sort_keys=False) + "\n")
        self._handle.flush()
        self.count += 1

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None


def read_events(path: str | Path) -> list[dict[str, Any]]:
    """The events of an episode folder (or of an ``events.jsonl`` file); a cut-short last line is dropped."""
    path = Path(path)
    if path.is_dir():
        path = path / EVENTS_FILE
    out = []
    lines = read_utf8_text(path, "an events file", limit=LIMITS["json"]).splitlines()
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as err:
            if number == len(lines):  # the run died while writing its last line
                break
            raise AcquisitionError(f"line {number}: not JSON ({err.msg})", path) from None
    return out


def check_name(name: str) -> str:
    """A survey name must be a plain folder name."""
    if not name or name in (".", "..") or name.startswith(".") or "/" in name or "\\" in name:
        raise AcquisitionError(f"survey name {name!r} must be a plain folder name (no slashes, not hidden)")
    for suffix in (PARTIAL_SUFFIX, REJECTED_SUFFIX):
        if name.endswith(suffix):
            raise AcquisitionError(f"survey name {name!r} must not end in {suffix}")
    return name


class Episode:
    """One survey's folder through its life: partial -> accepted | rejected (or left partial)."""

    def __init__(self, out: str | Path, name: str, *, overwrite: bool = False, clock: Clock | None = None) -> None:
        self.out = Path(out)
        self.name = check_name(name)
        self.overwrite = overwrite
        self.final_path = self.out / name
        self.partial_path = self.out / (name + PARTIAL_SUFFIX)
        self.rejected_path = self.out / (name + REJECTED_SUFFIX)
        existing = [p for p in (self.final_path, self.partial_path, self.rejected_path) if p.exists()]
        if existing and not overwrite:
            what = ", ".join(str(p) for p in existing)
            raise AcquisitionError(f"{what} already exists; choose another name or pass --overwrite")
        for old in existing:  # --overwrite deletes only folders an episode wrote
            if old.is_dir() and any(old.iterdir()) and not (old / EVENTS_FILE).is_file():
                raise AcquisitionError(f"is not a survey folder darp wrote (no {EVENTS_FILE}): refusing to delete "
                                       "it with --overwrite", old)
        if self.partial_path.exists():
            shutil.rmtree(self.partial_path)
        self.partial_path.mkdir(parents=True)
        # First file in, last file out: a folder holding PARTIAL.txt is unfinished, even after a SIGKILL.
        try:
            (self.partial_path / PARTIAL_FILE).write_text(
                "partial: running, or killed while running (the survey is incomplete)\n", encoding="utf-8")
        except OSError:  # a full or read-only disk: nothing was recorded, leave nothing behind
            shutil.rmtree(self.partial_path, ignore_errors=True)
            raise
        self.path = self.partial_path
        self.status = "running"
        self.events = EventLog(self.partial_path / EVENTS_FILE, clock)
        self.events("episode_start", name=name, folder=str(self.partial_path), overwrite=overwrite)

    # -- files ------------------------------------------------------------------------------------
    def write_json(self, filename: str, payload: Any) -> Path:
        """Write a JSON file into the episode folder, atomically."""
        target = self.path / filename
        write_json_atomic(target, to_jsonable(payload))
        return target

    def _outcome(self, status: str, reason: str, message: str, extra: dict[str, Any] | None) -> None:
        self.write_json(OUTCOME_FILE, {"name": self.name, "status": status, "reason": reason, "message": message,
                                       **(extra or {})})

    # -- endings ----------------------------------------------------------------------------------
    def _move_to(self, target: Path) -> Path:
        self.events.close()
        for old in (self.final_path, self.rejected_path):
            if old.exists():  # only reachable with overwrite (checked on creation)
                shutil.rmtree(old)
        self.partial_path.rename(target)
        self.path = target
        (target / PARTIAL_FILE).unlink(missing_ok=True)  # last: the outcome is written, the folder is whole
        return target

    def accept(self, message: str = "", extra: dict[str, Any] | None = None) -> Path:
        """Rename the folder to ``<out>/<NAME>``."""
        self.events("episode_accepted", message=message)
        self._outcome("accepted", "", message, extra)
        self.status = "accepted"
        return self._move_to(self.final_path)

    def reject(self, reason: str, message: str, report: dict[str, Any] | None = None,
               extra: dict[str, Any] | None = None) -> Path:
        """Rename the folder to ``<out>/<NAME>.rejected`` with ``REJECTED.txt`` (and the verification)."""
        self.events("episode_rejected", reason=reason, message=message)
        lines = [f"rejected: {reason}", message]
        if report is not None:
            self.write_json(VERIFICATION_FILE, report)
            failed = [c for c in report.get("checks", []) if not c.get("passed", True)]
            lines += [f"failed check {c['name']}: {c.get('detail', '')}" for c in failed]
        write_text_atomic(self.path / REJECTED_FILE, "\n".join(lines) + "\n")
        self._outcome("rejected", reason, message, extra)
        self.status = "rejected"
        return self._move_to(self.rejected_path)

    def mark_partial(self, reason: str, message: str, extra: dict[str, Any] | None = None) -> Path:
        """Leave the folder as ``<NAME>.partial`` with ``PARTIAL.txt`` (interrupted or failed run)."""
        self.events("episode_partial", reason=reason, message=message)
        write_text_atomic(self.path / PARTIAL_FILE, f"partial: {reason}\n{message}\n"
                          "The files here were closed properly and can be read; the survey is incomplete.\n")
        self._outcome("partial", reason, message, extra)
        self.events.close()
        self.status = "partial"
        return self.path


__all__ = [
    "EVENTS_FILE",
    "OUTCOME_FILE",
    "PARTIAL_FILE",
    "REJECTED_FILE",
    "VERIFICATION_FILE",
    "Episode",
    "EventLog",
    "check_name",
    "read_events",
]
