"""The Z1 model: its table against the facts, FK against an independent chain (scipy), Pinocchio and MuJoCo
built from the facts table, Jacobian against Pinocchio, MuJoCo and finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import KinematicsError
from darp.kinematics import transforms as tf
from darp.kinematics import z1
from helpers.z1_reference import FACTS_JOINTS, FACTS_TOOL_X_M, reference_fk, reference_links, reference_urdf

RNG_SEED = 7


def test_joint_table_is_the_facts_table() -> None:
    assert [(j.name, j.origin_xyz_m, j.axis, j.lower_rad, j.upper_rad) for j in z1.Z1_JOINTS] == list(FACTS_JOINTS)
    assert [(j.parent, j.child) for j in z1.Z1_JOINTS] == [(f"link0{i}", f"link0{i + 1}") for i in range(6)]
    assert z1.FRAME_OFFSETS_M == FACTS_TOOL_X_M


def test_joint_positions_at_zero_match_the_facts() -> None:
    expected = [(0, 0, 0.0585), (0, 0, 0.1035), (-0.35, 0, 0.1035), (-0.132, 0, 0.1605),
                (-0.062, 0, 0.1605), (-0.0128, 0, 0.1605)]
    np.testing.assert_allclose(z1.joint_positions(np.zeros(6)), expected, atol=1e-12)
    # Every joint origin has zero rotation: all link frames are parallel to the base at q = 0.
    for T in z1.link_transforms(np.zeros(6)):
        np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-15)


def test_tool_frames_at_zero() -> None:
    np.testing.assert_allclose(z1.fk(np.zeros(6))[:3, 3], [0.049, 0, 0.1605], atol=1e-12)
    np.testing.assert_allclose(z1.fk(np.zeros(6), "gripper")[:3, 3], [0.0872, 0, 0.1605], atol=1e-12)
    np.testing.assert_allclose(z1.fk(np.zeros(6), "link06")[:3, 3], [-0.0128, 0, 0.1605], atol=1e-12)


def test_forward_configuration_matches_the_facts() -> None:
    T = z1.fk(z1.NAMED_CONFIGS["forward"])
    # Facts: flange near (0.375, 0, 0.405), pitch about -0.04 rad.
    np.testing.assert_allclose(T[:3, 3], [0.375, 0.0, 0.405], atol=2e-3)
    roll, pitch, yaw = tf.rotation_to_rpy(T[:3, :3])
    assert pitch == pytest.approx(-0.04, abs=2e-3)
    assert roll == pytest.approx(0.0, abs=1e-12) and yaw == pytest.approx(0.0, abs=1e-12)
    # In the sagittal plane the tool pitch is the sum of the three pitch joints (all about +y).
    q = z1.NAMED_CONFIGS["forward"]
    assert pitch == pytest.approx(q[1] + q[2] + q[3], abs=1e-12)


def test_named_configurations_are_within_limits() -> None:
    for name, q in z1.NAMED_CONFIGS.items():
        if name == "stow":  # the facts' stow has q4 = 1.5707, 3 deg past joint 4's 1.5184 limit
            assert not z1.within_limits(q)
            assert z1.within_limits(q, tol_rad=0.053)
            continue
        assert z1.within_limits(q), name
        assert z1.within_limits(q, "sdk"), name


def test_limits_tables() -> None:
    assert z1.JOINT_LOWER.shape == z1.JOINT_UPPER.shape == (6,)
    assert np.all(z1.JOINT_LOWER < z1.JOINT_UPPER)
    assert z1.SDK_JOINT_UPPER[1] == pytest.approx(2.879793)
    assert z1.SDK_JOINT_LOWER[2] == pytest.approx(-2.885593)
    np.testing.assert_allclose(z1.VELOCITY_LIMIT_RAD_S, np.pi)
    assert [j.name for j in z1.Z1_JOINTS] == list(z1.JOINT_NAMES)
    assert not z1.within_limits(np.array([0, -0.01, 0, 0, 0, 0]))
    assert not z1.within_limits(np.array([0, 2.9, 0, 0, 0, 0]), "sdk")
    assert z1.within_limits(np.array([0, 2.9, 0, 0, 0, 0]), "urdf")
    batch = z1.within_limits(np.array([[0, 1, -1, 0, 0, 0], [3.0, 1, -1, 0, 0, 0]]))
    assert batch.tolist() == [True, False]


def test_fk_batch_equals_fk_per_row() -> None:
    Q = z1.random_configurations(64, RNG_SEED)
    for frame in ("flange", "gripper", "link06"):
        batch = z1.fk_batch(Q, frame)
        for i in range(len(Q)):
            np.testing.assert_allclose(batch[i], z1.fk(Q[i], frame), atol=1e-15)
    links = z1.link_transforms_batch(Q)
    np.testing.assert_allclose(links[5], z1.link_transforms(Q[5]), atol=1e-15)
    np.testing.assert_allclose(links[:, 6] @ tf.make_transform(t=[0.0618, 0, 0]), z1.fk_batch(Q), atol=1e-15)


def test_fk_matches_an_independent_chain_of_scipy_rotations() -> None:
    """The oracle shares neither darp's table nor its transforms: the facts table, one scipy rotation per joint."""
    Q = z1.random_configurations(20, RNG_SEED + 1)
    for frame in ("flange", "gripper", "link06"):
        expected = np.array([reference_fk(q, frame) for q in Q])
        np.testing.assert_allclose(z1.fk_batch(Q, frame), expected, atol=1e-14)
        for q, T in zip(Q, expected, strict=True):
            np.testing.assert_allclose(z1.fk(q, frame), T, atol=1e-14)
    for q in Q[:5]:
        np.testing.assert_allclose(z1.link_transforms(q), np.array(reference_links(q)), atol=1e-14)


