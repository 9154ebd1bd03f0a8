"""Camera-to-joint-log time offset from a survey's own depth (issue 16, item 2).

A camera stamps a frame some time ``delta`` after its exposure (USB transfer, driver; the twin's paper
profile: 5 ms + 1 ms jitter). Eq. 1 samples the joint log at the stamp, so a frame taken while the arm
moves gets the pose the arm had ``delta`` later. Still frames do not care; moving frames do.

The estimate: the settled frames of the survey (both arms, poses from eq. 1) form a reference surface
inside the object's support region; each moving frame's depth, placed with the pose at
``stamp - delta`` for ``delta`` on a grid, is scored by its truncated point-to-plane distance to that
surface. The cost summed over moving frames is smallest near the true ``delta``; a parabola through the
grid minimum and its neighbours gives the estimate, and a bootstrap over moving frames its standard
error. Per arm: each camera has its own latency.

What it cannot do: with no moving frame overlapping the support region (a survey recorded only at rest)
there is nothing to estimate; a parabola that does not open upwards, or a minimum on the grid's edge,
is reported as not estimated. The pose errors that calibration leaves vary along the path and enter the
cost as a floor that moves with the configuration, so the estimate is noisy when the arm moves slowly
or the calibration is poor: an estimate whose bootstrap std exceeds ``max_std_s`` is not applied, and
the cameras' moving frames pooled (one latency for cameras of one model) are tried instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from darp.formats.realsense.types import Intrinsics
from darp.kinematics.camera_poses import camera_poses
from darp.reconstruction.backproject import DepthFilterSettings, PosedDepth, Region, backproject


@dataclass(frozen=True)
class TimeAlignSettings:
    """Grid, frame choice and robust cost of the time-offset estimate."""

    grid_min_s: float = -0.030
    grid_max_s: float = 0.040
    grid_step_s: float = 0.0025
    moving_frames: int = 40  # moving frames scored per arm (spread over the survey: the pose errors that
    # calibration leaves vary along the path and bias a cost made of a few nearby frames)
    reference_frames: int = 16  # settled frames of the arm in the reference surface
    min_joint_speed_rad_s: float = 0.15  # a frame is 'moving' above this largest joint speed
    points_per_frame: int = 2000
    min_points_per_frame: int = 300
    truncate_m: float = 0.005  # point-to-plane distances beyond this count as this (outliers, new surface)
    reference_voxel_m: float = 0.002
    bootstrap: int = 200
    seed: int = 0
    max_std_s: float = 0.004  # an estimate less certain than this is not applied (paper mode for that camera)
    max_disagreement_sigma: float = 2.5  # cameras whose estimates differ more than this are not pooled


@dataclass
class TimeOffsetEstimate:
    """One camera's estimated offset (log sampled at ``stamp - offset_s``) and how it was found."""

    arm: str
    offset_s: float | None  # None: not estimated (see ``reason``)
    std_s: float | None = None
    n_moving: int = 0
    n_reference: int = 0
    reason: str = ""
    grid_s: list[float] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    frame_costs: np.ndarray | None = field(default=None, repr=False)  # (moving frames, grid) for pooling

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"offset_s": self.offset_s, "std_s": self.std_s, "n_moving_frames": self.n_moving,
                               "n_reference_frames": self.n_reference}
        if self.reason:
            out["reason"] = self.reason
        if self.grid_s:
            out["grid_s"] = [round(v, 6) for v in self.grid_s]
            out["cost_mm2"] = [round(1e6 * v, 5) for v in self.cost]
        return out


@dataclass(frozen=True)
class ArmFrames:
    """What the estimator needs of one arm: its joint log, eq. 1 inputs and a depth decoder."""

    arm: str
    log_t_s: np.ndarray
    log_q_rad: np.ndarray
    frame_t_s: np.ndarray  # (N,) frame stamps on the host clock (camera time minus any clock offset)
    T_world_cam: np.ndarray  # (N, 4, 4) eq. 1 poses at the stamps (NaN: unposed)
    joint_speed_rad_s: np.ndarray  # (N,) largest joint speed (NaN: unposed)
    still: np.ndarray  # (N,) bool settled frames
    T_world_base: np.ndarray
    T_wrist_cam: np.ndarray
    joint_offsets_rad: np.ndarray
    intrinsics: Intrinsics
    depth_scale: float
    read_depth: Callable[[int], np.ndarray]  # frame index -> raw uint16 depth
    # forward kinematics of eq. 1 (None: the nominal Z1's; the richer model's with corrections.kinematics)
    fk_batch: Callable[[np.ndarray], np.ndarray] | None = None


