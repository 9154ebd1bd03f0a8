"""The ``corrections`` switch of ``darp process``: paper mode by default, parsed the same from file and flag."""

from __future__ import annotations

from pathlib import Path

import pytest

from darp.cli._app import run
from darp.errors import ConfigError
from darp.processing.settings import CORRECTIONS, CorrectionSettings, ProcessSettings, load_settings


def test_paper_mode_is_the_default() -> None:
    assert ProcessSettings().corrections.applied == ()
    assert ProcessSettings().corrections.label == "paper"


@pytest.mark.parametrize(("spec", "applied"), [
    ("paper", ()), ("none", ()), ("all", CORRECTIONS), ("depth", ("depth",)),
    ("refine, kinematics", ("kinematics", "refine")), ("TIME,depth", ("time", "depth")),
])
def test_specs_parse(spec: str, applied: tuple[str, ...]) -> None:
    assert CorrectionSettings.parse(spec).applied == applied


@pytest.mark.parametrize("spec", ["", "depht", "all,depth", "paper,refine"])
def test_bad_specs_name_the_problem(spec: str) -> None:
    with pytest.raises(ConfigError, match="corrections"):
        CorrectionSettings.parse(spec)


def test_labels() -> None:
    assert CorrectionSettings.parse("all").label == "all"
    assert CorrectionSettings.parse("refine,depth").label == "depth+refine"


def test_a_settings_file_switches_corrections_and_rejects_unknown_keys(tmp_path: Path) -> None:
    good = tmp_path / "good.yaml"
    good.write_text("corrections: {depth: true, refine: true}\n")
    assert load_settings(good).corrections.applied == ("depth", "refine")
    bad = tmp_path / "bad.yaml"
    bad.write_text("corrections: {colour: true}\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_settings(bad)


def test_a_bad_flag_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = run(["process", str(tmp_path), "--truth-poses", "--out", str(tmp_path / "o"), "--corrections", "magic"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("darp: error: Invalid value for '--corrections'") and "magic" in err


def test_time_shifted_poses_keep_the_kinematic_model(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With kinematics and time both on, the second (time-shifted) eq. 1 still uses the richer model."""
    import types

    import numpy as np

    from darp.formats.calibration import ArmCalibration, Calibration
    from darp.processing import pipeline

    calls: list[dict[str, object]] = []

    def fake_recover(*args: object, **kwargs: object) -> types.SimpleNamespace:
        calls.append(kwargs)
        return types.SimpleNamespace(time_alignment={})

    monkeypatch.setattr(pipeline, "recover_survey_poses", fake_recover)
    arm = ArmCalibration(serial="1", T_world_base=np.eye(4), T_wrist_cam=np.eye(4))
    arm.time_offset_s = 0.004  # from the calibration: no estimate from frames needed
    cal = Calibration(epoch="e", date="2026-12-02", arms={"arm110": arm})
    job = pipeline.SurveyJob(survey=types.SimpleNamespace(arms=("arm110",)), out=tmp_path, calibration=cal,
                             calibration_path=None,
                             settings=ProcessSettings(corrections=CorrectionSettings.parse("kinematics,time")))
    job.poses()
    assert len(calls) == 2
    assert all(c["kinematics"] is True for c in calls)
    assert calls[0]["time_offsets_s"] is None and calls[1]["time_offsets_s"] == {"arm110": 0.004}