def test_fk_outside_limits_and_at_half_turns() -> None:
    """The closed form has no hidden range assumption: half turns, multiple turns, tiny angles."""
    Q = np.array([[np.pi, -np.pi, np.pi, -np.pi, np.pi, np.pi], [7.0, -9.5, 12.0, 3.3, -4.0, 20.0],
                  [1e-300, -1e-12, 1e-9, 0.0, -0.0, 5e-324], [3 * np.pi, 0.5, -2.0, 1.0, -0.3, -np.pi / 2]])
    expected = np.array([reference_fk(q) for q in Q])
    np.testing.assert_allclose(z1.fk_batch(Q), expected, atol=1e-14)
    np.testing.assert_allclose(z1.link_transforms_batch(Q)[:, 6, :3, :3], expected[:, :3, :3], atol=1e-14)
    for q, T in zip(Q, expected, strict=True):
        np.testing.assert_allclose(z1.fk(q), T, atol=1e-14)


def test_fk_and_jacobian_agree_with_pinocchio() -> None:
    """Pinocchio loads the facts table as a URDF: link placements, tool frames and frame Jacobians."""
    pin = pytest.importorskip("pinocchio")
    model = pin.buildModelFromXML(reference_urdf())
    data = model.createData()
    np.testing.assert_allclose(model.lowerPositionLimit, z1.JOINT_LOWER)
    np.testing.assert_allclose(model.upperPositionLimit, z1.JOINT_UPPER)
    for q in z1.random_configurations(25, RNG_SEED + 6):
        pin.framesForwardKinematics(model, data, q)
        links = z1.link_transforms(q)
        for i in range(1, 7):
            np.testing.assert_allclose(links[i], data.oMi[i].homogeneous, atol=1e-12)
        for frame in ("flange", "gripper"):
            fid = model.getFrameId(frame)
            np.testing.assert_allclose(z1.fk(q, frame), data.oMf[fid].homogeneous, atol=1e-12)
            J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)  # base axes, frame origin
            np.testing.assert_allclose(z1.jacobian(q, frame), J, atol=1e-12)


def test_fk_batch_blocks_and_out_buffer() -> None:
    Q = z1.random_configurations(z1._FK_BLOCK * 2 + 17, RNG_SEED + 5)  # spans three blocks
    out = np.full((len(Q), 4, 4), np.nan)
    result = z1.fk_batch(Q, "gripper", out=out)
    assert result is out
    np.testing.assert_allclose(out[::97], np.array([z1.fk(q, "gripper") for q in Q[::97]]), atol=1e-15)
    with pytest.raises(KinematicsError, match="out must be"):
        z1.fk_batch(Q, out=np.zeros((3, 4, 4)))
    assert z1.fk_batch(np.zeros((0, 6))).shape == (0, 4, 4)


