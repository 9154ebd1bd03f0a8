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

import functools
from dataclasses import dataclass

import numpy as np

from darp.kinematics import z1
from darp.kinematics.kinematic_model import LINK_MASSES, chain_fk, gravity_torques, tilted_axes
from darp.twin.settings import ArmErrorSettings

REACH_M = 0.5  # typical flange distance from joint 2 in a survey; converts repeatability to joint angles


TYPICAL_BAND = 0.1
"""How far (relative) a drawn arm's unabsorbable geometric error may be from its expected size."""
MAX_REDRAWS = 200
TYPICAL_Q_RANGE = (np.array([-0.6, 1.4, -2.6, 0.3, -0.75, -1.6]), np.array([0.6, 2.5, -1.2, 1.4, 0.75, 1.6]))
"""Box of joint angles (rad) of the arm's typical views of the table (5-95 % of calibration captures)."""
_PROBE_FLANGE = np.array([[0.4, 0.0, 0.0], [0.4, 0.1, 0.0], [0.4, -0.1, 0.0], [0.4, 0.0, 0.1], [0.4, 0.0, -0.1]])
"""Points in the flange frame (metres) where the error is measured: a board-sized patch 0.4 m ahead."""


@functools.lru_cache(maxsize=1)
def _unabsorbed_operator() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear map from geometric errors (origins (18,), tilts (18,)) to the probe points' errors (P,) that are
    left after the best joint-zero, base and flange-side (hand-eye) correction, over 48 typical views."""
    from darp.kinematics.transforms import make_transform, rotvec_to_rotation

    Q = np.random.default_rng(0).uniform(*TYPICAL_Q_RANGE, (48, 6))  # fixed: the same for every seed
    origins0 = np.asarray(z1.JOINT_ORIGINS_M, dtype=float)

    def points(p: np.ndarray) -> np.ndarray:
        origins = origins0 + p[:18].reshape(6, 3)
        F = chain_fk(Q + p[42:48], origins, tilted_axes(p[18:36].reshape(6, 3)), "flange")
        base = make_transform(rotvec_to_rotation(p[36:39]), p[39:42])
        tool = make_transform(rotvec_to_rotation(p[48:51]), p[51:54])
        F = np.einsum("ij,njk,kl->nil", base, F, tool)
        out: np.ndarray = (np.einsum("nij,pj->npi", F[:, :3, :3], _PROBE_FLANGE) + F[:, None, :3, 3]).ravel()
        return out

    p0 = np.zeros(54)
    f0 = points(p0)
    eps = 1e-6
    J = np.empty((f0.size, 54))
    for k in range(54):
        dp = p0.copy()
        dp[k] = eps
        J[:, k] = (points(dp) - f0) / eps
    absorb = J[:, 36:]
    M = J[:, :36] - absorb @ np.linalg.lstsq(absorb, J[:, :36], rcond=None)[0]
    gram = M.T @ M / (f0.size // 3)  # mean squared point error per unit error
    nominal = np.asarray(z1.JOINT_AXES, dtype=float)
    return M, gram, nominal


def unabsorbed_m(origin_m: np.ndarray, axis_tilt_rad: np.ndarray) -> float:
    """RMS point error (m) at typical views that joint zeros, base and hand-eye cannot absorb (linearised)."""
    M, _, _ = _unabsorbed_operator()
    r = M @ np.concatenate([np.ravel(origin_m), np.ravel(axis_tilt_rad)])
    return float(np.sqrt(np.mean(r.reshape(-1, 3) ** 2) * 3))


def expected_unabsorbed_m(origin_length_m: float, tilt_angle_rad: float) -> float:
    """:func:`unabsorbed_m`'s root mean square over random directions of the given fixed sizes."""
    _, gram, nominal = _unabsorbed_operator()
    total = 0.0
    for j in range(6):
        o, t = slice(3 * j, 3 * j + 3), slice(18 + 3 * j, 18 + 3 * j + 3)
        total += origin_length_m**2 / 3.0 * float(np.trace(gram[o, o]))
        perp = np.eye(3) - np.outer(nominal[j], nominal[j])
        total += tilt_angle_rad**2 / 2.0 * float(np.trace(gram[t, t] @ perp))
    return float(np.sqrt(total))


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
        # Fixed size, random direction: every arm gets errors of the stated size (a Gaussian draw of 36
        # components made the unabsorbable part, and so the hand-eye figure, vary by +-30 % between seeds).
        # Origins: length sqrt(3) x the per-axis std (the same mean square as N(0, std) per axis).
        # Tilts: perpendicular to the nominal axis (a rotation about the axis itself leaves the axis as it
        # is), angle sqrt(2) x the std (the mean square of the two perpendicular Gaussian components).
        # The directions are drawn again (same generator) until the part no calibration of darp's model can
        # absorb is within TYPICAL_BAND of its expected size: a typical unit, neither a lucky nor an
        # unlucky one (at most MAX_REDRAWS tries, then the closest).
        length = np.sqrt(3.0) * settings.link_origin_std_mm * 1e-3
        angle = np.sqrt(2.0) * np.deg2rad(settings.axis_tilt_std_deg)
        nominal = np.asarray(z1.JOINT_AXES, dtype=float)
        expected = expected_unabsorbed_m(length, angle)
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        for _ in range(MAX_REDRAWS):
            origin = _fixed_length(rng.normal(0.0, 1.0, (6, 3)), length)
            raw = rng.normal(0.0, 1.0, (6, 3))
            raw -= np.sum(raw * nominal, axis=1, keepdims=True) * nominal
            tilt = _fixed_length(raw, angle)
            miss = abs(unabsorbed_m(origin, tilt) / expected - 1.0) if expected > 0 else 0.0
            if best is None or miss < best[0]:
                best = (miss, origin, tilt)
            if miss <= TYPICAL_BAND:
                break
        assert best is not None
        return cls(best[1], best[2])

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
