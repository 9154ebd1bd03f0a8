"""Clearance checks for one arm's planned configurations and for the joint-space paths between them.

Planning works in the arm's commanded (SDK) angles ``q``; the collision model is evaluated at
``q + dq`` with the calibration's joint-zero offsets, its base pose and its camera mount (eq. 1's
model), so a calibrated rig plans with its calibrated geometry and an uncalibrated one with the
nominal geometry (the margins absorb the difference).

Checked for a configuration (each failure has a reason code, in this order):

- ``joint_limits``: every joint at least ``joint_limit_rad`` inside the Z1 limits (commanded and
  corrected angles both);
- ``table``: arm and camera at least ``table_m`` above the table top (the base stands on it);
- ``self``: non-adjacent links and the camera at least ``self_m`` apart;
- ``parked_arm``: at least ``arm_arm_m`` from the other arm, which stays parked;
- ``envelope``: at least ``envelope_m`` from the obstacle (the object envelope, or while searching
  the whole placement workspace).

A joint-space move of the Z1 (``MoveJ``, and the twin's synchronised quintic) follows the straight
line between its end configurations, so :meth:`ArmCollisionModel.check_path` samples that line at
most ``max_step_rad`` apart per joint. Each sample first gets cheap lower bounds (every shape's
bounding capsule against the table plane, the obstacle and the parked arm); the exact distance
queries of :mod:`darp.kinematics.collision` run only where a bound falls below its margin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import NDArray

from darp.backend import RigBackend, RigFault
from darp.errors import AcquisitionError, DarpError
from darp.formats.calibration import Calibration
from darp.kinematics import collision, z1
from darp.kinematics.collision import ADJACENT_LINKS, ALLOWED_PAIRS, Primitive, PrimitiveSet
from darp.kinematics.collision_shapes import _bounding_segment, concatenate, segment_distances
from darp.kinematics.rig import Rig

Array = NDArray[np.float64]

REASONS = ("joint_limits", "table", "self", "parked_arm", "envelope")
_BOUND_SLACK_M = 1e-4  # lower bounds within this of a margin are decided by the exact query


@dataclass(frozen=True)
class ClearanceMargins:
    """Distances (m) and the joint-limit margin (rad) planning keeps."""

    table_m: float = 0.03
    self_m: float = 0.01
    arm_arm_m: float = 0.05
    envelope_m: float = 0.04
    joint_limit_rad: float = 0.05

    def __post_init__(self) -> None:
        for name in ("table_m", "self_m", "arm_arm_m", "envelope_m", "joint_limit_rad"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise AcquisitionError(f"clearance margin {name} must be a finite value >= 0, got {value}")

    @classmethod
    def from_rig(cls, rig: Rig, envelope_m: float = 0.04, self_m: float = 0.01) -> ClearanceMargins:
        """The rig file's margins plus the object-envelope and self-collision margins."""
        m = rig.margins
        return cls(table_m=m.table_clearance_m, self_m=self_m, arm_arm_m=m.arm_arm_margin_m,
                   envelope_m=envelope_m, joint_limit_rad=m.joint_limit_margin_rad)


@dataclass(frozen=True)
class Verdict:
    """Outcome of a check: ``reason`` is one of :data:`REASONS` (or empty when ``ok``)."""

    ok: bool
    reason: str = ""
    detail: str = ""
    distances_m: dict[str, float] = field(default_factory=dict)
    path_fraction: float | None = None  # where along a path the check failed (0..1)


def envelope_obstacle(centre_m: Array, radius_m: float, height_m: float, table_z_m: float) -> Primitive:
    """The object envelope as an obstacle: a vertical cylinder standing on the table."""
    return collision.envelope_primitive(np.asarray(centre_m, dtype=float), float(radius_m), float(height_m),
                                        table_height_z=table_z_m)


