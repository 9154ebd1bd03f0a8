"""``truth_errors``, which grades every calibration accuracy test, against calibrations with a known injected error.

The truth is a rig in darp's world definition (base origins at x = -+0.7 m on the table, z up); each case
changes one quantity of the estimate by a known amount and checks that exactly that error is reported, in the
right unit, sign and frame, and nothing else. Expected values are derived by hand (rotations built with scipy),
not with darp's pose arithmetic.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.calibration.evaluate import truth_errors
from darp.formats.calibration import ArmCalibration, Calibration
from darp.kinematics import z1

ARMS = ("arm110", "arm111")
SEPARATION_MM = 1400.0
T_WRIST_CAM_T = np.array([0.012, -0.018, 0.055])  # camera origin in the flange frame (m)
TRUE_DQ = np.array([0.004, -0.003, 0.002, 0.001, -0.002, 0.003])
Q = {arm: z1.random_configurations(8, seed) for seed, arm in enumerate(ARMS)}


def pose(rotvec: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
         t: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def about(axis: str, angle_rad: float) -> np.ndarray:
    """A pure rotation about a coordinate axis (4x4)."""
    return pose(angle_rad * np.eye(3)["xyz".index(axis)])


def truth() -> Calibration:
    arms = {
        "arm110": ArmCalibration("348522076490", pose((0.0, 0.0, 0.02), (-0.7, 0.0, 0.0)),
                                 pose((0.1, 1.5, -0.2), T_WRIST_CAM_T), TRUE_DQ.copy()),
        "arm111": ArmCalibration("405622074504", pose((0.0, 0.0, np.pi - 0.03), (0.7, 0.0, 0.0)),
                                 pose((-0.2, 1.4, 0.1), T_WRIST_CAM_T), -TRUE_DQ),
    }
    return Calibration(epoch="truth", date="2025-01-01", arms=arms)


def errors(est: Calibration, true: Calibration | None = None, **kwargs: Any) -> dict[str, Any]:
    return truth_errors(est, truth() if true is None else true, ARMS, q_by_arm=Q, **kwargs)


def assert_pose_err(entry: dict[str, float], mm: float, deg: float) -> None:
    assert entry["translation_mm"] == pytest.approx(mm, abs=1e-6)
    assert entry["rotation_deg"] == pytest.approx(deg, abs=1e-6)


def assert_camera(entry: dict[str, float], mm: float, deg: float) -> None:
    """The same camera pose error at every configuration: median and max equal."""
    for key in ("translation_mm_median", "translation_mm_max"):
        assert entry[key] == pytest.approx(mm, abs=1e-6), key
    for key in ("rotation_deg_median", "rotation_deg_max"):
        assert entry[key] == pytest.approx(deg, abs=1e-6), key


def assert_zero_except(out: dict[str, Any], *changed: str) -> None:
    """Every reported error not named in ``changed`` ("arm111.hand_eye", "base_to_base", ...) is zero."""
    for arm in ARMS:
        entry = out["arms"][arm]
        for key in ("hand_eye", "base_in_world"):
            if f"{arm}.{key}" not in changed:
                assert_pose_err(entry[key], 0.0, 0.0)
        if f"{arm}.camera_pose" not in changed:
            assert_camera(entry["camera_pose"], 0.0, 0.0)
        if f"{arm}.joints" not in changed:
            assert entry["joint_offset_error_deg"] == pytest.approx([0.0] * 6, abs=1e-9)
            assert entry["max_identifiable_joint_offset_error_deg"] == pytest.approx(0.0, abs=1e-9)
    if "base_to_base" not in changed:
        assert_pose_err(out["base_to_base"], 0.0, 0.0)


def test_the_truth_against_itself_is_zero_everywhere() -> None:
    out = errors(truth())
    assert set(out) == {"arms", "base_to_base"} and set(out["arms"]) == set(ARMS)
    assert_zero_except(out)


def test_the_truth_in_another_world_is_reexpressed_in_darps_before_comparing() -> None:
    """A truth given in any frame (here turned, lifted and tilted 10 deg about x) is first re-expressed in
    darp's world (base midpoint, base-to-base x, ``truth_up``); the estimate is taken as given."""
    G = pose((np.radians(10.0), 0.0, 0.0), (0.3, -0.2, 0.75)) @ about("z", 0.7)
    elsewhere = truth()
    for arm in elsewhere.arms.values():
        arm.T_world_base = G @ arm.T_world_base
    assert_zero_except(errors(truth(), elsewhere, truth_up=G[:3, :3] @ [0.0, 0.0, 1.0]))
    # a frame tilted 10 deg about the base-to-base line, read with the wrong up (that frame's z): darp's world
    # is tilted by as much, so each base is reported turned by exactly 10 deg, not moved; base-to-base does
    # not depend on the world
    tilted_frame = pose((np.radians(10.0), 0.0, 0.0), (0.3, -0.2, 0.75))
    elsewhere = truth()
    for arm in elsewhere.arms.values():
        arm.T_world_base = tilted_frame @ arm.T_world_base
    tilted = errors(truth(), elsewhere)
    for arm in ARMS:
        assert_pose_err(tilted["arms"][arm]["base_in_world"], 0.0, 10.0)
    assert_pose_err(tilted["base_to_base"], 0.0, 0.0)


