"""The calibrated chain of eq. 1 applied to board observations: parameters, observations, prediction.

For capture i of arm a (logged joints q_i), the board corner P (board frame) is seen at

    u = pi(K_i, T_stream_depth_i @ inv(T_ref_base_a @ fk(q_i + dq_a) @ T_wrist_cam_a) @ T_ref_board @ P)

in the *ideal* pinhole image of the capture's stream (pixels undistorted at detection).
``T_ref_*`` are expressed in the **reference frame** of the solve: the base frame of the first arm,
whose own ``T_ref_base`` is the identity. The world frame is chosen afterwards
(:mod:`darp.calibration.world_frame`). Everything is vectorised over captures and corners.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from darp.calibration.board import corners_board_m
from darp.calibration.detect import Detection
from darp.errors import CalibrationError
from darp.formats.calibration import CharucoBoardSpec
from darp.kinematics import z1
from darp.kinematics.kinematic_model import KinematicParams, fk_batch_params
from darp.kinematics.transforms import invert_transform


@dataclass
class ChainParams:
    """Every unknown of the rig in the reference (first base) frame."""

    arms: tuple[str, ...]
    T_ref_base: dict[str, np.ndarray]
    T_wrist_cam: dict[str, np.ndarray]
    dq: dict[str, np.ndarray]
    T_ref_board: np.ndarray
    # arm -> kinematic parameter errors of the richer model (absent: the nominal Z1, the paper's model)
    kin: dict[str, KinematicParams] = field(default_factory=dict)

    def copy(self) -> ChainParams:
        return replace(self, T_ref_base={a: T.copy() for a, T in self.T_ref_base.items()},
                       T_wrist_cam={a: T.copy() for a, T in self.T_wrist_cam.items()},
                       dq={a: v.copy() for a, v in self.dq.items()}, T_ref_board=self.T_ref_board.copy(),
                       kin={a: k.copy() for a, k in self.kin.items()})


@dataclass(eq=False)
class Observations:
    """Accepted detections flattened for vectorised residuals."""

    arms: tuple[str, ...]
    capture_ids: list[str]
    arm_index: np.ndarray  # (M,) index into arms
    q_rad: np.ndarray  # (M, 6) logged joints
    T_stream_depth: np.ndarray
    K: np.ndarray  # (M, 3, 3)
    corner_capture: np.ndarray  # (C,) capture index of each corner
    corner_id: np.ndarray  # (C,)
    P_board: np.ndarray  # (C, 3)
    uv: np.ndarray  # (C, 2) ideal pixels
    T_depth_board_pnp: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    # (M, 4, 4) measured base-from-flange poses of an arm darp has no model of (any arm,
    # :mod:`darp.calibration.anyarm`); when set they replace ``fk(q + dq)`` and no joint offset applies.
    T_base_flange: np.ndarray | None = None
    # (M, 6) direction (-1 / 0 / +1) each joint last moved in before the capture (the capture record's
    # ``extra.move_direction``); None when any capture lacks it (older or real files): no backlash term.
    move_dir: np.ndarray | None = None

    @property
    def n_captures(self) -> int:
        return len(self.capture_ids)

    def subset(self, captures: np.ndarray) -> Observations:
        """The observations of the captures selected by a boolean mask or index array (M,)."""
        idx = np.flatnonzero(captures) if np.asarray(captures).dtype == bool else np.asarray(captures, int)
        remap = -np.ones(self.n_captures, dtype=int)
        remap[idx] = np.arange(len(idx))
        keep = remap[self.corner_capture] >= 0
        return Observations(arms=self.arms, capture_ids=[self.capture_ids[i] for i in idx],
                            arm_index=self.arm_index[idx], q_rad=self.q_rad[idx],
                            T_stream_depth=self.T_stream_depth[idx], K=self.K[idx],
                            corner_capture=remap[self.corner_capture[keep]], corner_id=self.corner_id[keep],
                            P_board=self.P_board[keep], uv=self.uv[keep],
                            T_depth_board_pnp=self.T_depth_board_pnp[idx],
                            T_base_flange=None if self.T_base_flange is None else self.T_base_flange[idx],
                            move_dir=None if self.move_dir is None else self.move_dir[idx])

    def for_arm(self, arm: str) -> np.ndarray:
        """Boolean capture mask of ``arm``."""
        return cast(np.ndarray, self.arm_index == self.arms.index(arm))


def build_observations(detections: Sequence[Detection], board: CharucoBoardSpec,
                       arms: Sequence[str] | None = None) -> Observations:
    """Observations from the accepted detections (``ok``); ``arms`` fixes the order (first = reference)."""
    good = [d for d in detections if d.ok]
    if not good:
        raise CalibrationError("no capture has a usable board detection")
    arm_order = tuple(arms) if arms is not None else tuple(dict.fromkeys(d.arm for d in good))
    good = [d for d in good if d.arm in arm_order]
    P = corners_board_m(board)
    arm_index = np.array([arm_order.index(d.arm) for d in good])
    counts = np.array([len(d.ids) for d in good])
    return Observations(
        move_dir=move_directions(good),
        arms=arm_order,
        capture_ids=[d.capture_id for d in good],
        arm_index=arm_index,
        q_rad=np.array([d.record.q_rad for d in good], dtype=float),
        T_stream_depth=invert_transform(np.array([d.record.T_depth_stream for d in good])),
        K=np.array([d.K for d in good]),
        corner_capture=np.repeat(np.arange(len(good)), counts),
        corner_id=np.concatenate([d.ids for d in good]),
        P_board=np.concatenate([P[d.ids] for d in good]),
        uv=np.concatenate([d.corners_ideal_px for d in good]),
        T_depth_board_pnp=np.array([d.T_depth_board for d in good]),
    )


def move_directions(detections: Sequence[Detection]) -> np.ndarray | None:
    """(M, 6) joint move directions of the captures (``extra.move_direction``), or None when any lacks it."""
    rows = []
    for d in detections:
        value = d.record.extra.get("move_direction")
        try:
            row = np.sign(np.asarray(value, dtype=float)).reshape(6) if value is not None else None
        except (TypeError, ValueError):
            row = None
        if row is None or not np.all(np.isfinite(row)):
            return None
        rows.append(row)
    return np.array(rows, dtype=float).reshape(-1, 6)


def flange_poses(obs: Observations, sel: np.ndarray, dq: np.ndarray, wrist_frame: str = "flange",
                 kin: KinematicParams | None = None) -> np.ndarray:
    """``T_base_flange`` (n, 4, 4) of the selected captures: measured poses when given, else ``fk(q + dq)``
    (with the richer model's parameter errors ``kin`` when given, its backlash with the captures' move
    directions)."""
    if obs.T_base_flange is not None:
        return cast(np.ndarray, obs.T_base_flange[sel])
    if kin is not None:
        direction = None if obs.move_dir is None else obs.move_dir[sel]
        return fk_batch_params(obs.q_rad[sel] + dq, kin, wrist_frame, direction)
    return cast(np.ndarray, z1.fk_batch(obs.q_rad[sel] + dq, wrist_frame))


def camera_poses(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """``T_ref_cam`` (M, 4, 4) of every capture (depth optical frame) by eq. 1."""
    T = np.empty((obs.n_captures, 4, 4))
    for a, arm in enumerate(obs.arms):
        sel = obs.arm_index == a
        if np.any(sel):
            T[sel] = (params.T_ref_base[arm] @ flange_poses(obs, sel, params.dq[arm], wrist_frame,
                                                            params.kin.get(arm))
                      @ params.T_wrist_cam[arm])
    return T


def board_in_stream(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """Predicted ``T_stream_board`` (M, 4, 4) of every capture."""
    T_depth_ref = invert_transform(camera_poses(params, obs, wrist_frame))
    return cast(np.ndarray, obs.T_stream_depth @ T_depth_ref @ params.T_ref_board)


def predict_points(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """Predicted corners in their capture's stream frame (C, 3)."""
    T = board_in_stream(params, obs, wrist_frame)[obs.corner_capture]
    return cast(np.ndarray, np.einsum("cij,cj->ci", T[:, :3, :3], obs.P_board) + T[:, :3, 3])