def workspace_obstacle(rig: Rig, grow_m: float = 0.0) -> Primitive:
    """The placement workspace box (grown by ``grow_m`` sideways): while the object is unknown it
    may stand anywhere in it, so the search keeps the arm out of the whole box."""
    ws = rig.workspace
    lo = np.array([ws.x_range_m[0] - grow_m, ws.y_range_m[0] - grow_m, rig.table.height_m])
    hi = np.array([ws.x_range_m[1] + grow_m, ws.y_range_m[1] + grow_m, rig.table.height_m + ws.z_range_m[1]])
    T = np.eye(4)
    T[:3, 3] = 0.5 * (lo + hi)
    return Primitive.box(T, hi - lo, "workspace", "object")


def _self_pairs(names: tuple[str, ...], links: tuple[str, ...]) -> tuple[Array, Array]:
    """Index pairs checked for self-collision (the rule of :func:`collision.self_collision_distance`)."""
    skip = {frozenset(p) for p in ALLOWED_PAIRS}
    pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))
             if links[i] != links[j] and frozenset((links[i], links[j])) not in ADJACENT_LINKS
             and frozenset((names[i], names[j])) not in skip]
    arr = np.array(pairs, dtype=int).reshape(-1, 2)
    return arr[:, 0], arr[:, 1]


def _capsules(s: PrimitiveSet) -> tuple[Array, Array, Array]:
    (a, b), r = _bounding_segment(s.R, s.centre, s.half, s.kinds)
    return a, b, r