def test_a_hand_eye_translation_error_is_its_length_in_mm() -> None:
    est = truth()
    est.arms["arm111"].T_wrist_cam = est.arms["arm111"].T_wrist_cam.copy()
    est.arms["arm111"].T_wrist_cam[:3, 3] += [0.002, 0.0, -0.001]  # in the flange frame
    out = errors(est)
    assert_pose_err(out["arms"]["arm111"]["hand_eye"], np.sqrt(5.0), 0.0)
    assert_camera(out["arms"]["arm111"]["camera_pose"], np.sqrt(5.0), 0.0)  # the camera moves with it everywhere
    assert_zero_except(out, "arm111.hand_eye", "arm111.camera_pose")


def test_a_hand_eye_rotation_error_is_its_angle_in_degrees() -> None:
    est = truth()
    est.arms["arm110"].T_wrist_cam = est.arms["arm110"].T_wrist_cam @ pose(np.radians(0.3) * np.array([0.6, 0.0, 0.8]))
    out = errors(est)
    assert_pose_err(out["arms"]["arm110"]["hand_eye"], 0.0, 0.3)  # turned about the camera's own origin
    assert_camera(out["arms"]["arm110"]["camera_pose"], 0.0, 0.3)
    assert_zero_except(out, "arm110.hand_eye", "arm110.camera_pose")


def test_a_base_moved_in_the_world_moves_base_to_base_by_as_much() -> None:
    est = truth()
    est.arms["arm111"].T_world_base = pose(t=(0.0, 0.003, 0.004)) @ est.arms["arm111"].T_world_base
    out = errors(est)
    assert_pose_err(out["arms"]["arm111"]["base_in_world"], 5.0, 0.0)
    assert_pose_err(out["base_to_base"], 5.0, 0.0)
    assert_camera(out["arms"]["arm111"]["camera_pose"], 5.0, 0.0)
    assert_zero_except(out, "arm111.base_in_world", "base_to_base", "arm111.camera_pose")


def test_a_base_yaw_error_swings_the_other_base_in_base_to_base() -> None:
    """arm110's base turned 0.5 deg about its own vertical axis: in its frame, arm111's base (1.4 m away, level)
    moves along an arc of chord 2 * 1400 mm * sin(0.25 deg)."""
    est = truth()
    est.arms["arm110"].T_world_base = est.arms["arm110"].T_world_base @ about("z", np.radians(0.5))
    out = errors(est)
    assert_pose_err(out["arms"]["arm110"]["base_in_world"], 0.0, 0.5)
    assert_pose_err(out["base_to_base"], 2.0 * SEPARATION_MM * np.sin(np.radians(0.25)), 0.5)
    cam = out["arms"]["arm110"]["camera_pose"]
    assert cam["rotation_deg_median"] == pytest.approx(0.5, abs=1e-6)
    assert cam["translation_mm_max"] > 0.0
    assert_zero_except(out, "arm110.base_in_world", "base_to_base", "arm110.camera_pose")


