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


def test_fusion_rules_apply_only_when_switched_on_and_only_where_the_user_kept_the_default() -> None:
    from darp.processing.settings import DEPTH_FILTER_RULES, FUSION_RULES

    paper = ProcessSettings()
    assert paper.fusion_used == paper.fusion  # paper mode: the paper's fusion, unchanged
    on = settings_from_dict({"corrections": {"fusion": True}})
    used = on.fusion_used
    assert all(getattr(used, k) == v for k, v in FUSION_RULES.items())
    assert all(getattr(used.depth, k) == v for k, v in DEPTH_FILTER_RULES.items())
    assert used.voxel_size_m == paper.fusion.voxel_size_m and used.min_frames == paper.fusion.min_frames
    assert on.to_dict()["fusion"] == paper.to_dict()["fusion"]  # the rules live in the switch, not the group
    given = settings_from_dict({"corrections": {"fusion": True},
                                "fusion": {"sor_local_ratio": 3.0, "depth": {"edge_margin_px": 1}}})
    assert given.fusion_used.sor_local_ratio == 3.0 and given.fusion_used.depth.edge_margin_px == 1
    assert given.fusion_used.arm_support_from_fused == FUSION_RULES["arm_support_from_fused"]
    assert CorrectionSettings.parse("all").fusion and "fusion" in CorrectionSettings.parse("fusion,depth").applied
    from darp.processing.results import rules_used

    assert rules_used(given) == {"fusion": {**FUSION_RULES, "sor_local_ratio": 3.0,
                                            "depth": {"edge_margin_px": 1}}}  # what results.json records


def test_mesh_rules_apply_only_when_switched_on() -> None:
    assert not ProcessSettings().mesh_used.split_sides  # paper mode: one ball-pivoting pass
    on = settings_from_dict({"corrections": {"mesh": True}})
    assert on.mesh_used.split_sides and on.mesh_used.radius_factors == on.mesh.radius_factors
    assert on.to_dict()["mesh"] == ProcessSettings().to_dict()["mesh"]
    from darp.processing.results import rules_used

    assert rules_used(on) == {"mesh": {"split_sides": True}} and rules_used(ProcessSettings()) == {}
    assert CorrectionSettings.parse("all").mesh and CorrectionSettings.parse("mesh").applied == ("mesh",)


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
    if isinstance(value, bool):
        other_value: object = not value
    elif isinstance(value, str):
        other_value = {"keyframe": "view"}[value]  # the other choice of a str setting
    else:
        other_value = value + 1
    changed = settings_from_dict({group: {name: other_value}})
    assert changed.to_dict()[group][name] != value
    assert changed.fingerprint(group) != default.fingerprint(group)
    other = "evaluation" if group == "mesh" else "mesh"
    assert changed.fingerprint(other) == default.fingerprint(other)


def test_a_bad_flag_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "s").mkdir()  # the output beside the survey, not inside it (that is refused first: issue 32)
    code = run(["process", str(tmp_path / "s"), "--truth-poses", "--out", str(tmp_path / "o"), "--corrections",
                "magic"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("darp: error: Invalid value for '--corrections'") and "magic" in err


def test_time_shifted_poses_keep_the_kinematic_model(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With kinematics and time both on, the second (time-shifted) eq. 1 still uses the richer model."""
    import types

    import numpy as np

    from darp.formats.calibration import ArmCalibration, Calibration
    from darp.processing import job as job_module

    calls: list[dict[str, object]] = []

    def fake_recover(*args: object, **kwargs: object) -> types.SimpleNamespace:
        calls.append(kwargs)
        return types.SimpleNamespace(time_alignment={})

    monkeypatch.setattr(job_module, "recover_survey_poses", fake_recover)
    arm = ArmCalibration(serial="1", T_world_base=np.eye(4), T_wrist_cam=np.eye(4))
    arm.time_offset_s = 0.004  # from the calibration: no estimate from frames needed
    cal = Calibration(epoch="e", date="2026-12-02", arms={"arm110": arm})
    job = job_module.SurveyJob(survey=types.SimpleNamespace(arms=("arm110",)), out=tmp_path, calibration=cal,
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
    from darp.processing import job as job_module

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
        job = job_module.SurveyJob(survey=types.SimpleNamespace(arms=("arm110",), arm_poses=lambda: log),
                                 out=tmp_path, calibration=cal, calibration_path=None,
                                 settings=ProcessSettings(corrections=CorrectionSettings.parse(spec)))
        monkeypatch.setattr(job, "recording", lambda a: recording)
        frames = job._arm_frames("arm110", poses)
        assert np.allclose(frames.T_world_base, base_kin if expect_kin else np.eye(4))
        assert (frames.fk_batch is not None) == expect_kin
        assert np.allclose(frames.joint_offsets_rad, 0.001 if expect_kin else 0.0)


def test_time_estimator_gets_the_backlash_adjusted_joint_log(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The time-offset estimator re-poses frames from the joint log: with the richer model's backlash, that log
    must be the link angles the poses stage used (each joint behind its last move), not the raw encoder log."""
    import types

    import numpy as np

    from darp.formats.calibration import ArmCalibration, Calibration
    from darp.kinematics.kinematic_model import KinematicParams
    from darp.processing import job as job_module
    from darp.reconstruction.poses import motion_directions

    backlash = np.full(6, 0.002)
    kin = {"model": "kinematic+compliance+backlash", **KinematicParams(backlash_rad=backlash).to_dict()}
    cal = Calibration(epoch="e", date="2026-12-02",
                      arms={"arm110": ArmCalibration("1", np.eye(4), np.eye(4), kinematics=kin)})
    ramp = np.r_[np.zeros(20), np.linspace(0.0, 0.3, 40), np.full(30, 0.3)]
    log_q = np.zeros((ramp.size, 6))
    log_q[:, 1] = ramp
    t = np.arange(ramp.size) / 33.0
    traj = types.SimpleNamespace(speed_noise_rad_s=0.0, poses=types.SimpleNamespace(
        t_s=t, T_world_cam=np.tile(np.eye(4), (t.size, 1, 1)), joint_speed_rad_s=np.zeros(t.size)))
    log = types.SimpleNamespace(times=lambda a: t, joints=lambda a: log_q)
    recording = types.SimpleNamespace(stream=lambda k: types.SimpleNamespace(intrinsics=object()), depth_scale=0.001)
    expected = log_q - backlash * motion_directions(log_q)
    assert np.abs(expected - log_q).max() > 0.001  # the log moved, so the backlash shows
    for spec, want in (("kinematics,time", expected), ("time", log_q)):
        job = job_module.SurveyJob(survey=types.SimpleNamespace(arms=("arm110",), arm_poses=lambda: log),
                                 out=tmp_path, calibration=cal, calibration_path=None,
                                 settings=ProcessSettings(corrections=CorrectionSettings.parse(spec)))
        monkeypatch.setattr(job, "recording", lambda a: recording)
        frames = job._arm_frames("arm110", types.SimpleNamespace(trajectories={"arm110": traj}))
        assert np.allclose(frames.log_q_rad, want, atol=1e-12)
