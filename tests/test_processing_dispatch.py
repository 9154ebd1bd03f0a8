"""One dispatch for darp process in this process and for a Ray task (darp.processing.batch.process_folder)."""

from __future__ import annotations

from pathlib import Path

import pytest

from darp.batch.tasks import process_one
from darp.processing.batch import FAILED, process_folder
from darp.processing.runner import StageFailure
from darp.processing.settings import ProcessSettings


def test_a_survey_without_truth_or_calibration_fails_at_open_the_same_way_both_ways(tmp_path: Path) -> None:
    survey = tmp_path / "s0"
    survey.mkdir()
    with pytest.raises(StageFailure) as info:  # what darp process's loop records
        process_folder(survey, tmp_path / "out" / "s0", None, truth_poses=True)
    assert info.value.stage == "open" and "no truth/calibration.json" in info.value.reason
    outcome = process_one(str(survey), str(tmp_path / "out" / "s0"), None, True, ProcessSettings().to_dict(), False)
    assert (outcome.status, outcome.stage, outcome.name) == (FAILED, "open", "s0")  # what a Ray task returns
    assert outcome.reason == info.value.reason


def test_a_missing_calibration_file_is_named(tmp_path: Path) -> None:
    survey = tmp_path / "s1"
    survey.mkdir()
    outcome = process_one(str(survey), str(tmp_path / "o"), str(tmp_path / "cal.json"), False,
                          ProcessSettings().to_dict(), False)
    assert outcome.status == FAILED and outcome.stage == "open" and "cal.json" in (outcome.reason or "")
