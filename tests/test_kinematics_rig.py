"""The dual-arm rig: the packaged default, the paper's geometry, validation, park poses, eq. 1 helpers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from darp.errors import ConfigError, KinematicsError
from darp.formats.calibration import read_calibration, write_calibration
from darp.kinematics import collision, z1
from darp.kinematics.rig import default_rig_path, load_rig
from darp.kinematics.transforms import make_transform, rot_z


def default_dict() -> dict[str, Any]:
    return yaml.safe_load(default_rig_path().read_text())


def write_yaml(tmp_path: Path, data: Any, name: str = "rig.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_default_rig_has_the_two_darp_arms(rig) -> None:
    assert rig.arm_ids == ("arm110", "arm111")
    assert rig.arm("arm110").side == "left" and rig.arm("arm111").side == "right"
    assert rig.arm("arm110").camera_serial == "348522076490"
    assert rig.arm("arm111").camera_serial == "405622074504"
    assert rig.arm_for_serial("405622074504").arm_id == "arm111"
    assert rig.wrist_frame == "flange"
    assert rig.source == default_rig_path()


def test_base_geometry_matches_the_paper(rig) -> None:
    assert rig.base_separation_m == pytest.approx(1.3986, abs=1e-9)
    assert rig.relative_yaw_deg == pytest.approx(178.4, abs=1e-9)
    b110, b111 = rig.arm("arm110").T_world_base, rig.arm("arm111").T_world_base
    # facing each other across the table: each base's x axis points at the other base
    towards = (b111[:3, 3] - b110[:3, 3]) / rig.base_separation_m
    assert b110[:3, 0] @ towards > 0.999
    assert b111[:3, 0] @ -towards > 0.999
    # both bases stand on the table top, z up, and the world origin is midway between them
    for T in (b110, b111):
        assert T[2, 3] == pytest.approx(rig.table.height_m)
        np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose((b110[:3, 3] + b111[:3, 3]) / 2, 0.0, atol=1e-12)


def test_camera_looks_along_the_tool_axis(rig) -> None:
    T_fc = rig.arm("arm110").T_wrist_cam
    np.testing.assert_allclose(T_fc[:3, 2], [1, 0, 0], atol=1e-12)  # optical z = flange x
    np.testing.assert_allclose(T_fc[:3, 1], [0, 0, -1], atol=1e-12)  # image down = flange -z
    assert 0.02 < np.linalg.norm(T_fc[:3, 3]) < 0.10


def test_parked_cameras_look_down_at_the_workspace(rig) -> None:
    for arm_id in rig.arm_ids:
        T = rig.T_world_cam(arm_id, rig.arm(arm_id).park_q_rad)
        origin, axis = T[:3, 3], T[:3, 2]
        assert axis[2] < -0.2  # looking down
        hit = origin + axis * (rig.table.height_m - origin[2]) / axis[2]  # optical axis meets the table
        assert rig.workspace.contains(hit[None])[0], f"{arm_id} looks at {hit}"


def test_park_configurations_are_collision_free(rig) -> None:
    park = {arm_id: rig.arm(arm_id).park_q_rad for arm_id in rig.arm_ids}
    margin = rig.margins.joint_limit_margin_rad
    for q in park.values():
        assert z1.within_limits(q) and np.all(q >= z1.JOINT_LOWER + margin) and np.all(q <= z1.JOINT_UPPER - margin)
    clear = rig.clearances(park)
    for arm_id in rig.arm_ids:
        assert clear[f"{arm_id}.table"].distance_m >= rig.margins.table_clearance_m
        assert clear[f"{arm_id}.self"].distance_m > 0.0
    assert clear["arm_arm"].distance_m >= rig.margins.arm_arm_margin_m
    # the camera body is part of the checked geometry: parked, it stays above the table too
    shapes = rig.arm_primitives("arm110", park["arm110"])
    body = shapes.names.index("camera_body")
    assert shapes.lowest_z()[body] - rig.table.height_m > rig.margins.table_clearance_m


def test_clearances_detect_a_camera_driven_into_the_table(rig) -> None:
    q_down = np.array([0.0, 2.6, -0.8, 0.5, 0.0, 0.0])  # upper arm tipped forward, wrist into the table
    clear = rig.clearances({"arm110": q_down})
    assert clear["arm110.table"].distance_m < -0.05
    assert clear["arm110.table"].name_a == "camera_body"


def test_camera_mount_in_collision_model_follows_the_rig(rig) -> None:
    mount = rig.camera_mount("arm111")
    np.testing.assert_allclose(mount.T_wrist_cam, rig.arm("arm111").T_wrist_cam)
    np.testing.assert_allclose(mount.body_size_m, rig.camera_body.size_m)
    assert isinstance(mount, collision.CameraMount)


def test_T_world_cam_is_eq1_nominal_and_batched(rig) -> None:
    rng = np.random.default_rng(0)
    Q = z1.random_configurations(5, rng)
    arm = rig.arm("arm111")
    expected = np.array([arm.T_world_base @ z1.fk(q) @ arm.T_wrist_cam for q in Q])
    np.testing.assert_allclose(rig.T_world_cam("arm111", Q), expected, atol=1e-12)
    np.testing.assert_allclose(rig.T_world_cam("arm111", Q[0]), expected[0], atol=1e-12)
    np.testing.assert_allclose(rig.camera_positions("arm111", Q), expected[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(rig.T_world_wrist("arm111", Q[1]), arm.T_world_base @ z1.fk(Q[1]), atol=1e-12)
    with pytest.raises(KinematicsError, match="arm112"):
        rig.T_world_cam("arm112", Q[0])
    with pytest.raises(KinematicsError, match="6 values"):
        rig.T_world_cam("arm110", np.zeros(5))


def test_T_world_cam_with_a_calibration_uses_it(rig, tmp_path: Path) -> None:
    cal = rig.nominal_calibration()
    arm = cal.arms["arm110"]
    arm.T_world_base = make_transform(rot_z(0.01), [-0.70, 0.002, 0.001])
    arm.T_wrist_cam = make_transform(rot_z(0.02) @ rig.arm("arm110").T_wrist_cam[:3, :3], [0.001, -0.002, 0.056])
    arm.joint_offsets_rad = np.array([0.01, -0.02, 0.015, 0.0, 0.01, -0.01])
    path = tmp_path / "calibration.json"
    write_calibration(path, cal)  # the nominal calibration is a valid calibration file
    cal = read_calibration(path)
    q = np.array([0.2, 1.3, -1.0, -0.3, 0.1, 0.2])
    got = rig.T_world_cam("arm110", q, calibration=cal)
    a = cal.arms["arm110"]
    np.testing.assert_allclose(got, a.T_world_base @ z1.fk(q + a.joint_offsets_rad) @ a.T_wrist_cam, atol=1e-12)
    wrong_sign = a.T_world_base @ z1.fk(q - a.joint_offsets_rad) @ a.T_wrist_cam
    assert np.linalg.norm(got[:3, 3] - wrong_sign[:3, 3]) > 0.01
    # the nominal calibration reproduces the nominal poses
    nominal = rig.nominal_calibration()
    np.testing.assert_allclose(rig.T_world_cam("arm111", q, calibration=nominal), rig.T_world_cam("arm111", q))
    assert nominal.arms["arm111"].serial == "405622074504"


def test_yaml_round_trip(rig, tmp_path: Path) -> None:
    path = tmp_path / "copy.yaml"
    path.write_text(rig.to_yaml())
    again = load_rig(path)
    assert again.arm_ids == rig.arm_ids
    for arm_id in rig.arm_ids:
        a, b = rig.arm(arm_id), again.arm(arm_id)
        np.testing.assert_allclose(b.T_world_base, a.T_world_base, atol=1e-10)
        np.testing.assert_allclose(b.T_wrist_cam, a.T_wrist_cam, atol=1e-10)
        np.testing.assert_array_equal(b.park_q_rad, a.park_q_rad)
        assert b.camera_serial == a.camera_serial
    assert again.table == rig.table and again.workspace == rig.workspace and again.margins == rig.margins
    assert again.base_separation_m == pytest.approx(1.3986)


def test_matrix_form_of_a_transform_is_accepted(tmp_path: Path) -> None:
    data = default_dict()
    T = make_transform(rot_z(np.radians(178.4)), [0.6993, 0.0, 0.0])
    data["arms"]["arm111"]["T_world_base"] = {"matrix": T.tolist()}
    rig = load_rig(write_yaml(tmp_path, data))
    assert rig.relative_yaw_deg == pytest.approx(178.4)


def _set(data: dict, dotted: str, value: Any) -> None:
    keys = dotted.split(".")
    for key in keys[:-1]:
        data = data[key]
    if value is _DELETE:
        del data[keys[-1]]
    else:
        data[keys[-1]] = value


_DELETE = object()
_SHEAR = [[1.0, 0.2, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("table.height_m", _DELETE, "table.height_m: missing field"),
        ("arms.arm110.T_flange_cam", _DELETE, "arms.arm110.T_flange_cam: missing field"),
        ("arms.arm111.T_world_base", {"matrix": _SHEAR}, "arms.arm111.T_world_base: not a rigid transform"),
        ("arms.arm110.T_world_base.xyz_m", [0.0, 0.0], "xyz_m: expected a list of 3 numbers"),
        ("arms.arm110.T_world_base.rpy_deg", [0, 0, "ninety"], "rpy_deg: expected numbers"),
        ("arms.arm110.park_q_rad", [0.0, -0.5, -1.2, 1.2, 0.0, 0.0], "park_q_rad: joint2"),
        ("arms.arm111.camera_serial", "348522076490", "both arms name camera"),
        ("arms.arm111.side", "left", "one left and one right"),
        ("arms.arm111.side", "middle", "arms.arm111.side: must be one of"),
        ("table.x_range_m", [0.5, -0.5], "table.x_range_m: expected [min, max]"),
        ("margins.table_clearance_m", -0.01, "margins.table_clearance_m"),
        ("camera_body.size_m", [0.09, 0.0, 0.025], "camera_body.size_m"),
        ("wrist_frame", "elbow", "wrist_frame: must be one of"),
        ("schema", "darp-rig/9", "schema: expected"),
        ("arms.arm111", _DELETE, "exactly two arms"),
        ("workspace", [1, 2], "workspace: expected a mapping"),
    ],
)
def test_invalid_rig_files_name_the_file_and_field(tmp_path: Path, field: str, value: Any, message: str) -> None:
    data = default_dict()
    _set(data, field, value)
    path = write_yaml(tmp_path, data, "broken_rig.yaml")
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    text = str(info.value)
    assert text.startswith(str(path) + ": "), text
    assert message in text
    assert "\n" not in text


def test_bad_yaml_syntax_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "syntax.yaml"
    path.write_text("name: x\narms:\n  arm110: {side: left\n")
    with pytest.raises(ConfigError, match=r"syntax\.yaml: invalid YAML at line \d+"):
        load_rig(path)


@pytest.mark.parametrize(("content", "message"), [("", "top level must be a mapping, got empty"),
                                                   ("- 1\n- 2\n", "got list")])
def test_non_mapping_files_are_refused(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "odd.yaml"
    path.write_text(content)
    with pytest.raises(ConfigError, match=message):
        load_rig(path)


def test_missing_rig_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_rig(tmp_path / "nope.yaml")


def test_rig_objects_are_read_only(rig) -> None:
    with pytest.raises(ValueError):
        rig.arm("arm110").T_world_base[0, 3] = 1.0
