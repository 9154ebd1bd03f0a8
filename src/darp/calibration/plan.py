"""Capture plan: diverse, reachable, collision-free wrist poses looking at the board, for each arm.

Candidates are drawn at random (seeded): a target point on the board (jittered about its centre), a
viewing direction (tilt from the board normal up to ``max_tilt_deg``, azimuth within
``azimuth_range_deg`` of the direction towards the arm's base), a distance in ``distance_range_m`` and
a roll about the optical axis (image-up turned up to ``roll_range_deg`` from "away from the arm's
base"). Each is solved with :func:`darp.kinematics.ik.solve_look_at` on the
*nominal* rig and kept only when

- the joints are within limits by the rig's ``joint_limit_margin_rad``;
- the arm (with its camera) clears the table by ``table_clearance_m``, itself by ``self_margin_m`` and
  the other arm, parked, by ``arm_arm_margin_m``;
- at least ``min_visible_fraction`` of the board's corners project inside the image.

From the survivors a greedy farthest-point selection picks the most diverse set in (viewing direction,
roll, distance, target) space: diversity in rotation axes is what makes hand-eye and joint offsets
observable. The poses are ordered to shorten joint travel, and each joint-space move (straight line
in joint space, as the Z1's MoveJ and the twin do) is checked along the way; a move that would
collide goes through the park pose, and a pose no safe move reaches is dropped.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.calibration.board import board_size_m, corners_board_m
from darp.calibration.captures import board_from_dict, board_to_dict
from darp.errors import CalibrationError, FormatError
from darp.formats.calibration import CharucoBoardSpec
from darp.formats.realsense.types import Intrinsics
from darp.formats.schema import as_array, load_json_object, write_json_checked
from darp.kinematics import collision, z1
from darp.kinematics.ik import solve_look_at
from darp.kinematics.rig import Rig
from darp.kinematics.transforms import axis_angle_to_rotation, invert_transform, make_transform

PLAN_SCHEMA = "darp-calib-plan/1"
# D435 colour at 640x480 (nominal): what the planner assumes the camera sees.
PLANNING_INTRINSICS = Intrinsics(640, 480, 610.0, 610.0, 319.5, 239.5)


@dataclass(frozen=True)
class PlanSettings:
    """How many poses, from where, and how strictly checked."""

    n_per_arm: int = 30
    distance_range_m: tuple[float, float] = (0.30, 0.60)
    max_tilt_deg: float = 50.0
    roll_range_deg: float = 90.0
    target_jitter: float = 0.3  # fraction of the board's half size
    n_candidates: int = 300
    azimuth_range_deg: float = 80.0  # viewing azimuth within this of the direction towards the arm's base
    min_visible_fraction: float = 0.5
    image_margin_px: float = 12.0
    self_margin_m: float = 0.01
    path_step_rad: float = 0.1

    def __post_init__(self) -> None:
        lo, hi = self.distance_range_m
        if self.n_per_arm < 1 or self.n_candidates < self.n_per_arm:
            raise CalibrationError("plan needs n_per_arm >= 1 and n_candidates >= n_per_arm")
        if not 0.1 <= lo < hi:
            raise CalibrationError(f"distance range must be [min, max] with 0.1 <= min < max, got {lo}, {hi}")
        if not 0.0 <= self.max_tilt_deg < 85.0 or not 0.0 <= self.roll_range_deg <= 180.0:
            raise CalibrationError("max_tilt_deg must be in [0, 85) and roll_range_deg in [0, 180]")


@dataclass
class PlannedPose:
    """One capture pose of one arm (SDK joint angles) and how it views the board (nominal rig)."""

    arm: str
    q_rad: np.ndarray
    T_world_cam: np.ndarray
    distance_m: float
    tilt_deg: float
    azimuth_deg: float
    roll_deg: float
    visible_fraction: float
    via_park: bool = False


@dataclass
class CapturePlan:
    """Poses per arm, with the board they look at and the settings that made them."""

    board: CharucoBoardSpec
    T_world_board: np.ndarray
    seed: int
    settings: PlanSettings
    poses: dict[str, list[PlannedPose]]
    rejected: dict[str, dict[str, int]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": PLAN_SCHEMA, "seed": self.seed, "board": board_to_dict(self.board),
            "T_world_board": self.T_world_board.tolist(), "settings": asdict(self.settings),
            "rejected": self.rejected,
            "poses": {arm: [{"q_rad": p.q_rad.tolist(), "T_world_cam": p.T_world_cam.tolist(),
                             "distance_m": p.distance_m, "tilt_deg": p.tilt_deg, "azimuth_deg": p.azimuth_deg,
                             "roll_deg": p.roll_deg, "visible_fraction": p.visible_fraction,
                             "via_park": p.via_park} for p in poses]
                      for arm, poses in self.poses.items()},
        }

    def save(self, path: str | Path) -> None:
        write_json_checked(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> CapturePlan:
        """Read a plan written by :meth:`save`."""
        path = Path(path)
        data = load_json_object(path)
        if data.get("schema") != PLAN_SCHEMA:
            raise FormatError(f"schema: expected {PLAN_SCHEMA!r}, got {data.get('schema')!r}", path)
        try:
            s = dict(data["settings"])
            s["distance_range_m"] = tuple(s["distance_range_m"])
            settings = PlanSettings(**s)
            poses = {arm: [PlannedPose(arm=arm, q_rad=as_array(p["q_rad"], f"poses.{arm}.q_rad", path, (6,)),
                                       T_world_cam=as_array(p["T_world_cam"], f"poses.{arm}.T_world_cam", path,
                                                            (4, 4)),
                                       distance_m=float(p["distance_m"]), tilt_deg=float(p["tilt_deg"]),
                                       azimuth_deg=float(p["azimuth_deg"]), roll_deg=float(p["roll_deg"]),
                                       visible_fraction=float(p["visible_fraction"]),
                                       via_park=bool(p["via_park"])) for p in items]
                     for arm, items in data["poses"].items()}
            return cls(board=board_from_dict(data["board"], path),
                       T_world_board=as_array(data["T_world_board"], "T_world_board", path, (4, 4)),
                       seed=int(data["seed"]), settings=settings, poses=poses,
                       rejected=dict(data.get("rejected", {})))
        except (KeyError, TypeError, ValueError) as err:
            raise FormatError(f"not a valid capture plan: {err}", path) from None


def default_board_pose(rig: Rig, board: CharucoBoardSpec, yaw_rad: float = 0.0,
                       thickness_m: float = 0.003) -> np.ndarray:
    """``T_world_board`` of the board lying face up, centred on the workspace, turned ``yaw_rad``.

    Face up: the board's z (into the board) points down, its x along world x turned by the yaw.
    """
    w, h = board_size_m(board)
    cx, cy = (float(np.mean(r)) for r in (rig.workspace.x_range_m, rig.workspace.y_range_m))
    R = axis_angle_to_rotation([0.0, 0.0, 1.0], yaw_rad) @ np.diag([1.0, -1.0, -1.0])
    centre = np.array([cx, cy, rig.table.height_m + thickness_m])
    return make_transform(R, centre - R @ np.array([w / 2, h / 2, 0.0]))


class _Checker:
    """Collision and limit checks of one arm with the other parked (nominal rig)."""

    def __init__(self, rig: Rig, arm: str, settings: PlanSettings) -> None:
        self.rig, self.arm, self.s = rig, arm, settings
        cfg = rig.arm(arm)
        self.T_world_base = cfg.T_world_base
        self.mount = rig.camera_mount(arm)
        other = next(a for a in rig.arm_ids if a != arm)
        self.other_prims = collision.arm_primitives(rig.arm(other).park_q_rad, rig.arm(other).T_world_base,
                                                    rig.camera_mount(other))
        margin = rig.margins.joint_limit_margin_rad
        self.lower, self.upper = z1.JOINT_LOWER + margin, z1.JOINT_UPPER - margin

    def reason(self, q: np.ndarray) -> str:
        """Empty when ``q`` is safe, else what is wrong."""
        if np.any(q < self.lower) or np.any(q > self.upper):
            return "joint limit margin"
        m = self.rig.margins
        if collision.arm_table_distance(q, self.T_world_base, self.rig.table.height_m,
                                        self.mount).distance_m < m.table_clearance_m:
            return "table clearance"
        if collision.self_collision_distance(q, self.mount).distance_m < self.s.self_margin_m:
            return "self collision"
        prims = collision.arm_primitives(q, self.T_world_base, self.mount)
        if collision.min_distance(prims, self.other_prims).distance_m < m.arm_arm_margin_m:
            return "other arm"
        return ""

    def path_ok(self, q_a: np.ndarray, q_b: np.ndarray) -> bool:
        """Every sample of the straight joint-space move is safe (ends excluded: checked already)."""
        n = int(np.ceil(np.max(np.abs(q_b - q_a)) / self.s.path_step_rad))
        return all(not self.reason(q_a + (q_b - q_a) * k / n) for k in range(1, n))


def _visible_fraction(T_world_cam: np.ndarray, corners_world: np.ndarray, s: PlanSettings) -> float:
    T = invert_transform(T_world_cam)
    P = corners_world @ T[:3, :3].T + T[:3, 3]
    K = PLANNING_INTRINSICS
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K.fx * P[:, 0] / P[:, 2] + K.ppx
        v = K.fy * P[:, 1] / P[:, 2] + K.ppy
    m = s.image_margin_px
    inside = (P[:, 2] > 0.05) & (u >= m) & (u <= K.width - 1 - m) & (v >= m) & (v <= K.height - 1 - m)
    return float(np.mean(inside))


def _candidates(rig: Rig, arm: str, board: CharucoBoardSpec, T_world_board: np.ndarray, s: PlanSettings,
                rng: np.random.Generator, rejected: dict[str, int]) -> list[PlannedPose]:
    cfg = rig.arm(arm)
    checker = _Checker(rig, arm, s)
    T_base_world = invert_transform(cfg.T_world_base)
    w, h = board_size_m(board)
    centre_board = np.array([w / 2, h / 2, 0.0])
    normal = -T_world_board[:3, 2]  # printed face looks along -z of the board frame
    corners_world = corners_board_m(board) @ T_world_board[:3, :3].T + T_world_board[:3, 3]
    base_xy = cfg.T_world_base[:3, 3]
    e1 = np.cross(normal, [0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    to_base = base_xy - T_world_board[:3, :3] @ centre_board - T_world_board[:3, 3]
    base_azimuth = float(np.arctan2(to_base @ e2, to_base @ e1))
    out: list[PlannedPose] = []
    for _ in range(s.n_candidates):
        jitter = rng.uniform(-1.0, 1.0, 2) * s.target_jitter * np.array([w / 2, h / 2])
        target = T_world_board[:3, :3] @ (centre_board + [jitter[0], jitter[1], 0.0]) + T_world_board[:3, 3]
        tilt = np.arccos(rng.uniform(np.cos(np.radians(s.max_tilt_deg)), 1.0))  # uniform on the cap
        azimuth = base_azimuth + np.radians(rng.uniform(-s.azimuth_range_deg, s.azimuth_range_deg))
        distance = rng.uniform(*s.distance_range_m)
        roll = np.radians(rng.uniform(-s.roll_range_deg, s.roll_range_deg))
        to_cam = np.cos(tilt) * normal + np.sin(tilt) * (np.cos(azimuth) * e1 + np.sin(azimuth) * e2)
        view = -to_cam  # camera -> target
        away = target - base_xy
        away -= (away @ view) * view
        if np.linalg.norm(away) < 1e-6:
            away = np.cross(view, e1)
        up = axis_angle_to_rotation(view, roll) @ (away / np.linalg.norm(away))
        res = solve_look_at(T_base_world[:3, :3] @ target + T_base_world[:3, 3], distance,
                            T_frame_cam=cfg.T_wrist_cam, view_dir_base=T_base_world[:3, :3] @ view,
                            up_hint=T_base_world[:3, :3] @ up, frame=rig.wrist_frame)
        if not res.success:
            rejected["no IK solution"] = rejected.get("no IK solution", 0) + 1
            continue
        q = res.q
        why = checker.reason(q)
        if why:
            rejected[why] = rejected.get(why, 0) + 1
            continue
        T_world_cam = cfg.T_world_base @ z1.fk(q, rig.wrist_frame) @ cfg.T_wrist_cam
        frac = _visible_fraction(T_world_cam, corners_world, s)
        if frac < s.min_visible_fraction:
            rejected["board not in view"] = rejected.get("board not in view", 0) + 1
            continue
        image_up = -T_world_cam[:3, 1]
        ref = away / np.linalg.norm(away)
        achieved_roll = np.arctan2(np.cross(ref, image_up) @ view, ref @ image_up)
        out.append(PlannedPose(arm, q, T_world_cam, float(distance), float(np.degrees(tilt)),
                               float(np.degrees(azimuth)), float(np.degrees(achieved_roll)), frac))
    return out


def _features(poses: list[PlannedPose], s: PlanSettings, T_world_board: np.ndarray) -> np.ndarray:
    rows = []
    lo, hi = s.distance_range_m
    for p in poses:
        view = p.T_world_cam[:3, 2]
        roll = np.radians(p.roll_deg)
        centre = p.T_world_cam[:3, 3] + p.distance_m * view
        offset = (centre - T_world_board[:3, 3])[:2]
        rows.append(np.concatenate([view, 0.7 * np.array([np.cos(roll), np.sin(roll)]),
                                    [0.5 * (p.distance_m - lo) / (hi - lo)], 0.5 * offset / 0.1]))
    return np.array(rows)


def _select(poses: list[PlannedPose], n: int, s: PlanSettings, T_world_board: np.ndarray) -> list[PlannedPose]:
    """Greedy farthest-point selection, starting from the pose nearest the mean feature."""
    if len(poses) <= n:
        return list(poses)
    F = _features(poses, s, T_world_board)
    chosen = [int(np.argmin(np.linalg.norm(F - F.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(F - F[chosen[0]], axis=1)
    while len(chosen) < n:
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(F - F[k], axis=1))
    return [poses[k] for k in chosen]


def _order(rig: Rig, arm: str, poses: list[PlannedPose], s: PlanSettings,
           rejected: dict[str, int]) -> list[PlannedPose]:
    """Nearest-neighbour order from the park pose; unsafe moves go through park, unreachable poses drop."""
    checker = _Checker(rig, arm, s)
    park = np.asarray(rig.arm(arm).park_q_rad, dtype=float)
    weights = np.array([1.0, 1.0, 1.0, 0.6, 0.6, 0.3])
    left = list(poses)
    current = park
    ordered: list[PlannedPose] = []
    while left:
        k = int(np.argmin([np.max(weights * np.abs(p.q_rad - current)) for p in left]))
        pose = left.pop(k)
        if checker.path_ok(current, pose.q_rad):
            pose.via_park = False
        elif checker.path_ok(current, park) and checker.path_ok(park, pose.q_rad):
            pose.via_park = True
        else:
            rejected["no safe move"] = rejected.get("no safe move", 0) + 1
            continue
        ordered.append(pose)
        current = pose.q_rad
    return ordered


def plan_captures(rig: Rig, board: CharucoBoardSpec, T_world_board: np.ndarray | None = None, *,
                  settings: PlanSettings | None = None, seed: int = 0,
                  arms: tuple[str, ...] | None = None) -> CapturePlan:
    """A capture plan for ``arms`` (default both) of the nominal ``rig``; deterministic for ``seed``."""
    s = settings or PlanSettings()
    T_wb = default_board_pose(rig, board) if T_world_board is None else np.asarray(T_world_board, float)
    poses: dict[str, list[PlannedPose]] = {}
    rejected: dict[str, dict[str, int]] = {}
    for index, arm in enumerate(arms or rig.arm_ids):
        rng = np.random.default_rng([seed, index, 0xCA1])
        rej: dict[str, int] = {}
        pool = _candidates(rig, arm, board, T_wb, s, rng, rej)
        chosen = _select(pool, s.n_per_arm, s, T_wb)
        poses[arm] = _order(rig, arm, chosen, s, rej)
        rejected[arm] = rej
        if len(poses[arm]) < min(6, s.n_per_arm):
            raise CalibrationError(f"{arm}: only {len(poses[arm])} feasible capture poses found "
                                   f"(rejected: {rej}); move the board closer to the arm or relax the plan")
    return CapturePlan(board=board, T_world_board=T_wb, seed=seed, settings=s, poses=poses, rejected=rejected)


__all__ = ["PLANNING_INTRINSICS", "CapturePlan", "PlanSettings", "PlannedPose", "default_board_pose",
           "plan_captures"]
