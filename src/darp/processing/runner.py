"""The stage runner: a job goes through named stages, each declaring the files it writes.

A :class:`Stage` is ``run(job) -> summary`` with its ``outputs`` (paths relative to the job's output
folder: a tuple, or a function of the job when they depend on it, e.g. one cloud per arm) and the
settings groups its result depends on. :func:`process_survey` runs the stages in order; it knows
nothing of surveys beyond the small :class:`RunJob` interface, so it is tested with fake stages.

**Resume.** After each stage ``stages.json`` records the stage's fingerprint (a hash chaining the
previous stage's fingerprint, the job's identity and the settings groups the stage uses) and its
summary. With ``resume`` a stage whose fingerprint matches and whose outputs all exist is skipped;
once a stage runs, every later stage runs too.

**Nothing unfinished looks finished.** ``UNFINISHED.txt`` is written into the output folder before the
first stage runs and removed only when the last stage has completed; it says which stage was running
or failed and why, so an interrupted or failed run (SIGKILL included) leaves a folder that every reader
(:func:`unfinished_reason`: ``darp report``, the batch summary) treats as unfinished. A stage writes its
files under temporary names (:func:`staged_outputs`) renamed when all are written; when a stage fails,
its outputs and those of every later stage are removed and :class:`StageFailure` is raised: one line
naming the survey, the stage and the reason.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from darp.errors import DarpError, DarpWarning, FormatError, ProcessingError
from darp.formats.atomic import UNFINISHED_FILE, atomic_path, write_json_atomic, write_text_atomic
from darp.formats.io_input import marker_text
from darp.formats.schema import load_json_object

STAGES_FILE = "stages.json"


class RunJob(Protocol):
    """What the runner needs of a job: where it writes, its name, what identifies its inputs, a hash of
    the settings groups a stage uses, progress, and a way to release what it opened."""

    out: Path

    @property
    def name(self) -> str: ...

    def identity(self) -> dict[str, Any]: ...

    def settings_fingerprint(self, groups: Sequence[str]) -> str: ...

    def report(self, stage: str, done: float, total: float | None) -> None: ...

    def close(self) -> None: ...


J = TypeVar("J", bound=RunJob)


@dataclass(frozen=True)
class Stage(Generic[J]):
    """A named step: ``run(job) -> summary``; ``outputs`` (paths relative to ``job.out``, or a function of
    the job giving them) exist once it is done and are removed when it or an earlier stage fails."""

    name: str
    run: Callable[[J], dict[str, Any]]
    outputs: Sequence[str] | Callable[[J], Sequence[str]]
    settings_groups: tuple[str, ...] = ()

    def outputs_of(self, job: J) -> tuple[str, ...]:
        """This stage's outputs for ``job``."""
        return tuple(self.outputs(job) if callable(self.outputs) else self.outputs)


class StageFailure(ProcessingError):
    """A survey failed in one stage: ``survey``, ``stage`` and ``reason`` (the original one-line error)."""

    def __init__(self, survey: str, stage: str, reason: str, path: str | Path | None = None) -> None:
        self.survey, self.stage, self.reason = survey, stage, reason
        super().__init__(f"survey {survey}: {stage} failed: {reason}")
        self.file = Path(path) if path is not None else None


@contextlib.contextmanager
def staged_outputs(folder: Path, names: Sequence[str]) -> Iterator[dict[str, Path]]:
    """Write a stage's files under temporary names (unique, ending in ``.partial``: two runs never share
    one), renamed to their final names only when every one is written; on an error the temporary files
    go and no final name is touched."""
    with contextlib.ExitStack() as stack:
        yield {name: stack.enter_context(atomic_path(folder / name)) for name in names}


# -- stages.json and UNFINISHED.txt ---------------------------------------------------------------------------
def stage_fingerprints(job: RunJob, stages: Sequence[Stage[Any]]) -> dict[str, str]:
    """Each stage's fingerprint: a hash of the previous one, its name and the settings it uses."""
    previous = hashlib.sha256(json.dumps(job.identity(), sort_keys=True, default=str).encode()).hexdigest()
    out = {}
    for stage in stages:
        groups = job.settings_fingerprint(stage.settings_groups) if stage.settings_groups else ""
        previous = hashlib.sha256(f"{previous}|{stage.name}|{groups}".encode()).hexdigest()[:16]
        out[stage.name] = previous
    return out


def read_stage_state(out: Path, *, strict: bool = False) -> dict[str, Any]:
    """``stages.json`` of an output folder ({} when absent). A file that is unreadable or not of its shape is
    {}: nothing is skipped; with ``strict`` (``--resume``, which trusts it) a DarpWarning names it and says so."""
    path = out / STAGES_FILE
    if not path.exists():
        return {}
    try:
        state = load_json_object(path)
        stages = state.get("stages", {})
        if not isinstance(stages, dict) or not all(isinstance(v, dict) for v in stages.values()):
            raise FormatError("'stages' must map each stage name to its record", path)
    except FormatError as err:
        if strict:
            warnings.warn(DarpWarning(f"{err.message}: not trusted, every stage runs again", path), stacklevel=2)
        return {}
    return state


def unfinished_reason(out: str | Path) -> str | None:
    """The first line of ``UNFINISHED.txt`` in an output folder, or None when the run completed."""
    marker = Path(out) / UNFINISHED_FILE
    if not marker.exists():
        return None
    text = marker_text(marker).strip()  # a marker that cannot be read (a pipe, a folder) still marks
    return text.splitlines()[0] if text else "unfinished"


