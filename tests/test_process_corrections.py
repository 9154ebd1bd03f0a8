"""The ``corrections`` switch of ``darp process``: paper mode by default, parsed the same from file and flag."""

from __future__ import annotations

from pathlib import Path

import pytest

from darp.cli._app import run
from darp.errors import ConfigError
from darp.processing.settings import (
    ADDED_LATER,
    CORRECTIONS,
    CorrectionSettings,
    ProcessSettings,
    load_settings,
    settings_from_dict,
)


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


@pytest.mark.parametrize(("group", "name"), ADDED_LATER)
def test_settings_added_later_are_absent_at_their_default_and_recorded_when_changed(group: str, name: str) -> None:
    default = ProcessSettings()
    assert name not in default.to_dict()[group]
    value = getattr(getattr(default, group), name)
    changed = settings_from_dict({group: {name: (not value) if isinstance(value, bool) else value + 1}})
    assert changed.to_dict()[group][name] != value
    assert changed.fingerprint(group) != default.fingerprint(group)
    other = "evaluation" if group == "mesh" else "mesh"
    assert changed.fingerprint(other) == default.fingerprint(other)


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


def test_time_estimator_uses_the_kinematic_model(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With kinematics on, the time-offset estimator's eq. 1 (``_arm_frames``) uses the richer model's own
    transforms and forward kinematics, not the paper model's; with it off, the paper model's."""
    import types

    import numpy as np

    from darp.formats.calibration import ArmCalibration, Calibration
    from darp.processing import pipeline

    base_kin = np.eye(4)
    base_kin[:3, 3] = [0.7, 0.0, -0.001]
    kin = {"model": "kinematic", "T_world_base": base_kin.tolist(), "T_wrist_cam": np.eye(4).tolist(),
           "joint_offsets_rad": [0.001] * 6, "joint_origin_offsets_m": np.zeros((6, 3)).tolist(),
           "joint_axis_tilts_rad": np.zeros((6, 3)).tolist(), "compliance_rad_per_nm": [0, 0.001, 0, 0, 0, 0]}
    arm = ArmCalibration(serial="1", T_world_base=np.eye(4), T_wrist_cam=np.eye(4))
    arm.kinematics = kin
    cal = Calibration(epoch="e", date="2026-12-02", arms={"arm110": arm})
    n = 3
    traj = types.SimpleNamespace(speed_noise_rad_s=0.0, poses=types.SimpleNamespace(
        t_s=np.arange(n, dtype=float), T_world_cam=np.tile(np.eye(4), (n, 1, 1)), joint_speed_rad_s=np.zeros(n)))
    poses = types.SimpleNamespace(trajectories={"arm110": traj})
    log = types.SimpleNamespace(times=lambda a: np.arange(n, dtype=float), joints=lambda a: np.zeros((n, 6)))
    recording = types.SimpleNamespace(stream=lambda k: types.SimpleNamespace(intrinsics=object()), depth_scale=0.001)
    for spec, expect_kin in (("kinematics,time", True), ("time", False)):
        job = pipeline.SurveyJob(survey=types.SimpleNamespace(arms=("arm110",), arm_poses=lambda: log),
                                 out=tmp_path, calibration=cal, calibration_path=None,
                                 settings=ProcessSettings(corrections=CorrectionSettings.parse(spec)))
        monkeypatch.setattr(job, "recording", lambda a: recording)
        frames = job._arm_frames("arm110", poses)
        assert np.allclose(frames.T_world_base, base_kin if expect_kin else np.eye(4))
        assert (frames.fk_batch is not None) == expect_kin
        assert np.allclose(frames.joint_offsets_rad, 0.001 if expect_kin else 0.0)
