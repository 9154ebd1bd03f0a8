"""Adaptive viewpoints per arm: an orbit about the confirmed object centre, checked and ordered.

**Standoff.** The DARP release table gives the nominal camera standoff per object; every row fits

    standoff = max(0.30 m + r, 4.5 r)

within 0.05 cm (r = 4.11 cm -> 34.1 cm, 7.22 -> 37.2, 11.60 -> 52.2): a 30 cm working distance to the
envelope surface, and for large objects a distance at which the envelope's diameter spans about
25 deg of the image (2 * atan(1 / 4.5)), so the whole object stays in view.

**Orbit shape** (:func:`orbit_shape`). Rings of camera elevations above the horizontal, azimuths spread
over a span centred on the arm's side of the object (the horizontal direction from the object to the
arm's base). Larger objects get more rings and a broader, denser span; tall ones a low ring for the sides:

| radius | elevations (deg) | azimuth span (deg) | azimuths per ring |
|---|---|---|---|
| < 6 cm | 35, 60 | 100 | 5 |
| 6-9 cm | 25, 45, 65 | 120 | 6 |
| >= 9 cm | 20, 40, 60 | 140 | 7 |
| height > 2 r | + a 15 deg ring | | |

**Checks** per candidate, in order, each with a reason code: ``ik`` (no look-at solution: camera
optical axis through the centre at the standoff, roll free), ``joint_limits``, ``workspace`` (flange
within ``reach_limit_m`` of the shoulder, camera over the table and at least ``camera_min_height_m``
above it), ``min_depth`` (every envelope point at least ``min_depth_m`` in front of the camera: the
D4's minimum depth), ``table``, ``self``, ``parked_arm``, ``envelope`` (see
:mod:`darp.acquisition.motion_check`); then, along the ordered tour, ``joint_motion`` (a joint moves
more than ``max_joint_step_rad`` from the previous view) and ``path_<reason>`` (the joint-space move
from the previous view fails a clearance check). Rejected candidates are kept with their reason.

**Regeneration.** When fewer than ``min_views`` remain, the orbit is regenerated with relaxed
parameters (:data:`RELAXATIONS`: wider span with a lower ring, then a larger standoff, then a smaller
one with lower elevations, then the nominal rings 25 cm from the envelope's surface: a large object near
an arm's base puts the 4.5 r standoff's cameras behind that arm, out of its reach); every attempt is
recorded. The first attempt with enough views wins, else the one with most.

**Order** (:mod:`darp.acquisition.tour`). Views are ordered to shorten joint travel: greedy nearest
neighbour from the park configuration, then 2-opt, with the cost of a move being its largest joint change
(a synchronised joint move's duration grows with it); the tour starts and ends at park. Moves whose costs
differ by less than :data:`~darp.acquisition.tour.TIE_TOLERANCE_RAD` are ties, broken by the lower candidate
index: the orbit is symmetric about the arm's side, so mirror-image views are often equally far from park,
and the last bits of their costs (which change with the BLAS kernel) must not choose the tour's direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.motion_check import ArmCollisionModel
from darp.acquisition.tour import order_views, tour_cost
from darp.errors import AcquisitionError
from darp.formats.calibration import Calibration
from darp.formats.realsense.types import Intrinsics
from darp.kinematics import z1
from darp.kinematics.ik import solve_look_at
from darp.kinematics.rig import Rig

Array = NDArray[np.float64]

CANDIDATE_REASONS = ("ik", "joint_limits", "workspace", "min_depth", "table", "self", "parked_arm", "envelope",
                     "joint_motion")
ROLL_HINTS_DEG = (0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 135.0, -135.0, 180.0)
SHOULDER_BASE_M = np.array([0.0, 0.0, z1.JOINT_ORIGINS_M[0, 2] + z1.JOINT_ORIGINS_M[1, 2]])


def standoff_for_radius(radius_m: float) -> float:
    """Nominal camera-to-centre distance for an envelope radius (fits the DARP release table)."""
    if not (np.isfinite(radius_m) and radius_m > 0):
        raise AcquisitionError(f"envelope radius must be positive, got {radius_m}")
    return float(max(0.30 + radius_m, 4.5 * radius_m))


def min_depth_from_intrinsics(intrinsics: Intrinsics, baseline_m: float = 0.050, max_disparity_px: float = 126.0,
                              margin_m: float = 0.02) -> float:
    """The D4's minimum depth f * B / d_max for a depth stream, plus a margin (0.17 m at 640x480)."""
    return float(intrinsics.fx * baseline_m / max_disparity_px + margin_m)


