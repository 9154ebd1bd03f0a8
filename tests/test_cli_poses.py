"""``darp poses`` end to end on a tiny synthetic survey with known frame times and known arm motion.

arm110's camera starts before its joint log, runs past its end, and crosses a 0.3 s dropout of the
log; arm111's log covers all of its frames. The expected poses are computed here from the analytic
joint motion, the calibration and ``z1.fk`` (eq. 1 with +dq).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from darp.cli._app import run
from darp.formats.arm_poses import ArmPoseWriter
from darp.formats.calibration import Calibration, write_calibration
from darp.formats.envelope import Envelope, write_envelope
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile
from darp.kinematics import z1
from darp.kinematics.rig import load_rig
from darp.kinematics.transforms import make_transform, rot_x, rot_z

T0_S = 1_700_000_000.0  # host clock (Unix seconds), start of arm110's joint log
SERIALS = {"arm110": "348522076490", "arm111": "405622074504"}
Q0 = {"arm110": np.array([0.1, 0.9, -1.1, 0.4, 0.05, -0.1]), "arm111": np.array([-0.2, 1.0, -1.2, 0.5, -0.1, 0.2])}
VEL = {"arm110": np.array([0.3, -0.2, 0.25, 0.1, -0.15, 0.2]), "arm111": np.array([-0.1, 0.15, -0.1, 0.2, 0.1, -0.3])}
KINK = {"arm110": np.array([-0.4, 0.3, 0.0, -0.2, 0.25, 0.0]), "arm111": np.zeros(6)}
KINK_AT_S = 0.30  # seconds after T0, a logged sample of arm110
DQ = {"arm110": np.array([0.012, -0.015, 0.01, 0.008, -0.01, 0.02]),
      "arm111": np.array([-0.01, 0.01, 0.0, -0.012, 0.0, 0.015])}

# arm110's log: every 30 ms over [0, 0.51] and [0.81, 1.11] s; arm111's: every 30 ms over [-0.5, 2.0] s
LOG_S = {"arm110": np.concatenate([np.arange(18) * 0.03, 0.81 + np.arange(11) * 0.03]),
         "arm111": -0.5 + np.arange(84) * 0.03}
# camera frames at 30 Hz: arm110 from -0.085 s (3 before the log, 9 in the dropout, 4 after the log)
FRAMES_S = {"arm110": -0.085 + np.arange(40) / 30.0, "arm111": 0.011 + np.arange(30) / 30.0}
EXPECTED = {"arm110": {"frames": 40, "posed": 24, "before_log": 3, "after_log": 4, "in_gap": 9},
            "arm111": {"frames": 30, "posed": 30, "before_log": 0, "after_log": 0, "in_gap": 0}}


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM file as evo, an independent reader, reads it: (timestamps s, T (N, 4, 4))."""
    from evo.tools import file_interface

    traj = file_interface.read_tum_trajectory_file(str(path))
    return np.asarray(traj.timestamps), np.array(traj.poses_se3)

def q_true(arm: str, t_s: np.ndarray) -> np.ndarray:
    """The analytic joint motion: linear, with a change of slope at KINK_AT_S (arm110)."""
    t = np.asarray(t_s, dtype=np.float64)
    return Q0[arm] + np.outer(t, VEL[arm]) + np.outer(np.maximum(t - KINK_AT_S, 0.0), KINK[arm])


def _write_bag(path: Path, serial: str, frames_s: np.ndarray) -> None:
    intr = Intrinsics(8, 6, 6.0, 6.0, 3.5, 2.5)
    profile = StreamProfile("depth", "Depth", 0, 0, "z16", 30, 8, 6, intr)
    with BagWriter(path, DeviceInfo("Intel RealSense D435I", serial), [profile]) as writer:
        for k, t in enumerate(frames_s):
            writer.write_image("depth", np.full((6, 8), 400 + k, np.uint16), (T0_S + t) * 1000.0, 1000 + k)