class ArmCollisionModel:
    """One arm's planning world: table, its own links and camera, the other arm parked, an obstacle."""

    def __init__(self, rig: Rig, arm_id: str, *, calibration: Calibration | None = None,
                 other_q_rad: Array | None = None, obstacle: Primitive | None = None,
                 margins: ClearanceMargins | None = None) -> None:
        """``other_q_rad``: the other arm's commanded joints (default: its park configuration)."""
        self.rig = rig
        self.arm_id = arm_id
        rig.arm(arm_id)
        self.calibration = calibration
        self.margins = margins if margins is not None else ClearanceMargins.from_rig(rig)
        self.T_world_base, self.T_wrist_cam, self.dq = rig.extrinsics(arm_id, calibration)
        self.mount = rig.camera_mount(arm_id, calibration)
        others = [a for a in rig.arm_ids if a != arm_id]
        self.other_id = others[0]
        other_q = rig.arms[self.other_id].park_q_rad if other_q_rad is None else np.asarray(other_q_rad, float)
        self.other_q_rad = np.array(other_q, dtype=float)
        self.other_prims = rig.arm_primitives(self.other_id, self.other_q_rad, calibration=calibration)
        self.obstacle = obstacle
        self.table_z = rig.table.height_m
        lower, upper = z1.joint_limits("urdf")
        self.lower = lower + self.margins.joint_limit_rad
        self.upper = upper - self.margins.joint_limit_rad
        probe = self.primitives(rig.arms[arm_id].park_q_rad)
        self._moving = np.array([link != "link00" for link in probe.links])  # the base stands on the table
        self._self_i, self._self_j = _self_pairs(probe.names, probe.links)
        self._other_caps = _capsules(self.other_prims)
        self._obstacle_cap = None if obstacle is None else _capsules(PrimitiveSet.from_list([obstacle]))

    def with_obstacle(self, obstacle: Primitive | None) -> ArmCollisionModel:
        """The same model with another obstacle."""
        return ArmCollisionModel(self.rig, self.arm_id, calibration=self.calibration, other_q_rad=self.other_q_rad,
                                 obstacle=obstacle, margins=self.margins)

    # -- geometry ---------------------------------------------------------------------------------
    def model_q(self, q_rad: Array) -> Array:
        """Corrected joint angles (q + dq) that the kinematic model uses."""
        return cast(Array, np.asarray(q_rad, dtype=float) + self.dq)

    def primitives(self, q_rad: Array) -> PrimitiveSet:
        """World-frame shapes of the arm and its camera at commanded joints ``q_rad``."""
        return collision.arm_primitives(self.model_q(q_rad), self.T_world_base, self.mount)

    def T_world_cam(self, q_rad: Array) -> Array:
        """Eq. 1 at commanded joints ``q_rad``."""
        return cast(Array, self.T_world_base @ z1.fk(self.model_q(q_rad), self.rig.wrist_frame) @ self.T_wrist_cam)

    # -- configurations ---------------------------------------------------------------------------
    def joint_limit_verdict(self, q_rad: Array) -> Verdict:
        """Commanded and corrected joints inside the limits less the margin."""
        q = np.asarray(q_rad, dtype=float)
        for what, arr in (("commanded", q), ("corrected", self.model_q(q))):
            bad = np.flatnonzero((arr < self.lower) | (arr > self.upper))
            if bad.size:
                j = int(bad[0])
                return Verdict(False, "joint_limits",
                               f"{what} joint{j + 1} = {arr[j]:.3f} rad is within "
                               f"{self.margins.joint_limit_rad:.3f} rad of its limit or beyond")
        return Verdict(True)

    def check_configuration(self, q_rad: Array) -> Verdict:
        """Exact clearances at one configuration (reasons in the order of :data:`REASONS`)."""
        limits = self.joint_limit_verdict(q_rad)
        if not limits.ok:
            return limits
        prims = self.primitives(q_rad)
        q_model = self.model_q(q_rad)
        d: dict[str, float] = {}
        table = collision.arm_table_distance(q_model, self.T_world_base, self.table_z, self.mount)
        d["table"] = table.distance_m
        if table.distance_m < self.margins.table_m:
            return Verdict(False, "table", f"{table.name_a} {table.distance_m * 1000:.0f} mm above the table "
                           f"(margin {self.margins.table_m * 1000:.0f} mm)", d)
        own = collision.self_collision_distance(q_model, self.mount)
        d["self"] = own.distance_m
        if own.distance_m < self.margins.self_m:
            return Verdict(False, "self", f"{own.name_a} and {own.name_b} {own.distance_m * 1000:.0f} mm apart", d)
        other = collision.min_distance(prims, self.other_prims)
        d["parked_arm"] = other.distance_m
        if other.distance_m < self.margins.arm_arm_m:
            return Verdict(False, "parked_arm", f"{other.name_a} {other.distance_m * 1000:.0f} mm from "
                           f"{self.other_id}'s {other.name_b} (margin {self.margins.arm_arm_m * 1000:.0f} mm)", d)
        if self.obstacle is not None:
            env = collision.min_distance(prims, [self.obstacle])
            d["envelope"] = env.distance_m
            if env.distance_m < self.margins.envelope_m:
                return Verdict(False, "envelope", f"{env.name_a} {env.distance_m * 1000:.0f} mm from the "
                               f"{self.obstacle.name} (margin {self.margins.envelope_m * 1000:.0f} mm)", d)
        return Verdict(True, distances_m=d)

    # -- paths ------------------------------------------------------------------------------------
    def path_samples(self, q_from: Array, q_to: Array, max_step_rad: float = 0.03) -> Array:
        """Configurations (N, 6) on the straight joint-space line, end included, start excluded."""
        q0, q1 = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
        n = max(1, int(np.ceil(float(np.max(np.abs(q1 - q0))) / max_step_rad)))
        s = np.arange(1, n + 1) / n
        return cast(Array, q0 + s[:, None] * (q1 - q0))

    def check_path(self, q_from: Array, q_to: Array, max_step_rad: float = 0.03) -> Verdict:
        """Clearances along the straight joint-space move ``q_from`` -> ``q_to`` (start not rechecked)."""
        samples = self.path_samples(q_from, q_to, max_step_rad)
        for k, q in enumerate(samples):
            limits = self.joint_limit_verdict(q)
            if not limits.ok:
                return Verdict(False, limits.reason, limits.detail, path_fraction=(k + 1) / len(samples))
        sets = [self.primitives(q) for q in samples]
        n_prim = len(sets[0])
        allp = concatenate(sets)
        a, b, r = _capsules(allp)
        m = self.margins
        need = np.zeros(len(samples), dtype=bool)
        # Table: exact and cheap for every shape at once.
        low = allp.lowest_z().reshape(len(samples), n_prim)
        table = np.min(np.where(self._moving[None], low, np.inf), axis=1) - self.table_z
        bad_table = np.flatnonzero(table < m.table_m)
        first_bad = len(samples)
        if bad_table.size:
            first_bad = int(bad_table[0])
        # Parked arm, obstacle, self: bounding capsules give lower bounds; exact queries where needed.
        oa, ob, orad = self._other_caps
        d_other, _, _ = segment_distances(a[:, None], b[:, None], oa[None], ob[None])
        lb_other = np.min((d_other - r[:, None] - orad[None]).reshape(len(samples), -1), axis=1)
        need |= lb_other < m.arm_arm_m + _BOUND_SLACK_M
        if self._obstacle_cap is not None:
            ea, eb, er = self._obstacle_cap
            d_env, _, _ = segment_distances(a, b, ea[0][None], eb[0][None])
            lb_env = np.min((d_env - r - er[0]).reshape(len(samples), n_prim), axis=1)
            need |= lb_env < m.envelope_m + _BOUND_SLACK_M
        A = a.reshape(len(samples), n_prim, 3)
        B = b.reshape(len(samples), n_prim, 3)
        R = r.reshape(len(samples), n_prim)
        i, j = self._self_i, self._self_j
        d_self, _, _ = segment_distances(A[:, i], B[:, i], A[:, j], B[:, j])
        lb_self = np.min(d_self - R[:, i] - R[:, j], axis=1)
        need |= lb_self < m.self_m + _BOUND_SLACK_M
        for k_need in np.flatnonzero(need[:first_bad]):
            verdict = self.check_configuration(samples[k_need])
            if not verdict.ok:
                return Verdict(False, verdict.reason, verdict.detail, verdict.distances_m,
                               path_fraction=(k_need + 1) / len(samples))
        if bad_table.size:
            k = first_bad
            return Verdict(False, "table", f"path dips to {table[k] * 1000:.0f} mm above the table "
                           f"(margin {m.table_m * 1000:.0f} mm)", {"table": float(table[k])},
                           path_fraction=(k + 1) / len(samples))
        return Verdict(True, distances_m={"table": float(np.min(table))})


