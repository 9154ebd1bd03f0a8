"""Per-survey processing as a plain function of paths (what one Ray task runs).

A task never raises for a survey that fails: it returns that survey's
:class:`darp.processing.batch.SurveyOutcome` (failed, with its stage and reason), so a batch on Ray
goes on past a failed survey exactly as the local loop does.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from darp.errors import DarpError
from darp.formats.calibration import read_calibration
from darp.processing.batch import DONE, SurveyOutcome, outcome_of_failure, process_survey_folder
from darp.processing.imported import is_imported, process_imported
from darp.processing.settings import ProcessSettings, settings_from_dict

RECOVERABLE = (DarpError, ValueError, RuntimeError, ArithmeticError, MemoryError, OSError)


def process_one(folder: str, out: str, calibration: str | None, truth_poses: bool, settings_values: dict[str, Any],
                resume: bool) -> SurveyOutcome:
    """``darp process`` of one survey into ``out`` (the calibration given, or the twin's true one).

    ``settings_values`` is :meth:`ProcessSettings.to_dict` (plain data travels to a worker safely)."""
    survey_path, target = Path(folder), Path(out)
    try:
        settings = settings_from_dict(settings_values)
        if is_imported(survey_path):
            results = process_imported(survey_path, target, settings.fusion, settings.mesh)
        else:
            cal_path = Path(calibration) if calibration is not None else survey_path / "truth" / "calibration.json"
            results = process_survey_folder(survey_path, target, read_calibration(cal_path),
                                            calibration_path=None if calibration is None else cal_path,
                                            settings=settings, truth_poses=truth_poses, resume=resume)
    except RECOVERABLE as err:
        return outcome_of_failure(survey_path, target, err)
    return SurveyOutcome(survey_path.name, survey_path, target, DONE, warnings=list(results.get("warnings") or []))


def process_batch(folders: Sequence[Path], out: Path, calibration: Path | None, truth_poses: bool,
                  settings: ProcessSettings, resume: bool, executor: Any, progress: Any = None) -> list[SurveyOutcome]:
    """:func:`process_one` of every survey folder into ``out/<name>`` on ``executor`` (one task each)."""
    from darp.batch.executor import run_tasks

    calls = [(str(f), str(out / f.name), None if calibration is None else str(calibration), truth_poses,
              settings.to_dict(), resume) for f in folders]
    return list(run_tasks(process_one, calls, executor, progress=progress))


__all__ = ["process_batch", "process_one"]