def _mujoco_model() -> tuple[object, object]:
    mujoco = pytest.importorskip("mujoco")
    xml, close = "", ""
    for i, (name, origin, axis_name, _, _) in enumerate(FACTS_JOINTS):  # the facts table, not darp's
        axis = " ".join(str(v) for v in np.eye(3)["xyz".index(axis_name)])
        pos = " ".join(str(v) for v in origin)
        xml += f'<body name="link0{i + 1}" pos="{pos}"><joint name="{name}" axis="{axis}"/>'
        xml += '<geom type="sphere" size="0.01" mass="0.1"/>'
        close += "</body>"
    xml += f'<site name="flange" pos="{FACTS_TOOL_X_M["flange"]} 0 0"/>'
    model = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{xml}{close}</worldbody></mujoco>")
    return model, mujoco.MjData(model)


def test_fk_and_jacobian_agree_with_mujoco() -> None:
    mujoco = pytest.importorskip("mujoco")
    model, data = _mujoco_model()
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for q in z1.random_configurations(25, RNG_SEED + 2):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        T = z1.fk(q)
        np.testing.assert_allclose(T[:3, 3], data.site_xpos[0], atol=1e-12)
        np.testing.assert_allclose(T[:3, :3], data.site_xmat[0].reshape(3, 3), atol=1e-12)
        mujoco.mj_jacSite(model, data, jacp, jacr, 0)
        J = z1.jacobian(q)
        np.testing.assert_allclose(J[:3], jacp, atol=1e-12)
        np.testing.assert_allclose(J[3:], jacr, atol=1e-12)


@pytest.mark.parametrize("frame", ["flange", "gripper"])
def test_jacobian_matches_finite_differences(frame: str) -> None:
    h = 1e-6
    for q in z1.random_configurations(10, RNG_SEED + 3):
        J = z1.jacobian(q, frame)
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            T_plus, T_minus = z1.fk(q + dq, frame), z1.fk(q - dq, frame)
            v = (T_plus[:3, 3] - T_minus[:3, 3]) / (2 * h)
            w = tf.rotation_to_rotvec(T_plus[:3, :3] @ T_minus[:3, :3].T) / (2 * h)  # base-frame omega
            np.testing.assert_allclose(J[:3, i], v, atol=1e-8)
            np.testing.assert_allclose(J[3:, i], w, atol=1e-8)
    Q = z1.random_configurations(5, RNG_SEED + 4)
    np.testing.assert_allclose(z1.jacobian_batch(Q, frame)[3], z1.jacobian(Q[3], frame), atol=1e-15)


def test_singularity_measures() -> None:
    q = z1.NAMED_CONFIGS["forward"]
    J = z1.jacobian(q)
    assert z1.manipulability(q) == pytest.approx(np.sqrt(np.linalg.det(J @ J.T)))
    assert z1.min_singular_value(q) > 0.05
    # Elbow fully stretched (upper arm and forearm in line; just outside the URDF joint-3 limit):
    beta = np.arctan2(0.057, 0.218)
    stretched = np.array([0.0, 1.0, beta - np.pi, 0.3, 0.2, 0.1])
    assert z1.min_singular_value(stretched) < 1e-9
    assert z1.manipulability(stretched) < 1e-9
    assert z1.condition_number(stretched) > 1e8
    assert z1.condition_number(q) < 1e3


def test_bad_input_raises() -> None:
    with pytest.raises(KinematicsError, match=r"shape \(6,\)"):
        z1.fk(np.zeros(5))
    with pytest.raises(KinematicsError, match="NaN"):
        z1.fk(np.array([0, np.nan, 0, 0, 0, 0]))
    with pytest.raises(KinematicsError, match="available: link06, flange, gripper"):
        z1.fk(np.zeros(6), "tcp")
    with pytest.raises(KinematicsError, match=r"\(N, 6\)"):
        z1.fk_batch(np.zeros(6))
    with pytest.raises(KinematicsError, match="limit set"):
        z1.within_limits(np.zeros(6), "vendor")


def test_random_configurations_are_deterministic_and_inside() -> None:
    a, b = z1.random_configurations(100, 3), z1.random_configurations(100, 3)
    np.testing.assert_array_equal(a, b)
    assert np.all(z1.within_limits(a))
    assert np.all(z1.within_limits(z1.random_configurations(100, 4, "sdk"), "sdk"))