def shoulder_offsets_m(rig: Rig, calibration: Calibration) -> dict[str, float]:
    """Per arm: how far (m, + up) the calibration's base pose puts the shoulder (the joint-2 axis on the base's
    vertical axis, whose height no joint changes) from where the rig file stands it on the table."""
    out = {}
    for arm_id in rig.arm_ids:
        nominal, _, _ = rig.extrinsics(arm_id)
        solved, _, _ = rig.extrinsics(arm_id, calibration)
        shoulder = np.r_[SHOULDER_BASE_M, 1.0]
        out[arm_id] = float((solved @ shoulder)[2] - (nominal @ shoulder)[2])
    return out


def calibration_table_problem(rig: Rig, calibration: Calibration, table_clearance_m: float) -> str:
    """Empty when every arm's calibrated shoulder height is within ``table_clearance_m`` of the rig's; otherwise
    why the clearance checks cannot be trusted with this calibration (one line).

    The bases stand on the table, so their parts' heights are the rig's whatever the calibration; a calibrated
    base pose that moves the shoulder by more than the table clearance moves every part of the arm's model by
    about as much: lower, and even the arm's own park pose fails the table check (every view is refused);
    higher, and planned moves may pass the check while the real arm touches the table."""
    offsets = shoulder_offsets_m(rig, calibration)
    bad = {a: d for a, d in offsets.items() if abs(d) > table_clearance_m}
    if not bad:
        return ""
    what = " and ".join(f"of {a} {abs(d) * 1000:.0f} mm {'higher' if d > 0 else 'lower'}" for a, d in bad.items())
    others = "; ".join(f"{a}: {d * 1000:+.0f} mm" for a, d in offsets.items() if a not in bad)
    return (f"the calibration puts the shoulder {what} than the rig file, whose bases stand on the table"
            f"{f' ({others})' if others else ''}: more than the {table_clearance_m * 1000:.0f} mm table clearance "
            f"that planned moves keep, so the clearance checks cannot be trusted with it (recalibrate)")


@dataclass(frozen=True)
class OrbitShape:
    """Rings (elevations) and the azimuth span and count of one orbit, and its standoff."""

    standoff_m: float
    elevations_deg: tuple[float, ...]
    azimuth_span_deg: float
    n_azimuth: int

    def to_record(self) -> dict[str, Any]:
        return {"standoff_m": self.standoff_m, "elevations_deg": list(self.elevations_deg),
                "azimuth_span_deg": self.azimuth_span_deg, "n_azimuth": self.n_azimuth}


def orbit_shape(radius_m: float, height_m: float) -> OrbitShape:
    """The nominal orbit for an envelope (see the module's table)."""
    standoff = standoff_for_radius(radius_m)
    if radius_m < 0.06:
        elevations, span, n_az = [35.0, 60.0], 100.0, 5
    elif radius_m < 0.09:
        elevations, span, n_az = [25.0, 45.0, 65.0], 120.0, 6
    else:
        elevations, span, n_az = [20.0, 40.0, 60.0], 140.0, 7
    if height_m > 2.0 * radius_m:
        elevations = [15.0, *elevations]
    return OrbitShape(standoff, tuple(elevations), span, n_az)


def _relax_wider(shape: OrbitShape) -> OrbitShape:
    low = max(10.0, min(shape.elevations_deg) - 10.0)
    return replace(shape, elevations_deg=tuple(sorted({low, *shape.elevations_deg})),
                   azimuth_span_deg=min(200.0, shape.azimuth_span_deg + 40.0), n_azimuth=shape.n_azimuth + 2)


def _relax_further(shape: OrbitShape) -> OrbitShape:
    return replace(_relax_wider(shape), standoff_m=shape.standoff_m + 0.05)


