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
from functools import lru_cache

import numpy as np

from darp.kinematics import z1
from darp.kinematics.kinematic_model import LINK_MASSES, chain_fk, gravity_torques, tilted_axes
from darp.kinematics.rig import load_rig
from darp.kinematics.transforms import make_transform, rotvec_to_rotation
from darp.twin.settings import ArmErrorSettings

REACH_M = 0.5  # typical flange distance from joint 2 in a survey; converts repeatability to joint angles

# Typical calibration configurations (rad): every second pose of `darp calib plan` at seeds 1000 and 1001
# (both arms, the default board and rig; 60 rows). The unabsorbable size of a kinematic draw is measured here
# (:func:`unabsorbable_mm`); it predicts the size at the capture plans of seeds 0-8 with correlation 0.91.
CALIBRATION_Q_RAD = np.array([
    [-0.421, 1.261, -1.104, 0.619, 0.328, -1.143],
    [-0.164, 1.975, -1.476, 0.384, 0.108, -0.780],
    [-0.468, 2.094, -1.567, 0.504, 0.586, -1.415],
    [-0.773, 1.968, -1.879, 1.227, 0.787, -2.006],
    [-0.036, 1.743, -1.228, 0.270, 0.181, 0.989],
    [0.003, 1.722, -0.974, -0.048, 0.051, 1.329],
    [0.356, 1.703, -1.585, 0.795, -0.375, 0.826],
    [0.715, 1.821, -1.592, 1.038, -0.773, 0.753],
    [0.317, 1.928, -2.016, 1.113, -0.508, -0.801],
    [-0.065, 1.920, -1.979, 1.074, -0.057, -1.098],
    [-0.252, 2.220, -2.047, 0.897, 0.427, 0.493],
    [0.018, 2.119, -2.019, 0.993, 0.080, 0.747],
    [0.364, 2.424, -2.565, 1.389, -0.638, -0.523],
    [-0.200, 2.401, -2.523, 1.287, 0.258, -1.182],
    [-0.496, 1.678, -1.689, 0.951, 0.638, 1.344],
    [-0.165, 1.453, -1.242, 0.527, 0.110, -1.060],
    [0.095, 1.560, -1.100, 0.309, -0.070, 0.418],
    [0.566, 1.530, -1.649, 1.066, -0.487, 1.803],
    [0.460, 1.646, -1.587, 0.954, -0.475, -0.479],
    [0.226, 2.075, -2.096, 1.081, -0.345, -0.168],
    [0.615, 2.432, -2.518, 1.412, -0.751, 1.185],
    [-0.276, 2.258, -2.495, 1.434, 0.467, 0.756],
    [-0.424, 2.279, -2.164, 1.172, 0.829, 1.109],
    [-0.352, 2.245, -2.420, 1.323, 0.414, -0.643],
    [-0.550, 2.417, -2.352, 1.353, 0.763, -1.010],
    [-0.169, 1.951, -2.139, 1.210, 0.104, -1.387],
    [-0.603, 1.740, -1.289, 0.602, 0.734, -0.846],
    [-0.016, 1.964, -1.143, -0.066, 0.057, -0.656],
    [0.475, 2.154, -1.839, 0.827, -0.606, 1.516],
    [0.234, 2.524, -2.788, 1.396, -0.482, -0.824],
    [0.164, 1.368, -1.283, 0.681, -0.181, -0.175],
    [0.008, 1.901, -1.379, 0.366, 0.039, -0.019],
    [-0.401, 2.082, -1.868, 0.846, 0.545, -0.101],
    [-0.757, 2.199, -2.235, 1.374, 0.825, -1.504],
    [-0.357, 2.267, -2.415, 1.261, 0.439, -0.887],
    [0.159, 2.110, -2.213, 1.188, -0.337, -1.530],
    [0.281, 1.996, -1.832, 0.890, -0.423, -0.913],
    [0.497, 2.287, -2.149, 1.253, -0.769, 0.245],
    [0.475, 2.254, -2.023, 0.858, -0.625, 1.673],
    [-0.030, 1.749, -2.155, 1.360, 0.026, 0.376],
    [0.129, 1.793, -1.352, 0.306, -0.061, 1.559],
    [0.058, 1.885, -0.957, -0.224, 0.024, 1.071],
    [0.540, 1.753, -1.209, 0.461, -0.678, 0.686],
    [-0.322, 2.083, -1.572, 0.336, 0.348, -1.462],
    [-0.229, 2.393, -2.481, 1.223, 0.543, 1.011],
    [-0.077, 1.259, -1.435, 0.987, 0.050, -0.592],
    [0.167, 1.807, -1.624, 0.799, -0.154, 0.820],
    [-0.155, 2.149, -1.729, 0.539, 0.268, -0.079],
    [-0.379, 2.154, -1.798, 0.655, 0.544, -1.166],
    [-0.488, 1.761, -1.387, 0.590, 0.653, 0.063],
    [0.015, 1.928, -1.258, 0.052, 0.174, 1.376],
    [0.531, 1.859, -1.680, 0.873, -0.647, -0.216],
    [0.441, 2.264, -2.081, 1.131, -0.693, 0.029],
    [0.540, 2.511, -2.477, 1.365, -0.701, 0.855],
    [0.054, 2.418, -2.791, 1.428, 0.007, 0.989],
    [-0.400, 2.310, -2.267, 1.207, 0.749, 1.416],
    [-0.044, 2.038, -2.431, 1.440, 0.028, -0.860],
    [-0.582, 1.577, -1.414, 0.776, 0.588, -1.726],
    [0.590, 1.829, -1.609, 0.730, -0.586, 1.737],
    [0.886, 1.955, -1.798, 1.256, -0.843, 1.311],
])
# Points in the camera frame whose positions the unabsorbable size measures (the board's distance, +-0.1 m).
_TEST_POINTS_CAM_M = np.array([[0.0, 0.0, 0.4], [0.1, 0.0, 0.4], [-0.1, 0.0, 0.4], [0.0, 0.1, 0.4], [0.0, -0.1, 0.4]])
MAX_DRAWS = 400  # direction draws tried for ``unabsorbed_mm``
UNABSORBED_TOLERANCE = 0.05  # accept a draw within 5 % of ``unabsorbed_mm``


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
        """Draw one arm's errors, or None when both magnitudes are zero.

        With ``settings.unabsorbed_mm`` > 0 the directions are drawn again (sizes unchanged) until the
        draw's unabsorbable size (:func:`unabsorbable_mm`) is within 5 % of it; after ``MAX_DRAWS`` the
        closest draw is kept. With 0 the first draw is used (as before the setting existed).
        """
        if settings.link_origin_std_mm <= 0 and settings.axis_tilt_std_deg <= 0:
            return None
        first = cls._draw_once(settings, rng)
        target = settings.unabsorbed_mm
        if target <= 0:
            return first
        best, best_gap = first, abs(unabsorbable_mm(first) - target)
        for _ in range(MAX_DRAWS - 1):
            if best_gap <= UNABSORBED_TOLERANCE * target:
                break
            candidate = cls._draw_once(settings, rng)
            gap = abs(unabsorbable_mm(candidate) - target)
            if gap < best_gap:
                best, best_gap = candidate, gap
        return best

    @classmethod
    def _draw_once(cls, settings: ArmErrorSettings, rng: np.random.Generator) -> KinematicErrors:
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


