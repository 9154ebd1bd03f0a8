"""Camera pose recovery (eq. 1): interpolation, no extrapolation, gaps, joint-zero sign, composition."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.errors import KinematicsError
from darp.kinematics import camera_poses as cp
from darp.kinematics import z1
from helpers.z1_reference import reference_fk


def random_rigid(rng: np.random.Generator, scale_m: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-scale_m, scale_m, 3)
    return T


def jittered_log(rng: np.random.Generator, t0: float = 100.0, n: int = 200, period_s: float = 0.03) -> np.ndarray:
    return t0 + np.cumsum(rng.uniform(0.6, 1.4, n) * period_s)


Q_BASE = np.array([0.1, 1.2, -1.0, -0.3, 0.2, 0.1])


def test_interpolation_is_exact_for_piecewise_linear_motion() -> None:
    rng = np.random.default_rng(1)
    t_log = jittered_log(rng)
    t_kink = t_log[77]  # the motion's kink is at a logged sample
    a = Q_BASE
    b = rng.uniform(-0.3, 0.3, 6)
    c = rng.uniform(-0.5, 0.5, 6)

    def q_true(t: np.ndarray) -> np.ndarray:
        return a + np.outer(t - t_log[0], b) + np.outer(np.maximum(t - t_kink, 0.0), c)

    queries = rng.uniform(t_log[0], t_log[-1], 500)
    res = cp.interpolate_joints(t_log, q_true(t_log), queries)
    assert np.all(res.posed)
    np.testing.assert_allclose(res.q_rad, q_true(queries), atol=1e-12)
    expected_qd = b + np.outer(queries > t_kink, c)
    np.testing.assert_allclose(res.qd_rad_s, expected_qd, atol=1e-9)


def test_queries_on_samples_and_ends_are_posed_and_exact() -> None:
    rng = np.random.default_rng(2)
    t_log = jittered_log(rng, n=20)
    q_log = rng.uniform(-1, 1, (20, 6))
    res = cp.interpolate_joints(t_log, q_log, t_log)
    assert np.all(res.posed)
    np.testing.assert_array_equal(res.q_rad, q_log)


def test_frames_outside_the_log_get_no_pose() -> None:
    rng = np.random.default_rng(3)
    t_log = jittered_log(rng, t0=10.0, n=50)
    q_log = np.tile(Q_BASE, (50, 1))
    frames = np.array([t_log[0] - 1.0, t_log[0] - 1e-6, t_log[0], t_log[10] + 0.001, t_log[-1], t_log[-1] + 1e-6, 1e9])
    res = cp.camera_poses(t_log, q_log, frames, T_world_base=np.eye(4), T_wrist_cam=np.eye(4))
    names = [cp.STATUS_NAMES[s] for s in res.status]
    assert names == ["before_log", "before_log", "posed", "posed", "posed", "after_log", "after_log"]
    assert np.all(np.isnan(res.T_world_cam[~res.posed]))
    assert np.all(np.isfinite(res.T_world_cam[res.posed]))
    assert res.counts() == {"frames": 7, "posed": 3, "before_log": 2, "after_log": 2, "in_gap": 0}


def test_gap_longer_than_threshold_is_not_bridged() -> None:
    t_log = np.array([0.0, 0.03, 0.06, 0.56, 0.59, 0.62, 0.72])  # 0.5 s dropout, then a 0.1 s step
    q_log = np.outer(t_log, np.ones(6))
    frames = np.array([0.045, 0.06, 0.2, 0.4, 0.56, 0.575, 0.67])
    res = cp.interpolate_joints(t_log, q_log, frames, max_gap_s=0.2)
    assert [cp.STATUS_NAMES[s] for s in res.status] == [
        "posed", "posed", "in_gap", "in_gap", "posed", "posed", "posed"]
    assert np.all(np.isnan(res.q_rad[res.status == cp.IN_GAP]))
    # the 0.1 s step stays below the threshold; a larger threshold bridges the dropout too
    assert np.isclose(res.q_rad[-1, 0], 0.67)
    wide = cp.interpolate_joints(t_log, q_log, frames, max_gap_s=0.6)
    assert np.all(wide.posed)
    np.testing.assert_allclose(wide.q_rad[:, 0], frames)
    tight = cp.interpolate_joints(t_log, q_log, frames, max_gap_s=0.05)
    assert tight.status[-1] == cp.IN_GAP


def test_joint_velocity_is_the_bracketing_slope() -> None:
    t_log = np.array([0.0, 0.1, 0.3, 0.35])
    q_log = np.zeros((4, 6))
    q_log[:, 1] = [0.0, 0.2, 0.2, 0.1]
    res = cp.interpolate_joints(t_log, q_log, np.array([0.05, 0.2, 0.34, 0.35]))
    np.testing.assert_allclose(res.qd_rad_s[:, 1], [2.0, 0.0, -2.0, -2.0])
    poses = cp.camera_poses(t_log, q_log + Q_BASE, np.array([0.05, 0.2]), T_world_base=np.eye(4), T_wrist_cam=np.eye(4))
    np.testing.assert_allclose(poses.joint_speed_rad_s, [2.0, 0.0])


def test_eq1_composition_matches_an_independent_computation() -> None:
    rng = np.random.default_rng(4)
    T_world_base, T_wrist_cam = random_rigid(rng), random_rigid(rng, 0.1)
    dq = rng.uniform(-0.02, 0.02, 6)
    t_log = jittered_log(rng, n=60)
    q_log = Q_BASE + 0.4 * np.sin(np.outer(t_log - t_log[0], rng.uniform(0.5, 2.0, 6)))
    frames = rng.uniform(t_log[0], t_log[-1], 40)
    res = cp.camera_poses(t_log, q_log, frames, T_world_base=T_world_base, T_wrist_cam=T_wrist_cam,
                          joint_offsets_rad=dq)
    assert np.all(res.posed)
    # point-by-point: a camera-frame point goes wrist -> base -> world; no 4x4 products
    R_wb, t_wb = Rotation.from_matrix(T_world_base[:3, :3]), T_world_base[:3, 3]
    R_fc, t_fc = Rotation.from_matrix(T_wrist_cam[:3, :3]), T_wrist_cam[:3, 3]
    p_cam = np.array([[0.0, 0.0, 0.0], [0.1, -0.05, 0.4]])
    for i, t in enumerate(frames):
        q = np.array([np.interp(t, t_log, q_log[:, j]) for j in range(6)]) + dq
        T_bf = reference_fk(q)  # written independently of darp.kinematics.z1, from the facts table
        R_bf, t_bf = Rotation.from_matrix(T_bf[:3, :3]), T_bf[:3, 3]
        p_world = R_wb.apply(R_bf.apply(R_fc.apply(p_cam) + t_fc) + t_bf) + t_wb
        got = p_cam @ res.T_world_cam[i, :3, :3].T + res.T_world_cam[i, :3, 3]
        np.testing.assert_allclose(got, p_world, atol=1e-9)


def test_joint_zero_offsets_are_added_not_subtracted() -> None:
    dq = np.array([0.05, -0.03, 0.04, 0.0, 0.02, 0.0])
    t_log = np.array([0.0, 1.0])
    q_log = np.stack([Q_BASE, Q_BASE])
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = [-0.7, 0.0, 0.0]
    T_wrist_cam = np.eye(4)
    T_wrist_cam[:3, 3] = [0.0, 0.0, 0.055]
    res = cp.camera_poses(t_log, q_log, np.array([0.5]), T_world_base=T_world_base, T_wrist_cam=T_wrist_cam,
                          joint_offsets_rad=dq, max_gap_s=2.0)
    plus = T_world_base @ z1.fk(Q_BASE + dq) @ T_wrist_cam
    minus = T_world_base @ z1.fk(Q_BASE - dq) @ T_wrist_cam
    np.testing.assert_allclose(res.T_world_cam[0], plus, atol=1e-12)
    assert np.linalg.norm(plus[:3, 3] - minus[:3, 3]) > 0.02  # the sign is observable
    # and the interpolated q reported is the logged one, before correction
    np.testing.assert_allclose(res.q_rad[0], Q_BASE)


def test_clock_offset_shifts_the_sampling_time() -> None:
    t_log = np.array([0.0, 1.0, 2.0])
    q_log = np.stack([Q_BASE, Q_BASE + 0.2, Q_BASE + 0.4])
    offset = 0.25  # camera clock ahead of the host clock
    res = cp.camera_poses(t_log, q_log, np.array([0.75, 2.1, 2.3]), T_world_base=np.eye(4),
                          T_wrist_cam=np.eye(4), clock_offset_s=offset, max_gap_s=2.0)
    np.testing.assert_allclose(res.t_s, [0.5, 1.85, 2.05])
    np.testing.assert_allclose(res.q_rad[0], Q_BASE + 0.1)
    assert [cp.STATUS_NAMES[s] for s in res.status] == ["posed", "posed", "after_log"]
    np.testing.assert_allclose(res.T_world_cam[0], z1.fk(Q_BASE + 0.1), atol=1e-12)


def test_custom_fk_and_wrist_frame() -> None:
    t_log = np.array([0.0, 1.0])
    q_log = np.stack([Q_BASE, Q_BASE])
    res = cp.camera_poses(t_log, q_log, np.array([0.5]), T_world_base=np.eye(4), T_wrist_cam=np.eye(4),
                          wrist_frame="gripper", max_gap_s=2.0)
    np.testing.assert_allclose(res.T_world_cam[0], z1.fk(Q_BASE, frame="gripper"), atol=1e-12)


def test_duplicate_log_times_are_handled() -> None:
    t_log = np.array([0.0, 0.5, 0.5, 1.0])
    q_log = np.outer([0.0, 0.5, 0.5, 1.0], np.ones(6))
    res = cp.interpolate_joints(t_log, q_log, np.array([0.25, 0.5, 0.75, 1.0]), max_gap_s=1.0)
    assert np.all(res.posed)
    np.testing.assert_allclose(res.q_rad[:, 0], [0.25, 0.5, 0.75, 1.0])
    assert np.all(np.isfinite(res.qd_rad_s))


@pytest.mark.parametrize(
    ("t_log", "q_log", "kwargs", "match"),
    [
        (np.empty(0), np.empty((0, 6)), {}, "empty"),
        (np.array([0.0, 1.0, 0.5]), np.zeros((3, 6)), {}, "backwards"),
        (np.array([0.0, 1.0]), np.zeros((3, 6)), {}, "shapes"),
        (np.array([0.0, np.nan]), np.zeros((2, 6)), {}, "non-finite"),
        (np.array([0.0, 1.0]), np.zeros((2, 6)), {"joint_offsets_rad": np.zeros(5)}, "offsets"),
        (np.array([0.0, 1.0]), np.zeros((2, 6)), {"max_gap_s": 0.0}, "max_gap_s"),
        (np.array([0.0, 1.0]), np.zeros((2, 6)), {"T_world_base": np.diag([1.0, 1.0, 2.0, 1.0])}, "rigid"),
    ],
)
def test_bad_inputs_raise(t_log: np.ndarray, q_log: np.ndarray, kwargs: dict, match: str) -> None:
    args = {"T_world_base": np.eye(4), "T_wrist_cam": np.eye(4), **kwargs}
    with pytest.raises(KinematicsError, match=match):
        cp.camera_poses(t_log, q_log, np.array([0.5]), **args)


def test_single_sample_log_poses_only_exact_hits() -> None:
    res = cp.interpolate_joints(np.array([1.0]), Q_BASE[None], np.array([0.9, 1.0, 1.1]))
    assert [cp.STATUS_NAMES[s] for s in res.status] == ["before_log", "posed", "after_log"]
    np.testing.assert_allclose(res.q_rad[1], Q_BASE)
