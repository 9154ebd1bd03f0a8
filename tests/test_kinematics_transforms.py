"""Property tests of darp.kinematics.transforms (SE(3)/SO(3) algebra), with scipy as the oracle."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from darp.errors import KinematicsError
from darp.kinematics import transforms as tf

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=finite)
quat = arrays(np.float64, 4, elements=st.floats(-1.0, 1.0, allow_nan=False)).filter(
    lambda q: np.linalg.norm(q) > 0.1)
angles = st.floats(-np.pi, np.pi, allow_nan=False)
# Deterministic examples and no per-example deadline (the CI machine may be loaded).
stable = settings(derandomize=True, deadline=None)


def random_pose(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    return tf.make_transform(tf.quaternion_to_rotation(q), t)


@stable
@given(quat, vec3)
def test_inverse_composes_to_identity(q: np.ndarray, t: np.ndarray) -> None:
    T = random_pose(q, t)
    np.testing.assert_allclose(T @ tf.invert_transform(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(tf.invert_transform(T), np.linalg.inv(T), atol=1e-12)


@stable
@given(quat, vec3, quat, vec3, vec3)
def test_composition_and_point_mapping(q1: np.ndarray, t1: np.ndarray, q2: np.ndarray, t2: np.ndarray,
                                       p: np.ndarray) -> None:
    T_a_b, T_b_c = random_pose(q1, t1), random_pose(q2, t2)
    T_a_c = T_a_b @ T_b_c
    np.testing.assert_allclose(tf.invert_transform(T_a_c),
                               tf.invert_transform(T_b_c) @ tf.invert_transform(T_a_b), atol=1e-11)
    np.testing.assert_allclose(tf.transform_points(T_a_c, p),
                               tf.transform_points(T_a_b, tf.transform_points(T_b_c, p)), atol=1e-11)
    batch = tf.transform_points(np.stack([T_a_b, T_a_c]), np.stack([p, p]))
    np.testing.assert_allclose(batch[1], tf.transform_points(T_a_c, p), atol=1e-12)


@stable
@given(quat)
def test_quaternion_round_trip_and_scipy_agreement(q: np.ndarray) -> None:
    R = tf.quaternion_to_rotation(q)
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-12)  # scipy: (x, y, z, w)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = tf.rotation_to_quaternion(R)
    unit = q / np.linalg.norm(q)
    assert back[3] >= 0.0
    assert min(np.linalg.norm(back - unit), np.linalg.norm(back + unit)) < 1e-10


@stable
@given(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0, allow_nan=False)), st.floats(0.0, np.pi - 1e-6))
def test_rotvec_round_trip(axis: np.ndarray, angle: float) -> None:
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    rotvec = axis / np.linalg.norm(axis) * angle
    R = tf.rotvec_to_rotation(rotvec)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(tf.rotation_to_rotvec(R), rotvec, atol=1e-9)
    np.testing.assert_allclose(tf.axis_angle_to_rotation(axis, angle), R, atol=1e-12)
    assert tf.rotation_error_rad(np.eye(3), R) == pytest.approx(angle, abs=1e-9)


@stable
@given(angles, st.floats(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3), angles, vec3)
def test_sdk_posture_convention(roll: float, pitch: float, yaw: float, xyz: np.ndarray) -> None:
    R = tf.rpy_to_rotation(roll, pitch, yaw)
    # R = Rz(yaw) Ry(pitch) Rx(roll) is scipy's intrinsic "ZYX" with angles (yaw, pitch, roll).
    np.testing.assert_allclose(R, Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(tf.rotation_to_rpy(R), [roll, pitch, yaw], atol=1e-9)
    posture = np.array([roll, pitch, yaw, *xyz])
    T = tf.posture_to_transform(posture)
    np.testing.assert_allclose(tf.transform_to_posture(T), posture, atol=1e-9)


def test_rpy_gimbal_lock_still_reconstructs_rotation() -> None:
    R = tf.rpy_to_rotation(0.3, np.pi / 2, -0.4)
    np.testing.assert_allclose(tf.rpy_to_rotation(*tf.rotation_to_rpy(R)), R, atol=1e-12)


def test_rotvec_near_pi_is_accurate() -> None:
    rotvec = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5]) * (np.pi - 1e-9)
    back = tf.rotation_to_rotvec(tf.rotvec_to_rotation(rotvec))
    assert np.linalg.norm(back) == pytest.approx(np.pi - 1e-9, abs=1e-8)
    assert abs(abs(back @ rotvec) / (np.linalg.norm(back) * np.linalg.norm(rotvec)) - 1.0) < 1e-12


@given(vec3, vec3)
@settings(stable, max_examples=200)
def test_look_at_is_opencv_and_upright(eye: np.ndarray, target: np.ndarray) -> None:
    forward = target - eye
    if np.linalg.norm(forward) < 1e-3 or np.linalg.norm(np.cross(forward, [0, 0, 1])) < 1e-3 * np.linalg.norm(forward):
        return
    T = tf.look_at(eye, target)
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], forward / np.linalg.norm(forward), atol=1e-12)  # z forward
    assert R[:, 1] @ np.array([0.0, 0.0, 1.0]) < 0.0  # image y points down (away from up)
    assert abs(R[:, 0][2]) < 1e-12  # image x stays horizontal
    # The target projects onto the principal point: (0, 0, depth) in the camera frame.
    p_cam = tf.transform_points(tf.invert_transform(T), target)
    np.testing.assert_allclose(p_cam[:2], 0.0, atol=1e-9)
    assert p_cam[2] > 0


def test_orthonormalize_and_errors() -> None:
    R = tf.rotvec_to_rotation([0.1, 0.2, 0.3])
    noisy = R + 1e-4 * np.arange(9).reshape(3, 3)
    fixed = tf.orthonormalize(noisy)
    np.testing.assert_allclose(fixed.T @ fixed, np.eye(3), atol=1e-12)
    assert tf.rotation_error_rad(fixed, R) < 1e-3
    T1, T2 = tf.make_transform(R, [1, 2, 3]), tf.make_transform(np.eye(3), [1, 2, 4])
    pos, rot = tf.pose_error(T1, T2)
    assert pos == pytest.approx(1.0)
    assert rot == pytest.approx(np.linalg.norm([0.1, 0.2, 0.3]))


def test_bad_input_raises_darp_errors() -> None:
    with pytest.raises(KinematicsError, match="shape"):
        tf.make_transform(np.eye(2))
    with pytest.raises(KinematicsError, match="NaN"):
        tf.invert_transform(np.full((4, 4), np.nan))
    with pytest.raises(KinematicsError, match="zero norm"):
        tf.quaternion_to_rotation([0, 0, 0, 0])
    with pytest.raises(KinematicsError, match="parallel"):
        tf.look_at([0, 0, 0], [0, 0, 1])
    with pytest.raises(KinematicsError, match="coincide"):
        tf.look_at([1, 1, 1], [1, 1, 1])


def test_compose_and_matvec_equal_matmul_to_rounding() -> None:
    rng = np.random.default_rng(3)
    A, B, C = rng.standard_normal((3, 5, 4, 4))
    np.testing.assert_allclose(tf.compose(A, B, C), A @ B @ C, rtol=0, atol=1e-13)
    np.testing.assert_allclose(tf.compose(A[0], B), A[0] @ B, rtol=0, atol=1e-13)  # broadcast like @
    np.testing.assert_array_equal(tf.compose(A), A)
    v = rng.standard_normal((5, 4))
    np.testing.assert_allclose(tf.matvec(A, v), (A @ v[..., None])[..., 0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(tf.matvec(A[0], v), v @ A[0].T, rtol=0, atol=1e-13)
    with pytest.raises(KinematicsError):
        tf.compose()


KERNEL_PROBE = """
import hashlib
import numpy as np
from darp.kinematics import transforms as tf
A, B = np.random.default_rng(0).standard_normal((2, 50, 4, 4))
print(hashlib.sha256((A @ B).tobytes()).hexdigest())
print(hashlib.sha256(tf.compose(A, B).tobytes() + tf.matvec(A, B[:, 0]).tobytes()
                     + tf.rpy_to_rotation(*A[:, :3, 0].T).tobytes()).hexdigest())
"""


def test_compose_and_matvec_do_not_depend_on_the_openblas_kernel() -> None:
    """``@`` gives other bits with OpenBLAS's Haswell (FMA) and Sandybridge kernels; compose does not."""
    src = str(Path(tf.__file__).resolve().parents[2])  # the child imports the same darp as this process
    pythonpath = os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p)
    out = {}
    for kernel in ("Haswell", "Sandybridge"):
        result = subprocess.run([sys.executable, "-c", KERNEL_PROBE], capture_output=True, text=True, check=False,
                                env={**os.environ, "PYTHONPATH": pythonpath, "OPENBLAS_CORETYPE": kernel})
        if result.returncode == -4:  # SIGILL
            pytest.skip(f"this CPU cannot run the OpenBLAS {kernel} kernel")
        assert result.returncode == 0, result.stderr
        out[kernel] = result.stdout.split()
    if out["Haswell"][0] == out["Sandybridge"][0]:
        pytest.skip("OPENBLAS_CORETYPE had no effect (numpy without a dynamic-arch OpenBLAS?)")
    assert out["Haswell"][1] == out["Sandybridge"][1]
