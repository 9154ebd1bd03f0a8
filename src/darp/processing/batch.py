"""A batch of surveys: each processed on its own, a failure named and contained, the batch summary.

:func:`process_folder` is the one-survey unit that ``darp process`` (in this process) and a Ray task
(:mod:`darp.batch.tasks`) both call: it decides between a folder written by ``darp import`` and a
DARP survey, opens the calibration (the one given, or the twin's true one), and returns the survey's
``results.json`` document or raises a :class:`darp.errors.DarpError` whose one line names the survey,
the stage and the reason. :func:`process_survey_folder` is its DARP-survey half.
:func:`process_batch` calls it for every survey, goes on past a failure, and returns one
:class:`SurveyOutcome` per survey; ``darp process`` writes the summary (failed surveys listed) and exits
2 when any failed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from darp.errors import DarpError
from darp.formats.calibration import Calibration
from darp.processing.imported import is_imported, process_imported
from darp.processing.job import ProgressFn, open_job, survey_calibration
from darp.processing.results import read_results
from darp.processing.runner import StageFailure, process_survey
from darp.processing.settings import ProcessSettings
from darp.processing.stages import PROCESS_STAGES

DONE, FAILED = "done", "failed"


@dataclass
class SurveyOutcome:
    """What became of one survey of a batch."""

    name: str
    survey_path: Path
    out: Path
    status: str  # done | failed
    stage: str | None = None  # the failed stage ("open" when the survey could not be opened)
    reason: str | None = None  # the one-line reason of a failure
    warnings: list[str] = field(default_factory=list)  # implausible results, partial survey ...

    @property
    def message(self) -> str:
        """One line: survey, stage, reason (for a failure) or the survey and its warnings."""
        if self.status == FAILED:
            return f"survey {self.name} ({self.survey_path}): {self.stage} failed: {self.reason}"
        return f"survey {self.name}: " + ("; ".join(self.warnings) if self.warnings else "ok")

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "survey_path": str(self.survey_path), "folder": self.out.name,
                "status": self.status, "stage": self.stage, "reason": self.reason, "warnings": list(self.warnings)}


def process_survey_folder(survey_path: str | Path, out: str | Path, calibration: Calibration, *,
                          calibration_path: Path | None = None, settings: ProcessSettings | None = None,
                          truth_poses: bool = False, resume: bool = False,
                          progress: ProgressFn | None = None,
                          on_note: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Process one survey into ``out`` (its own output folder); returns its ``results.json`` document.

    Raises a :class:`darp.errors.DarpError` naming the survey, the stage and the reason on failure
    (the output folder is then marked ``UNFINISHED.txt``). ``on_note`` receives the survey's notes
    (no manip_envelope.json, a partial survey ...) before processing starts.
    """
    try:
        job = open_job(survey_path, out, calibration, calibration_path=calibration_path, settings=settings,
                       truth_poses=truth_poses, progress=progress)
    except DarpError as err:
        raise StageFailure(Path(survey_path).name, "open", str(err), err.path) from err
    for note in job.survey.notes:
        if on_note is not None:
            on_note(note)
    process_survey(job, PROCESS_STAGES, resume=resume)
    return read_results(job.out)


def process_folder(survey_path: str | Path, out: str | Path, calibration_path: str | Path | None, *,
                   settings: ProcessSettings | None = None, truth_poses: bool = False, resume: bool = False,
                   calibration: Calibration | None = None, progress: ProgressFn | None = None,
                   on_note: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Process any survey folder into ``out``: a ``darp import`` folder from its keyframes, a DARP survey
    with ``calibration_path`` (the twin's true calibration when None; ``calibration``: that file already
    read). Returns its ``results.json`` document; raises like :func:`process_survey_folder`."""
    survey_path, settings = Path(survey_path), settings or ProcessSettings()
    if is_imported(survey_path):
        return process_imported(survey_path, Path(out), settings.fusion_used, settings.mesh_used, settings.surface)
    if settings.surface.method == "measured":
        raise StageFailure(survey_path.name, "open", "surface.method measured applies to imported surveys only "
                           "(darp import); DARP surveys take auto or paper", None)
    cal_path = None if calibration_path is None else Path(calibration_path)
    if calibration is None:
        try:
            calibration = survey_calibration(survey_path, cal_path)
        except DarpError as err:
            raise StageFailure(survey_path.name, "open", str(err), err.path) from err
    return process_survey_folder(survey_path, out, calibration, calibration_path=cal_path, settings=settings,
                                 truth_poses=truth_poses, resume=resume, progress=progress, on_note=on_note)


def outcome_of_failure(survey_path: Path, out: Path, err: BaseException) -> SurveyOutcome:
    """A failed :class:`SurveyOutcome` from the error a survey raised."""
    if isinstance(err, StageFailure):
        return SurveyOutcome(survey_path.name, survey_path, out, FAILED, err.stage, err.reason)
    reason = str(err) if isinstance(err, DarpError) else f"{type(err).__name__}: {err}"
    return SurveyOutcome(survey_path.name, survey_path, out, FAILED, "open", reason.splitlines()[0] if reason else "")


def process_batch(folders: Sequence[Path], out: Path, run_one: Callable[[Path, Path], dict[str, Any]], *,
                  on_outcome: Callable[[SurveyOutcome], None] | None = None) -> list[SurveyOutcome]:
    """Run ``run_one(survey_folder, out/<name>)`` for each survey, going on past failures.

    A :class:`darp.errors.DarpError` (or a library error escaping a stage) fails that survey only;
    KeyboardInterrupt and SystemExit end the batch.
    """
    outcomes: list[SurveyOutcome] = []
    for folder in folders:
        target = out / folder.name
        try:
            results = run_one(folder, target)
        except (DarpError, ValueError, RuntimeError, ArithmeticError, MemoryError, OSError) as err:
            outcome = outcome_of_failure(folder, target, err)
        else:
            outcome = SurveyOutcome(folder.name, folder, target, DONE, warnings=list(results.get("warnings") or []))
        outcomes.append(outcome)
        if on_outcome is not None:
            on_outcome(outcome)
    return outcomes


__all__ = ["DONE", "FAILED", "SurveyOutcome", "outcome_of_failure", "process_batch", "process_folder",
           "process_survey_folder"]
