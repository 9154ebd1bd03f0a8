"""Synthetic calibration data for the calibration tests: a true rig, poses, exact corner projections, images.

The true rig comes from the twin's own error model (:func:`darp.twin.truth.draw_true_rig`: joint-zero
biases, mount and second-base errors drawn per seed), but nothing is rendered with MuJoCo: corners are
projected through the true chain with Gaussian pixel noise, and where an image is needed the printed
board is warped by the exact plane-to-image homography (a pinhole view of a plane *is* a homography).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from darp.calibration.board import DEFAULT_BOARD, board_image, board_size_m, corners_board_m
from darp.calibration.captures import CaptureRecord, CaptureWriter
from darp.calibration.detect import Detection, board_pose_pnp
from darp.calibration.plan import default_board_pose
from darp.formats.realsense.types import Intrinsics
from darp.kinematics.ik import solve_look_at
from darp.kinematics.rig import Rig, load_rig
from darp.kinematics.transforms import axis_angle_to_rotation, invert_transform, make_transform
from darp.twin.settings import TwinSettings
from darp.twin.truth import TrueRig, draw_true_rig

COLOR = Intrinsics(640, 480, 611.0, 609.5, 318.2, 243.1, "Inverse Brown Conrady")
T_DEPTH_COLOR = make_transform(axis_angle_to_rotation([0.3, 1.0, 0.2], np.radians(0.3)), [-0.0149, 0.0001, -0.0004])


def true_rig(seed: int = 0, profile: str = "realistic", rig: Rig | None = None,
             unabsorbed_mm: float | None = None) -> tuple[TrueRig, TwinSettings]:
    """The twin's true rig for ``profile`` and ``seed`` (``unabsorbed_mm``: override the arm-error setting)."""
    settings = TwinSettings.from_profile(profile, seed=seed)
    if unabsorbed_mm is not None:
        settings = dataclasses.replace(settings, arm_errors=dataclasses.replace(settings.arm_errors,
                                                                                unabsorbed_mm=unabsorbed_mm))
    return draw_true_rig(rig or load_rig(), settings), settings


def random_poses(rig: Rig, arm: str, n: int, T_world_board: np.ndarray, seed: int,
                 board=DEFAULT_BOARD) -> np.ndarray:
    """``n`` SDK joint vectors of ``arm`` looking at the board from varied directions (no collision checks)."""
    rng = np.random.default_rng([seed, 77, rig.arm_ids.index(arm)])
    cfg = rig.arm(arm)
    T_bw = invert_transform(cfg.T_world_base)
    w, h = board_size_m(board)
    centre = T_world_board[:3, :3] @ np.array([w / 2, h / 2, 0.0]) + T_world_board[:3, 3]
    to_base = cfg.T_world_base[:3, 3] - centre
    base_az = np.arctan2(to_base[1], to_base[0])
    out = []
    while len(out) < n:
        target = centre + np.r_[rng.uniform(-0.04, 0.04, 2), 0.0]
        tilt = np.radians(rng.uniform(15, 50))
        az = base_az + np.radians(rng.uniform(-70, 70))
        d = rng.uniform(0.3, 0.6)
        view = -np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        away = target - cfg.T_world_base[:3, 3]
        away -= (away @ view) * view
        up = axis_angle_to_rotation(view, np.radians(rng.uniform(-90, 90))) @ (away / np.linalg.norm(away))
        res = solve_look_at(T_bw[:3, :3] @ target + T_bw[:3, 3], d, T_frame_cam=cfg.T_wrist_cam,
                            view_dir_base=T_bw[:3, :3] @ view, up_hint=T_bw[:3, :3] @ up)
        if res.success:
            out.append(res.q)
    return np.array(out)


def board_pose(rig: Rig | None = None) -> np.ndarray:
    return default_board_pose(rig or load_rig(), DEFAULT_BOARD)


def true_T_color_board(truth: TrueRig, arm: str, q_sdk: np.ndarray, T_world_board: np.ndarray) -> np.ndarray:
    q_true = q_sdk + truth.arms[arm].joint_offsets_rad
    T_world_cam = truth.T_world_cam(arm, q_true)
    return invert_transform(T_world_cam @ T_DEPTH_COLOR) @ T_world_board