def _calibration() -> Calibration:
    cal = load_rig().nominal_calibration()
    cal.epoch, cal.date = "test-epoch", "2025-01-15"
    for arm, angle in (("arm110", 0.01), ("arm111", -0.02)):
        a = cal.arms[arm]
        a.T_world_base = a.T_world_base @ make_transform(rot_z(angle), [0.003, -0.002, 0.001])
        a.T_wrist_cam = make_transform(rot_x(angle), [0.002, 0.001, -0.003]) @ a.T_wrist_cam
        a.joint_offsets_rad = DQ[arm]
    return cal


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Calibration]:
    root = tmp_path_factory.mktemp("poses")
    folder = root / "Mug"
    folder.mkdir()
    for arm, serial in SERIALS.items():
        _write_bag(folder / f"cam{serial}.bag", serial, FRAMES_S[arm])
    rows = sorted((t, arm) for arm in SERIALS for t in LOG_S[arm])
    with ArmPoseWriter(folder / "arm_poses.csv") as log:
        for t, arm in rows:
            log.write(T0_S + t, arm, q_true(arm, np.array([t]))[0])
    write_envelope(folder / "manip_envelope.json",
                   Envelope(object_name="Mug", center_m=(0.0, 0.02, 0.05), radius_m=0.05, height_m=0.10,
                            standoff_m=0.3))
    cal = _calibration()
    write_calibration(root / "calibration.json", cal)
    return folder, root / "calibration.json", cal


