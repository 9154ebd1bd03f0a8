"""Per-survey processing as a plain function of paths (what one Ray task runs)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from darp.formats.calibration import read_calibration
from darp.formats.survey import open_survey
from darp.processing.pipeline import SurveyJob, process_survey
from darp.processing.settings import ProcessSettings, load_settings


def process_one(folder: str, out: str, calibration: str | None, truth_poses: bool, settings_file: str | None,
                resume: bool) -> str:
    """``darp process`` of one survey into ``out`` (the calibration's serials, or the twin's true one)."""
    from darp.processing.results import PROCESS_STAGES

    survey_path = Path(folder)
    cal = read_calibration(calibration if calibration is not None else survey_path / "truth" / "calibration.json")
    settings = ProcessSettings() if settings_file is None else load_settings(Path(settings_file))
    survey = open_survey(survey_path, serial_to_arm={arm.serial: name for name, arm in cal.arms.items()})
    job = SurveyJob(survey=survey, out=Path(out), calibration=cal,
                    calibration_path=None if calibration is None else Path(calibration), settings=settings,
                    truth_poses=truth_poses)
    try:
        process_survey(job, PROCESS_STAGES, resume=resume)
    finally:
        job.close()
    return str(job.out)


def process_batch(folders: Sequence[Path], out: Path, calibration: Path | None, truth_poses: bool,
                  settings_file: Path | None, resume: bool, executor: Any, progress: Any = None) -> list[Path]:
    """:func:`process_one` of every survey folder into ``out/<name>`` on ``executor`` (one task each)."""
    from darp.batch.executor import run_tasks

    calls = [(str(f), str(out / f.name), None if calibration is None else str(calibration), truth_poses,
              None if settings_file is None else str(settings_file), resume) for f in folders]
    return [Path(p) for p in run_tasks(process_one, calls, executor, progress=progress)]


__all__ = ["process_batch", "process_one"]
