"""Per-survey processing as a plain function of paths (what one Ray task runs).

A task never raises for a survey that fails: it returns that survey's
:class:`darp.processing.batch.SurveyOutcome` (failed, with its stage and reason), so a batch on Ray
goes on past a failed survey exactly as the local loop does. A task whose process crashed (a signal,
native code) on every one of its tries becomes a failed outcome too, at the stage ``worker``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from darp.errors import DarpError
from darp.processing.batch import DONE, FAILED, SurveyOutcome, outcome_of_failure, process_folder
from darp.processing.settings import ProcessSettings, settings_from_dict

RECOVERABLE = (DarpError, ValueError, RuntimeError, ArithmeticError, MemoryError, OSError)


def process_one(folder: str, out: str, calibration: str | None, truth_poses: bool, settings_values: dict[str, Any],
                resume: bool) -> SurveyOutcome:
    """``darp process`` of one survey into ``out`` (the calibration given, or the twin's true one).

    ``settings_values`` is :meth:`ProcessSettings.to_dict` (plain data travels to a worker safely)."""
    survey_path, target = Path(folder), Path(out)
    try:
        results = process_folder(survey_path, target, calibration, settings=settings_from_dict(settings_values),
                                 truth_poses=truth_poses, resume=resume)
    except RECOVERABLE as err:
        return outcome_of_failure(survey_path, target, err)
    return SurveyOutcome(survey_path.name, survey_path, target, DONE, warnings=list(results.get("warnings") or []))


def process_batch(folders: Sequence[Path], out: Path, calibration: Path | None, truth_poses: bool,
                  settings: ProcessSettings, resume: bool, executor: Any, progress: Any = None) -> list[SurveyOutcome]:
    """:func:`process_one` of every survey folder into ``out/<name>`` on ``executor`` (one task each)."""
    from darp.batch.executor import run_tasks

    calls = [(str(f), str(out / f.name), None if calibration is None else str(calibration), truth_poses,
              settings.to_dict(), resume) for f in folders]
    return list(run_tasks(process_one, calls, executor, progress=progress, failure=crashed_outcome,
                          costs=[survey_bytes(f) for f in folders]))


def survey_bytes(folder: Path) -> int:
    """A survey's size on disk (its bags dominate): the cost by which a batch submits the largest first."""
    try:
        return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file())
    except OSError:  # a folder that cannot be read fails in its task, with its reason
        return 0


def crashed_outcome(args: tuple[Any, ...], err: BaseException) -> SurveyOutcome:
    """The failed outcome of a :func:`process_one` call whose process died on every try."""
    survey_path, target = Path(args[0]), Path(args[1])
    reason = err.message if isinstance(err, DarpError) else str(err)
    return SurveyOutcome(survey_path.name, survey_path, target, FAILED, "worker", reason.splitlines()[0])


__all__ = ["crashed_outcome", "process_batch", "process_one", "survey_bytes"]
