"""Arm errors a calibration cannot absorb: kinematic parameter errors, gravity sag, backlash, repeatability.

The twin's true arm differs from darp's Z1 model (:mod:`darp.kinematics.z1`) in two ways here, both
drawn from :class:`darp.twin.settings.ArmErrorSettings` and the settings' seed:

- **geometry** (:class:`KinematicErrors`, per arm, fixed): each joint's origin in its parent link is off
  by a small vector (link lengths and offsets) and each joint's axis is tilted by a small rotation, each of
  a fixed size in a random direction (a unit's errors are one draw of about the stated size). The
  true chain is ``T = prod_i Trans(o_i + do_i) Rot(a_i, q_i)``; :func:`fk_batch_with_errors` computes it
  and :class:`darp.twin.world.TwinWorld` builds the MuJoCo arm with the same origins and axes, so the
  rendered views and ``truth/`` agree.
- **link-side deflection** (:class:`LinkDeflection`, per move and configuration): the encoders sit on
  the motor side, so what the gearbox and links do after them is invisible to the joint log: sag of
  joints 2-4 under gravity (links plus the camera load, divided by the joint stiffness), backlash (half
  the dead band behind the direction the joint last moved) and repeatability (a small random arrival
  offset per move). :class:`darp.twin.arm_sim.SimArm` adds it to its true (link) angles.

With all magnitudes zero nothing here is used: the twin's files are byte-identical to an exact arm's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from darp.kinematics import z1
from darp.kinematics.kinematic_model import LINK_MASSES, chain_fk, gravity_torques, tilted_axes
from darp.twin.settings import ArmErrorSettings

REACH_M = 0.5  # typical flange distance from joint 2 in a survey; converts repeatability to joint angles


def _fixed_length(vectors: np.ndarray, length: float) -> np.ndarray:
    """Each row of ``vectors`` (N, 3) scaled to exactly ``length`` (its direction kept)."""
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    out: np.ndarray = vectors / np.maximum(norms, 1e-12) * length
    return out

@dataclass(frozen=True, eq=False)
class KinematicErrors:
    """Per-joint origin errors (6, 3) in metres and axis tilts (6, 3) as rotation vectors in radians."""

    origin_m: np.ndarray
    axis_tilt_rad: np.ndarray

    @classmethod
    def draw(cls, settings: ArmErrorSettings, rng: np.random.Generator) -> KinematicErrors | None:
        """Draw one arm's errors, or None when both magnitudes are zero."""
        if settings.link_origin_std_mm <= 0 and settings.axis_tilt_std_deg <= 0:
            return None
        # Fixed size, random direction: every arm gets errors of the stated size (a Gaussian draw of 18
        # components made the unabsorbable part, and so the hand-eye figure, vary by +-30 % between seeds).
        # Origins: length sqrt(3) x the per-axis std (the same mean square as N(0, std) per axis).
        origin = _fixed_length(rng.normal(0.0, 1.0, (6, 3)), np.sqrt(3.0) * settings.link_origin_std_mm * 1e-3)
        # Tilts: perpendicular to the nominal axis (a rotation about the axis itself leaves the axis as it
        # is), angle sqrt(2) x the std (the mean square of the two perpendicular Gaussian components).
        nominal = np.asarray(z1.JOINT_AXES, dtype=float)
        raw = rng.normal(0.0, 1.0, (6, 3))
        raw -= np.sum(raw * nominal, axis=1, keepdims=True) * nominal
        tilt = _fixed_length(raw, np.sqrt(2.0) * np.deg2rad(settings.axis_tilt_std_deg))
        return cls(origin, tilt)

    def origins(self) -> np.ndarray:
        """True joint origins (6, 3) in their parent link."""
        origins: np.ndarray = np.asarray(z1.JOINT_ORIGINS_M, dtype=float) + self.origin_m
        return origins

    def axes(self) -> np.ndarray:
        """True joint axes (6, 3), unit vectors in the child link (= parent at zero angle)."""
        return tilted_axes(self.axis_tilt_rad)


def fk_batch_with_errors(Q: np.ndarray, errors: KinematicErrors, frame: str = "flange") -> np.ndarray:
    """``T_base_frame`` (N, 4, 4) of the true chain (perturbed origins and axes) for joint rows Q (N, 6)
    (the chain of :func:`darp.kinematics.kinematic_model.chain_fk`, shared with calibration and processing)."""
    return chain_fk(Q, errors.origins(), errors.axes(), frame)


class LinkDeflection:
    """Link-side angle errors the encoders do not see: sag, backlash and per-move repeatability."""

    def __init__(self, settings: ArmErrorSettings, rng: np.random.Generator) -> None:
        self.settings = settings
        self._rng = rng
        self._direction = np.zeros(6)  # sign of each joint's last motion (0: not moved yet)
        self.compliance = (1.0 / settings.joint_stiffness_nm_per_rad
                           if settings.joint_stiffness_nm_per_rad > 0 else 0.0)

    @property
    def active(self) -> bool:
        s = self.settings
        return self.compliance > 0 or s.backlash_deg > 0 or s.repeatability_mm > 0

    def move_offset(self, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
        """The constant link offset (6,) of a new move: backlash behind its direction plus repeatability."""
        step = np.asarray(q_to, float) - np.asarray(q_from, float)
        moved = np.abs(step) > 1e-9
        self._direction = np.where(moved, np.sign(step), self._direction)
        offset: np.ndarray = -0.5 * np.deg2rad(self.settings.backlash_deg) * self._direction
        if self.settings.repeatability_mm > 0:
            # Per-joint std so that the flange's 3-sigma spread is about the stated repeatability.
            sigma = self.settings.repeatability_mm * 1e-3 / (3.0 * REACH_M)
            offset = offset + self._rng.normal(0.0, sigma, 6)
        return offset

    def sag(self, Q: np.ndarray) -> np.ndarray:
        """Gravity sag (N, 6) in radians at link angles Q (N, 6)."""
        if self.compliance <= 0:
            return np.zeros(np.atleast_2d(Q).shape)
        sag: np.ndarray = gravity_torques(Q, self.settings.payload_kg) * self.compliance
        return sag


__all__ = ["LINK_MASSES", "KinematicErrors", "LinkDeflection", "fk_batch_with_errors", "gravity_torques"]
