"""IK: round trips on random reachable poses, failures that say why, and look-at placement."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import KinematicsError
from darp.kinematics import ik, z1
from darp.kinematics import transforms as tf
from darp.kinematics.collision import NOMINAL_T_WRIST_CAM

TOL = 1e-6


def _check_exact(result: ik.IKResult, T_target: np.ndarray, frame: str = "flange", limits: str = "urdf") -> None:
    assert result.success, result.message
    assert z1.within_limits(result.q, limits)
    pos, rot = tf.pose_error(z1.fk(result.q, frame), T_target)
    assert pos < TOL and rot < TOL
    assert result.position_error_m == pytest.approx(pos, abs=1e-12)
    assert result.rotation_error_rad == pytest.approx(rot, abs=1e-12)


def test_round_trip_1000_random_reachable_poses() -> None:
    Q = z1.random_configurations(1000, np.random.default_rng(11))
    T = z1.fk_batch(Q)
    results = [ik.solve_ik(T[i]) for i in range(len(Q))]
    ok = np.array([r.success for r in results])
    assert ok.mean() >= 0.99
    for r, T_i in zip(results, T, strict=True):
        if r.success:
            _check_exact(r, T_i)
    assert max(r.position_error_m for r in results if r.success) < TOL
    assert max(r.rotation_error_rad for r in results if r.success) < TOL


def test_nearest_solution_to_q_init_is_the_generating_one() -> None:
    Q = z1.random_configurations(200, np.random.default_rng(12))
    for q in Q:
        r = ik.solve_ik(z1.fk(q), q_init=q + 0.01)
        _check_exact(r, z1.fk(q))
        np.testing.assert_allclose(r.q, q, atol=1e-7)
        assert len(r.solutions) >= 1
        for alt in r.solutions:  # every alternative listed is exact as well
            assert tf.translation_error_m(z1.fk(alt), z1.fk(q)) < TOL


def test_batch_closed_form_matches_and_flags_failures() -> None:
    Q = z1.random_configurations(3000, np.random.default_rng(13))
    T = z1.fk_batch(Q)
    far = T[:10].copy()
    far[:, :3, 3] += [2.0, 0.0, 0.0]
    Qs, ok, pos, rot = ik.solve_ik_batch(np.concatenate([T, far]), q_init=np.concatenate([Q, Q[:10]]))
    assert ok[:3000].mean() >= 0.99 and not ok[3000:].any()
    assert np.all(np.isnan(Qs[3000:]))
    good = np.flatnonzero(ok)
    np.testing.assert_allclose(Qs[good], np.concatenate([Q, Q[:10]])[good], atol=1e-7)
    assert np.nanmax(pos) < TOL and np.nanmax(rot) < TOL


def test_gripper_frame_and_sdk_limits() -> None:
    Q = z1.random_configurations(200, np.random.default_rng(14), "sdk")
    for q in Q:
        T = z1.fk(q, "gripper")
        _check_exact(ik.solve_ik(T, frame="gripper", limits="sdk"), T, "gripper", "sdk")


def test_numeric_solver_alone_round_trips() -> None:
    Q = z1.random_configurations(100, np.random.default_rng(15))
    results = [ik.solve_ik(z1.fk(q), method="numeric", seed=i) for i, q in enumerate(Q)]
    assert np.mean([r.success for r in results]) >= 0.95
    for r, q in zip(results, Q, strict=True):
        if r.success:
            _check_exact(r, z1.fk(q))
            assert r.iterations > 0


def test_numeric_solver_respects_limits_near_boundaries() -> None:
    # Configurations on the joint-2/joint-3 limits (q2 = 0, q3 = 0 are both limits).
    for q in ([0.3, 0.0, -1.0, 0.2, 0.1, 0.0], [0.0, 1.2, 0.0, -0.5, 0.0, 0.4], z1.NAMED_CONFIGS["zero"]):
        T = z1.fk(np.asarray(q, dtype=float))
        for method in ("auto", "numeric"):
            _check_exact(ik.solve_ik(T, method=method), T)


def test_far_target_fails_with_reason() -> None:
    T = tf.make_transform(t=[1.5, 0.0, 0.3])
    for method in ("auto", "analytic", "numeric"):
        r = ik.solve_ik(T, method=method)
        assert not r.success
        assert r.position_error_m > 0.5
    assert "out of reach" in ik.solve_ik(T).message
    assert "did not converge" in ik.solve_ik(T, method="numeric").message


def test_pose_reachable_only_outside_limits_fails_with_reason() -> None:
    q_out = np.array([1.6, -0.83, -1.4, -0.65, -1.2, -0.65])  # joint 2 below its 0 limit
    T = z1.fk(q_out)
    r = ik.solve_ik(T)
    assert not r.success
    assert "violate joint limits" in r.message
    # The closed form is complete: one of its (limit-free) branches is the generating configuration.
    Q, ok, _ = ik.analytic_ik(T[None])
    assert np.min(np.linalg.norm(Q[0][ok[0]] - q_out, axis=1)) < 1e-9


def test_closed_form_failures_are_confirmed_by_the_numeric_solver() -> None:
    """Never silently wrong either way: where the closed form finds nothing within limits (though
    the wrist can reach), LM from 30 seeds finds nothing either, and every success is exact."""
    rng = np.random.default_rng(16)
    failures = successes = 0
    while failures < 12:
        T = tf.make_transform(tf.rotvec_to_rotation(rng.normal(size=3)),
                              rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 0.6]))
        r = ik.solve_ik(T)
        if r.success:
            _check_exact(r, T)
            successes += 1
            continue
        if "violate joint limits" not in r.message:
            continue  # out of reach: nothing to confirm
        failures += 1
        numeric = ik.solve_ik(T, method="numeric", n_random_seeds=24, seed=1, max_iters=60)
        assert not numeric.success
    assert successes > 0


def test_invalid_targets_raise() -> None:
    with pytest.raises(KinematicsError, match="shape"):
        ik.solve_ik(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(KinematicsError, match="orthonormal"):
        ik.solve_ik(bad)
    with pytest.raises(KinematicsError, match="method"):
        ik.solve_ik(np.eye(4), method="magic")
    with pytest.raises(KinematicsError, match="unknown Z1 frame"):
        ik.solve_ik(z1.fk(z1.NAMED_CONFIGS["forward"]), frame="tcp")


def _targets(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0.25, 0.5, n), rng.uniform(-0.25, 0.25, n), rng.uniform(0.0, 0.15, n)])


def _check_look_at(r: ik.LookAtResult, target: np.ndarray, distance: float) -> None:
    assert r.success, r.message
    assert z1.within_limits(r.q)
    T_bc = z1.fk(r.q) @ NOMINAL_T_WRIST_CAM  # recomputed independently of the result's pose
    np.testing.assert_allclose(r.T_base_cam, T_bc, atol=1e-12)
    rel = target - T_bc[:3, 3]
    depth = rel @ T_bc[:3, 2]
    assert np.linalg.norm(rel - depth * T_bc[:3, 2]) < TOL  # optical axis through the target
    assert abs(depth - distance) < TOL
    assert r.axis_offset_m < TOL and abs(r.distance_error_m) < TOL


def test_look_at_with_given_view_direction() -> None:
    for i, target in enumerate(_targets(30, 21)):
        view_dir = target - np.array([0.0, 0.0, 0.45])  # from above and behind, like an orbit view
        distance = 0.30 + 0.05 * (i % 3)
        r = ik.solve_look_at(target, distance, T_frame_cam=NOMINAL_T_WRIST_CAM, view_dir_base=view_dir)
        _check_look_at(r, target, distance)
        z_cam = r.T_base_cam[:3, 2]
        assert np.arccos(np.clip(z_cam @ view_dir / np.linalg.norm(view_dir), -1, 1)) < TOL
        assert r.view_angle_error_rad < TOL
        assert r.T_base_cam[:3, 1] @ [0, 0, 1] < 0  # default preference: image upright


def test_look_at_with_free_direction() -> None:
    for target in _targets(20, 22):
        r = ik.solve_look_at(target, 0.32, T_frame_cam=NOMINAL_T_WRIST_CAM)
        _check_look_at(r, target, 0.32)


def test_look_at_roll_follows_up_hint_and_q_init() -> None:
    target = np.array([0.4, 0.05, 0.05])
    view_dir = target - np.array([0.1, 0.0, 0.4])
    up = np.array([0.0, 1.0, 0.0])
    r = ik.solve_look_at(target, 0.3, T_frame_cam=NOMINAL_T_WRIST_CAM, view_dir_base=view_dir, up_hint=up)
    _check_look_at(r, target, 0.3)
    image_up = -r.T_base_cam[:3, 1]
    up_perp = up - (up @ r.T_base_cam[:3, 2]) * r.T_base_cam[:3, 2]
    angle = np.arccos(np.clip(image_up @ up_perp / np.linalg.norm(up_perp), -1, 1))
    assert r.roll_rad == 0.0 and angle < 1e-9  # exactly upright to the hint (reachable here)
    # With only q_init, the solution stays near it: a small target move gives a small joint move.
    r0 = ik.solve_look_at(target, 0.3, T_frame_cam=NOMINAL_T_WRIST_CAM, view_dir_base=view_dir)
    r1 = ik.solve_look_at(target + [0.005, 0.0, 0.0], 0.3, T_frame_cam=NOMINAL_T_WRIST_CAM,
                          view_dir_base=view_dir, q_init=r0.q)
    _check_look_at(r1, target + [0.005, 0.0, 0.0], 0.3)
    assert np.max(np.abs(r1.q - r0.q)) < 0.1


def test_look_at_impossible_requests() -> None:
    target = np.array([0.4, 0.0, 0.05])
    r = ik.solve_look_at(target, 2.0, T_frame_cam=NOMINAL_T_WRIST_CAM, view_dir_base=[1.0, 0.0, -0.5])
    assert not r.success and "no joint solution" in r.message
    with pytest.raises(KinematicsError, match="positive"):
        ik.solve_look_at(target, -0.1, T_frame_cam=NOMINAL_T_WRIST_CAM)
    with pytest.raises(KinematicsError, match="4x4"):
        ik.solve_look_at(target, 0.3, T_frame_cam=np.eye(3))
