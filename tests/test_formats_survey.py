"""The survey folder: discovery, serial-to-arm mapping, missing pieces, read-only access."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from darp.errors import FormatError, SurveyError
from darp.formats.arm_poses import ArmPoseWriter
from darp.formats.envelope import Envelope, write_envelope
from darp.formats.survey import find_survey_folders, looks_like_survey, open_survey

ARM110_SERIAL, ARM111_SERIAL = "348522076490", "405622074504"


BOTH_BAGS = (f"cam{ARM110_SERIAL}.bag", f"cam{ARM111_SERIAL}.bag")


def _folder(root: Path, *, recordings: tuple[str, ...] = BOTH_BAGS, poses: bool = True,
            envelope: bool = True) -> Path:
    """A survey folder whose recordings are placeholders: discovery looks only at names."""
    root.mkdir(parents=True, exist_ok=True)
    for name in recordings:
        (root / name).write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 100)
    if poses:
        with ArmPoseWriter(root / "arm_poses.csv") as writer:
            for k in range(5):
                writer.write(10.0 + 0.03 * k, "arm110", [0.0] * 6)
                writer.write(10.01 + 0.03 * k, "arm111", [0.1] * 6)
    if envelope:
        write_envelope(root / "manip_envelope.json", Envelope(object_name="Cube", radius_m=0.0431))
    return root


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


def test_discovery_of_a_complete_survey(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Cube")
    (root / "truth").mkdir()
    (root / "notes.txt").write_text("not part of the survey")
    before = _snapshot(root)
    survey = open_survey(root)
    assert survey.name == "Cube" and survey.path == root
    assert survey.arms == ("arm110", "arm111")
    assert survey.recording_paths == {"arm110": root / f"cam{ARM110_SERIAL}.bag",
                                      "arm111": root / f"cam{ARM111_SERIAL}.bag"}
    assert survey.serials == {"arm110": ARM110_SERIAL, "arm111": ARM111_SERIAL}
    assert survey.problems == () and survey.notes == ()
    assert survey.truth_path == root / "truth"
    log = survey.arm_poses()
    assert survey.arm_poses() is log  # cached
    assert log.rows("arm110") == 5 and log.rows("arm111") == 5
    assert survey.envelope().radius_m == 0.0431  # type: ignore[union-attr]
    expected_size = sum((root / n).stat().st_size for n in (
        f"cam{ARM110_SERIAL}.bag", f"cam{ARM111_SERIAL}.bag", "arm_poses.csv", "manip_envelope.json"))
    assert survey.size_bytes == expected_size  # notes.txt and truth/ are not the survey's files
    assert _snapshot(root) == before  # opening and reading changed nothing


def test_db3_recordings_are_accepted(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Mug", recordings=(f"cam{ARM110_SERIAL}.db3", f"cam{ARM111_SERIAL}.bag"))
    survey = open_survey(root)
    assert survey.recording_paths["arm110"].suffix == ".db3"
    assert survey.truth_path is None


def test_serial_mapping_override(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Rig2", recordings=("cam111.bag", "cam222.bag"))
    with pytest.raises(SurveyError) as info:
        open_survey(root)
    message = str(info.value)
    assert "cam111.bag: camera serial 111 is not mapped to an arm" in message
    assert "no recording for arm110 (expected cam348522076490.bag/.db3)" in message
    survey = open_survey(root, {"222": "arm110", "111": "arm111"})
    assert survey.recording_paths == {"arm110": root / "cam222.bag", "arm111": root / "cam111.bag"}
    assert survey.serials == {"arm110": "222", "arm111": "111"}


def test_missing_pieces_are_all_listed(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Half", recordings=(f"cam{ARM110_SERIAL}.bag", "camera_left.bag"), poses=False,
                   envelope=False)
    with pytest.raises(SurveyError) as info:
        open_survey(root)
    message = str(info.value)
    assert message.startswith(f"{root}: incomplete survey: ")
    assert "unexpected recording(s) camera_left.bag (expected cam<serial>.bag or .db3)" in message
    assert f"no recording for arm111 (expected cam{ARM111_SERIAL}.bag/.db3)" in message
    assert "missing arm_poses.csv" in message
    assert "\n" not in message
    survey = open_survey(root, strict=False)
    assert survey.arms == ("arm110",) and len(survey.problems) == 3
    assert survey.notes == ("no manip_envelope.json (object envelope unknown)",)
    assert survey.envelope() is None
    with pytest.raises(SurveyError, match="no arm_poses.csv in this survey"):
        survey.arm_poses()
    with pytest.raises(SurveyError, match="no recording for arm 'arm111' \\(recordings for: arm110\\)"):
        survey.open_recording("arm111")


def test_two_recordings_for_one_arm(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Dup", recordings=(f"cam{ARM110_SERIAL}.bag", f"cam{ARM110_SERIAL}.db3",
                                                 f"cam{ARM111_SERIAL}.bag"))
    expected = f"2 recordings for arm110: cam{ARM110_SERIAL}.bag, cam{ARM110_SERIAL}.db3"
    with pytest.raises(SurveyError, match=expected):
        open_survey(root)


def test_missing_envelope_is_a_note_not_an_error(tmp_path: Path) -> None:
    survey = open_survey(_folder(tmp_path / "NoEnv", envelope=False))
    assert survey.problems == () and survey.envelope() is None and survey.envelope_path is None
    assert "no manip_envelope.json" in survey.notes[0]


def test_not_a_survey(tmp_path: Path) -> None:
    with pytest.raises(SurveyError, match="no such survey folder"):
        open_survey(tmp_path / "nowhere")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(SurveyError, match="not a folder"):
        open_survey(tmp_path / "file.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SurveyError, match="not a survey folder"):
        open_survey(tmp_path / "empty")


def test_bad_joint_log_surfaces_with_its_line(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Bad")
    with open(root / "arm_poses.csv", "a", encoding="utf-8") as handle:
        handle.write("9.0,arm110,0,0,0,0,0,0\n")  # earlier than the rows before it
    survey = open_survey(root)
    with pytest.raises(FormatError, match="line 12: time goes backwards for arm110"):
        survey.arm_poses()


def test_find_survey_folders_expands_parents(tmp_path: Path) -> None:
    parent = tmp_path / "darp"
    b = _folder(parent / "b_mug")
    a = _folder(parent / "a_cube")
    (parent / "README.md").write_text("release notes")
    (parent / "scratch").mkdir()
    assert looks_like_survey(a) and not looks_like_survey(parent) and not looks_like_survey(parent / "scratch")
    assert find_survey_folders([parent]) == [a, b]
    assert find_survey_folders([b, a]) == [b, a]  # explicit surveys keep their order
    with pytest.raises(SurveyError, match="holds no survey folders"):
        find_survey_folders([parent / "scratch"])
    with pytest.raises(SurveyError, match="not a folder"):
        find_survey_folders([parent / "README.md"])
    with pytest.raises(SurveyError, match="no such survey folder"):
        find_survey_folders([tmp_path / os.sep.join(["x", "y"])])


def _real_bag(path: Path, serial: str, n_depth: int) -> None:
    import numpy as np

    from darp.formats.realsense.bag.writer import BagWriter
    from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile

    intr = Intrinsics(16, 12, 15.0, 15.0, 7.5, 5.5)
    with BagWriter(path, DeviceInfo("Intel RealSense D435", serial),
                   [StreamProfile("depth", "Depth", 0, 0, "z16", 30, 16, 12, intr)]) as writer:
        for k in range(n_depth):
            writer.write_image("depth", np.full((12, 16), k, np.uint16), 1.718e12 + 33.3 * k, k)


def test_open_recording_checks_the_serial_inside(tmp_path: Path) -> None:
    root = _folder(tmp_path / "Cube", recordings=())
    _real_bag(root / f"cam{ARM110_SERIAL}.bag", ARM110_SERIAL, 3)
    _real_bag(root / f"cam{ARM111_SERIAL}.bag", "999999999999", 2)  # renamed file from another camera
    survey = open_survey(root)
    with survey.open_recording("arm110") as recording:
        assert recording.device.serial == ARM110_SERIAL and recording.frame_count("depth") == 3
    expected = f"recording says camera serial 999999999999, but its name says {ARM111_SERIAL}"
    with pytest.raises(SurveyError, match=expected):
        survey.open_recording("arm111")
