"""Collision geometry: exact distances on constructed cases, MuJoCo as the oracle, arm scenarios."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import KinematicsError
from darp.kinematics import collision as col
from darp.kinematics import ik, z1
from darp.kinematics import transforms as tf
from darp.kinematics.collision_shapes import Primitive, PrimitiveSet, pair_distances, segment_distances

mujoco = pytest.importorskip("mujoco")

T_WORLD_BASE_A = tf.make_transform(t=[-0.6993, 0.0, 0.0])
T_WORLD_BASE_B = tf.make_transform(tf.rot_z(np.radians(178.4)), [0.6993, 0.0, 0.0])
PARK_Q = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])


def _d(a: Primitive, b: Primitive) -> float:
    return col.min_distance([a], [b]).distance_m


def test_segment_closest_points_constructed() -> None:
    # Parallel, overlapping in extent: the offset between the lines.
    d, p1, p2 = segment_distances(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.5, 0.3, 0.4]),
                                  np.array([2.0, 0.3, 0.4]))
    assert d == pytest.approx(0.5)
    assert p1[0] == pytest.approx(p2[0]) and 0.5 <= p1[0] <= 1.0
    # Crossing (skew, perpendicular) at 0.2 apart, closest points in the interiors.
    d, p1, p2 = segment_distances(np.array([-1.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.3, -1, 0.2]),
                                  np.array([0.3, 1, 0.2]))
    assert d == pytest.approx(0.2)
    np.testing.assert_allclose(p1, [0.3, 0, 0], atol=1e-15)
    np.testing.assert_allclose(p2, [0.3, 0, 0.2], atol=1e-15)
    # Collinear, disjoint: end to end.
    d, *_ = segment_distances(np.zeros(3), np.array([1.0, 0, 0]), np.array([1.25, 0, 0]), np.array([3.0, 0, 0]))
    assert d == pytest.approx(0.25)
    # Point (zero-length) against a segment, beyond its end.
    d, *_ = segment_distances(np.array([2.0, 1.0, 0]), np.array([2.0, 1.0, 0]), np.zeros(3), np.array([1.0, 0, 0]))
    assert d == pytest.approx(np.sqrt(2.0))


def test_capsule_pairs_exact() -> None:
    a = Primitive.capsule([0, 0, 0], [1, 0, 0], 0.02)
    assert _d(a, Primitive.capsule([0.2, 0.1, 0], [0.8, 0.1, 0], 0.03)) == pytest.approx(0.05)  # parallel
    assert _d(a, Primitive.capsule([0.5, -1, 0.05], [0.5, 1, 0.05], 0.03)) == pytest.approx(0.0, abs=1e-15)
    assert _d(a, Primitive.capsule([0.5, -1, 0.04], [0.5, 1, 0.04], 0.03)) == pytest.approx(-0.01)
    assert _d(a, Primitive.capsule([1.1, 0, 0], [2.0, 0, 0], 0.01)) == pytest.approx(0.07)  # end caps


def test_cylinder_and_box_pairs_exact() -> None:
    cyl = Primitive.cylinder([0, 0, 0], [0, 0, 0.1], 0.05)
    # Coaxial, end to end: flat faces 0.03 apart (a capsule model would say -0.07).
    assert _d(cyl, Primitive.cylinder([0, 0, 0.13], [0, 0, 0.3], 0.02)) == pytest.approx(0.03, abs=1e-9)
    # Side by side, parallel axes.
    assert _d(cyl, Primitive.cylinder([0.2, 0, 0.02], [0.2, 0, 0.5], 0.04)) == pytest.approx(0.11, abs=1e-9)
    # A horizontal cylinder above the top face, crossing the axis.
    assert _d(cyl, Primitive.cylinder([-1, 0, 0.15], [1, 0, 0.15], 0.01)) == pytest.approx(0.04, abs=1e-9)
    # Rim corner to a point: the corner at (0.05, 0, 0.1) and a tiny sphere-capsule diagonally off it.
    corner = Primitive.capsule([0.08, 0, 0.14], [0.08, 0, 0.14], 1e-3)
    assert _d(cyl, corner) == pytest.approx(0.05 - 1e-3, abs=1e-9)
    box = Primitive.box(tf.make_transform(tf.rot_z(0.3), [0.5, 0.0, 0.05]), [0.1, 0.2, 0.1])
    other = Primitive.box(tf.make_transform(tf.rot_z(0.3), [0.5, 0.0, 0.25]), [0.05, 0.05, 0.1])
    assert _d(box, other) == pytest.approx(0.1, abs=1e-9)  # face to face
    assert _d(box, Primitive.box(tf.make_transform(t=[0.5, 0, 0.12]), [0.05, 0.05, 0.05])) < 0  # overlap


def test_plane_distances_exact() -> None:
    tilt = 0.4
    u = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    c = np.array([0.1, 0.2, 0.5])
    cyl = Primitive.cylinder(c - 0.1 * u, c + 0.1 * u, 0.03)
    cap = Primitive.capsule(c - 0.1 * u, c + 0.1 * u, 0.03)
    low_cyl = c[2] - 0.1 * np.cos(tilt) - 0.03 * np.sin(tilt)
    low_cap = c[2] - 0.1 * np.cos(tilt) - 0.03
    s = PrimitiveSet.from_list([cyl, cap])
    np.testing.assert_allclose(s.lowest_z(), [low_cyl, low_cap], atol=1e-15)


def _mj_geom(p: Primitive, name: str) -> str:
    q = tf.rotation_to_quaternion(p.T_frame_shape[:3, :3])
    pos = " ".join(repr(float(v)) for v in p.T_frame_shape[:3, 3])
    quat = " ".join(repr(float(v)) for v in (q[3], q[0], q[1], q[2]))
    size = p.half_extents_m if p.kind == "box" else [p.half_extents_m[0], p.half_extents_m[2]]
    size_text = " ".join(repr(float(v)) for v in size)
    return f'<geom name="{name}" type="{p.kind}" size="{size_text}" pos="{pos}" quat="{quat}"/>'


def _mj_distances(prims_a: list[Primitive], prims_b: list[Primitive]) -> np.ndarray:
    geoms = ([_mj_geom(p, f"a{i}") for i, p in enumerate(prims_a)]
             + [_mj_geom(p, f"b{i}") for i, p in enumerate(prims_b)])
    model = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{''.join(geoms)}</worldbody></mujoco>")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    fromto = np.zeros(6)
    out = np.empty((len(prims_a), len(prims_b)))
    for i in range(len(prims_a)):
        for j in range(len(prims_b)):
            out[i, j] = mujoco.mj_geomDistance(model, data, i, len(prims_a) + j, 10.0, fromto)
    return out


def _random_primitive(rng: np.random.Generator, kind: str) -> Primitive:
    T = tf.make_transform(tf.rotvec_to_rotation(rng.normal(size=3)), rng.uniform(-0.08, 0.08, 3))
    if kind == "box":
        return Primitive.box(T, rng.uniform(0.01, 0.1, 3))
    r, h = rng.uniform(0.005, 0.04), rng.uniform(0.001, 0.06)
    a, b = T[:3, 3] - h * T[:3, 2], T[:3, 3] + h * T[:3, 2]
    return Primitive.cylinder(a, b, r) if kind == "cylinder" else Primitive.capsule(a, b, r)


def test_pair_distances_agree_with_mujoco() -> None:
    rng = np.random.default_rng(5)
    kinds = ("capsule", "cylinder", "box")
    A = [_random_primitive(rng, kinds[k % 3]) for k in range(450)]
    B = [_random_primitive(rng, kinds[(k // 3) % 3]) for k in range(450)]
    ours, _, _ = pair_distances(PrimitiveSet.from_list(A), PrimitiveSet.from_list(B))
    ref = np.array([_mj_distances([a], [b])[0, 0] for a, b in zip(A, B, strict=True)])
    apart = ref > 1e-5
    assert apart.sum() > 200 and (~apart).sum() > 50
    assert np.all(ours <= ref + 1e-9)  # never over-reported
    assert np.max(ref[apart] - ours[apart]) < 2e-6  # exact to the 1 um tolerance
    deep = ref < -1e-4
    assert np.all(ours[deep] < 0)  # overlaps are reported as overlaps


def test_link_geometry_is_the_facts_table() -> None:
    prims = col.arm_primitives(np.zeros(6), camera_mount=None)
    assert len(prims) == 8 and set(prims.kinds.tolist()) == {1}  # all cylinders
    i = prims.names.index("wrist_pitch_motor")
    # link04 origin at q = 0 is (-0.132, 0, 0.1605); the motor is centred 0.072 further along x.
    np.testing.assert_allclose(prims.centre[i], [-0.06, 0.0, 0.1605], atol=1e-12)
    np.testing.assert_allclose(prims.half[i], [0.0325, 0.0325, 0.0335], atol=1e-12)
    cam = col.arm_primitives(np.zeros(6)).to_list()
    body = next(p for p in cam if p.name == "camera_body")
    # Body centre: T_wrist_cam @ (0.0175, 0, -0.0083) with the flange at (0.049, 0, 0.1605).
    np.testing.assert_allclose(body.T_frame_shape[:3, 3], [0.049 - 0.0083, -0.0175, 0.1605 + 0.055], atol=1e-12)


def test_self_collision_named_configurations_are_free() -> None:
    for name, q in z1.NAMED_CONFIGS.items():
        assert not col.self_collision(q), name
        assert not col.self_collision(q, camera_mount=None), name
    # The folded rest pose q = 0 clears every checked pair by 1 mm (upper arm under the wrist motor) ...
    rest = col.self_collision_distance(np.zeros(6))
    assert rest.distance_m == pytest.approx(0.001, abs=1e-6)
    assert {rest.name_a, rest.name_b} == {"upper_arm", "wrist_pitch_motor"}
    # ... once the table's shoulder/flange motor overlap, 8 mm in that pose, is allowed.
    strict = col.self_collision_distance(np.zeros(6), allowed_pairs=())
    assert strict.distance_m == pytest.approx(-0.008, abs=1e-6)
    assert {strict.name_a, strict.name_b} == {"shoulder_motor", "flange_motor"}


def test_self_collision_detects_folding_into_itself() -> None:
    folded = np.array([0.0, 0.0, 0.0, 1.5, 0.0, 0.0])  # wrist pitched down onto the upper arm
    assert col.self_collision(folded)
    r = col.self_collision_distance(folded)
    assert r.distance_m < -0.03 and {r.name_a, r.name_b} == {"upper_arm", "wrist_pitch_motor"}
    assert col.self_collision(np.zeros(6), margin_m=0.002)  # within a 2 mm margin at rest


def test_arm_table_distance_reaching_down() -> None:
    down = tf.rot_y(np.pi / 2)  # flange x pointing down
    for height in (0.05, -0.01):
        r = ik.solve_ik(tf.make_transform(down, [0.35, 0.0, height]))
        assert r.success
        d = col.arm_table_distance(r.q, np.eye(4), 0.0)
        # Lowest point: the camera body's front face, 12.5 - 8.3 mm below the flange along the tool axis.
        assert d.distance_m == pytest.approx(height - (0.0125 - 0.0083), abs=1e-9)
        assert d.name_a == "camera_body"
        assert d.point_a[2] == pytest.approx(height - 0.0042, abs=1e-9)
    lifted = col.arm_table_distance(r.q, tf.make_transform(t=[0, 0, 0.2]), 0.0)
    assert lifted.distance_m == pytest.approx(0.2 - 0.01 - 0.0042, abs=1e-9)


def _arm_arm(qA: np.ndarray, qB: np.ndarray) -> col.DistanceResult:
    return col.arm_arm_distance(qA, T_WORLD_BASE_A, qB, T_WORLD_BASE_B)


def _reach(T_world_base: np.ndarray, point: list[float], x_dir: list[float]) -> np.ndarray:
    x = np.asarray(x_dir, dtype=float)
    y = np.cross([0.0, 0.0, 1.0], x)
    R = np.column_stack([x, y, np.cross(x, y)])
    r = ik.solve_ik(tf.invert_transform(T_world_base) @ tf.make_transform(R, point))
    assert r.success, r.message
    return r.q


def test_facing_arms_near_collision_and_parked() -> None:
    # Flanges facing each other along world x; each camera body's front face is 4.2 mm past its flange.
    qA = _reach(T_WORLD_BASE_A, [-0.002, 0.0, 0.25], [1.0, 0.0, 0.0])
    qB = _reach(T_WORLD_BASE_B, [0.002, 0.0, 0.25], [-1.0, 0.0, 0.0])
    near = _arm_arm(qA, qB)
    assert near.distance_m < 0.0
    qA = _reach(T_WORLD_BASE_A, [-0.01, 0.0, 0.25], [1.0, 0.0, 0.0])
    qB = _reach(T_WORLD_BASE_B, [0.01, 0.0, 0.25], [-1.0, 0.0, 0.0])
    close = _arm_arm(qA, qB)
    assert close.distance_m == pytest.approx(2 * (0.01 - 0.0042), abs=1e-6)
    assert {close.name_a, close.name_b} == {"camera_body"}
    swapped = col.arm_arm_distance(qB, T_WORLD_BASE_B, qA, T_WORLD_BASE_A)
    assert swapped.distance_m == pytest.approx(close.distance_m, abs=1e-9)
    for q in (PARK_Q, z1.NAMED_CONFIGS["zero"], z1.NAMED_CONFIGS["show_mid"]):
        assert _arm_arm(q, q).distance_m > 0.8


def test_arm_arm_and_envelope_agree_with_mujoco() -> None:
    qA = _reach(T_WORLD_BASE_A, [-0.08, 0.03, 0.2], [1.0, 0.0, 0.0])
    qB = _reach(T_WORLD_BASE_B, [0.06, -0.02, 0.22], [-1.0, 0.0, 0.0])
    prims_a = col.arm_geometry(qA, T_WORLD_BASE_A)
    prims_b = col.arm_geometry(qB, T_WORLD_BASE_B)
    ref = _mj_distances(prims_a, prims_b).min()
    ours = _arm_arm(qA, qB).distance_m
    assert ref > 0 and ref - 2e-6 < ours <= ref + 1e-9
    centre = np.array([0.0, 0.0, 0.06])
    env = col.envelope_primitive(centre, 0.05, 0.12)
    ours_env = col.arm_envelope_distance(qA, T_WORLD_BASE_A, centre, 0.05, 0.12).distance_m
    ref_env = _mj_distances(prims_a, [env]).min()
    assert ref_env - 2e-6 < ours_env <= ref_env + 1e-9
    # Standing on the table: the same cylinder when the table height puts it at [0, 0.12].
    standing = col.arm_envelope_distance(qA, T_WORLD_BASE_A, [0.0, 0.0, 0.5], 0.05, 0.12, table_height_z=0.0)
    assert standing.distance_m == pytest.approx(ours_env, abs=1e-12)


def test_envelope_distance_constructed() -> None:
    q = np.array([0.0, 1.5, -1.0, -0.5, 0.0, 0.0])  # tool axis horizontal along base x
    flange = z1.fk(q)[:3, 3]
    # A tall cylinder whose side is exactly 0.1 m in front of the flange motor's front face.
    face_x = flange[0] - (z1.WRIST_FRAMES["flange"] - 0.051)
    centre = np.array([face_x + 0.1 + 0.05, 0.0, 0.3])
    d = col.arm_envelope_distance(q, np.eye(4), centre, 0.05, 0.6, camera_mount=None)
    assert d.distance_m == pytest.approx(0.1, abs=1e-6)
    assert d.name_a == "flange_motor" and d.name_b == "envelope"
    inside = col.arm_envelope_distance(q, np.eye(4), flange, 0.05, 0.1)
    assert inside.distance_m < 0


def test_camera_mount_variants_and_errors() -> None:
    T_side = tf.make_transform(tf.rot_y(np.pi / 2), [0.0, 0.08, 0.0])
    mount = col.CameraMount(T_wrist_cam=T_side, body_size_m=(0.1, 0.03, 0.03))
    prims = col.arm_primitives(np.zeros(6), camera_mount=mount)
    body = prims.to_list()[prims.names.index("camera_body")]
    np.testing.assert_allclose(body.half_extents_m, [0.05, 0.015, 0.015])
    with pytest.raises(KinematicsError, match="positive"):
        col.CameraMount(body_size_m=(0.09, 0.0, 0.025))
    with pytest.raises(KinematicsError, match="4x4"):
        col.arm_primitives(np.zeros(6), T_world_base=np.eye(3))
    with pytest.raises(KinematicsError, match="at least one"):
        col.min_distance([], [Primitive.capsule([0, 0, 0], [1, 0, 0], 0.1)])
    with pytest.raises(KinematicsError, match="envelope"):
        col.arm_envelope_distance(np.zeros(6), np.eye(4), [0, 0], 0.05, 0.1)