def _relax_nearer(shape: OrbitShape) -> OrbitShape:
    wide = _relax_wider(shape)
    return replace(wide, standoff_m=max(0.25, shape.standoff_m - 0.04),
                   elevations_deg=tuple(sorted({max(10.0, e - 10.0) for e in wide.elevations_deg})))


def _relax_close(shape: OrbitShape) -> OrbitShape:
    """The nominal rings 25 cm from the envelope's surface, 5 cm inside the small objects' working distance and
    without the large-object rule (module docstring). The radius comes back from the standoff:
    ``r = min(s - 0.30, s / 4.5)`` inverts :func:`standoff_for_radius`."""
    r = min(shape.standoff_m - 0.30, shape.standoff_m / 4.5)
    return replace(shape, standoff_m=max(NEAR_STANDOFF_M, CLOSE_SURFACE_DISTANCE_M + r))


NEAR_STANDOFF_M = 0.25  # the closest orbit standoff a relaxation may choose (the min_depth check still applies)
CLOSE_SURFACE_DISTANCE_M = 0.25  # the last relaxation's camera distance to the envelope's surface
RELAXATIONS = (("nominal", lambda s: s), ("wider span, lower ring", _relax_wider),
               ("larger standoff", _relax_further), ("smaller standoff, lower rings", _relax_nearer),
               ("close", _relax_close))


@dataclass(frozen=True)
class ViewpointSettings:
    """Limits of viewpoint planning."""

    min_views: int = 6
    max_joint_step_rad: float = 1.6  # largest single-joint change between consecutive views
    reach_limit_m: float = 0.70  # flange distance from the shoulder (the Z1 reaches 0.756 m)
    camera_min_height_m: float = 0.06  # camera optical centre above the table
    min_depth_m: float = 0.17  # every envelope point at least this far in front of the camera
    path_step_rad: float = 0.03  # path sampling for the clearance checks between views
    two_opt_rounds: int = 50

    def __post_init__(self) -> None:
        if self.min_views < 1:
            raise AcquisitionError(f"min_views must be >= 1, got {self.min_views}")
        for name in ("max_joint_step_rad", "reach_limit_m", "min_depth_m", "path_step_rad"):
            if not getattr(self, name) > 0:
                raise AcquisitionError(f"viewpoint setting {name} must be positive")


@dataclass
class Candidate:
    """One candidate view: where the camera goes, the joints that put it there, and the verdict."""

    index: int
    elevation_deg: float
    azimuth_deg: float  # world azimuth of the camera about the centre
    standoff_m: float
    camera_m: Array  # intended optical centre (world)
    q_rad: Array | None = None  # commanded joints when IK succeeded
    ok: bool = False
    reason: str = ""
    detail: str = ""

    def to_record(self) -> dict[str, Any]:
        return {"index": self.index, "elevation_deg": round(self.elevation_deg, 3),
                "azimuth_deg": round(self.azimuth_deg, 3), "standoff_m": round(self.standoff_m, 4),
                "ok": self.ok, "reason": self.reason, "detail": self.detail,
                "q_rad": None if self.q_rad is None else [float(v) for v in self.q_rad]}

    @property
    def joints_rad(self) -> Array:
        """``q_rad`` of a candidate that IK solved (every feasible view: ``ok`` implies it)."""
        assert self.q_rad is not None, f"candidate {self.index} has no joints ({self.reason or 'unchecked'})"
        return self.q_rad


@dataclass
class ViewPlan:
    """The ordered, checked views of one arm and how they were found."""

    arm_id: str
    shape: OrbitShape
    views: list[Candidate]
    candidates: list[Candidate]
    attempts: list[dict[str, Any]] = field(default_factory=list)
    travel_rad: float = 0.0  # sum over the tour (park -> views -> park) of the largest joint change

    @property
    def q_views(self) -> Array:
        return np.array([c.joints_rad for c in self.views]) if self.views else np.zeros((0, 6))

    def to_record(self) -> dict[str, Any]:
        return {"arm": self.arm_id, "shape": self.shape.to_record(), "n_views": len(self.views),
                "travel_rad": round(self.travel_rad, 4), "attempts": self.attempts}