class UnsafeMoveError(AcquisitionError):
    """A commanded move would break a clearance (the arm was not moved)."""

    def __init__(self, message: str, verdict: Verdict) -> None:
        super().__init__(message)
        self.verdict = verdict


class MotionFault(AcquisitionError):
    """The rig reported a fault (a contact on the twin, a controller fault on hardware): every arm was told
    to stop and no further planned move may be commanded."""

    def __init__(self, fault: RigFault) -> None:
        super().__init__(fault.message)
        self.fault = fault


def stop_all_arms(backend: RigBackend) -> None:
    """Tell every arm to stop at once; an arm that cannot be told (its controller is down) is skipped."""
    for arm in backend.arms.values():
        try:
            arm.stop()
        except Exception:  # a faulted controller refuses commands; the others must still stop
            continue


def wait_at_rest(backend: RigBackend, arm_id: str, timeout_s: float, poll_s: float) -> bool:
    """Sleep until ``arm_id`` reports no motion (ignoring the latched fault); False on timeout or error."""
    arm, clock = backend.arms[arm_id], backend.clock
    deadline = clock.now() + timeout_s
    try:
        while arm.is_moving():
            if clock.now() >= deadline:
                return False
            clock.sleep(poll_s)
    except Exception:  # a faulted controller: its arm is left where it is
        return False
    return True