def synthetic_detections(truth: TrueRig, poses: dict[str, np.ndarray], T_world_board: np.ndarray, *,
                         noise_px: float = 0.1, encoder_noise_deg: float = 0.005, seed: int = 0,
                         board=DEFAULT_BOARD, intr: Intrinsics = COLOR) -> list[Detection]:
    """Detections with exact projections plus pixel noise, logged joints with encoder noise."""
    rng = np.random.default_rng([seed, 5])
    P = corners_board_m(board)
    out = []
    for arm, Q in poses.items():
        for k, q in enumerate(Q):
            T = true_T_color_board(truth, arm, q, T_world_board)
            Pc = P @ T[:3, :3].T + T[:3, 3]
            uv = Pc[:, :2] / Pc[:, 2:] * [intr.fx, intr.fy] + [intr.ppx, intr.ppy]
            inside = (uv[:, 0] > 5) & (uv[:, 0] < intr.width - 6) & (uv[:, 1] > 5) & (uv[:, 1] < intr.height - 6)
            ids = np.flatnonzero(inside)
            uv = uv[ids] + rng.normal(0.0, noise_px, (len(ids), 2))
            q_log = q + rng.normal(0.0, np.radians(encoder_noise_deg), 6)
            record = CaptureRecord(f"{arm}_{k:03d}", arm, truth.arms[arm].serial, float(k), q_log, "color",
                                   f"{arm}_{k:03d}.png", intr, T_DEPTH_COLOR)
            T_pnp, rms = board_pose_pnp(P[ids], uv, intr.K)
            out.append(Detection(record, ids, uv, uv, ok=len(ids) >= 12 and T_pnp is not None,
                                 T_stream_board=T_pnp, pnp_rms_px=rms))
    return out


def render_board(T_cam_board: np.ndarray, intr: Intrinsics = COLOR, board=DEFAULT_BOARD,
                 background: int = 150, px_per_square: int = 80, blur: float = 0.5,
                 noise_dn: float = 1.0, rng: np.random.Generator | None = None, supersample: int = 3) -> np.ndarray:
    """An 8-bit grey image of the board seen from ``T_cam_board`` (exact homography; pinhole, no distortion).

    Rendered ``supersample`` times finer and box-filtered down (anti-aliased), then blurred and noised.
    """
    margin = px_per_square // 3
    tex = board_image(board, px_per_square, margin)
    s = board.square_length_m / px_per_square
    # texture pixel centres are at integers, so the first square's outer edge (board x = 0) is at
    # u = margin - 0.5: texture (u, v) -> board ((u - margin + 0.5) s, (v - margin + 0.5) s, 0)
    A = np.array([[s, 0.0, -(margin - 0.5) * s], [0.0, s, -(margin - 0.5) * s], [0.0, 0.0, 1.0]])
    k = supersample
    K = intr.K.copy()
    K[0, 0] *= k
    K[1, 1] *= k
    K[0, 2] = (K[0, 2] + 0.5) * k - 0.5  # pixel centres stay at integers in both images
    K[1, 2] = (K[1, 2] + 0.5) * k - 0.5
    Rt = np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
    H = K @ Rt @ A
    size = (intr.width * k, intr.height * k)
    mask = cv2.warpPerspective(np.full(tex.shape, 255, np.uint8), H, size, flags=cv2.INTER_LINEAR)
    img = cv2.warpPerspective(tex, H, size, flags=cv2.INTER_LINEAR)
    out = img.astype(np.float32) * (mask / 255.0) + background * (1.0 - mask / 255.0)
    out = cv2.resize(out, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    if blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    if noise_dn > 0:
        out += (rng or np.random.default_rng(0)).normal(0.0, noise_dn, out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def write_synthetic_captures(folder: Path, truth: TrueRig, poses: dict[str, np.ndarray], T_world_board: np.ndarray,
                             *, seed: int = 0, encoder_noise_deg: float = 0.005, board=DEFAULT_BOARD) -> Path:
    """A capture folder with homography-rendered images of the board from every pose."""
    rng = np.random.default_rng([seed, 9])
    writer = CaptureWriter(folder, board, source="synthetic", overwrite=True)
    for arm, Q in poses.items():
        for q in Q:
            T = true_T_color_board(truth, arm, q, T_world_board)
            image = render_board(T, rng=rng, board=board)
            q_log = q + rng.normal(0.0, np.radians(encoder_noise_deg), 6)
            writer.add(arm=arm, camera_serial=truth.arms[arm].serial, time_s=0.0, q_rad=q_log, image=image,
                       intrinsics=COLOR, T_depth_stream=T_DEPTH_COLOR)
    writer.close()
    return folder


def shared_once(tmp_path_factory: Any, name: str, build: Callable[[Path], None]) -> Path:
    """A folder built once per test run, shared by pytest-xdist workers (``build(folder)`` fills it).

    The first worker to create the folder builds it and writes ``.done``; the others wait for that.
    """
    import os
    import time

    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = root / f"shared-{name}"
    try:
        folder.mkdir()
    except FileExistsError:
        deadline = time.monotonic() + 900.0
        while not (folder / ".done").exists():
            if (folder / ".failed").exists() or time.monotonic() > deadline:
                raise RuntimeError(f"building the shared test folder {folder} failed in another worker") from None
            time.sleep(0.5)
        return folder
    try:
        build(folder)
    except BaseException:
        (folder / ".failed").touch()
        raise
    (folder / ".done").touch()
    return folder
