"""Calibration quality: held-out corner errors (k-fold over captures) and errors against a true calibration.

**Held-out geometric error** (the paper's "held-out geometric errors", :data:`darp.paper.HANDEYE_HELDOUT_MM`): captures
are split into ``k`` folds per arm; for each fold the whole calibration (OpenCV initialisation,
identifiability, refinement) is computed *without* that fold, and each withheld capture's board corners
are predicted through the calibrated chain (eq. 1 with the logged joints, and the board pose the
calibration found) and compared with what that image alone shows:

- ``corner_3d_mm``: distance between the predicted corner and the corner placed by the image's own
  PnP board pose, in the camera frame (what a fused point cloud would feel; includes the PnP's own
  depth uncertainty);
- ``ray_mm``: distance from the predicted corner to the ray through the detected pixel (the lateral
  part only, free of PnP depth noise);
- ``reprojection_px``: predicted vs detected pixel.

**Against truth** (the twin): quantities compared are those the captures can determine. Joint 1's
offset is one with the base yaw and joint 6's with the hand-eye about the flange x axis
(:mod:`darp.calibration.refine`), so bases are compared as ``T_world_base @ Rz(dq1)`` and hand-eyes as
``Rx(dq6) @ T_wrist_cam``; the true calibration is first re-expressed in darp's measured world
definition (:mod:`darp.calibration.world_frame`). Camera pose errors over the captured configurations
compare the whole chain.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, cast

import numpy as np

from darp.calibration.model import ChainParams, Observations, board_in_stream
from darp.calibration.world_frame import canonical_world
from darp.formats.calibration import Calibration
from darp.kinematics import z1
from darp.kinematics.transforms import invert_transform, make_transform, pose_error, rot_x, rot_z

Solver = Callable[[Observations], ChainParams]


def corner_errors(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> dict[str, np.ndarray]:
    """Per-corner errors of ``obs`` predicted by ``params``: corner_3d_mm, ray_mm, reprojection_px (C,)."""
    T_pred = board_in_stream(params, obs, wrist_frame)[obs.corner_capture]
    T_obs = (obs.T_stream_depth @ obs.T_depth_board_pnp)[obs.corner_capture]
    P_pred = np.einsum("cij,cj->ci", T_pred[:, :3, :3], obs.P_board) + T_pred[:, :3, 3]
    P_obs = np.einsum("cij,cj->ci", T_obs[:, :3, :3], obs.P_board) + T_obs[:, :3, 3]
    K = obs.K[obs.corner_capture]
    ray = np.stack([(obs.uv[:, 0] - K[:, 0, 2]) / K[:, 0, 0], (obs.uv[:, 1] - K[:, 1, 2]) / K[:, 1, 1],
                    np.ones(len(obs.uv))], axis=1)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    along = np.sum(P_pred * ray, axis=1, keepdims=True)
    z = np.maximum(P_pred[:, 2], 1e-6)
    uv = np.stack([K[:, 0, 0] * P_pred[:, 0] / z + K[:, 0, 2], K[:, 1, 1] * P_pred[:, 1] / z + K[:, 1, 2]], 1)
    return {"corner_3d_mm": 1e3 * np.linalg.norm(P_pred - P_obs, axis=1),
            "ray_mm": 1e3 * np.linalg.norm(P_pred - along * ray, axis=1),
            "reprojection_px": np.linalg.norm(uv - obs.uv, axis=1)}


def fold_assignment(obs: Observations, k: int, seed: int = 0) -> np.ndarray:
    """Fold index (M,) per capture: each arm's captures shuffled (seeded) and dealt round-robin."""
    folds = np.zeros(obs.n_captures, dtype=int)
    rng = np.random.default_rng([seed, 0xF01D])
    for a in range(len(obs.arms)):
        idx = np.flatnonzero(obs.arm_index == a)
        folds[rng.permutation(idx)] = np.arange(len(idx)) % k
    return folds


def kfold_heldout(obs: Observations, solver: Solver, k: int = 5, seed: int = 0,
                  wrist_frame: str = "flange", progress: Callable[[], None] | None = None) -> dict[str, Any]:
    """Held-out corner errors: per arm, arrays over every withheld corner, and per-capture medians."""
    folds = fold_assignment(obs, k, seed)
    per_corner: dict[str, dict[str, list[np.ndarray]]] = {a: {} for a in obs.arms}
    per_capture: dict[str, dict[str, float]] = {}
    for f in range(k):
        test = folds == f
        if not np.any(test):
            continue
        params = solver(obs.subset(~test))
        sub = obs.subset(test)
        errs = corner_errors(params, sub, wrist_frame)
        for a, arm in enumerate(obs.arms):
            mine = sub.arm_index[sub.corner_capture] == a
            for key, value in errs.items():
                per_corner[arm].setdefault(key, []).append(value[mine])
        for m, cid in enumerate(sub.capture_ids):
            sel = sub.corner_capture == m
            per_capture[cid] = {key: float(np.median(v[sel])) for key, v in errs.items()}
        if progress is not None:
            progress()
    arrays = {arm: {key: np.concatenate(v) for key, v in d.items()} for arm, d in per_corner.items()}
    return {"per_arm": arrays, "per_capture": per_capture, "folds": k}


