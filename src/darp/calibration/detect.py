"""ChArUco detection and single-image board pose, with the reason for every rejected capture.

Per image: ``cv2.aruco.CharucoDetector`` finds the markers (sub-pixel marker corners) and
interpolates the chessboard corners, which OpenCV refines to sub-pixel itself. An extra
``cornerSubPix`` pass (``subpix=True``) is available but off: its window, whatever its size, catches
the edges of the neighbouring ArUco markers and pulled corners off (median 0.07 px error without it,
0.09-0.24 px with it, on exactly rendered boards). The corners are then undistorted with the stream's own
model (:func:`darp.calibration.geometry.undistort_pixels`) and the board pose is found by PnP (IPPE for
planar targets, then Levenberg-Marquardt) on the ideal pinhole image.

A detection is rejected, with a reason, when it has too few corners, when its corners are degenerate
(all on one board row or column, or covering too little of the image), or when the PnP reprojection
error is too high (a wrong corner id or a blurred image).

Any-arm captures (:mod:`darp.calibration.anyarm`) use :func:`detect_corners` on any :class:`Board`
(ChArUco or chessboard) and :func:`ideal_pixels` with the intrinsics file's camera model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np

from darp.calibration.board import Board, corners_board_m, cv_board
from darp.calibration.captures import CaptureRecord, CaptureSet
from darp.calibration.geometry import undistort_pixels
from darp.formats.calibration import CharucoBoardSpec
from darp.formats.intrinsics import CameraModel
from darp.formats.realsense.types import Intrinsics
from darp.geometry.pinhole import project
from darp.geometry.transforms import transform_points


@dataclass(frozen=True)
class DetectionSettings:
    """Thresholds of :func:`detect_capture`."""

    min_corners: int = 12
    max_pnp_rms_px: float = 1.0
    min_coverage: float = 0.02  # convex hull of the corners / image area
    subpix: bool = False  # extra cornerSubPix pass (see the module docstring)


@dataclass(eq=False)
class Detection:
    """The corners of one capture and its board pose (``ok`` False: rejected, see ``reason``)."""

    record: CaptureRecord
    ids: np.ndarray  # (N,) ChArUco corner ids
    corners_px: np.ndarray  # (N, 2) as detected (distorted stream pixels)
    corners_ideal_px: np.ndarray  # (N, 2) undistorted to the pinhole camera with the stream's K
    ok: bool
    reason: str = ""
    T_stream_board: np.ndarray | None = None
    pnp_rms_px: float = float("nan")
    coverage: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)

    @property
    def capture_id(self) -> str:
        return self.record.capture_id

    @property
    def arm(self) -> str:
        return self.record.arm

    @property
    def K(self) -> np.ndarray:
        return self.record.intrinsics.K

    @property
    def T_depth_board(self) -> np.ndarray | None:
        """Board pose in the depth (hand-eye) frame from this image alone."""
        if self.T_stream_board is None:
            return None
        return cast(np.ndarray, self.record.T_depth_stream @ self.T_stream_board)


class CharucoCornerDetector:
    """A reusable detector for one board."""

    def __init__(self, board: CharucoBoardSpec, settings: DetectionSettings | None = None) -> None:
        self.board = board
        self.settings = settings or DetectionSettings()
        self.object_points = corners_board_m(board)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        charuco = cv2.aruco.CharucoParameters()
        charuco.tryRefineMarkers = True
        self._detector = cv2.aruco.CharucoDetector(cv_board(board), charuco, params)
        # Neighbour corner ids on the grid, for sizing the sub-pixel window.
        self._cols = board.squares_x - 1

    def corners(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ids (N,), corners (N, 2)) found in an 8-bit grey image (empty arrays when none)."""
        corners, ids, _, _ = self._detector.detectBoard(grey)
        if ids is None or len(ids) == 0:
            return np.zeros(0, dtype=int), np.zeros((0, 2))
        ids = ids.reshape(-1).astype(int)
        pts = corners.reshape(-1, 2).astype(np.float64)
        if self.settings.subpix and len(ids) >= 2:
            pts = self._refine(grey, ids, pts)
        order = np.argsort(ids, kind="stable")
        return ids[order], pts[order]

    def _refine(self, grey: np.ndarray, ids: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """cornerSubPix with a half-window of about a twelfth of the local square size."""
        grid = np.stack([ids % self._cols, ids // self._cols], axis=1)
        d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
        g = np.abs(grid[:, None] - grid[None]).sum(axis=2)
        d[g != 1] = np.inf
        local = np.min(d, axis=1)
        square_px = float(np.median(local[np.isfinite(local)])) if np.any(np.isfinite(local)) else 20.0
        half = int(np.clip(round(square_px / 12.0), 2, 10))
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
        refined = cv2.cornerSubPix(grey, pts.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                                   criteria)
        out = refined.reshape(-1, 2).astype(np.float64)
        moved = np.linalg.norm(out - pts, axis=1)
        return np.where((moved < 0.5 * half)[:, None], out, pts)  # keep OpenCV's corner if refining ran off

    def detect(self, record: CaptureRecord, grey: np.ndarray) -> Detection:
        """Corners, pose and verdict for one capture's image."""
        s = self.settings
        ids, pts = self.corners(grey)
        ideal = undistort_pixels(pts, record.intrinsics) if len(ids) else pts
        det = Detection(record=record, ids=ids, corners_px=pts, corners_ideal_px=ideal, ok=False)
        if len(ids) < s.min_corners:
            det.reason = f"too few corners ({len(ids)} < {s.min_corners})"
            return det
        grid = np.stack([ids % self._cols, ids // self._cols], axis=1)
        if len(np.unique(grid[:, 0])) < 2 or len(np.unique(grid[:, 1])) < 2:
            det.reason = "degenerate corners: all on one board row or column"
            return det
        hull = cv2.convexHull(pts.astype(np.float32))
        det.coverage = float(cv2.contourArea(hull)) / float(grey.shape[0] * grey.shape[1])
        if det.coverage < s.min_coverage:
            det.reason = f"corners cover {det.coverage:.1%} of the image (< {s.min_coverage:.0%})"
            return det
        T, rms = board_pose_pnp(self.object_points[ids], ideal, record.intrinsics.K)
        det.T_stream_board, det.pnp_rms_px = T, rms
        if T is None:
            det.reason = "PnP failed"
        elif not rms <= s.max_pnp_rms_px:
            det.reason = f"PnP reprojection error {rms:.2f} px > {s.max_pnp_rms_px} px"
        else:
            det.ok = True
        return det


def board_pose_pnp(object_points: np.ndarray, ideal_px: np.ndarray, K: np.ndarray
                   ) -> tuple[np.ndarray | None, float]:
    """``T_cam_board`` from planar board points (N, 3) and ideal pinhole pixels (N, 2); RMS error (px)."""
    obj = np.ascontiguousarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(ideal_px, dtype=np.float64).reshape(-1, 1, 2)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None, float("inf")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    if T[2, 3] <= 0:
        return None, float("inf")
    residual = project(transform_points(T[None], object_points), K) - ideal_px  # batched form: einsum
    return T, float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def detect_corners(board: Board, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids (N,), distorted pixels (N, 2)) of any board's inner corners in an 8-bit grey image."""
    if board.kind == "charuco":
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        charuco = cv2.aruco.CharucoParameters()
        charuco.tryRefineMarkers = True
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_charuco(), charuco, params).detectBoard(grey)
        if ids is None or len(ids) == 0:
            return np.zeros(0, int), np.zeros((0, 2))
        ids = ids.reshape(-1).astype(int)
        order = np.argsort(ids, kind="stable")
        return ids[order], corners.reshape(-1, 2).astype(np.float64)[order]
    size = (board.squares_x - 1, board.squares_y - 1)
    found, pts = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not found:
        found, pts = cv2.findChessboardCorners(grey, size)
        if not found:
            return np.zeros(0, int), np.zeros((0, 2))
        pts = cv2.cornerSubPix(grey, pts, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3))
    return np.arange(size[0] * size[1]), pts.reshape(-1, 2).astype(np.float64)


def ideal_pixels(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) -> ideal pinhole pixels of the same K: OpenCV's ``undistortPoints`` for its own
    model, librealsense's equations (:func:`darp.calibration.geometry.undistort_pixels`) for a recording's."""
    if not np.any(camera.dist) or len(uv) == 0:
        return np.asarray(uv, np.float64)
    if camera.model != "Brown Conrady":  # a RealSense model: librealsense's own equations
        K = camera.K
        c = tuple(float(v) for v in (list(camera.dist) + [0.0] * 5)[:5])
        intr = Intrinsics(int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1)), float(K[0, 0]),
                          float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), camera.model, c)  # type: ignore[arg-type]
        return np.asarray(undistort_pixels(np.asarray(uv, np.float64), intr))
    out = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2), camera.K, camera.dist, P=camera.K)
    return cast(np.ndarray, out.reshape(-1, 2))


def detect_captures(captures: CaptureSet, settings: DetectionSettings | None = None,
                    progress: Callable[[], object] | None = None) -> list[Detection]:
    """Detect every capture of a folder (``progress``: optional callable advanced once per image)."""
    detector = CharucoCornerDetector(captures.board, settings)
    out = []
    for record in captures.captures:
        out.append(detector.detect(record, captures.load_image(record)))
        if progress is not None:
            progress()
    return out


__all__ = ["CharucoCornerDetector", "Detection", "DetectionSettings", "board_pose_pnp", "detect_captures",
           "detect_corners", "ideal_pixels"]