def _reject_counts(cands: list[Candidate]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for c in cands:
        if not c.ok:
            counts[c.reason] = counts.get(c.reason, 0) + 1
    return counts


REASON_WORDS = {"ik": "IK", "joint_limits": "joint limits", "workspace": "workspace", "min_depth": "minimum depth",
                "table": "table clearance", "self": "self-collision", "parked_arm": "parked-arm",
                "envelope": "envelope clearance", "joint_motion": "joint motion"}
"""How a refusal reason reads in a message; ``path_<reason>`` reads as "path <words>"."""


def reason_words(reason: str) -> str:
    """A refusal reason code in words (``path_table`` -> ``path table clearance``)."""
    if reason.startswith("path_"):
        return "path " + REASON_WORDS.get(reason[5:], reason[5:])
    return REASON_WORDS.get(reason, reason or "unchecked")


def feasibility_summary(plan: ViewPlan) -> str:
    """Why an arm's candidate views were refused, for a user: ``0 feasible of 36 candidates: 20 IK,
    12 table clearance, 4 parked-arm; e.g. IK: <detail>; table clearance: <detail>`` (the first refusal's detail
    for each of the two most frequent reasons). The counts are those of
    the orbit the plan kept (the relaxation with the most views; the first one when all have none); the most
    frequent reason comes first, ties in :data:`CANDIDATE_REASONS` order."""
    counts = _reject_counts(plan.candidates)
    order = {r: k for k, r in enumerate(CANDIDATE_REASONS)}
    ranked = sorted(counts, key=lambda r: (-counts[r], order.get(r, len(order)), r))
    text = f"{len(plan.views)} feasible of {len(plan.candidates)} candidates"
    kept = [a["relaxation"] for a in plan.attempts if a.get("shape") == plan.shape.to_record()]
    if len(plan.attempts) > 1 and kept:
        text += f" (the {kept[0]} orbit, best of {len(plan.attempts)} tried)"
    if ranked:
        text += ": " + ", ".join(f"{counts[r]} {reason_words(r)}" for r in ranked)
        examples = [(r, next(c.detail for c in plan.candidates if not c.ok and c.reason == r)) for r in ranked[:2]]
        if any(detail for _, detail in examples):
            text += "; e.g. " + "; ".join(f"{reason_words(r)}: {detail}" for r, detail in examples if detail)
    return text


def envelope_points(centre_m: Array, radius_m: float, height_m: float, table_z_m: float, n: int = 16) -> Array:
    """Points on the envelope cylinder's rims (bottom, middle, top) for depth and visibility checks."""
    a = np.arange(n) * 2.0 * np.pi / n
    ring = np.stack([np.cos(a), np.sin(a)], axis=1) * radius_m + np.asarray(centre_m)[:2]
    zs = table_z_m + np.array([0.0, 0.5, 1.0]) * height_m
    pts = [np.column_stack([ring, np.full(n, z)]) for z in zs]
    pts.append(np.array([[centre_m[0], centre_m[1], table_z_m + height_m]]))
    return np.vstack(pts)


class ViewpointPlanner:
    """Generates, checks and orders the views of one arm about a given envelope."""

    def __init__(self, model: ArmCollisionModel, centre_m: Array, radius_m: float, height_m: float,
                 settings: ViewpointSettings | None = None, q_park_rad: Array | None = None) -> None:
        """``model``: the arm's collision world with the envelope as its obstacle (see
        :func:`darp.acquisition.motion_check.envelope_obstacle`)."""
        self.model = model
        self.settings = settings if settings is not None else ViewpointSettings()
        self.centre = np.asarray(centre_m, dtype=float)
        self.radius = float(radius_m)
        self.height = float(height_m)
        rig = model.rig
        self.q_park = np.array(rig.arms[model.arm_id].park_q_rad if q_park_rad is None else q_park_rad, float)
        self.table = rig.table
        self.T_base_world = np.linalg.inv(model.T_world_base)
        self.envelope_pts = envelope_points(self.centre, self.radius, self.height, rig.table.height_m)
        self.roll_hints_deg: tuple[float, ...] = ROLL_HINTS_DEG
        base_xy = model.T_world_base[:2, 3] - self.centre[:2]
        self.side_azimuth_deg = float(np.degrees(np.arctan2(base_xy[1], base_xy[0])))

    # -- candidates -------------------------------------------------------------------------------
    def candidates(self, shape: OrbitShape) -> list[Candidate]:
        """Camera positions of an orbit: rings bottom-up, azimuths across the arm's side."""
        out: list[Candidate] = []
        half = 0.5 * shape.azimuth_span_deg
        az_offsets = np.linspace(-half, half, shape.n_azimuth) if shape.n_azimuth > 1 else np.zeros(1)
        for elev in shape.elevations_deg:
            for off in az_offsets:
                az = self.side_azimuth_deg + float(off)
                e, a = np.radians(elev), np.radians(az)
                direction = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
                out.append(Candidate(len(out), float(elev), float(az), shape.standoff_m,
                                     self.centre + shape.standoff_m * direction))
        return out

    def check_candidate(self, cand: Candidate, q_init: Array | None = None) -> Candidate:
        """Solve look-at IK and run the per-view checks; fills ``q_rad``, ``ok``, ``reason``, ``detail``."""
        s, m = self.settings, self.model
        target_base = (self.T_base_world @ np.r_[self.centre, 1.0])[:3]
        view_dir_world = self.centre - cand.camera_m
        view_dir_base = self.T_base_world[:3, :3] @ view_dir_world
        q_seed = m.model_q(self.q_park if q_init is None else q_init)
        q, message = self._look_at(target_base, view_dir_base, cand.standoff_m, q_seed)
        if q is None:
            return _fail(cand, "ik", message)
        cand.q_rad = q
        limits = m.joint_limit_verdict(q)
        if not limits.ok:
            return _fail(cand, "joint_limits", limits.detail)
        flange_base = z1.fk(m.model_q(q), m.rig.wrist_frame)[:3, 3]
        reach = float(np.linalg.norm(flange_base - SHOULDER_BASE_M))
        if reach > s.reach_limit_m:
            return _fail(cand, "workspace", f"flange {reach:.3f} m from the shoulder (limit {s.reach_limit_m:.2f} m)")
        T_world_cam = m.T_world_cam(q)
        cam = T_world_cam[:3, 3]
        (x0, x1), (y0, y1) = self.table.x_range_m, self.table.y_range_m
        if not (x0 <= cam[0] <= x1 and y0 <= cam[1] <= y1):
            return _fail(cand, "workspace", f"camera at ({cam[0]:.3f}, {cam[1]:.3f}) is not over the table")
        if cam[2] - self.table.height_m < s.camera_min_height_m:
            return _fail(cand, "workspace", f"camera {cam[2] - self.table.height_m:.3f} m above the table "
                         f"(minimum {s.camera_min_height_m:.2f} m)")
        depth = (np.linalg.inv(T_world_cam) @ np.c_[self.envelope_pts, np.ones(len(self.envelope_pts))].T)[2]
        if float(np.min(depth)) < s.min_depth_m:
            return _fail(cand, "min_depth", f"envelope point {np.min(depth):.3f} m in front of the camera "
                         f"(minimum depth {s.min_depth_m:.3f} m)")
        verdict = m.check_configuration(q)
        if not verdict.ok:
            return _fail(cand, verdict.reason, verdict.detail)
        cand.ok, cand.reason, cand.detail = True, "", ""
        return cand

    def _look_at(self, target_base: Array, view_dir_base: Array, distance_m: float,
                 q_seed: Array) -> tuple[Array | None, str]:
        """Commanded joints viewing the target, roll free: image-up hints are tried from upright
        outwards (:data:`ROLL_HINTS_DEG`) and the first solution inside the margined limits wins;
        otherwise the upright one (for the joint-limit verdict), or None when IK has no solution."""
        m = self.model
        d = view_dir_base / np.linalg.norm(view_dir_base)
        up = self.T_base_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
        up = up - (up @ d) * d
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.cross(d, [0.0, 1.0, 0.0])
        side = np.cross(d, up)
        first: Array | None = None
        message = ""
        for roll_deg in self.roll_hints_deg:
            a = np.radians(roll_deg)
            hint = np.cos(a) * up + np.sin(a) * side
            result = solve_look_at(target_base, distance_m, T_frame_cam=m.T_wrist_cam, view_dir_base=view_dir_base,
                                   frame=m.rig.wrist_frame, q_init=q_seed, up_hint=hint)
            if not result.success:
                message = result.message
                continue
            q = result.q - m.dq
            if m.joint_limit_verdict(q).ok:
                return q, ""
            if first is None:
                first = q
        return first, message

    # -- planning ---------------------------------------------------------------------------------
    def plan(self, shape: OrbitShape | None = None) -> ViewPlan:
        """Views for the orbit (nominal for the envelope unless given), regenerated relaxed if too few."""
        base_shape = shape if shape is not None else orbit_shape(self.radius, self.height)
        best: ViewPlan | None = None
        attempts: list[dict[str, Any]] = []
        for name, relax in RELAXATIONS:
            attempt_shape = relax(base_shape)
            views, cands = self._attempt(attempt_shape)
            attempts.append({"relaxation": name, "shape": attempt_shape.to_record(), "candidates": len(cands),
                             "views": len(views), "rejected": _reject_counts(cands)})
            plan = ViewPlan(self.model.arm_id, attempt_shape, views, cands, attempts)
            if best is None or len(views) > len(best.views):
                best = plan
            if len(views) >= self.settings.min_views:
                best = plan
                break
        assert best is not None
        best.attempts = attempts
        best.travel_rad = tour_cost(self.q_park, best.q_views, self.q_park)
        return best

    def _attempt(self, shape: OrbitShape) -> tuple[list[Candidate], list[Candidate]]:
        cands = self.candidates(shape)
        q_prev = self.q_park
        for cand in cands:  # IK seeded from the previous solution keeps neighbours' joints close
            self.check_candidate(cand, q_init=q_prev)
            if cand.ok:
                q_prev = cand.joints_rad
        good = [c for c in cands if c.ok]
        return self._tour(good), cands

    def _tour(self, good: list[Candidate]) -> list[Candidate]:
        """Order the feasible views; drop views whose move is excessive or fails the path checks."""
        s = self.settings
        self._paths: dict[tuple[int, int], Any] = {}  # path verdicts by (from, to) candidate index; -1: park
        while good:
            order = order_views(self.q_park, np.array([c.joints_rad for c in good]), self.q_park, s.two_opt_rounds)
            tour = [good[i] for i in order]
            dropped = self._first_bad_move(tour)
            if dropped is None:
                return tour
            good = [c for c in good if c is not dropped]
        return []

    def _first_bad_move(self, tour: list[Candidate]) -> Candidate | None:
        """The view that ends (or, for the return to park, starts) the first infeasible move."""
        s = self.settings
        q_prev, i_prev = self.q_park, -1
        for cand in [*tour, None]:
            q_next = self.q_park if cand is None else cand.joints_rad
            i_next = -1 if cand is None else cand.index
            step = float(np.max(np.abs(q_next - q_prev)))
            culprit = tour[-1] if cand is None else cand
            between_views = cand is not None and q_prev is not self.q_park  # moves from/to park are long anyway
            if step > s.max_joint_step_rad and between_views:
                return _fail(culprit, "joint_motion",
                             f"a joint moves {step:.2f} rad from the previous view (limit {s.max_joint_step_rad:.2f})")
            key = (i_prev, i_next)
            if key not in self._paths:
                self._paths[key] = self.model.check_path(q_prev, q_next, s.path_step_rad)
            verdict = self._paths[key]
            if not verdict.ok:
                return _fail(culprit, f"path_{verdict.reason}",
                             f"move {'to' if cand is not None else 'back to park from'} this view: {verdict.detail}")
            q_prev, i_prev = q_next, i_next
        return None


def _fail(cand: Candidate, reason: str, detail: str) -> Candidate:
    cand.ok, cand.reason, cand.detail = False, reason, detail
    return cand


__all__ = [
    "CANDIDATE_REASONS",
    "RELAXATIONS",
    "Candidate",
    "OrbitShape",
    "ViewPlan",
    "ViewpointPlanner",
    "ViewpointSettings",
    "calibration_table_problem",
    "envelope_points",
    "feasibility_summary",
    "min_depth_from_intrinsics",
    "orbit_shape",
    "reason_words",
    "shoulder_offsets_m",
    "standoff_for_radius",
]