def park_after_fault(backend: RigBackend, arm_id: str, model: Callable[[], ArmCollisionModel], park_q_rad: Array,
                     settings: MotionSettings, events: Callable[..., None]) -> str:
    """After a fault stopped the rig: park ``arm_id`` (not involved in the fault) if it is at rest and its path to
    ``park_q_rad`` is clear in ``model()``'s world; says in words what happened to it."""
    if not wait_at_rest(backend, arm_id, settings.timeout_s, settings.poll_s):
        return f"{arm_id} left where it stopped (not at rest)"
    arm = backend.arms[arm_id]
    try:
        q_now = np.asarray(arm.read_state().q_rad, dtype=float)
        if np.max(np.abs(q_now - park_q_rad)) < settings.start_tolerance_rad:
            return f"{arm_id} parked"
        verdict = model().check_path(q_now, park_q_rad, settings.path_step_rad)
        if not verdict.ok:
            return f"{arm_id} left where it stopped (its path to park is not clear: {verdict.reason})"
        arm.move_to(park_q_rad, settings.speed_rad_s)
        wait_at_rest(backend, arm_id, settings.timeout_s, settings.poll_s)
        q_end = np.asarray(arm.read_state().q_rad, dtype=float)
    except Exception as err:  # the backend refused: leave the arm for the operator
        return f"{arm_id} left where it stopped ({type(err).__name__}: {err})"
    if np.max(np.abs(q_end - park_q_rad)) < settings.start_tolerance_rad:
        events("parked", arm=arm_id, after_fault=True)
        return f"{arm_id} parked"
    return f"{arm_id} stopped short of park (stopped again on the way)"


def _raise_on_fault(backend: RigBackend) -> None:
    fault = backend.fault()
    if fault is not None:
        stop_all_arms(backend)
        raise MotionFault(fault)


@dataclass(frozen=True)
class MotionSettings:
    """How moves are executed: speed, settling, timeouts, path sampling."""

    speed_rad_s: float | None = None  # None: the backend's default joint speed
    settle_s: float = 0.5  # pause after every move (the paper's settling interval)
    timeout_s: float = 30.0
    poll_s: float = 0.02
    path_step_rad: float = 0.03
    start_tolerance_rad: float = 0.02  # the start of a path is the arm's state if within this of the plan


def checked_move(backend: RigBackend, model: ArmCollisionModel, q_target_rad: Array,
                 settings: MotionSettings | None = None, *, settle: bool = True) -> float:
    """Check the straight joint path from the arm's present state to ``q_target_rad``, then move there
    (non-blocking command, waiting on the rig clock) and settle. Returns the time the move took (s).

    Raises :class:`UnsafeMoveError` (nothing moved) when the path fails a check,
    :class:`MotionFault` when the rig reports a fault before or during the move (every arm is told to
    stop at once; an error the moving arm raises while moving counts as its fault) and
    :class:`AcquisitionError` when the arm does not arrive in time.
    """
    s = settings if settings is not None else MotionSettings()
    _raise_on_fault(backend)
    arm = backend.arms[model.arm_id]
    q_now = np.asarray(arm.read_state().q_rad, dtype=float)
    q_target = np.asarray(q_target_rad, dtype=float)
    verdict = model.check_path(q_now, q_target, s.path_step_rad)
    if not verdict.ok:
        raise UnsafeMoveError(f"{model.arm_id}: move refused ({verdict.reason}): {verdict.detail}", verdict)
    t0 = backend.clock.now()
    try:
        arm.move_to(q_target, s.speed_rad_s)
        arrived = backend.wait_until_still(model.arm_id, s.timeout_s, s.poll_s)
    except DarpError as err:  # the arm itself failed while moving: a fault of that arm
        stop_all_arms(backend)
        raise MotionFault(backend.fault() or RigFault(f"{model.arm_id}: {err}", (model.arm_id,))) from err
    _raise_on_fault(backend)
    if not arrived:
        arm.stop()
        raise AcquisitionError(f"{model.arm_id} did not reach its target within {s.timeout_s:.0f} s")
    took = backend.clock.now() - t0
    if settle and s.settle_s > 0:
        backend.clock.sleep(s.settle_s)
        _raise_on_fault(backend)
    return took


__all__ = ["REASONS", "ArmCollisionModel", "ClearanceMargins", "MotionFault", "MotionSettings", "UnsafeMoveError",
           "Verdict", "checked_move", "envelope_obstacle", "park_after_fault", "stop_all_arms", "wait_at_rest",
           "workspace_obstacle"]