@pytest.fixture(scope="module")
def outputs(survey, tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder, cal_path, _ = survey
    out = tmp_path_factory.mktemp("out") / "poses"
    assert run(["poses", str(folder), "--calibration", str(cal_path), "--out", str(out)]) == 0
    return out


def expected_poses(arm: str, cal: Calibration, host_t_s: np.ndarray) -> np.ndarray:
    a = cal.arms[arm]
    return np.array([a.T_world_base @ z1.fk(q + a.joint_offsets_rad) @ a.T_wrist_cam
                     for q in q_true(arm, host_t_s - T0_S)])


def test_outputs_are_all_there(outputs: Path) -> None:
    names = sorted(p.name for p in outputs.iterdir())
    assert names == sorted([f"cam{SERIALS['arm110']}_arm110.npz", f"cam{SERIALS['arm110']}_arm110.tum",
                            f"cam{SERIALS['arm111']}_arm111.npz", f"cam{SERIALS['arm111']}_arm111.tum",
                            "summary.json", "trajectories.png"])
    assert (outputs / "trajectories.png").read_bytes()[:4] == b"\x89PNG"


def test_summary_counts(outputs: Path, survey) -> None:
    summary = json.loads((outputs / "summary.json").read_text())
    assert summary["calibration"]["epoch"] == "test-epoch" and summary["calibration"]["nominal"] is False
    for arm, counts in EXPECTED.items():
        entry = summary["arms"][arm]
        assert {k: entry[k] for k in counts} == counts
        assert entry["serial"] == SERIALS[arm]
        assert entry["log_rows"] == LOG_S[arm].size
        np.testing.assert_allclose(entry["log_span_s"], T0_S + LOG_S[arm][[0, -1]], atol=1e-6)
        np.testing.assert_allclose(entry["camera_span_s"], T0_S + FRAMES_S[arm][[0, -1]], atol=1e-6)
        assert entry["timestamp_domains"] == ["Global Time"]
    assert summary["warnings"] == []


@pytest.mark.parametrize("arm", ["arm110", "arm111"])
def test_tum_poses_equal_eq1_of_the_known_motion(outputs: Path, survey, arm: str) -> None:
    _, _, cal = survey
    t_s, T = read_tum(outputs / f"cam{SERIALS[arm]}_{arm}.tum")
    assert t_s.size == EXPECTED[arm]["posed"]
    expected = expected_poses(arm, cal, t_s)
    np.testing.assert_allclose(T[:, :3, 3], expected[:, :3, 3], atol=2e-6)  # TUM keeps 1e-9 m; time 1e-6 s
    np.testing.assert_allclose(T[:, :3, :3], expected[:, :3, :3], atol=2e-6)
    # the joint-zero offsets matter at this tolerance: without them the poses are millimetres away
    a = cal.arms[arm]
    no_dq = np.array([a.T_world_base @ z1.fk(q) @ a.T_wrist_cam for q in q_true(arm, t_s - T0_S)])
    assert np.min(np.linalg.norm(no_dq[:, :3, 3] - expected[:, :3, 3], axis=1)) > 1e-3


def test_npz_holds_every_frame_with_status_and_velocity(outputs: Path, survey) -> None:
    _, _, cal = survey
    data = np.load(outputs / f"cam{SERIALS['arm110']}_arm110.npz")
    frames_s = data["timestamps_ms"] / 1000.0
    np.testing.assert_allclose(frames_s, T0_S + FRAMES_S["arm110"], atol=1e-6)
    np.testing.assert_array_equal(data["frame_numbers"], 1000 + np.arange(40))
    names = [str(n) for n in data["status_names"]]
    status = np.array([names[s] for s in data["status"]])
    t_rel = frames_s - T0_S
    np.testing.assert_array_equal(status == "before_log", t_rel < 0)
    np.testing.assert_array_equal(status == "after_log", t_rel > 1.11)
    np.testing.assert_array_equal(status == "in_gap", (t_rel > 0.51) & (t_rel < 0.81))
    posed = status == "posed"
    T = data["T_world_cam"]
    assert np.all(np.isnan(T[~posed])) and np.all(np.isfinite(T[posed]))
    np.testing.assert_allclose(T[posed], expected_poses("arm110", cal, frames_s[posed]), atol=1e-6)
    expected_velocity = VEL["arm110"] + np.outer(t_rel[posed] > KINK_AT_S, KINK["arm110"])
    np.testing.assert_allclose(data["joint_velocity"][posed], expected_velocity, atol=1e-4)


def test_without_calibration_the_nominal_rig_is_used_with_a_warning(
        survey, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder, _, _ = survey
    out = tmp_path / "nominal"
    assert run(["poses", str(folder), "--out", str(out), "--no-figure"]) == 0
    err = capsys.readouterr().err
    assert "warning: no --calibration given" in err
    assert not (out / "trajectories.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["calibration"]["nominal"] is True
    nominal = load_rig().nominal_calibration()
    t_s, T = read_tum(out / f"cam{SERIALS['arm111']}_arm111.tum")
    np.testing.assert_allclose(T[:, :3, 3], expected_poses("arm111", nominal, t_s)[:, :3, 3], atol=2e-6)


def test_clock_offset_moves_frames_against_the_log(survey, tmp_path: Path) -> None:
    folder, cal_path, cal = survey
    out = tmp_path / "offset"
    # camera clock 0.2 s ahead: every arm110 frame is sampled 0.2 s earlier on the host clock
    assert run(["poses", str(folder), "-c", str(cal_path), "--out", str(out), "--no-figure",
                "--clock-offset-s", "0.2"]) == 0
    data = np.load(out / f"cam{SERIALS['arm110']}_arm110.npz")
    host_rel = data["timestamps_ms"] / 1000.0 - 0.2 - T0_S
    assert np.count_nonzero(data["status"] == 1) == np.count_nonzero(host_rel < 0)  # before_log
    posed = data["status"] == 0
    np.testing.assert_allclose(data["T_world_cam"][posed],
                               expected_poses("arm110", cal, host_rel[posed] + T0_S), atol=1e-6)


def test_an_interrupted_recording_is_posed_with_one_warning(survey, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    import shutil

    from helpers.damaged_recordings import salvage_warning, unindexed_copy

    folder, cal_path, cal = survey
    copy = shutil.copytree(folder, tmp_path / folder.name)
    bag = copy / f"cam{SERIALS['arm110']}.bag"
    unindexed_copy(bag, tmp_path / "interrupted.bag").replace(bag)
    out = tmp_path / "poses"
    assert run(["poses", str(copy), "-c", str(cal_path), "--out", str(out), "--no-figure"]) == 0
    salvage_warning(capsys.readouterr().err, bag, "no index (interrupted recording?)", "recovered 40 depth frames")
    summary = json.loads((out / "summary.json").read_text())
    for arm, counts in EXPECTED.items():  # every frame of the interrupted recording was recovered
        assert {k: summary["arms"][arm][k] for k in counts} == counts
    t_s, T = read_tum(out / f"cam{SERIALS['arm110']}_arm110.tum")
    np.testing.assert_allclose(T[:, :3, 3], expected_poses("arm110", cal, t_s)[:, :3, 3], atol=2e-6)


def test_bad_survey_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "Broken"
    broken.mkdir()
    (broken / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n1.0,arm110,0,0,0,0,0,0\n")
    assert run(["poses", str(broken), "--out", str(tmp_path / "out")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("darp: warning")]
    assert len(err) == 1 and err[0].startswith("darp: error: ") and "no recording for arm110" in err[0]
    assert not (tmp_path / "out").exists()


def test_calibration_of_other_cameras_is_refused(survey, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder, _, cal = survey
    other = _calibration()
    other.arms["arm110"].serial = "111111111111"
    other.arms["arm111"].serial = "222222222222"
    path = tmp_path / "other.json"
    write_calibration(path, other)
    assert run(["poses", str(folder), "-c", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("darp: error: ")


def test_library_refuses_a_calibration_whose_serial_differs(survey) -> None:
    from darp.errors import SurveyError
    from darp.formats.survey import open_survey
    from darp.reconstruction.poses import recover_survey_poses

    folder, _, _ = survey
    cal = _calibration()
    cal.arms["arm111"].serial = "222222222222"
    with pytest.raises(SurveyError, match="calibrated camera 222222222222 on arm111"):
        recover_survey_poses(open_survey(folder), cal)


def test_kinematics_switch_uses_the_richer_model_and_warns_without_it(survey) -> None:
    """corrections.kinematics: eq. 1 with the calibration's richer model (its own transforms, origins, tilts,
    compliance); off, or for an arm whose calibration has none, the paper's eq. 1 (with a warning)."""
    from darp.formats.survey import open_survey
    from darp.kinematics.kinematic_model import KinematicParams, fk_batch_params
    from darp.reconstruction.poses import recover_survey_poses

    folder, _, _ = survey
    cal = _calibration()
    rng = np.random.default_rng(0)
    kin = KinematicParams(rng.normal(0, 1e-3, (6, 3)), rng.normal(0, 3e-3, (6, 3)),
                          np.array([0, 1e-3, 5e-4, 2e-3, 0, 0]))
    T_wb = cal.arms["arm110"].T_world_base @ make_transform(rot_z(0.002), [0.001, 0.0, 0.0])
    dq = DQ["arm110"] + 0.001
    cal.arms["arm110"].kinematics = {"model": "kinematic+compliance", **kin.to_dict(), "T_world_base": T_wb.tolist(),
                                     "T_wrist_cam": cal.arms["arm110"].T_wrist_cam.tolist(),
                                     "joint_offsets_rad": dq.tolist(), "estimated": ["joint2.compliance"]}
    survey_ = open_survey(folder)
    paper = recover_survey_poses(survey_, cal)
    rich = recover_survey_poses(survey_, cal, kinematics=True)
    assert "kinematics" not in paper.summary()  # off: the summary is what it always was
    assert rich.kinematics is not None and rich.kinematics["arm110"]["applied"] is True
    assert rich.kinematics["arm111"]["applied"] is False
    assert len([w for w in rich.warnings if "arm111" in w and "no kinematics" in w]) == 1
    traj, traj_paper = rich.trajectories["arm110"].poses, paper.trajectories["arm110"].poses
    ok = traj.posed
    expected = T_wb @ fk_batch_params(traj.q_rad[ok] + dq, kin) @ cal.arms["arm110"].T_wrist_cam
    assert np.allclose(traj.T_world_cam[ok], expected, atol=1e-12)
    assert np.max(np.abs(traj.T_world_cam[ok][:, :3, 3] - traj_paper.T_world_cam[ok][:, :3, 3])) > 1e-3
    assert np.array_equal(rich.trajectories["arm111"].poses.T_world_cam, paper.trajectories["arm111"].poses.T_world_cam,
                          equal_nan=True)
