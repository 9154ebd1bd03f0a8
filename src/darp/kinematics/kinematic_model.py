"""A richer Z1 model than joint zeros: joint origin offsets, joint axis tilts and joint compliance.

The nominal chain (:mod:`darp.kinematics.z1`) is ``T = prod_i Trans(o_i) Rot(e_i, q_i)``. The richer
chain, written once here and used by the calibration (to estimate it), by processing (to apply it)
and by the twin (to simulate the true arm), is

    T = prod_i Trans(o_i + do_i) Rot(Exp(w_i) e_i, q_i + c_i tau_i(q))

- ``do_i`` (6, 3): each joint's origin offset in its parent link (link lengths and offsets), metres;
- ``w_i`` (6, 3): a small rotation vector tilting joint i's axis (its component along the axis has no
  effect), radians;
- ``c_i`` (6,): compliance, rad per N m; ``tau(q)`` is the gravity torque of the links plus the camera
  payload about each joint, from the nominal mass model :data:`LINK_MASSES` (only joints 2-4 are loaded
  with the base level, z up). Link angle = motor angle + ``c * tau``: the encoders do not see the sag.
- ``b_i`` (6,): backlash, half the dead band of joint i in radians: the link sits ``b_i`` behind the
  direction ``d_i`` (-1, 0, +1) of the joint's last motion, so the link angle is ``q_i - b_i d_i``
  before the sag is added (``q - b d + c tau(q - b d)``). The direction is data (the move that brought
  the arm to a capture pose, or the joint log's history), passed beside the joints; without it
  (``direction=None``) the term is left out.

All zero is the nominal Z1, bit for bit the same as :func:`darp.kinematics.z1.fk_batch` up to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.kinematics import z1
from darp.kinematics.transforms import compose, matvec, rotvec_to_rotation

GRAVITY_M_S2 = 9.81
DEFAULT_PAYLOAD_KG = 0.2  # D435 (72 g) + bracket + cable strain relief, 3 cm past the flange

# Nominal lumped link masses (kg) and centres of mass in their link frame (m): the Z1's arm is about
# 4.1-4.4 kg (docs/twin.md); link01 and the base do not load joints 2-4.
LINK_MASSES: tuple[tuple[int, float, tuple[float, float, float]], ...] = (
    (2, 1.50, (-0.17, 0.0, 0.0)),  # link02: upper arm (two motors at joint 2 sit below it)
    (3, 0.80, (0.12, 0.0, 0.05)),  # link03: forearm with the joint-4 motor
    (4, 0.40, (0.05, 0.0, 0.0)),  # link04
    (5, 0.35, (0.03, 0.0, 0.0)),  # link05
    (6, 0.30, (0.03, 0.0, 0.0)),  # link06 (without gripper)
)
SAG_JOINTS = (1, 2, 3)  # joints 2, 3, 4 (0-based): horizontal axes, the ones gravity loads
PAYLOAD_OFFSET_M = 0.03  # payload centre past the flange along the flange x axis

# Parameter names of the flat vector (:meth:`KinematicParams.to_vector`), per joint: origin x y z, tilt x y z,
# then the compliances of joints 2-4.
AXES = ("x", "y", "z")
PARAM_NAMES: tuple[str, ...] = tuple(
    [f"joint{j + 1}.origin.{a}" for j in range(6) for a in AXES]
    + [f"joint{j + 1}.tilt.{a}" for j in range(6) for a in AXES]
    + [f"joint{j + 1}.compliance" for j in SAG_JOINTS]
    + [f"joint{j + 1}.backlash" for j in range(6)])
N_PARAMS = len(PARAM_NAMES)  # 45
ORIGIN_SLICE = slice(0, 18)
TILT_SLICE = slice(18, 36)
COMPLIANCE_SLICE = slice(36, 39)
BACKLASH_SLICE = slice(39, 45)


@dataclass(eq=False)
class KinematicParams:
    """Kinematic parameter errors of one arm (all zero: the nominal Z1)."""

    origin_m: np.ndarray = field(default_factory=lambda: np.zeros((6, 3)))
    axis_tilt_rad: np.ndarray = field(default_factory=lambda: np.zeros((6, 3)))
    compliance_rad_per_nm: np.ndarray = field(default_factory=lambda: np.zeros(6))
    payload_kg: float = DEFAULT_PAYLOAD_KG
    backlash_rad: np.ndarray = field(default_factory=lambda: np.zeros(6))  # half dead band per joint

    def copy(self) -> KinematicParams:
        return KinematicParams(self.origin_m.copy(), self.axis_tilt_rad.copy(), self.compliance_rad_per_nm.copy(),
                               self.payload_kg, self.backlash_rad.copy())

    @property
    def has_backlash(self) -> bool:
        return bool(np.any(self.backlash_rad != 0))

    @property
    def has_compliance(self) -> bool:
        return bool(np.any(self.compliance_rad_per_nm != 0))

    def origins(self) -> np.ndarray:
        """Joint origins (6, 3) in their parent link."""
        origins: np.ndarray = np.asarray(z1.JOINT_ORIGINS_M, dtype=float) + self.origin_m
        return origins

    def axes(self) -> np.ndarray:
        """Joint axes (6, 3), unit vectors in the child link (= parent at zero angle)."""
        return tilted_axes(self.axis_tilt_rad)

    def to_vector(self) -> np.ndarray:
        """The flat parameter vector (:data:`PARAM_NAMES` order)."""
        return np.concatenate([self.origin_m.ravel(), self.axis_tilt_rad.ravel(),
                               self.compliance_rad_per_nm[list(SAG_JOINTS)], self.backlash_rad])

    @classmethod
    def from_vector(cls, v: np.ndarray, payload_kg: float = DEFAULT_PAYLOAD_KG) -> KinematicParams:
        v = np.asarray(v, float)
        c = np.zeros(6)
        c[list(SAG_JOINTS)] = v[COMPLIANCE_SLICE]
        b = v[BACKLASH_SLICE].copy() if v.size >= N_PARAMS else np.zeros(6)
        return cls(v[ORIGIN_SLICE].reshape(6, 3).copy(), v[TILT_SLICE].reshape(6, 3).copy(), c, payload_kg, b)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "joint_origin_offsets_m": self.origin_m.tolist(), "joint_axis_tilts_rad": self.axis_tilt_rad.tolist(),
            "compliance_rad_per_nm": self.compliance_rad_per_nm.tolist(), "payload_kg": self.payload_kg}
        if self.has_backlash:  # optional: files of the models without it are unchanged
            out["backlash_rad"] = self.backlash_rad.tolist()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "kinematics") -> KinematicParams:
        try:
            origin = np.asarray(d["joint_origin_offsets_m"], float)
            tilt = np.asarray(d["joint_axis_tilts_rad"], float)
            comp = np.asarray(d.get("compliance_rad_per_nm", np.zeros(6)), float)
            payload = float(d.get("payload_kg", DEFAULT_PAYLOAD_KG))
            backlash = np.asarray(d.get("backlash_rad", np.zeros(6)), float)
        except (KeyError, TypeError, ValueError) as err:
            raise FormatError(f"{where}: expected joint_origin_offsets_m (6x3), joint_axis_tilts_rad (6x3), "
                              f"compliance_rad_per_nm (6), optional backlash_rad (6) ({err})") from None
        if origin.shape != (6, 3) or tilt.shape != (6, 3) or comp.shape != (6,) or backlash.shape != (6,):
            raise FormatError(f"{where}: shapes must be 6x3, 6x3, 6 and 6")
        if not all(np.all(np.isfinite(v)) for v in (origin, tilt, comp, backlash)):
            raise FormatError(f"{where}: non-finite values")
        if (np.max(np.abs(origin)) > 0.01 or np.max(np.abs(tilt)) > np.radians(2.0) or np.max(np.abs(comp)) > 0.05
                or np.max(np.abs(backlash)) > np.radians(1.0)):
            raise FormatError(f"{where}: parameters beyond plausible ranges (origin 10 mm, tilt 2 deg, "
                              "compliance 0.05 rad/N m, backlash 1 deg)")
        return cls(origin, tilt, comp, payload, backlash)


def tilted_axes(axis_tilt_rad: np.ndarray) -> np.ndarray:
    """Joint axes (6, 3) of the Z1 tilted by rotation vectors (6, 3)."""
    nominal = np.eye(3)[list(z1.JOINT_AXIS_INDEX)]
    axes = matvec(rotvec_to_rotation(np.asarray(axis_tilt_rad, float)), nominal)
    unit: np.ndarray = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    return unit


def chain_links(Q: np.ndarray, origins: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Link transforms (N, 7, 4, 4) in the base frame of the chain with ``origins`` and ``axes`` (6, 3) at
    link angles Q (N, 6): entry 0 is the base, entry j + 1 the child of joint j (origin = joint j)."""
    Qa = z1.check_q(Q, batched=True)
    n = Qa.shape[0]
    links = np.empty((n, 7, 4, 4))
    T = np.tile(np.eye(4), (n, 1, 1))
    links[:, 0] = T
    for i, (origin, axis) in enumerate(zip(origins, axes, strict=True)):
        step = np.zeros((n, 4, 4))
        step[:, :3, :3] = rotvec_to_rotation(axis[None, :] * Qa[:, i][:, None])
        step[:, :3, 3] = origin
        step[:, 3, 3] = 1.0
        T = compose(T, step)
        links[:, i + 1] = T
    return links