def _points(Q: np.ndarray, origins: np.ndarray, axes: np.ndarray, dq: np.ndarray,
            base: np.ndarray, hand_eye: np.ndarray, flange_cam: np.ndarray) -> np.ndarray:
    """Test points (N * P * 3,) in the base frame through a chain with small base / hand-eye corrections
    (rotation vector and translation, 6 each) and joint offsets ``dq``."""
    T = chain_fk(Q + dq, origins, axes, "flange")
    T = _small(base)[None] @ T @ _small(hand_eye)[None] @ flange_cam[None]
    P = np.einsum("nij,pj->npi", T[:, :3, :3], _TEST_POINTS_CAM_M) + T[:, None, :3, 3]
    out: np.ndarray = P.ravel()
    return out


def _small(v: np.ndarray) -> np.ndarray:
    return make_transform(rotvec_to_rotation(v[:3]), v[3:])


@lru_cache(maxsize=1)
def _unabsorbable_map() -> np.ndarray:
    """Linear map (N * P * 3, 36) from origin errors (6 x 3, m) and axis tilts (6 x 3, rad) to the part of
    the test points' displacement that joint offsets, a base and a hand-eye correction cannot absorb."""
    Q = CALIBRATION_Q_RAD
    rig = load_rig()  # the default rig's nominal camera mount (both arms mount it alike)
    flange_cam = np.asarray(rig.arms[sorted(rig.arms)[0]].T_wrist_cam, dtype=float)
    o0, a0 = np.asarray(z1.JOINT_ORIGINS_M, float), tilted_axes(np.zeros((6, 3)))
    zero6 = np.zeros(6)
    p0 = _points(Q, o0, a0, zero6, zero6, zero6, flange_cam)
    h = 1e-6
    err_cols, abs_cols = [], []
    for k in range(36):
        d = np.zeros(36)
        d[k] = h
        o, t = o0 + d[:18].reshape(6, 3), d[18:].reshape(6, 3)
        err_cols.append((_points(Q, o, tilted_axes(t), zero6, zero6, zero6, flange_cam) - p0) / h)
    for k in range(18):
        d = np.zeros(18)
        d[k] = h
        abs_cols.append((_points(Q, o0, a0, d[12:], d[:6], d[6:12], flange_cam) - p0) / h)
    J_err, A = np.stack(err_cols, 1), np.stack(abs_cols, 1)
    U, sv, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, sv > 1e-9 * sv[0]]
    out: np.ndarray = J_err - U @ (U.T @ J_err)
    return out


def unabsorbable_mm(errors: KinematicErrors) -> float:
    """The part of ``errors`` that darp's calibration model (joint offsets, base, hand-eye) cannot absorb at
    typical calibration configurations (:data:`CALIBRATION_Q_RAD`): median displacement (mm) of points 0.4 m
    in front of the camera after the best linearised fit of those 18 parameters."""
    r = _unabsorbable_map() @ np.concatenate([errors.origin_m.ravel(), errors.axis_tilt_rad.ravel()])
    return 1e3 * float(np.median(np.linalg.norm(r.reshape(-1, 3), axis=1)))


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


__all__ = ["CALIBRATION_Q_RAD", "LINK_MASSES", "KinematicErrors", "LinkDeflection", "fk_batch_with_errors",
           "gravity_torques", "unabsorbable_mm"]
