"""``darp collect``: argument checks, clean endings on the twin, and an accepted twin survey (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from darp.cli._app import run

FAST = ["--fps", "6", "--resolution", "424x240", "--quiet"]


@pytest.mark.parametrize("argv, message", [
    (["collect", "s"], "'--twin' / '--hardware': choose exactly one"),
    (["collect", "s", "--twin", "--hardware"], "'--twin' / '--hardware': choose exactly one"),
    (["collect", "s", "--hardware"], "'--calibration': required with --hardware"),
    (["collect", "a/b", "--twin"], "must be a plain folder name"),
    (["collect", "s", "--twin", "--placement", "1,2"], "'--placement': expected x,y,yaw_deg"),
    (["collect", "s", "--twin", "--resolution", "big"], "'--resolution': expected WIDTHxHEIGHT"),
    (["collect", "s", "--twin", "--object", "teapot"], "unknown object 'teapot'"),
    (["collect", "s", "--twin", "--calibration", "missing.json"], "missing.json"),
])
def test_bad_arguments_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                           message: str) -> None:
    assert run([*argv, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("darp: error:") and message in err and "\n" not in err
    assert not any(tmp_path.iterdir())  # nothing was created


def test_object_outside_the_workspace_is_refused_with_exit_2(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["collect", "far", "--twin", "--object", "cup", "--placement", "0.0,0.37,0", "--out", str(tmp_path), *FAST]
    assert run(argv) == 2
    err = capsys.readouterr().err
    assert "outside the reachable workspace" in err and not any(tmp_path.iterdir())


def test_empty_table_is_rejected_with_exit_1_and_not_overwritten(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["collect", "empty", "--twin", "--object", "none", "--out", str(tmp_path), *FAST]
    assert run(argv) == 1
    err = capsys.readouterr().err
    assert "survey rejected (no_object)" in err and "empty.rejected" in err
    assert (tmp_path / "empty.rejected" / "REJECTED.txt").read_text().startswith("rejected: no_object")
    # a second run refuses to overwrite it, then --overwrite replaces it
    assert run(argv) == 2
    assert "already exists" in capsys.readouterr().err
    assert run([*argv, "--overwrite"]) == 1


@pytest.mark.slow
def test_twin_survey_is_accepted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from darp.formats.survey import open_survey

    argv = ["collect", "mug", "--twin", "--object", "mug", "--placement", "0.04,-0.06,30", "--seed", "3",
            "--truth-calibration", "--out", str(tmp_path), *FAST]
    assert run(argv) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"accepted: {tmp_path / 'mug'}")
    survey = open_survey(tmp_path / "mug")
    env = survey.envelope()
    assert env is not None and abs(env.center_m[0] - 0.04) < 0.02 and abs(env.center_m[1] + 0.06) < 0.02
    assert json.loads((tmp_path / "mug" / "truth" / "contacts.json").read_text()) == []
    assert (tmp_path / "mug" / "truth" / "camera_poses_arm110.npz").is_file()
    assert json.loads((tmp_path / "mug" / "verification.json").read_text())["passed"] is True
    assert env.extra["coverage"]["strategy"] == "coverage"  # the default planner; orbit only when asked


def test_hardware_branch_runs_the_same_procedure(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``--hardware`` opens the rig YAML's HardwareRig; here a fake backend stands in for the devices."""
    import darp.hardware.rig as hardware_rig
    from darp.formats.calibration import write_calibration
    from darp.kinematics.rig import default_rig_path, load_rig
    from helpers.acquisition_fakes import Cylinder, FakeRig

    opened: list[Path] = []
    fake = FakeRig([Cylinder(0.0, -0.05, 0.05, 0.1)])

    def open_fake(path: Path, **kwargs: object) -> FakeRig:
        opened.append(Path(path))
        return fake

    monkeypatch.setattr(hardware_rig.HardwareRig, "open", staticmethod(open_fake))
    cal_path = tmp_path / "cal.json"
    write_calibration(cal_path, load_rig().nominal_calibration())
    argv = ["collect", "real", "--hardware", "--rig", str(default_rig_path()), "--calibration", str(cal_path),
            "--out", str(tmp_path), "--quiet"]
    assert run(argv) == 0
    assert opened == [default_rig_path()] and fake.closed
    assert capsys.readouterr().out.startswith(f"accepted: {tmp_path / 'real'}")
    env = json.loads((tmp_path / "real" / "manip_envelope.json").read_text())
    assert env["localisation"]["calibration"] == load_rig().nominal_calibration().epoch
    assert env["coverage"]["strategy"] == "coverage"  # the same default planner as on the twin
    assert not (tmp_path / "real" / "truth").exists()