def _mark_unfinished(out: Path, line: str) -> None:
    write_text_atomic(out / UNFINISHED_FILE, f"{line}\nThis folder's processing did not complete: its outputs "
                      "are not results. Run darp process again (--resume keeps the completed stages).\n")


# -- the run --------------------------------------------------------------------------------------------------
def process_survey(job: J, stages: Sequence[Stage[J]], *, resume: bool = False) -> dict[str, Any]:
    """Run ``stages`` in order on one job; returns ``{stage: {"skipped", "seconds", "summary"}}``.

    ``UNFINISHED.txt`` marks the output folder until the last stage completes. A stage that fails
    raises :class:`StageFailure` (survey, stage, reason on one line), leaves ``stages.json`` and the
    marker saying so, and removes its outputs and those of the later stages. ``job.close()`` is called
    at the end, whatever happened.
    """
    job.out.mkdir(parents=True, exist_ok=True)
    fingerprints = stage_fingerprints(job, stages)
    state = read_stage_state(job.out, strict=True) if resume else {}
    stages_state: dict[str, Any] = dict(state.get("stages", {}))
    report: dict[str, Any] = {}
    _mark_unfinished(job.out, f"running: {', '.join(s.name for s in stages)}")
    try:
        _run_stages(job, stages, resume, fingerprints, stages_state, report)
    finally:
        job.close()
    (job.out / UNFINISHED_FILE).unlink(missing_ok=True)
    return report


def _is_done(before: Any, fingerprint: str, outputs: Sequence[Path], out: Path) -> bool:
    """A stage is done when its fingerprint matches and every file it declared, and every file it wrote (its
    record's ``files``: keyframe .npz files as well as keyframes.json), is still there."""
    if not (isinstance(before, dict) and before.get("fingerprint") == fingerprint):
        return False
    written = before.get("files", [])
    if not isinstance(written, list) or not all(isinstance(f, str) for f in written):
        return False
    return all(o.exists() for o in outputs) and all((out / f).is_file() for f in written)


def _files(out: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``out`` (relative path -> size, mtime) but the runner's own."""
    found = {}
    for p in out.rglob("*"):
        if p.is_file() and p.name not in (STAGES_FILE, UNFINISHED_FILE) and not p.name.endswith(".partial"):
            st = p.stat()
            found[p.relative_to(out).as_posix()] = (st.st_size, st.st_mtime_ns)
    return found


def _run_stages(job: J, stages: Sequence[Stage[J]], resume: bool, fingerprints: dict[str, str],
                stages_state: dict[str, Any], report: dict[str, Any]) -> None:
    rerun = False
    for stage in stages:
        before = stages_state.get(stage.name, {})
        if resume and not rerun and _is_done(before, fingerprints[stage.name],
                                             [job.out / o for o in stage.outputs_of(job)], job.out):
            report[stage.name] = {"skipped": True, "seconds": before.get("seconds"), "summary": before.get("summary")}
            job.report(stage.name, 1, 1)
            continue
        rerun = True
        start = time.perf_counter()
        existing = _files(job.out)
        _mark_unfinished(job.out, f"running: {stage.name}")
        try:
            summary = stage.run(job)
        except DarpError as err:
            _fail(job, stages, stage, stages_state, str(err), err.path)
        except OSError as err:  # a full or read-only disk while the stage writes: this stage's failure, named
            where = f"{os.fsdecode(err.filename)}: " if err.filename is not None else ""
            _fail(job, stages, stage, stages_state, f"{where}{(err.strerror or str(err)).lower()}",
                  None if err.filename is None else Path(os.fsdecode(err.filename)))
        except (ValueError, RuntimeError, ArithmeticError, IndexError, KeyError, MemoryError) as err:
            # a library failing inside a stage (Open3D, numpy, ...): still this survey's, named and contained
            _fail(job, stages, stage, stages_state, f"{type(err).__name__}: {err}".splitlines()[0], None)
        seconds = round(time.perf_counter() - start, 3)
        written = sorted(f for f, st in _files(job.out).items() if existing.get(f) != st)
        stages_state[stage.name] = {"fingerprint": fingerprints[stage.name], "seconds": seconds, "summary": summary,
                                    "files": written}
        for later in stages[stages.index(stage) + 1:]:
            stages_state.pop(later.name, None)  # stale once this stage changed
        write_json_atomic(job.out / STAGES_FILE, {"survey": job.name, "stages": stages_state})
        report[stage.name] = {"skipped": False, "seconds": seconds, "summary": summary}


def _fail(job: J, stages: Sequence[Stage[J]], stage: Stage[J], stages_state: dict[str, Any], reason: str,
          path: Path | None) -> None:
    """Record the failure (stages.json, UNFINISHED.txt), remove the outputs of the failed stage and of every
    later one, raise StageFailure."""
    for later in stages[stages.index(stage):]:
        stages_state.pop(later.name, None)
        for output in later.outputs_of(job):
            target = job.out / output
            if target.is_file():
                target.unlink()
    with contextlib.suppress(OSError):  # on a full disk these may fail too: the marker of the run start stays
        write_json_atomic(job.out / STAGES_FILE, {"survey": job.name, "stages": stages_state,
                                                  "failed": {"stage": stage.name, "reason": reason}})
        _mark_unfinished(job.out, f"failed: {stage.name}: {reason}")
    raise StageFailure(job.name, stage.name, reason, path)


__all__ = [
    "STAGES_FILE",
    "UNFINISHED_FILE",
    "RunJob",
    "Stage",
    "StageFailure",
    "process_survey",
    "read_stage_state",
    "stage_fingerprints",
    "staged_outputs",
    "unfinished_reason",
]
