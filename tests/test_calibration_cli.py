"""``darp calib solve`` / ``check`` / ``plan`` end to end on synthetic image captures (homography-rendered).

A calibration is solved from 2 x 20 synthetic captures of a true rig with random errors; a few new
captures then either come from the same rig (the check must pass, even with the board moved) or from
the rig with arm110's camera mount knocked by 2 mm / 0.5 deg (the check must flag it).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from darp.calibration.captures import read_captures
from darp.calibration.check import check_calibration
from darp.cli._app import run
from darp.errors import FormatError
from darp.formats.calibration import read_calibration
from darp.kinematics.transforms import axis_angle_to_rotation, make_transform
from helpers.calibration_synthetic import board_pose, random_poses, shared_once, true_rig, write_synthetic_captures

ARMS = ("arm110", "arm111")
SEED = 2


@pytest.fixture(scope="module")
def solved(tmp_path_factory: pytest.TempPathFactory):
    truth, settings = true_rig(SEED)
    T_wb = board_pose(truth.nominal)

    def build(root: Path) -> None:
        poses = {a: random_poses(truth.nominal, a, 20, T_wb, SEED) for a in ARMS}
        caps = write_synthetic_captures(root / "caps", truth, poses, T_wb, seed=SEED, encoder_noise_deg=0.002)
        rc = run(["calib", "solve", str(caps), "--out", str(root / "cal.json"), "--report", str(root / "report"),
                  "--folds", "3", "--truth", str(_write_truth(root, truth, settings)), "--epoch", "test-epoch", "-q"])
        assert rc == 0

    return shared_once(tmp_path_factory, "calib-cli", build), truth, T_wb


def _write_truth(root: Path, truth, settings) -> Path:
    from darp.formats.calibration import write_calibration

    write_calibration(root / "truth.json", truth.calibration(settings))
    return root / "truth.json"


def _new_captures(folder: Path, truth, T_wb: np.ndarray, seed: int) -> Path:
    poses = {a: random_poses(truth.nominal, a, 5, T_wb, seed) for a in ARMS}
    return write_synthetic_captures(folder, truth, poses, T_wb, seed=seed, encoder_noise_deg=0.002)


def test_solve_writes_a_valid_calibration_and_report(solved) -> None:
    root, truth, _ = solved
    cal = read_calibration(root / "cal.json")
    assert cal.epoch == "test-epoch" and cal.board is not None and cal.board.squares_x == 10
    assert "midway between the base origins" in cal.world_frame
    for arm in ARMS:
        a = cal.arms[arm]
        assert a.serial == truth.arms[arm].serial and a.n_captures == 20
        assert a.identifiable == (False, True, True, True, True, False)
        assert a.joint_offsets_std_rad is not None and a.joint_offsets_std_rad[0] == 0.0
        held = a.residuals["heldout"]["corner_3d_mm"]
        assert held["n"] > 300 and held["median"] < 0.5
    rep = cal.report
    assert rep["truth"]["darp"]["base_to_base"]["translation_mm"] < 1.0
    assert set(rep["heldout"]) == {"darp", "darp_no_offsets", "opencv_hand_eye", "opencv_robot_world"}
    assert len(rep["T_world_board"]) == 4 and rep["identifiability"]["identifiable"]["arm110"][0] is False
    for name in ("report.json", "summary.md", "per_capture_error.png", "residual_vectors.png", "heldout_histogram.png"):
        assert (root / "report" / name).stat().st_size > 200, name
    summary = (root / "report" / "summary.md").read_text()
    assert "fixed (not identifiable)" in summary and "Against truth" in summary


def test_check_passes_for_an_unchanged_rig_even_with_the_board_moved(solved, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    root, truth, T_wb = solved
    moved_board = make_transform(axis_angle_to_rotation([0, 0, 1], np.radians(12)), [0.04, -0.03, 0.0]) @ T_wb
    caps = _new_captures(tmp_path / "new", truth, moved_board, seed=11)
    assert run(["calib", "check", str(caps), "-c", str(root / "cal.json"), "--out", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert "calibration holds" in out and "arm110: ok" in out
    result = json.loads((tmp_path / "c.json").read_text())
    assert result["ok"] is True
    assert result["board_disagreement"]["translation_mm"] < 1.0
    # the refitted board is where it was put
    assert np.allclose(np.array(result["T_world_board"])[:3, 3], moved_board[:3, 3], atol=3e-3)
    # ... but told that the board did not move, the check sees the 4 cm shift
    assert run(["calib", "check", str(caps), "-c", str(root / "cal.json"), "--board-unmoved"]) == 1


def test_check_flags_a_knocked_camera_mount(solved, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root, truth, T_wb = solved
    knock = make_transform(axis_angle_to_rotation([1.0, 0.4, -0.3], np.radians(0.5)), [0.002, 0.0, 0.0])
    arms = dict(truth.arms)
    arms["arm110"] = dataclasses.replace(arms["arm110"], T_wrist_cam=knock @ arms["arm110"].T_wrist_cam)
    knocked = dataclasses.replace(truth, arms=arms)
    caps = _new_captures(tmp_path / "knocked", knocked, T_wb, seed=12)
    assert run(["calib", "check", str(caps), "-c", str(root / "cal.json")]) == 1
    out = capsys.readouterr().out
    assert "arm110: STALE" in out and "calibration is stale" in out
    result = check_calibration(read_calibration(root / "cal.json"), read_captures(caps))
    a110, a111 = result.arms["arm110"], result.arms["arm111"]
    assert not a110.ok and a110.corner_3d_mm["median"] > 2 * a110.limit_mm
    # blame: arm110's own captures disagree with each other, arm111's do not
    assert a110.self_consistency_mm > a110.limit_mm and any("on its own" in r for r in a110.reasons)
    assert a111.self_consistency_mm < a111.limit_mm / 2


def test_solve_and_check_errors_are_one_line(solved, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root, _, _ = solved
    assert run(["calib", "solve", str(tmp_path / "none"), "--out", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none' does not exist" in err[0]
    assert run(["calib", "check", str(root / "caps"), "-c", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.json' does not exist" in err[0]
    cal = json.loads((root / "cal.json").read_text())
    cal["arms"]["arm110"]["serial"] = "999"
    (tmp_path / "wrong.json").write_text(json.dumps(cal))
    assert run(["calib", "check", str(root / "caps"), "-c", str(tmp_path / "wrong.json")]) == 2
    assert "captures are from camera 348522076490 but the calibration is for camera 999" in capsys.readouterr().err
    assert run(["calib", "capture", "--out", str(tmp_path / "x")]) == 2
    assert "'--twin' / '--hardware': choose exactly one" in capsys.readouterr().err


def test_too_few_usable_captures_is_refused(solved, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _, truth, T_wb = solved
    poses = {a: random_poses(truth.nominal, a, 3, T_wb, 5) for a in ARMS}
    caps = write_synthetic_captures(tmp_path / "few", truth, poses, T_wb, seed=5)
    assert run(["calib", "solve", str(caps), "--out", str(tmp_path / "c.json"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "arm110: only 3 usable captures (need 6)" in err
    assert not (tmp_path / "c.json").exists()


def test_plan_command_writes_a_plan(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert run(["calib", "plan", "--out", str(tmp_path / "plan.json"), "--captures", "4", "--seed", "1",
                "--candidates", "40"]) == 0
    data = json.loads((tmp_path / "plan.json").read_text())
    assert data["schema"] == "darp-calib-plan/1" and {len(v) for v in data["poses"].values()} == {4}
    assert "arm110: 4" in capsys.readouterr().out


def test_twin_capture_run_completes_and_unmarks_its_folder(tmp_path: Path) -> None:
    """`darp calib capture --twin` ends with a finished folder that `calib solve` can read (the writer reads its own
    folder back while the run's UNFINISHED.txt is still there: that read must not refuse it)."""
    out = tmp_path / "caps"
    assert run(["calib", "capture", "--twin", "--seed", "0", "--captures", "2", "--out", str(out), "-q"]) == 0
    assert not (out / "UNFINISHED.txt").exists()
    assert len(read_captures(out).captures) == 4
    (out / "UNFINISHED.txt").write_text("interrupted\n")
    with pytest.raises(FormatError, match="unfinished capture folder"):
        read_captures(out)