def _spread(indices: np.ndarray, k: int) -> np.ndarray:
    if indices.size <= k:
        return indices
    return np.asarray(indices[np.round(np.linspace(0, indices.size - 1, k)).astype(int)])


def _camera_points(arm: ArmFrames, index: int, settings: DepthFilterSettings) -> tuple[np.ndarray, np.ndarray]:
    """Filtered camera-frame points and normals of one frame (identity pose)."""
    frame = PosedDepth(arm.arm, index, arm.read_depth(index), arm.depth_scale, arm.intrinsics, np.eye(4))
    cloud = backproject(frame, settings)
    return np.asarray(cloud.points, np.float64), np.asarray(cloud.normals, np.float64)


def _apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    return np.asarray(P @ T[:3, :3].T + T[:3, 3])


def reference_surface(arms: Sequence[ArmFrames], region: Region | None, settings: TimeAlignSettings,
                      depth_settings: DepthFilterSettings) -> tuple[cKDTree, np.ndarray, int] | None:
    """KD-tree of the settled frames' points in ``region`` (voxel-thinned), their normals, frames used."""
    pts, nrm, used = [], [], 0
    for arm in arms:
        still = np.flatnonzero(arm.still & np.all(np.isfinite(arm.T_world_cam[:, 0, :]), axis=1))
        for i in _spread(still, settings.reference_frames).tolist():
            P, N = _camera_points(arm, i, depth_settings)
            T = arm.T_world_cam[i]
            P, N = _apply(T, P), N @ T[:3, :3].T
            if region is not None:
                keep = np.asarray(region.contains(P), bool)
                P, N = P[keep], N[keep]
            if len(P):
                pts.append(P)
                nrm.append(N)
                used += 1
    if not pts:
        return None
    P, N = np.concatenate(pts), np.concatenate(nrm)
    keys = np.floor(P / settings.reference_voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return cKDTree(P[first]), N[first], used


def _parabola_min(grid: np.ndarray, cost: np.ndarray) -> float | None:
    k = int(np.argmin(cost))
    if k == 0 or k == grid.size - 1:
        return None
    lo, hi = max(0, k - 2), min(grid.size, k + 3)
    a, b, _ = np.polyfit(grid[lo:hi], cost[lo:hi], 2)
    if not a > 0:
        return None
    x = -b / (2 * a)
    return float(np.clip(x, grid[lo], grid[hi - 1]))


def estimate_arm_offset(arm: ArmFrames, reference: tuple[cKDTree, np.ndarray, int], region: Region | None,
                        settings: TimeAlignSettings | None = None,
                        depth_settings: DepthFilterSettings | None = None) -> TimeOffsetEstimate:
    """The time offset of one arm's camera against the reference surface (see the module docstring)."""
    s = settings or TimeAlignSettings()
    ds = depth_settings or DepthFilterSettings()
    tree, normals, n_ref = reference
    grid = np.arange(s.grid_min_s, s.grid_max_s + 0.5 * s.grid_step_s, s.grid_step_s)
    posed = np.all(np.isfinite(arm.T_world_cam[:, 0, :]), axis=1)
    moving = np.flatnonzero(posed & np.isfinite(arm.joint_speed_rad_s)
                            & (np.nan_to_num(arm.joint_speed_rad_s) > s.min_joint_speed_rad_s))
    rng = np.random.default_rng(s.seed)
    costs = []
    for i in _spread(moving, s.moving_frames).tolist():
        P, _ = _camera_points(arm, i, ds)
        if region is not None and len(P):
            P = P[np.asarray(region.contains(_apply(arm.T_world_cam[i], P)), bool)]
        if len(P) < s.min_points_per_frame:
            continue
        if len(P) > s.points_per_frame:
            P = P[rng.choice(len(P), s.points_per_frame, replace=False)]
        poses = camera_poses(arm.log_t_s, arm.log_q_rad, arm.frame_t_s[i] - grid, T_world_base=arm.T_world_base,
                             T_wrist_cam=arm.T_wrist_cam, joint_offsets_rad=arm.joint_offsets_rad,
                             fk_batch=arm.fk_batch)
        if not np.all(poses.posed):
            continue
        row = np.empty(grid.size)
        for g, T in enumerate(poses.T_world_cam):
            W = _apply(T, P)
            _, nn = tree.query(W)
            d = np.einsum("ij,ij->i", W - tree.data[nn], normals[nn])
            row[g] = float(np.mean(np.minimum(d * d, s.truncate_m ** 2)))
        costs.append(row)
    est = TimeOffsetEstimate(arm.arm, None, n_moving=len(costs), n_reference=n_ref, grid_s=grid.tolist())
    if len(costs) < 3:
        est.reason = f"only {len(costs)} moving frames overlap the support region (need 3)"
        return est
    est.frame_costs = np.array(costs)
    return _from_costs(est, grid, est.frame_costs, s)


def _from_costs(est: TimeOffsetEstimate, grid: np.ndarray, C: np.ndarray,
                s: TimeAlignSettings) -> TimeOffsetEstimate:
    """The parabola minimum of the mean cost and its bootstrap std over frames (rows of ``C``)."""
    rng = np.random.default_rng(s.seed + 1)
    total = C.mean(axis=0)
    est.cost = total.tolist()
    best = _parabola_min(grid, total)
    if best is None:
        est.reason = "the cost has no interior minimum on the grid"
        return est
    boots = []
    for _ in range(s.bootstrap):
        b = _parabola_min(grid, C[rng.integers(0, len(C), len(C))].mean(axis=0))
        if b is not None:
            boots.append(b)
    est.offset_s = best
    # a resample without an interior minimum counts as the grid's half-width away
    boots += [best + 0.5 * (grid[-1] - grid[0])] * (s.bootstrap - len(boots))
    est.std_s = float(np.std(boots, ddof=1)) if len(boots) > 1 else None
    return est


def pooled_offset(estimates: Sequence[TimeOffsetEstimate], settings: TimeAlignSettings | None = None
                  ) -> TimeOffsetEstimate:
    """One offset for all cameras from their moving frames together (cameras of one model share a latency)."""
    s = settings or TimeAlignSettings()
    usable = [e for e in estimates if e.frame_costs is not None]
    est = TimeOffsetEstimate("pooled", None, n_moving=sum(e.n_moving for e in usable),
                             n_reference=sum(e.n_reference for e in usable))
    if not usable:
        est.reason = "no camera had moving frames to score"
        return est
    est.grid_s = usable[0].grid_s
    frame_costs = [e.frame_costs for e in usable if e.frame_costs is not None]
    est = _from_costs(est, np.asarray(est.grid_s), np.concatenate(frame_costs), s)
    # the cameras must agree: systematic pose errors that vary along a path bias one camera's estimate
    # more than its bootstrap std says (paper profile, true calibration: 19.8 +- 4.0 vs 5.6 +- 2.3 ms)
    each = [e for e in usable if e.offset_s is not None and e.std_s is not None]
    for i, a in enumerate(each):
        for b in each[i + 1:]:
            gap = abs(float(a.offset_s) - float(b.offset_s))  # type: ignore[arg-type]
            allowed = s.max_disagreement_sigma * float(np.hypot(a.std_s, b.std_s))  # type: ignore[arg-type]
            if gap > allowed:
                est.reason = (f"{a.arm} and {b.arm} disagree by {1e3 * gap:.1f} ms (more than "
                              f"{s.max_disagreement_sigma:g} combined std): not pooled")
                est.offset_s = None
    return est


def accept(est: TimeOffsetEstimate, settings: TimeAlignSettings | None = None) -> bool:
    """Whether ``est`` is certain enough to apply (an offset with a std at most ``max_std_s``)."""
    s = settings or TimeAlignSettings()
    return est.offset_s is not None and est.std_s is not None and est.std_s <= s.max_std_s


__all__ = ["ArmFrames", "TimeAlignSettings", "TimeOffsetEstimate", "accept", "estimate_arm_offset", "pooled_offset",
           "reference_surface"]