def predict_pixels(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """Predicted ideal pixels (C, 2) of every observed corner."""
    P = predict_points(params, obs, wrist_frame)
    K = obs.K[obs.corner_capture]
    z = np.maximum(P[:, 2], 1e-6)
    return np.stack([K[:, 0, 0] * P[:, 0] / z + K[:, 0, 2], K[:, 1, 1] * P[:, 1] / z + K[:, 1, 2]], axis=1)


def reprojection_errors(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """Per-corner reprojection error (C,) in pixels."""
    return cast(np.ndarray, np.linalg.norm(predict_pixels(params, obs, wrist_frame) - obs.uv, axis=1))


def per_capture(values: np.ndarray, obs: Observations, reduce: str = "median") -> np.ndarray:
    """Reduce per-corner values (C,) to per-capture values (M,)."""
    reducers: dict[str, Callable[[np.ndarray], Any]] = {
        "median": np.median, "mean": np.mean, "max": np.max, "rms": lambda v: np.sqrt(np.mean(v**2))}
    fn = reducers[reduce]
    return np.array([fn(values[obs.corner_capture == m]) for m in range(obs.n_captures)])


__all__ = ["ChainParams", "Observations", "board_in_stream", "build_observations", "camera_poses", "flange_poses",
           "move_directions", "per_capture", "predict_pixels", "predict_points", "reprojection_errors"]