def test_joint_offset_errors_are_estimate_minus_truth_in_degrees_per_joint() -> None:
    injected_deg = np.array([0.0, 0.1, -0.2, 0.0, 0.05, 0.0])  # joints 2, 3, 5: neither base nor hand-eye
    est = truth()
    est.arms["arm110"].joint_offsets_rad = est.arms["arm110"].joint_offsets_rad + np.radians(injected_deg)
    out = errors(est)
    entry = out["arms"]["arm110"]
    assert entry["joint_offset_error_deg"] == pytest.approx(injected_deg.tolist(), abs=1e-9)
    assert entry["max_identifiable_joint_offset_error_deg"] == pytest.approx(0.2, abs=1e-9)
    assert entry["camera_pose"]["translation_mm_max"] > 0.1  # the chain moves the camera
    assert_zero_except(out, "arm110.joints", "arm110.camera_pose")
    # joints not identifiable are left out: None in the list, not in the maximum
    ident = {"arm110": np.array([True, True, False, True, True, True]), "arm111": np.ones(6, bool)}
    masked = errors(est, identifiable=ident)["arms"]["arm110"]
    assert masked["joint_offset_error_deg"][2] is None
    assert masked["joint_offset_error_deg"][1] == pytest.approx(0.1, abs=1e-9)
    assert masked["max_identifiable_joint_offset_error_deg"] == pytest.approx(0.1, abs=1e-9)
    none = errors(est, identifiable={arm: np.zeros(6, bool) for arm in ARMS})["arms"]["arm110"]
    assert none["joint_offset_error_deg"] == [None] * 6 and none["max_identifiable_joint_offset_error_deg"] is None


def test_joint_1_and_6_offsets_are_one_with_the_base_yaw_and_the_hand_eye() -> None:
    """dq1 turns the arm about the base z, dq6 the flange about its x: a calibration that trades one for the
    other sees the same camera poses and is graded only on the joint offset."""
    delta, eps = np.radians(0.4), np.radians(-0.7)
    traded = truth()
    arm = traded.arms["arm111"]
    arm.joint_offsets_rad = arm.joint_offsets_rad + [delta, 0.0, 0.0, 0.0, 0.0, eps]
    arm.T_world_base = arm.T_world_base @ about("z", -delta)
    arm.T_wrist_cam = about("x", -eps) @ arm.T_wrist_cam
    out = errors(traded)
    assert out["arms"]["arm111"]["joint_offset_error_deg"] == pytest.approx([0.4, 0, 0, 0, 0, -0.7], abs=1e-9)
    assert_zero_except(out, "arm111.joints")
    # the same dq6 error without the trade: the camera turns about the flange x axis by 0.7 deg, its origin
    # on a circle of radius |(t_y, t_z)| around that axis
    alone = truth()
    alone.arms["arm110"].joint_offsets_rad = alone.arms["arm110"].joint_offsets_rad + [0, 0, 0, 0, 0, eps]
    out = errors(alone)
    chord_mm = 1e3 * 2.0 * np.hypot(*T_WRIST_CAM_T[1:]) * np.sin(abs(eps) / 2)
    assert_pose_err(out["arms"]["arm110"]["hand_eye"], chord_mm, 0.7)
    assert_camera(out["arms"]["arm110"]["camera_pose"], chord_mm, 0.7)
    assert_zero_except(out, "arm110.joints", "arm110.hand_eye", "arm110.camera_pose")


def test_camera_poses_only_where_configurations_are_given() -> None:
    est = truth()
    assert "camera_pose" not in truth_errors(est, truth(), ARMS)["arms"]["arm110"]
    partial = truth_errors(est, truth(), ARMS, q_by_arm={"arm110": Q["arm110"], "arm111": np.zeros((0, 6))})
    assert "camera_pose" in partial["arms"]["arm110"] and "camera_pose" not in partial["arms"]["arm111"]
