"""darp.geometry: the one rigidity rule, point transforms, skew/Rodrigues and the pinhole model, against scipy and
OpenCV; and the rule's consequence: what darp's readers accept, processing accepts."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation

from darp.errors import ConfigError, DarpError, FormatError, KinematicsError, ReconstructionError
from darp.geometry.pinhole import (
    backproject_rays,
    distort_normalised,
    normalised_pixels,
    project,
    undistort_normalised,
)
from darp.geometry.rigid import (
    NEAR_RIGID_LIMIT,
    RIGID_TOLERANCE,
    OrthonormalisedWarning,
    check_rigid,
    orthonormalised,
    rotation_error,
    warn_orthonormalised,
)
from darp.geometry.transforms import rotvec_to_rotation, skew, transform_columns, transform_points

RNG = np.random.default_rng(11)


def pose(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def off_orthonormal(T: np.ndarray, error: float) -> np.ndarray:
    """``T`` with its rotation scaled along x so that ``max |R^T R - I|`` is about ``error``."""
    out = T.copy()
    out[:3, 0] *= np.sqrt(1.0 + error)
    return out


# -- the rule ------------------------------------------------------------------------------------------------------

def test_six_decimal_rotations_are_rigid_and_a_scale_or_shear_is_not() -> None:
    T = pose(RNG.normal(size=3), RNG.normal(size=3))
    written = np.round(T, 6)  # a pose saved as %.6f text
    assert 1e-7 < rotation_error(written) < RIGID_TOLERANCE
    np.testing.assert_array_equal(check_rigid(written, "pose"), written)
    with pytest.raises(DarpError, match=r"pose: not a rigid transform: rotation is not orthonormal \(error 1\.4e-04"):
        check_rigid(off_orthonormal(T, 1.4e-4), "pose")
    shear = np.eye(4)
    shear[0, 1] = 0.2
    with pytest.raises(DarpError, match="not orthonormal"):
        check_rigid(shear, "shear")


@pytest.mark.parametrize(("change", "message"), [
    (lambda T: T @ np.diag([1.0, 1.0, -1.0, 1.0]), "rotation is a reflection"),
    (lambda T: np.vstack([T[:3], [0.0, 0.0, 0.1, 1.0]]), r"last row must be \[0, 0, 0, 1\]"),
    (lambda T: np.where(np.eye(4, dtype=bool), np.nan, T), "values must be finite"),
    (lambda T: T[:3], r"expected a 4x4 matrix, got shape \(3, 4\)"),
])
def test_each_broken_rule_is_named_with_the_callers_error_and_file(change, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError, match=f"rig.yaml: arms.arm110.T_world_base: .*{message}") as info:
        check_rigid(change(pose(np.array([0.1, 0.2, 0.3]), np.ones(3))), "arms.arm110.T_world_base",
                    Path("rig.yaml"), error=ConfigError)
    assert info.value.path == Path("rig.yaml")


def test_a_stack_names_its_first_bad_member() -> None:
    T = np.stack([pose(RNG.normal(size=3), RNG.normal(size=3)) for _ in range(5)])
    T[3] = off_orthonormal(T[3], 1e-3)
    with pytest.raises(KinematicsError, match=r"IK target\[3\]: not a rigid transform"):
        check_rigid(T, "IK target", error=KinematicsError)
    np.testing.assert_array_equal(check_rigid(T[:3], "IK target"), T[:3])


def test_near_rotations_become_the_nearest_rotation_and_far_ones_are_refused() -> None:
    T = pose(RNG.normal(size=3), RNG.normal(size=3))
    near = off_orthonormal(T, 1.4e-4)  # what real 7-Scenes pose files have
    fixed, err = orthonormalised(near, "pose", "frame-000001.pose.txt")
    assert err == pytest.approx(rotation_error(near)) and RIGID_TOLERANCE < err < NEAR_RIGID_LIMIT
    nearest, _ = scipy.linalg.polar(near[:3, :3])  # the orthogonal factor of the polar decomposition
    np.testing.assert_allclose(fixed[:3, :3], nearest, atol=1e-14)
    np.testing.assert_array_equal(fixed[:3, 3], near[:3, 3])
    check_rigid(fixed, "fixed")
    assert orthonormalised(T, "pose")[1] == 0.0
    with pytest.raises(FormatError, match=r"frame 7: not a rigid transform: rotation is not orthonormal"):
        orthonormalised(off_orthonormal(T, 2.5 * NEAR_RIGID_LIMIT), "frame 7", "t.log", error=FormatError)


def test_one_warning_per_file_names_it_and_the_largest_error() -> None:
    with pytest.warns(OrthonormalisedWarning, match=r"poses: 2 pose rotation\(s\) off orthonormal by up to 3\.0e-04"):
        warn_orthonormalised([0.0, 1.4e-4, 3e-4, 0.0], Path("poses"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_orthonormalised([0.0, 0.0], Path("poses"))


# -- what the readers accept, processing accepts -------------------------------------------------------------------

def test_a_pose_file_import_reads_is_a_pose_processing_takes(tmp_path: Path) -> None:
    from darp.formats.trajectories import read_pose_txt
    from darp.reconstruction.backproject import check_pose

    T = pose(np.array([0.3, -0.2, 1.0]), np.array([0.5, 0.1, 1.2]))
    for k, error in enumerate((0.0, 1.4e-4)):
        np.savetxt(tmp_path / f"frame-{k:06d}.pose.txt", off_orthonormal(T, error))
    with pytest.warns(OrthonormalisedWarning, match="1 pose rotation"):
        poses = read_pose_txt(tmp_path)
    for key in ("0", "1"):
        np.testing.assert_allclose(check_pose(poses[key]), T, atol=2e-4)
    with pytest.raises(ReconstructionError, match="T_world_cam: not a rigid transform"):  # as given, refused
        check_pose(off_orthonormal(T, 1.4e-4))


def test_a_calibration_the_reader_accepts_gives_camera_poses(tmp_path: Path) -> None:
    """A rotation 4e-6 off (a few six-decimal roundings): the calibration reader accepted it (1e-5) and eq. 1 refused
    it (1e-6)."""
    from darp.formats.calibration import read_calibration
    from darp.kinematics.camera_poses import camera_poses

    T_world_base = pose(np.array([0.01, -0.02, 1.5]), np.array([0.4, -0.3, 0.0]))
    T_wrist_cam = pose(np.array([1.2, 0.4, -0.3]), np.array([0.05, 0.0, 0.03]))
    T_wrist_cam[:3, 1] += 4e-6 * T_wrist_cam[:3, 0]  # a shear: R^T R off by 4e-6 off the diagonal
    assert 3.9e-6 < rotation_error(T_wrist_cam) < RIGID_TOLERANCE
    payload = {"schema_version": 1, "epoch": "e", "date": "2026-01-01T00:00:00+00:00",
               "arms": {"arm110": {"serial": "1", "T_world_base": T_world_base.tolist(),
                                   "T_wrist_cam": T_wrist_cam.tolist(), "joint_offsets_rad": [0.0] * 6}}}
    (tmp_path / "cal.json").write_text(json.dumps(payload))
    arm = read_calibration(tmp_path / "cal.json").arms["arm110"]
    out = camera_poses(np.arange(34) * 0.03, np.zeros((34, 6)), np.array([0.5]), T_world_base=arm.T_world_base,
                       T_wrist_cam=arm.T_wrist_cam)
    assert np.all(np.isfinite(out.T_world_cam))


# -- transforms ----------------------------------------------------------------------------------------------------

def test_transform_points_matches_scipy_single_batched_and_float32() -> None:
    rotvecs, ts, P = RNG.normal(size=(4, 3)), RNG.normal(size=(4, 3)), RNG.normal(size=(50, 3))
    T = np.stack([pose(r, t) for r, t in zip(rotvecs, ts, strict=True)])
    want = np.stack([Rotation.from_rotvec(r).apply(P) + t for r, t in zip(rotvecs, ts, strict=True)])
    np.testing.assert_allclose(transform_points(T[0], P), want[0], atol=1e-12)
    np.testing.assert_allclose(transform_points(T[:, None], P[None]), want, atol=1e-12)
    p32 = P.astype(np.float32)
    got32 = transform_columns(T[1], p32[:, 0], p32[:, 1], p32[:, 2])
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, want[1], atol=1e-5)
    with pytest.raises(KinematicsError, match="points"):
        transform_points(T[0], np.full((2, 3), np.nan))


def test_skew_is_the_cross_product_and_rodrigues_is_scipys() -> None:
    v, u = RNG.normal(size=(20, 3)), RNG.normal(size=(20, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(v), u), np.cross(v, u), atol=1e-14)
    w = np.concatenate([RNG.normal(size=(20, 3)), [[1e-9, 0.0, 0.0], [0.0, np.pi, 0.0]]])
    np.testing.assert_allclose(rotvec_to_rotation(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-14)


# -- pinhole -------------------------------------------------------------------------------------------------------

def test_backprojected_pixels_project_back() -> None:
    K = np.array([[610.0, 0.0, 321.3], [0.0, 612.0, 238.7], [0.0, 0.0, 1.0]])
    u, v, z = RNG.uniform(0, 640, 100), RNG.uniform(0, 480, 100), RNG.uniform(0.2, 3.0, 100)
    P = backproject_rays(*normalised_pixels(u, v, K[0, 0], K[1, 1], K[0, 2], K[1, 2]), z)
    np.testing.assert_allclose(P[:, 2], z)
    np.testing.assert_allclose(project(P, K), np.stack([u, v], axis=1), atol=1e-9)
    cv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, None)
    np.testing.assert_allclose(cv.reshape(-1, 2), np.stack([u, v], axis=1), atol=1e-9)


def test_brown_conrady_is_opencvs_and_undistortion_inverts_it() -> None:
    k = np.array([0.12, -0.25, 0.001, -0.0015, 0.08])
    x, y = RNG.uniform(-0.5, 0.5, 200), RNG.uniform(-0.4, 0.4, 200)
    xd, yd = distort_normalised(x, y, k, tangential_on_radial=False)
    cv, _ = cv2.projectPoints(np.stack([x, y, np.ones_like(x)], axis=1), np.zeros(3), np.zeros(3), np.eye(3), k)
    np.testing.assert_allclose(np.stack([xd, yd], axis=1), cv.reshape(-1, 2), atol=1e-12)
    for inverse in (False, True):
        xd, yd = distort_normalised(x, y, k, inverse)
        xu, yu = undistort_normalised(xd, yd, k, inverse, iterations=30)
        np.testing.assert_allclose(np.stack([xu, yu]), np.stack([x, y]), atol=1e-9)
