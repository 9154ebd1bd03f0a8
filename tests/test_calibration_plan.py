"""The capture plan: feasible, collision-free, board in view, diverse, deterministic, saved and loaded."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD, board_size_m, corners_board_m
from darp.calibration.plan import (
    PLANNING_INTRINSICS,
    CapturePlan,
    PlanSettings,
    default_board_pose,
    plan_captures,
)
from darp.errors import CalibrationError, FormatError
from darp.kinematics import collision, z1

SETTINGS = PlanSettings(n_per_arm=10, n_candidates=120)


@pytest.fixture(scope="module")
def plan(rig):
    return plan_captures(rig, DEFAULT_BOARD, settings=SETTINGS, seed=3)


def test_board_pose_lies_face_up_on_the_table_centred(rig) -> None:
    T = default_board_pose(rig, DEFAULT_BOARD, yaw_rad=np.radians(30), thickness_m=0.003)
    assert np.allclose(T[:3, 2], [0, 0, -1])  # board z into the board: points down
    w, h = board_size_m(DEFAULT_BOARD)
    centre = T[:3, :3] @ [w / 2, h / 2, 0] + T[:3, 3]
    assert np.allclose(centre, [0.0, 0.0, 0.003], atol=1e-12)
    assert np.degrees(np.arctan2(T[1, 0], T[0, 0])) == pytest.approx(30.0)


def test_every_pose_is_feasible_safe_and_sees_the_board(rig, plan) -> None:
    corners = corners_board_m(DEFAULT_BOARD) @ plan.T_world_board[:3, :3].T + plan.T_world_board[:3, 3]
    m = rig.margins
    for arm, poses in plan.poses.items():
        assert len(poses) == SETTINGS.n_per_arm
        cfg = rig.arm(arm)
        other = next(a for a in rig.arm_ids if a != arm)
        for p in poses:
            assert np.all(p.q_rad >= z1.JOINT_LOWER + m.joint_limit_margin_rad - 1e-9)
            assert np.all(p.q_rad <= z1.JOINT_UPPER - m.joint_limit_margin_rad + 1e-9)
            T = cfg.T_world_base @ z1.fk(p.q_rad) @ cfg.T_wrist_cam
            assert np.allclose(T, p.T_world_cam, atol=1e-9)
            clear = rig.clearances({arm: p.q_rad, other: rig.arm(other).park_q_rad})
            assert clear[f"{arm}.table"].distance_m >= m.table_clearance_m
            assert clear["arm_arm"].distance_m >= m.arm_arm_margin_m
            assert clear[f"{arm}.self"].distance_m >= SETTINGS.self_margin_m
            # the board is in front of the camera, at the planned distance, mostly in the image
            Tc = np.linalg.inv(T)
            P = corners @ Tc[:3, :3].T + Tc[:3, 3]
            assert np.all(P[:, 2] > 0.15)
            u = PLANNING_INTRINSICS.fx * P[:, 0] / P[:, 2] + PLANNING_INTRINSICS.ppx
            v = PLANNING_INTRINSICS.fy * P[:, 1] / P[:, 2] + PLANNING_INTRINSICS.ppy
            assert np.mean((u > 0) & (u < 639) & (v > 0) & (v < 479)) >= SETTINGS.min_visible_fraction
            assert SETTINGS.distance_range_m[0] - 1e-9 <= p.distance_m <= SETTINGS.distance_range_m[1] + 1e-9
            assert p.tilt_deg <= SETTINGS.max_tilt_deg + 1e-9


def test_moves_between_poses_are_collision_free(rig, plan) -> None:
    for arm, poses in plan.poses.items():
        cfg = rig.arm(arm)
        mount = rig.camera_mount(arm)
        park = np.asarray(cfg.park_q_rad)
        current = park
        for p in poses:
            legs = [(current, park), (park, p.q_rad)] if p.via_park else [(current, p.q_rad)]
            for a, b in legs:
                for s in np.linspace(0.0, 1.0, 25):
                    q = a + s * (b - a)
                    h = collision.arm_table_distance(q, cfg.T_world_base, rig.table.height_m, mount).distance_m
                    assert h >= rig.margins.table_clearance_m - 0.01
            current = p.q_rad


def test_poses_are_diverse(plan) -> None:
    for poses in plan.poses.values():
        views = np.array([p.T_world_cam[:3, 2] for p in poses])
        rolls = np.array([p.roll_deg for p in poses])
        dist = np.array([p.distance_m for p in poses])
        angles = np.degrees(np.arccos(np.clip(views @ views.T, -1, 1)))
        assert angles.max() > 40.0  # viewing directions span a wide cone
        assert np.ptp(rolls) > 90.0 and np.ptp(dist) > 0.15
        # no two captures nearly the same
        off_diagonal = angles + np.eye(len(poses)) * 180
        assert np.all((off_diagonal > 2.0) | (np.abs(dist[:, None] - dist[None]) > 0.02)
                      | (np.abs(rolls[:, None] - rolls[None]) > 5.0))


def test_deterministic_for_a_seed_and_round_trips(rig, plan, tmp_path: Path) -> None:
    again = plan_captures(rig, DEFAULT_BOARD, settings=SETTINGS, seed=3)
    other = plan_captures(rig, DEFAULT_BOARD, settings=SETTINGS, seed=4)
    for arm in rig.arm_ids:
        assert np.array_equal(np.array([p.q_rad for p in again.poses[arm]]),
                              np.array([p.q_rad for p in plan.poses[arm]]))
        assert not np.array_equal(np.array([p.q_rad for p in other.poses[arm]]),
                                  np.array([p.q_rad for p in plan.poses[arm]]))
    plan.save(tmp_path / "plan.json")
    back = CapturePlan.load(tmp_path / "plan.json")
    assert back.settings == plan.settings and back.board == plan.board and back.seed == 3
    assert np.allclose(back.poses["arm111"][4].q_rad, plan.poses["arm111"][4].q_rad)
    (tmp_path / "bad.json").write_text('{"schema": "darp-calib-plan/1", "seed": 1}')
    with pytest.raises(FormatError, match="not a valid capture plan"):
        CapturePlan.load(tmp_path / "bad.json")


def test_unreachable_board_is_refused(rig) -> None:
    far = default_board_pose(rig, DEFAULT_BOARD)
    far[:3, 3] += [0.0, 3.0, 0.0]  # 3 m to the side: out of reach
    with pytest.raises(CalibrationError, match="feasible capture poses"):
        plan_captures(rig, DEFAULT_BOARD, far, settings=PlanSettings(n_per_arm=6, n_candidates=30), seed=0)
    with pytest.raises(CalibrationError, match="distance range"):
        PlanSettings(distance_range_m=(0.6, 0.3))