def chain_fk(Q: np.ndarray, origins: np.ndarray, axes: np.ndarray, frame: str = "flange") -> np.ndarray:
    """``T_base_frame`` (N, 4, 4) of the chain with ``origins`` and ``axes`` at link angles Q (N, 6)."""
    T = chain_links(Q, origins, axes)[:, 6]
    tool = np.eye(4)
    tool[0, 3] = z1.frame_offset_m(frame)
    out: np.ndarray = compose(T, tool)
    return out


def gravity_torques(Q: np.ndarray, payload_kg: float) -> np.ndarray:
    """Gravity torques (N, 6) in N m about each joint's axis (positive: about +axis) for joint rows Q (N, 6).

    Nominal lumped masses (:data:`LINK_MASSES`) plus ``payload_kg`` (camera and bracket) 3 cm past the
    flange, on the nominal chain with the base level; only joints 2-4 are loaded (1, 5, 6 get 0).
    """
    Qa = np.atleast_2d(np.asarray(Q, dtype=float))
    links = z1.link_transforms_batch(Qa)  # (N, 7, 4, 4)
    masses: list[tuple[int, float, np.ndarray]] = [(i, m, np.asarray(c)) for i, m, c in LINK_MASSES]
    if payload_kg > 0:
        masses.append((6, payload_kg, np.array([z1.WRIST_FRAMES["flange"] + PAYLOAD_OFFSET_M, 0.0, 0.0])))
    tau = np.zeros((Qa.shape[0], 6))
    down = np.array([0.0, 0.0, -GRAVITY_M_S2])
    for j in SAG_JOINTS:
        p = links[:, j + 1, :3, 3]  # joint j's origin = child link (j + 1)'s origin
        axis = links[:, j + 1, :3, z1.JOINT_AXIS_INDEX[j]]
        for link, mass, centre in masses:
            if link < j + 1:
                continue
            r = matvec(links[:, link, :3, :3], centre) + links[:, link, :3, 3]
            moment = np.cross(r - p, mass * down)
            tau[:, j] += np.sum(moment * axis, axis=-1)
    return tau


