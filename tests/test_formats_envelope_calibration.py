"""manip_envelope.json and the calibration file: round trips and one clear error per defect."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.errors import FormatError
from darp.formats.calibration import (
    ArmCalibration,
    Calibration,
    CharucoBoardSpec,
    read_calibration,
    write_calibration,
)
from darp.formats.envelope import Envelope, read_envelope, write_envelope


def _error(reader, path: Path) -> str:  # type: ignore[no-untyped-def]
    with pytest.raises(FormatError) as info:
        reader(path)
    message = str(info.value)
    assert path.name in message and "\n" not in message, message
    return message


def _dump(path: Path, payload: object) -> Path:
    path.write_text(json.dumps(payload, indent=2), encoding="utf-8")
    return path


# -- envelope ---------------------------------------------------------------------------------------
def _envelope() -> Envelope:
    return Envelope(
        object_name="Mug",
        center_m=(0.012, -0.034, 0.0315),
        radius_m=0.0722,
        height_m=0.063,
        standoff_m=0.372,
        park_q_rad={"arm110": (0.0, 1.2, -1.0, 0.1, 0.0, 0.0), "arm111": (0.0, 1.1, -0.9, 0.0, 0.2, 0.0)},
        view_q_rad={"arm110": [(0.1, 0.9, -0.8, 0.0, 0.3, 0.0), (0.2, 0.9, -0.8, 0.0, 0.3, 0.1)], "arm111": []},
        localisation={"searching_arm": "arm110", "confirmed": True, "estimates": [[0.01, -0.03, 0.03]]},
        extra={"operator_note": "placed near the centre", "planner": {"n_views": 12}},
    )


def test_envelope_round_trip_keeps_everything(tmp_path: Path) -> None:
    path = tmp_path / "manip_envelope.json"
    env = _envelope()
    write_envelope(path, env)
    back = read_envelope(path)
    assert back == env
    raw = json.loads(path.read_text())
    assert raw["schema_version"] == 1 and raw["operator_note"] == "placed near the centre"  # extra at top level
    assert not list(tmp_path.glob("*.partial"))  # atomic write leaves no temporary file


def test_envelope_with_absent_values(tmp_path: Path) -> None:
    # like the paper's Red Bull survey: no geometry at all
    path = _dump(tmp_path / "manip_envelope.json", {"schema_version": 1, "object": "Red Bull", "radius_m": None})
    env = read_envelope(path)
    assert env.object_name == "Red Bull"
    assert (env.center_m, env.radius_m, env.height_m, env.standoff_m) == (None, None, None, None)
    assert not env.has_geometry and env.park_q_rad == {} and env.extra == {}
    write_envelope(path, env)
    assert read_envelope(path) == env


def test_envelope_legacy_file_without_schema_version(tmp_path: Path) -> None:
    payload = {
        "name": "Dumbbell", "center": [0.02, -0.01, 0.018], "radius": 0.069, "height": 0.0366,
        "standoff": 0.369, "robot_config": {"arm110": "park"}, "timestamp": "2025-05-02T10:00:00",
    }
    env = read_envelope(_dump(tmp_path / "manip_envelope.json", payload))
    assert env.schema_version is None
    assert env.object_name == "Dumbbell" and env.center_m == (0.02, -0.01, 0.018)
    assert (env.radius_m, env.height_m, env.standoff_m) == (0.069, 0.0366, 0.369)
    assert env.extra == {"robot_config": {"arm110": "park"}, "timestamp": "2025-05-02T10:00:00"}


@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        ({"radius_m": -0.05}, "radius_m: must be positive, got -0.05"),
        ({"height_m": 0}, "height_m: must be positive, got 0.0"),
        ({"standoff_m": "35 cm"}, "standoff_m: expected a number, got a string"),
        ({"radius_m": True}, "radius_m: expected a number, got a boolean"),
        ({"center_m": [0.0, 0.1]}, "center_m: expected shape (3,), got (2,)"),
        ({"center_m": [0.0, "x", 0.1]}, "center_m: expected numbers, found a string"),
        ({"object": 5}, "object: expected a string, got a number"),
        ({"park_q_rad": {"arm110": [0, 0, 0]}}, "park_q_rad.arm110: expected shape (6,), got (3,)"),
        ({"view_q_rad": {"arm111": [[0, 0, 0, 0, 0, 0], [0, 0]]}}, "view_q_rad.arm111: expected a list of shape"),
        ({"localisation": [1, 2]}, "localisation: expected an object, got a list"),
        ({"schema_version": 2}, "schema_version 2 is newer than this darp understands (1)"),
        ({"schema_version": "1"}, "schema_version: expected an integer, got a string"),
    ],
)
def test_envelope_wrong_values(tmp_path: Path, payload: dict, expected: str) -> None:
    path = _dump(tmp_path / "manip_envelope.json", {"schema_version": 1, **payload})
    assert expected in _error(read_envelope, path)


def test_envelope_nan_is_refused_on_read_and_write(tmp_path: Path) -> None:
    path = tmp_path / "manip_envelope.json"
    path.write_text('{"schema_version": 1, "radius_m": NaN}')
    assert "radius_m: must be finite, got nan" in _error(read_envelope, path)
    with pytest.raises(FormatError, match="radius_m: must be finite"):
        write_envelope(tmp_path / "out.json", Envelope(radius_m=float("nan")))
    assert not (tmp_path / "out.json").exists()
    with pytest.raises(FormatError, match="extra keys clash with schema keys: radius_m"):
        write_envelope(tmp_path / "out.json", Envelope(extra={"radius_m": 1.0}))


@pytest.mark.parametrize("reader", [read_envelope, read_calibration])
def test_malformed_json_names_line_and_column(tmp_path: Path, reader) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "bad.json"
    path.write_text('{\n  "schema_version": 1,\n  "radius_m": 0.05,,\n}\n')
    assert "invalid JSON at line 3 column 20" in _error(reader, path)
    path.write_text("[1, 2]")
    assert "top level must be a JSON object, not a list" in _error(reader, path)
    path.write_text("")
    assert "empty file" in _error(reader, path)
    assert "no such file" in _error(reader, tmp_path / "missing.json")


# -- calibration --------------------------------------------------------------------------------------
def _transform(rotvec: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _calibration() -> Calibration:
    rng = np.random.default_rng(3)
    arms = {}
    for arm, serial, yaw in (("arm110", "348522076490", 0.0), ("arm111", "405622074504", np.deg2rad(178.4))):
        arms[arm] = ArmCalibration(
            serial=serial,
            T_world_base=_transform((0.0, 0.0, yaw), (0.0 if yaw == 0 else 1.3986, 0.01, 0.0)),
            T_wrist_cam=_transform(tuple(rng.normal(0, 0.5, 3)), tuple(rng.normal(0, 0.05, 3))),
            joint_offsets_rad=rng.normal(0, 0.01, 6),
            joint_offsets_std_rad=np.full(6, 1e-3),
            identifiable=(True, True, True, True, True, False),
            residuals={"heldout_rms_m": 0.00358, "n_inliers": 142},
            n_captures=40,
        )
    return Calibration(
        epoch="2025-05-rig-a",
        date="2025-05-01T09:30:00+00:00",
        arms=arms,
        board=CharucoBoardSpec(7, 5, 0.04, 0.03, "DICT_5X5_100"),
        world_frame="arm110 base frame: x forward, z up",
        report={"solver": "park-martin", "settings": {"min_corners": 12}},
    )


def test_calibration_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    cal = _calibration()
    write_calibration(path, cal)
    back = read_calibration(path)
    assert (back.epoch, back.date, back.board, back.world_frame, back.report) == (
        cal.epoch, cal.date, cal.board, cal.world_frame, cal.report)
    for name, arm in cal.arms.items():
        got = back.arm(name)
        np.testing.assert_array_equal(got.T_world_base, arm.T_world_base)  # exact: JSON keeps repr digits
        np.testing.assert_array_equal(got.T_wrist_cam, arm.T_wrist_cam)
        np.testing.assert_array_equal(got.joint_offsets_rad, arm.joint_offsets_rad)
        np.testing.assert_array_equal(got.joint_offsets_std_rad, arm.joint_offsets_std_rad)
        assert (got.serial, got.identifiable, got.residuals, got.n_captures) == (
            arm.serial, arm.identifiable, arm.residuals, arm.n_captures)
    assert back.arm_for_serial("405622074504") == "arm111"
    with pytest.raises(FormatError, match="no calibration for arm 'arm112' \\(arms: arm110, arm111\\)"):
        back.arm("arm112")


def test_calibration_minimal_and_optional_fields(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    cal = Calibration(epoch="nominal", date="2025-05-01", arms={
        "arm110": ArmCalibration(serial="348522076490", T_world_base=np.eye(4), T_wrist_cam=np.eye(4))})
    write_calibration(path, cal)
    back = read_calibration(path)
    assert back.board is None and back.arm("arm110").joint_offsets_std_rad is None
    assert back.arm("arm110").identifiable is None and back.arm("arm110").n_captures is None
    np.testing.assert_array_equal(back.arm("arm110").joint_offsets_rad, np.zeros(6))


def _payload_with(change) -> dict:  # type: ignore[no-untyped-def]
    from darp.formats.calibration import calibration_to_dict
    from darp.formats.schema import to_jsonable

    payload = to_jsonable(calibration_to_dict(_calibration()))
    change(payload)
    return payload


def _set(path: tuple, value: object):  # type: ignore[no-untyped-def]
    def change(payload: dict) -> None:
        node = payload
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return change


def _del(*path: str):  # type: ignore[no-untyped-def]
    def change(payload: dict) -> None:
        node = payload
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]
    return change


SCALED = (np.diag([1.01, 1.0, 1.0, 1.0])).tolist()
REFLECTED = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()
BAD_LAST_ROW = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.1, 1]]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (_del("schema_version"), "missing schema_version"),
        (_del("epoch"), "missing epoch"),
        (_del("arms", "arm110", "T_wrist_cam"), "arms.arm110: missing T_wrist_cam"),
        (_set(("date",), "yesterday"), "date: not an ISO 8601 date: 'yesterday'"),
        (_set(("arms",), {}), "arms: no arm calibrated"),
        (_set(("arms", "arm110", "serial"), 348522076490), "arms.arm110.serial: expected a string, got a number"),
        (_set(("arms", "arm111", "T_world_base"), SCALED),
         "arms.arm111.T_world_base: not a rigid transform: rotation is not orthonormal"),
        (_set(("arms", "arm111", "T_wrist_cam"), REFLECTED),
         "arms.arm111.T_wrist_cam: not a rigid transform: rotation is a reflection"),
        (_set(("arms", "arm110", "T_wrist_cam"), BAD_LAST_ROW),
         "T_wrist_cam: not a rigid transform: last row must be [0, 0, 0, 1]"),
        (_set(("arms", "arm110", "T_wrist_cam"), [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
         "expected shape (4, 4), got (3, 3)"),
        (_set(("arms", "arm110", "joint_offsets_rad"), [0.0] * 5), "joint_offsets_rad: expected shape (6,), got (5,)"),
        (_set(("arms", "arm110", "identifiable"), [1, 1, 1, 1, 1, 1]), "identifiable: expected a list of 6 booleans"),
        (_set(("arms", "arm110", "n_captures"), -1), "arms.arm110.n_captures: must be >= 0, got -1"),
        (_set(("arms", "arm110", "residuals"), [0.1]), "arms.arm110.residuals: expected an object, got a list"),
        (_set(("board", "marker_length_m"), 0.05), "board: marker_length_m must be smaller than square_length_m"),
        (_set(("board", "squares_x"), 7.0), "board.squares_x: expected an integer, got a number"),
        (_del("board", "dictionary"), "board: missing dictionary"),
        (_set(("schema_version",), 7), "schema_version 7 is newer than this darp understands (1)"),
    ],
)
def test_calibration_wrong_values(tmp_path: Path, change, expected: str) -> None:  # type: ignore[no-untyped-def]
    path = _dump(tmp_path / "calibration.json", _payload_with(change))
    assert expected in _error(read_calibration, path)


def test_calibration_nan_and_non_rigid_refused(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    payload = _payload_with(_set(("arms", "arm110", "joint_offsets_rad"), [0.0, float("nan"), 0, 0, 0, 0]))
    path.write_text(json.dumps(payload))  # json.dumps writes NaN as the bare token NaN
    assert "arms.arm110.joint_offsets_rad: all values must be finite" in _error(read_calibration, path)
    cal = _calibration()
    cal.arms["arm111"].T_wrist_cam = cal.arms["arm111"].T_wrist_cam @ np.diag([1.0, 1.0, 1.001, 1.0])
    with pytest.raises(FormatError,
                       match="arms.arm111.T_wrist_cam: not a rigid transform: rotation is not orthonormal"):
        write_calibration(tmp_path / "out.json", cal)
    assert not (tmp_path / "out.json").exists()
