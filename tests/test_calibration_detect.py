"""Corner detection, single-image pose and rejection reasons; undistortion against librealsense and OpenCV."""

from __future__ import annotations

import numpy as np
import pyrealsense2 as rs
import pytest

from darp.calibration.board import DEFAULT_BOARD, corners_board_m
from darp.calibration.captures import CaptureRecord
from darp.calibration.detect import CharucoCornerDetector, DetectionSettings
from darp.calibration.geometry import undistort_pixels
from darp.errors import CalibrationError
from darp.formats.realsense.types import Intrinsics
from darp.kinematics.transforms import look_at, pose_error
from helpers.calibration_synthetic import COLOR, render_board

T_WORLD_BOARD = np.eye(4)


def _record(intr: Intrinsics = COLOR) -> CaptureRecord:
    return CaptureRecord("arm110_000", "arm110", "348522076490", 0.0, np.zeros(6), "color", "x.png", intr, np.eye(4))


def _view(eye: list[float], target: list[float] | None = None) -> np.ndarray:
    """``T_cam_board`` for a camera at ``eye`` (board frame; the printed face looks along -z) looking at ``target``."""
    centre = [0.15, 0.105, 0.0] if target is None else target
    T_board_cam = look_at(eye, centre, up=[0.0, -1.0, 0.0])
    return np.linalg.inv(T_board_cam)


@pytest.mark.parametrize("eye", [[0.15, 0.105, -0.40], [0.35, 0.0, -0.35], [-0.1, 0.3, -0.45]])
def test_detects_corners_and_pose_of_a_rendered_board(eye: list[float]) -> None:
    T_cam_board = _view(eye)
    image = render_board(T_cam_board, rng=np.random.default_rng(1))
    det = CharucoCornerDetector(DEFAULT_BOARD).detect(_record(), image)
    assert det.ok, det.reason
    assert len(det.ids) >= 30
    P = corners_board_m(DEFAULT_BOARD)[det.ids] @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    uv = P[:, :2] / P[:, 2:] * [COLOR.fx, COLOR.fy] + [COLOR.ppx, COLOR.ppy]
    err = np.linalg.norm(det.corners_px - uv, axis=1)
    assert np.median(err) < 0.15 and det.pnp_rms_px < 0.3
    t, r = pose_error(det.T_stream_board, T_cam_board)
    assert t < 1e-3 and np.degrees(r) < 0.2
    assert np.allclose(det.T_depth_board, det.T_stream_board)  # identity T_depth_stream


def test_rejections_say_why() -> None:
    detector = CharucoCornerDetector(DEFAULT_BOARD)
    blank = np.full((480, 640), 128, np.uint8)
    det = detector.detect(_record(), blank)
    assert not det.ok and det.reason == "too few corners (0 < 12)"
    far = render_board(_view([0.15, 0.105, -2.2]))
    det = detector.detect(_record(), far)
    assert not det.ok and ("too few corners" in det.reason or "cover" in det.reason)
    good = render_board(_view([0.15, 0.105, -0.4]))
    strict = CharucoCornerDetector(DEFAULT_BOARD, DetectionSettings(max_pnp_rms_px=1e-4)).detect(_record(), good)
    assert not strict.ok and strict.reason.startswith("PnP reprojection error")
    coverage = CharucoCornerDetector(DEFAULT_BOARD, DetectionSettings(min_coverage=0.9)).detect(_record(), good)
    assert not coverage.ok and "of the image" in coverage.reason


def _rs_intrinsics(intr: Intrinsics, model: str) -> rs.intrinsics:
    i = rs.intrinsics()
    i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy
    i.model = {"Brown Conrady": rs.distortion.brown_conrady,
               "Modified Brown Conrady": rs.distortion.modified_brown_conrady,
               "Inverse Brown Conrady": rs.distortion.inverse_brown_conrady}[model]
    i.coeffs = list(intr.coeffs)
    return i


@pytest.mark.parametrize("model", ["Brown Conrady", "Modified Brown Conrady", "Inverse Brown Conrady"])
def test_undistortion_inverts_librealsense_projection(model: str) -> None:
    intr = Intrinsics(640, 480, 600.0, 601.0, 321.0, 239.0, model, (0.12, -0.21, 0.0015, -0.001, 0.08))
    rsi = _rs_intrinsics(intr, model)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.45, 0.45, (50, 2)), np.ones(50)]
    distorted = np.array([rs.rs2_project_point_to_pixel(rsi, list(p)) for p in pts])
    ideal = pts[:, :2] * [intr.fx, intr.fy] + [intr.ppx, intr.ppy]
    assert np.abs(undistort_pixels(distorted, intr) - ideal).max() < 1e-3


def test_undistortion_matches_librealsense_deprojection() -> None:
    intr = Intrinsics(640, 480, 610.0, 609.0, 318.0, 244.0, "Inverse Brown Conrady",
                      (0.05, -0.02, 0.001, 0.0005, 0.003))
    rsi = _rs_intrinsics(intr, intr.model)
    uv = np.random.default_rng(1).uniform([0, 0], [639, 479], (50, 2))
    rays = np.array([rs.rs2_deproject_pixel_to_point(rsi, list(p), 1.0) for p in uv])
    ideal = rays[:, :2] * [intr.fx, intr.fy] + [intr.ppx, intr.ppy]
    assert np.abs(undistort_pixels(uv, intr) - ideal).max() < 1e-3


def test_zero_coefficients_and_unsupported_models() -> None:
    uv = np.array([[10.0, 20.0], [600.0, 400.0]])
    assert np.array_equal(undistort_pixels(uv, COLOR), uv)
    with pytest.raises(CalibrationError, match="not supported"):
        undistort_pixels(uv, Intrinsics(640, 480, 600, 600, 320, 240, "Kannala Brandt4", (0.1, 0, 0, 0, 0)))