def backlash_angles(Q: np.ndarray, params: KinematicParams, direction: np.ndarray | None) -> np.ndarray:
    """Motor-side joints Q (N, 6) moved by the backlash: ``Q - b d`` (``direction`` d (N, 6) or None: Q)."""
    Qa = np.atleast_2d(np.asarray(Q, dtype=float))
    if direction is None or not params.has_backlash:
        return Qa
    out: np.ndarray = Qa - params.backlash_rad * np.asarray(direction, dtype=float)
    return out


def link_angles(Q: np.ndarray, params: KinematicParams, direction: np.ndarray | None = None) -> np.ndarray:
    """Link-side angles (N, 6) for motor-side joints Q (N, 6) (joint zeros already added):
    ``Q' + c tau(Q')`` with ``Q' = Q - b d`` (backlash behind each joint's last motion direction d)."""
    Qa = backlash_angles(Q, params, direction)
    if not params.has_compliance:
        return Qa
    out: np.ndarray = Qa + params.compliance_rad_per_nm * gravity_torques(Qa, params.payload_kg)
    return out


def fk_batch_params(Q: np.ndarray, params: KinematicParams, frame: str = "flange",
                    direction: np.ndarray | None = None) -> np.ndarray:
    """``T_base_frame`` (N, 4, 4) of the richer chain for motor-side joints Q (N, 6) (joint zeros added);
    ``direction`` (N, 6): each joint's last motion direction, for the backlash (None: left out)."""
    return chain_fk(link_angles(Q, params, direction), params.origins(), params.axes(), frame)


def links_params(Q: np.ndarray, params: KinematicParams, direction: np.ndarray | None = None) -> np.ndarray:
    """Link transforms (N, 7, 4, 4) of the richer chain for motor-side joints Q (N, 6)."""
    return chain_links(link_angles(Q, params, direction), params.origins(), params.axes())


__all__ = ["BACKLASH_SLICE", "COMPLIANCE_SLICE", "DEFAULT_PAYLOAD_KG", "LINK_MASSES", "N_PARAMS", "ORIGIN_SLICE",
           "PARAM_NAMES", "SAG_JOINTS", "TILT_SLICE", "KinematicParams", "backlash_angles", "chain_fk", "chain_links",
           "fk_batch_params", "gravity_torques", "link_angles", "links_params", "tilted_axes"]
