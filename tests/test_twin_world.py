"""Twin building blocks: settings, true rig, clock, simulated arm, waypoints and the MuJoCo world."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from darp.errors import ConfigError, KinematicsError, TwinError
from darp.formats.realsense.types import Intrinsics
from darp.kinematics import z1
from darp.kinematics.transforms import look_at, make_transform, rotation_error_rad
from darp.twin.arm_sim import SimArm
from darp.twin.clock import SimClock
from darp.twin.settings import TwinSettings
from darp.twin.truth import draw_true_rig
from darp.twin.waypoints import load_waypoints
from darp.twin.world import TwinWorld


@pytest.fixture(scope="module")
def true_rig(rig):
    return draw_true_rig(rig, TwinSettings.from_profile("realistic", seed=11))


@pytest.fixture(scope="module")
def world(rig, true_rig):
    return TwinWorld(rig, true_rig.arms, seed=11)


# -- settings ---------------------------------------------------------------------------------------

def test_profiles_and_yaml_round_trip(tmp_path: Path) -> None:
    ideal = TwinSettings.from_profile("ideal", seed=3)
    assert ideal.joints.zero_bias_max_deg == 0 and ideal.joints.encoder_noise_std_deg == 0
    assert ideal.mounts.hand_eye_translation_mm == 0 and ideal.timing.joint_log_jitter_ms == 0
    assert ideal.camera.depth_noise == "ideal"
    real = TwinSettings.from_profile("realistic", seed=3).with_camera(width=424, height=240, fps=15)
    assert real.joints.zero_bias_max_deg == pytest.approx(1.0)
    real.save(tmp_path / "s.yaml")
    assert TwinSettings.load(tmp_path / "s.yaml") == real
    with pytest.raises(ConfigError, match="unknown twin profile"):
        TwinSettings.from_profile("perfect")


def test_settings_errors_name_the_file_and_field(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("profile: realistic\njoints: {zero_bias_max_deg: -1}\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: joints.zero_bias_max_deg"):
        TwinSettings.load(bad)
    bad.write_text("camera: {exposure: 3}\n")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) camera\.exposure "):
        TwinSettings.load(bad)


def test_named_random_streams_are_independent_of_other_settings() -> None:
    a = TwinSettings.from_profile("realistic", seed=4)
    b = a.with_camera(fps=15)
    assert a.rng("rig").random() == b.rng("rig").random()
    assert a.rng("rig").random() != a.rng("other").random()


# -- true rig ---------------------------------------------------------------------------------------

def test_true_rig_errors_have_the_set_magnitudes(rig) -> None:
    s = TwinSettings.from_profile("realistic", seed=8)
    true = draw_true_rig(rig, s)
    first, second = rig.arm_ids
    for arm_id, arm in true.arms.items():
        assert np.all(np.abs(arm.joint_offsets_rad) <= np.deg2rad(s.joints.zero_bias_max_deg))
        assert np.max(np.abs(arm.joint_offsets_rad)) > np.deg2rad(0.1)
        T_err = np.linalg.inv(rig.arms[arm_id].T_wrist_cam) @ arm.T_wrist_cam
        assert np.linalg.norm(T_err[:3, 3]) * 1e3 == pytest.approx(s.mounts.hand_eye_translation_mm)
        assert np.degrees(rotation_error_rad(np.eye(3), T_err[:3, :3])) == pytest.approx(s.mounts.hand_eye_rotation_deg)
    # the second base is off its nominal place relative to the first by the set magnitudes
    nominal = np.linalg.inv(rig.arms[first].T_world_base) @ rig.arms[second].T_world_base
    moved = np.linalg.inv(true.arms[first].T_world_base) @ true.arms[second].T_world_base
    shift = true.arms[first].T_world_base[:3, :3] @ (moved[:3, 3] - nominal[:3, 3])
    assert abs(shift[2]) < 1e-12 and np.linalg.norm(shift) * 1e3 == pytest.approx(s.mounts.base_translation_mm)
    expected_deg = np.hypot(s.mounts.base_yaw_deg, s.mounts.base_tilt_deg)
    assert np.degrees(rotation_error_rad(nominal, moved)) == pytest.approx(expected_deg, rel=1e-3)
    # and the truth is expressed in the world as the rig defines it (and a calibration realises it):
    # origin midway between the true base origins, x from the first to the second, z = the table normal
    o1, o2 = true.arms[first].T_world_base[:3, 3], true.arms[second].T_world_base[:3, 3]
    np.testing.assert_allclose(0.5 * (o1 + o2), 0.0, atol=1e-12)
    assert abs(o2[1]) < 1e-12 and abs(o2[2]) < 1e-12 and o2[0] > 0.6
    np.testing.assert_allclose(true.arms[first].T_world_base[:3, 2], [0, 0, 1], atol=1e-12)  # first base upright
    ideal = draw_true_rig(rig, TwinSettings.from_profile("ideal", seed=8))  # no base error: the nominal world
    for arm_id in rig.arm_ids:
        np.testing.assert_allclose(ideal.arms[arm_id].T_world_base, rig.arms[arm_id].T_world_base, atol=1e-12)
    moved = true.arms[second].T_world_base
    again = draw_true_rig(rig, s)
    np.testing.assert_array_equal(again.arms[second].T_world_base, moved)
    other = draw_true_rig(rig, TwinSettings.from_profile("realistic", seed=9))
    assert not np.allclose(other.arms[first].joint_offsets_rad, true.arms[first].joint_offsets_rad)


def test_ideal_true_rig_is_the_nominal_rig(rig) -> None:
    true = draw_true_rig(rig, TwinSettings.from_profile("ideal", seed=8))
    for arm_id, arm in true.arms.items():
        np.testing.assert_array_equal(arm.T_world_base, rig.arms[arm_id].T_world_base)
        np.testing.assert_array_equal(arm.T_wrist_cam, rig.arms[arm_id].T_wrist_cam)
        np.testing.assert_array_equal(arm.joint_offsets_rad, np.zeros(6))


# -- clock and arm ----------------------------------------------------------------------------------

def test_clock_runs_events_in_time_order_and_keeps_integer_time() -> None:
    clock = SimClock(100.0)
    seen: list[tuple[str, int]] = []
    clock.add_process("a", lambda t: (seen.append(("a", t)), t + 30_000_000)[1])
    clock.add_process("b", lambda t: (seen.append(("b", t)), t + 20_000_000)[1], first_due_ns=5_000_000)
    clock.sleep(0.1)
    times = [t for _, t in seen]
    assert times == sorted(times)
    assert [n for n, t in seen if n == "a"] == ["a"] * 4  # 0, 30, 60, 90 ms
    assert clock.now() == pytest.approx(100.1) and clock.elapsed_ns == 100_000_000
    with pytest.raises(TwinError):
        clock.sleep(-1.0)


def test_arm_moves_smoothly_within_limits_and_reports_sdk_angles() -> None:
    clock = SimClock()
    dq = np.deg2rad([0.5, -0.8, 0.3, 0.9, -0.2, 0.6])
    q0 = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
    arm = SimArm("arm110", clock, q0, joint_offsets_rad=dq, max_speed_rad_s=0.5, max_accel_rad_s2=1.5, settle_s=0.1)
    np.testing.assert_allclose(arm.read_state().q_rad, q0, atol=1e-12)
    target = np.array([0.4, 1.1, -0.9, 0.3, 0.2, -0.1])
    arm.move_to(target)
    assert arm.is_moving()
    t = np.linspace(0, arm.move_end_ns, 2001).astype(np.int64)
    q, qd, qdd = arm.true_state(t)
    assert np.max(np.abs(qd)) <= 0.5 * 1.001 and np.max(np.abs(qdd)) <= 1.5 * 1.001
    np.testing.assert_allclose(q[0], q0 + dq, atol=1e-12)
    np.testing.assert_allclose(q[-1], target + dq, atol=1e-12)
    # every joint arrives together: normalised progress is the same for all moving joints
    progress = (q[1000] - q[0]) / (q[-1] - q[0])
    np.testing.assert_allclose(progress, progress[0], atol=1e-9)
    clock.sleep(0.7)
    before = arm.true_state()
    arm.move_to(q0)  # a new command mid-move blends: position and velocity stay continuous
    after = arm.true_state()
    np.testing.assert_allclose(after[0], before[0], atol=1e-12)
    np.testing.assert_allclose(after[1], before[1], atol=1e-12)
    clock.sleep(30.0)
    assert not arm.is_moving()
    np.testing.assert_allclose(arm.read_state().q_rad, q0, atol=1e-12)
    with pytest.raises(KinematicsError, match="joint2 target"):
        arm.move_to(np.array([0.0, -0.5, -1.0, 0.0, 0.0, 0.0]))


def test_encoder_noise_has_the_set_spread() -> None:
    clock = SimClock()
    arm = SimArm("arm111", clock, np.zeros(6), encoder_noise_std_rad=1e-4, rng=np.random.default_rng(1))
    q = np.array([arm.read_state().q_rad for _ in range(4000)])
    assert np.std(q) == pytest.approx(1e-4, rel=0.05)
    assert abs(np.mean(q)) < 1e-5


# -- waypoints --------------------------------------------------------------------------------------

def test_waypoints_yaml_and_csv(tmp_path: Path) -> None:
    y = tmp_path / "w.yaml"
    y.write_text("dwell_s: 0.2\norder: [arm111, arm110]\narms:\n"
                 "  arm110:\n    - [0, 1.0, -1.0, 0.2, 0, 0]\n    - {named: forward, speed_rad_s: 0.3}\n"
                 "  arm111:\n    - {q_deg: [10, 60, -60, 10, 0, 0], dwell_s: 1}\n")
    plan = load_waypoints(y, arm_ids=("arm110", "arm111"))
    assert plan.order == ("arm111", "arm110") and plan.n_waypoints == 3
    np.testing.assert_allclose(plan.arms["arm110"][1].q_rad, z1.NAMED_CONFIGS["forward"])
    assert plan.arms["arm110"][1].speed_rad_s == 0.3 and plan.arms["arm110"][0].dwell_s == 0.2
    np.testing.assert_allclose(plan.arms["arm111"][0].q_rad, np.deg2rad([10, 60, -60, 10, 0, 0]))
    c = tmp_path / "w.csv"
    c.write_text("arm,q1,q2,q3,q4,q5,q6,dwell_s\narm110,0,1,-1,0.2,0,0,0.3\narm111,0,1.2,-1,0,0,0,\n")
    plan = load_waypoints(c)
    assert plan.order == ("arm110", "arm111") and plan.arms["arm110"][0].dwell_s == 0.3


@pytest.mark.parametrize(("text", "message"), [
    ("arms:\n  arm110:\n    - [0, 1, -1]\n", r"arms.arm110\[0\]: expected six"),
    ("arms:\n  arm110:\n    - [0, -1, -1, 0, 0, 0]\n", r"joint2 = -1.0000 rad is outside"),
    ("arms:\n  arm112:\n    - [0, 1, -1, 0, 0, 0]\n", r"unknown arm\(s\) arm112"),
    ("arms:\n  arm110:\n    - {named: flying}\n", r"unknown named configuration 'flying'"),
    ("speed: 3\narms: {}\n", r"unknown key\(s\) speed"),
])
def test_bad_waypoints_name_the_file_and_entry(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as err:
        load_waypoints(path, arm_ids=("arm110", "arm111"))
    assert "bad.yaml" in str(err.value)


# -- world ------------------------------------------------------------------------------------------

def test_mujoco_links_and_cameras_follow_darp_kinematics(rig, true_rig, world) -> None:
    rng = np.random.default_rng(0)
    for q in z1.random_configurations(5, rng):
        for arm_id in true_rig.arms:
            world.set_arm_q(arm_id, q)
        world.forward()
        for arm_id, arm in true_rig.arms.items():
            T_links = arm.T_world_base @ z1.link_transforms(q)
            for k in range(7):
                np.testing.assert_allclose(world.T_world_body(f"{arm_id}_link0{k}"), T_links[k], atol=1e-12)
            np.testing.assert_allclose(world.T_world_camera(arm_id), true_rig.T_world_cam(arm_id, q), atol=1e-12)


def test_contacts_table_other_arm_and_none_at_park(rig, world) -> None:
    for arm_id in world.arm_ids:
        world.set_arm_q(arm_id, rig.arms[arm_id].park_q_rad)
    world.forward()
    assert world.contacts() == []
    assert world.clearance("arm110")[0] > 0.03
    world.set_arm_q("arm110", np.array([0.0, 2.6, -0.3, 0.0, 0.0, 0.0]))  # reach down through the table
    world.forward()
    hits = world.contacts()
    assert hits and all(c.arm_id == "arm110" and c.other == "table" for c in hits)
    assert world.clearance("arm110")[0] < 0
    reach = np.array([0.0, 2.9, -2.65, -0.25, 0.0, 0.0])  # both flanges 0.746 m out: they meet midway
    for arm_id in world.arm_ids:
        world.set_arm_q(arm_id, reach)
    world.forward()
    others = {(c.arm_id, c.other) for c in world.contacts()}
    assert ("arm110", "arm111") in others or ("arm111", "arm110") in others


def test_object_geoms_flags_and_contacts(rig, true_rig) -> None:
    from darp.twin.objects.shapes import ObjectPart

    box = trimesh.creation.box((0.06, 0.06, 0.06))
    box.apply_translation([0.0, 0.0, 0.03])
    flat = trimesh.Trimesh([[0.04, -0.02, 0.0], [0.08, -0.02, 0.0], [0.08, 0.02, 0.0]], [[0, 1, 2]], process=False)
    parts = [ObjectPart("block", box, (0.1, 0.1, 0.1, 1), dark=True),
             ObjectPart("sticker", flat, (0.9, 0.9, 0.2, 1), specular=True)]
    base = rig.arms["arm110"].T_world_base
    world = TwinWorld(rig, true_rig.arms, parts=parts, T_world_object=base @ make_transform(t=[0.5, 0.0, 0.0]),
                      seed=1)
    block, sticker = world.model.geom("object_0_block").id, world.model.geom("object_1_sticker").id
    assert world.geoms.dark[block] and not world.geoms.dark[sticker] and world.geoms.specular[sticker]
    assert world.model.geom_contype[sticker] == 0  # a flat part has no convex hull: visual only
    for arm_id in world.arm_ids:
        world.set_arm_q(arm_id, rig.arms[arm_id].park_q_rad)
    world.forward()
    assert world.contacts() == []
    # flange at (0.5, 0, 0.04), pointing down
    world.set_arm_q("arm110", np.array([0.0, 2.543, -1.926, 0.954, 0.0, 0.0]))
    world.forward()
    hits = world.contacts()
    assert any(c.other == "object" and c.other_geom == "object_0_block" for c in hits)


def test_part_texture_row_zero_is_the_top_of_v(rig, true_rig) -> None:
    from darp.twin.camera.render import SceneRenderer
    from darp.twin.objects.shapes import ObjectPart

    texture = np.full((64, 64, 3), 255, np.uint8)
    texture[:8] = (255, 0, 0)  # image row 0 is v = 1 (ObjectPart convention): the quad's +y edge
    quad = trimesh.Trimesh([[-0.05, -0.05, 0.001], [0.05, -0.05, 0.001], [0.05, 0.05, 0.001], [-0.05, 0.05, 0.001]],
                           [[0, 1, 2], [0, 2, 3]], process=False)
    part = ObjectPart("label", quad, (1, 1, 1, 1), texture, np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float))
    world = TwinWorld(rig, true_rig.arms, parts=[part], seed=1)
    intr = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)
    T = look_at([0.0, -1e-4, 0.4], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    with SceneRenderer(world.model, 160, 120) as renderer:
        view = renderer.render(world.data, T, intr)
    for y, red in ((0.04, True), (-0.04, False)):
        p = np.linalg.inv(T) @ np.array([0.0, y, 0.001, 1.0])
        u, v = intr.fx * p[0] / p[2] + intr.ppx, intr.fy * p[1] / p[2] + intr.ppy
        r, g, b = view.rgb[round(v), round(u)].astype(int)
        assert (r > 100 and g < 40 and b < 40) == red, (y, r, g, b)


def test_board_lies_on_the_table_where_its_pose_says(rig, true_rig) -> None:
    import cv2

    from darp.calibration.board import corners_board_m, cv_board
    from darp.formats.calibration import CharucoBoardSpec
    from darp.twin.camera.render import SceneRenderer
    from darp.twin.objects.board import BOARD_THICKNESS_M

    board = CharucoBoardSpec(squares_x=7, squares_y=5, square_length_m=0.03, marker_length_m=0.022,
                             dictionary="DICT_5X5_100")
    T_world_board = make_transform(np.diag([1.0, -1.0, -1.0]), [-0.1, 0.08, BOARD_THICKNESS_M + 2e-4])
    world = TwinWorld(rig, true_rig.arms, board=board, T_world_board=T_world_board, seed=2)
    intr = Intrinsics(640, 480, 600.0, 600.0, 319.5, 239.5)
    T_world_cam = look_at([0.0, -0.05, 0.45], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    with SceneRenderer(world.model, 640, 480) as renderer:
        view = renderer.render(world.data, T_world_cam, intr)
    grey = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board(board)).detectBoard(grey)
    assert ids is not None and len(ids) >= 10
    pts_world = (T_world_board @ np.c_[corners_board_m(board), np.ones(len(corners_board_m(board)))].T).T
    pts_cam = (np.linalg.inv(T_world_cam) @ pts_world.T).T[:, :3]
    proj = pts_cam[:, :2] / pts_cam[:, 2:] * [intr.fx, intr.fy] + [intr.ppx, intr.ppy]
    err = np.linalg.norm(corners.reshape(-1, 2) - proj[ids.ravel()], axis=1)
    assert np.median(err) < 0.3 and err.max() < 1.0


def test_mjcf_text_loads_back_in_mujoco(world, tmp_path: Path) -> None:
    import mujoco

    model = mujoco.MjModel.from_xml_string(world.mjcf(tmp_path / "textures"))
    assert model.ngeom == world.model.ngeom and model.ntex == world.model.ntex
    assert (tmp_path / "textures" / "table_tex.png").is_file()