def summarise(values: np.ndarray) -> dict[str, float]:
    """median, mean, rms, p90, max of an error array (NaN-free; empty -> zeros and n = 0)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return {"n": 0, "median": 0.0, "mean": 0.0, "rms": 0.0, "p90": 0.0, "max": 0.0}
    return {"n": int(v.size), "median": float(np.median(v)), "mean": float(np.mean(v)),
            "rms": float(np.sqrt(np.mean(v**2))), "p90": float(np.percentile(v, 90)), "max": float(np.max(v))}


# -- against truth ------------------------------------------------------------------------------------

def effective_base(T_world_base: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """The base as the captures see it: joint 1's zero offset folded into the yaw."""
    return np.asarray(T_world_base) @ make_transform(rot_z(float(dq[0])))


def effective_hand_eye(T_wrist_cam: np.ndarray, dq: np.ndarray) -> np.ndarray:
    """The hand-eye as the captures see it: joint 6's zero offset folded in (about the flange x axis)."""
    return cast(np.ndarray, make_transform(rot_x(float(dq[5]))) @ np.asarray(T_wrist_cam))


def canonicalised(cal: Calibration, arms: tuple[str, str], up_world: np.ndarray | None = None) -> Calibration:
    """``cal`` re-expressed in darp's measured world definition (bases' midpoint, base-to-base x, ``up``).

    ``up_world``: the table normal in ``cal``'s world (default its z axis).
    """
    up = np.array([0.0, 0.0, 1.0]) if up_world is None else np.asarray(up_world, float)
    a, b = arms
    T_old_new = canonical_world(cal.arms[a].T_world_base[:3, 3], cal.arms[b].T_world_base[:3, 3], up)
    T_new_old = invert_transform(T_old_new)
    out = Calibration(epoch=cal.epoch, date=cal.date, arms={}, board=cal.board, world_frame=cal.world_frame,
                      report=dict(cal.report))
    for name, arm in cal.arms.items():
        out.arms[name] = replace(arm, T_world_base=T_new_old @ arm.T_world_base)
    return out


def _pose_err(T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    t, r = pose_error(T_est, T_true)
    return {"translation_mm": 1e3 * float(t), "rotation_deg": float(np.degrees(r))}


def truth_errors(est: Calibration, truth: Calibration, arms: tuple[str, str],
                 identifiable: dict[str, np.ndarray] | None = None,
                 q_by_arm: dict[str, np.ndarray] | None = None, wrist_frame: str = "flange",
                 truth_up: np.ndarray | None = None) -> dict[str, Any]:
    """Errors of ``est`` against ``truth`` (both re-expressed in darp's world definition)."""
    t = canonicalised(truth, arms, truth_up)
    a, b = arms
    out: dict[str, Any] = {"arms": {}}
    eff_base = {}
    for cal_name, cal in (("est", est), ("true", t)):
        eff_base[cal_name] = {x: effective_base(cal.arms[x].T_world_base, cal.arms[x].joint_offsets_rad)
                              for x in arms}
    for x in arms:
        e, tr = est.arms[x], t.arms[x]
        he = _pose_err(effective_hand_eye(e.T_wrist_cam, e.joint_offsets_rad),
                       effective_hand_eye(tr.T_wrist_cam, tr.joint_offsets_rad))
        dq_err = np.degrees(np.asarray(e.joint_offsets_rad) - np.asarray(tr.joint_offsets_rad))
        ident = np.ones(6, bool) if identifiable is None else np.asarray(identifiable[x], bool)
        entry: dict[str, Any] = {
            "hand_eye": he,
            "base_in_world": _pose_err(eff_base["est"][x], eff_base["true"][x]),
            "joint_offset_error_deg": [float(v) if ident[j] else None for j, v in enumerate(dq_err)],
            "max_identifiable_joint_offset_error_deg": float(np.max(np.abs(dq_err[ident]))) if ident.any() else None,
        }
        if q_by_arm is not None and len(q_by_arm.get(x, ())):
            Q = np.asarray(q_by_arm[x])
            T_e = e.T_world_base @ z1.fk_batch(Q + e.joint_offsets_rad, wrist_frame) @ e.T_wrist_cam
            T_t = tr.T_world_base @ z1.fk_batch(Q + tr.joint_offsets_rad, wrist_frame) @ tr.T_wrist_cam
            dt, dr = pose_error(T_e, T_t)
            entry["camera_pose"] = {"translation_mm_median": 1e3 * float(np.median(dt)),
                                    "translation_mm_max": 1e3 * float(np.max(dt)),
                                    "rotation_deg_median": float(np.degrees(np.median(dr))),
                                    "rotation_deg_max": float(np.degrees(np.max(dr)))}
        out["arms"][x] = entry
    rel_est = invert_transform(eff_base["est"][a]) @ eff_base["est"][b]
    rel_true = invert_transform(eff_base["true"][a]) @ eff_base["true"][b]
    out["base_to_base"] = _pose_err(rel_est, rel_true)
    return out


__all__ = ["canonicalised", "corner_errors", "effective_base", "effective_hand_eye", "fold_assignment",
           "kfold_heldout", "summarise", "truth_errors"]
