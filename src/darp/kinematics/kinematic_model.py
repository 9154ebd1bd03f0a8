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
    + [f"joint{j + 1}.compliance" for j in SAG_JOINTS])
N_PARAMS = len(PARAM_NAMES)  # 39
ORIGIN_SLICE = slice(0, 18)
TILT_SLICE = slice(18, 36)
COMPLIANCE_SLICE = slice(36, 39)


@dataclass(eq=False)
class KinematicParams:
    """Kinematic parameter errors of one arm (all zero: the nominal Z1)."""

    origin_m: np.ndarray = field(default_factory=lambda: np.zeros((6, 3)))
    axis_tilt_rad: np.ndarray = field(default_factory=lambda: np.zeros((6, 3)))
    compliance_rad_per_nm: np.ndarray = field(default_factory=lambda: np.zeros(6))
    payload_kg: float = DEFAULT_PAYLOAD_KG

    def copy(self) -> KinematicParams:
        return KinematicParams(self.origin_m.copy(), self.axis_tilt_rad.copy(), self.compliance_rad_per_nm.copy(),
                               self.payload_kg)

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
                               self.compliance_rad_per_nm[list(SAG_JOINTS)]])

    @classmethod
    def from_vector(cls, v: np.ndarray, payload_kg: float = DEFAULT_PAYLOAD_KG) -> KinematicParams:
        v = np.asarray(v, float)
        c = np.zeros(6)
        c[list(SAG_JOINTS)] = v[COMPLIANCE_SLICE]
        return cls(v[ORIGIN_SLICE].reshape(6, 3).copy(), v[TILT_SLICE].reshape(6, 3).copy(), c, payload_kg)

    def to_dict(self) -> dict[str, Any]:
        return {"joint_origin_offsets_m": self.origin_m.tolist(), "joint_axis_tilts_rad": self.axis_tilt_rad.tolist(),
                "compliance_rad_per_nm": self.compliance_rad_per_nm.tolist(), "payload_kg": self.payload_kg}

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "kinematics") -> KinematicParams:
        try:
            origin = np.asarray(d["joint_origin_offsets_m"], float)
            tilt = np.asarray(d["joint_axis_tilts_rad"], float)
            comp = np.asarray(d.get("compliance_rad_per_nm", np.zeros(6)), float)
            payload = float(d.get("payload_kg", DEFAULT_PAYLOAD_KG))
        except (KeyError, TypeError, ValueError) as err:
            raise FormatError(f"{where}: expected joint_origin_offsets_m (6x3), joint_axis_tilts_rad (6x3), "
                              f"compliance_rad_per_nm (6) ({err})") from None
        if origin.shape != (6, 3) or tilt.shape != (6, 3) or comp.shape != (6,):
            raise FormatError(f"{where}: shapes must be 6x3, 6x3 and 6")
        if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(tilt)) and np.all(np.isfinite(comp))):
            raise FormatError(f"{where}: non-finite values")
        if np.max(np.abs(origin)) > 0.01 or np.max(np.abs(tilt)) > np.radians(2.0) or np.max(np.abs(comp)) > 0.05:
            raise FormatError(f"{where}: parameters beyond plausible ranges (origin 10 mm, tilt 2 deg, "
                              "compliance 0.05 rad/N m)")
        return cls(origin, tilt, comp, payload)


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


def link_angles(Q: np.ndarray, params: KinematicParams) -> np.ndarray:
    """Link-side angles (N, 6) for motor-side joints Q (N, 6) (joint zeros already added): ``Q + c tau(Q)``."""
    Qa = np.atleast_2d(np.asarray(Q, dtype=float))
    if not params.has_compliance:
        return Qa
    out: np.ndarray = Qa + params.compliance_rad_per_nm * gravity_torques(Qa, params.payload_kg)
    return out


def fk_batch_params(Q: np.ndarray, params: KinematicParams, frame: str = "flange") -> np.ndarray:
    """``T_base_frame`` (N, 4, 4) of the richer chain for motor-side joints Q (N, 6) (joint zeros added)."""
    return chain_fk(link_angles(Q, params), params.origins(), params.axes(), frame)


def links_params(Q: np.ndarray, params: KinematicParams) -> np.ndarray:
    """Link transforms (N, 7, 4, 4) of the richer chain for motor-side joints Q (N, 6)."""
    return chain_links(link_angles(Q, params), params.origins(), params.axes())


__all__ = ["COMPLIANCE_SLICE", "DEFAULT_PAYLOAD_KG", "LINK_MASSES", "N_PARAMS", "ORIGIN_SLICE", "PARAM_NAMES",
           "SAG_JOINTS", "TILT_SLICE", "KinematicParams", "chain_fk", "chain_links", "fk_batch_params",
           "gravity_torques", "link_angles", "links_params", "tilted_axes"]
