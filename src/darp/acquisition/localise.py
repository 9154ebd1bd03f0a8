"""Object localisation: the structured pan-based search with one eye-in-hand camera, and refinement.

The searching arm (the other parked) looks at candidate tabletop regions in a deterministic order
(:func:`search_targets`: the workspace centre first, then pans to either side, then the far and the
near rows), each view a look-at pose from the arm's side checked by
:class:`~darp.acquisition.motion_check.ArmCollisionModel` with the whole placement workspace as the
obstacle (the object may stand anywhere in it), every move path-checked. Each view's depth goes to
:func:`~darp.acquisition.estimate.estimate_from_depth`. At the first valid estimate (or a rejected one
worth a closer look: truncated, too few points, outside the workspace) the arm looks straight at it
from its side at the size's standoff (refinement, repeated while the centre moves more than
``refine_tolerance_m``), then parks keeping clear of the estimate. A hint (another arm's estimate) is
looked at first; the sweep follows only if that fails.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.estimate import (
    REJECTION_REASONS,
    LocaliseSettings,
    ObjectEstimate,
    Observation,
    estimate_from_depth,
)
from darp.acquisition.motion_check import (
    ArmCollisionModel,
    ClearanceMargins,
    MotionSettings,
    UnsafeMoveError,
    checked_move,
    envelope_obstacle,
    workspace_obstacle,
)
from darp.acquisition.viewpoints import Candidate, ViewpointPlanner, ViewpointSettings, standoff_for_radius
from darp.backend import LiveFrameSet, RigBackend
from darp.formats.calibration import Calibration
from darp.formats.realsense.types import Intrinsics
from darp.kinematics.rig import Rig

Array = NDArray[np.float64]


def capture_view(backend: RigBackend, rig: Rig, arm_id: str, calibration: Calibration | None,
                 settings: LocaliseSettings) -> list[tuple[Array, Intrinsics, Array]]:
    """Grab ``frames_per_view`` live depth frames of a still arm with their eq.-1 camera poses."""
    out = []
    camera = backend.cameras[arm_id]
    arm = backend.arms[arm_id]
    for k in range(settings.frames_per_view):
        if k:
            backend.clock.sleep(settings.frame_interval_s)
        frame: LiveFrameSet = camera.latest_frameset()
        state = arm.read_state()
        T_world_cam = rig.T_world_cam(arm_id, np.asarray(state.q_rad), calibration=calibration)
        out.append((np.asarray(frame.depth_m), frame.depth_intrinsics, T_world_cam))
    return out


# -- search ---------------------------------------------------------------------------------------
def search_targets(rig: Rig, arm_id: str, calibration: Calibration | None = None) -> Array:
    """Table points the search looks at, in order: workspace centre, pans to either side (the arm's
    right first), then the far and the near rows (far/near from the arm's base)."""
    ws, z = rig.workspace, rig.table.height_m
    T_world_base, _, _ = rig.extrinsics(arm_id, calibration)
    cx, cy = float(np.mean(ws.x_range_m)), float(np.mean(ws.y_range_m))
    hx, hy = 0.5 * (ws.x_range_m[1] - ws.x_range_m[0]), 0.5 * (ws.y_range_m[1] - ws.y_range_m[0])
    to_centre = np.array([cx, cy]) - T_world_base[:2, 3]
    forward = to_centre / np.linalg.norm(to_centre)
    right = np.array([forward[1], -forward[0]])
    along = np.abs(forward) @ np.array([hx, hy])
    across = np.abs(right) @ np.array([hx, hy])
    offsets = [(0.0, 0.0), (0.0, 1.0), (0.0, -1.0), (1.0, 0.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 0.0),
               (-1.0, 1.0), (-1.0, -1.0)]
    pts = [np.array([cx, cy]) + fa * along * forward + fr * across * right for fa, fr in offsets]
    return np.array([[p[0], p[1], z] for p in pts])


EventSink = Callable[..., None]  # events(kind, **fields)
HINT_REASONS = ("truncated", "few_points", "outside_workspace", "too_tall")  # rejected, but worth a closer look


@dataclass
class LocalisationResult:
    """The outcome of one arm's localisation: an estimate, or why there is none, and every view."""

    arm_id: str
    estimate: ObjectEstimate | None
    reason: str = ""
    detail: str = ""
    candidate: ObjectEstimate | None = None  # the last rejected estimate (e.g. outside the workspace)
    views: list[dict[str, Any]] = field(default_factory=list)

    def to_record(self) -> dict[str, Any]:
        return {"arm": self.arm_id, "ok": self.estimate is not None, "reason": self.reason, "detail": self.detail,
                "estimate": None if self.estimate is None else self.estimate.to_record(),
                "rejected_estimate": None if self.candidate is None else self.candidate.to_record(),
                "views": self.views}


class Localiser:
    """Drives one arm through the search and refinement views and estimates the object."""

    def __init__(self, backend: RigBackend, rig: Rig, calibration: Calibration | None, *,
                 settings: LocaliseSettings | None = None, motion: MotionSettings | None = None,
                 margins: ClearanceMargins | None = None, events: EventSink | None = None) -> None:
        self.backend, self.rig, self.calibration = backend, rig, calibration
        self.settings = settings if settings is not None else LocaliseSettings()
        self.motion = motion if motion is not None else MotionSettings()
        self.margins = margins if margins is not None else ClearanceMargins.from_rig(rig)
        self.events: EventSink = events if events is not None else (lambda kind, **fields: None)

    def _planner(self, arm_id: str, centre: Array, radius: float, height: float, obstacle: Any) -> ViewpointPlanner:
        model = ArmCollisionModel(self.rig, arm_id, calibration=self.calibration, obstacle=obstacle,
                                  margins=self.margins)
        return ViewpointPlanner(model, centre, radius, height, ViewpointSettings(min_views=1))

    def _view(self, arm_id: str, result: LocalisationResult, stage: str, planner: ViewpointPlanner,
              distance_m: float, elevations_deg: tuple[float, ...]) -> Observation | None:
        """Look at the planner's centre from the arm's side (first feasible elevation); estimate."""
        q_now = np.asarray(self.backend.arms[arm_id].read_state().q_rad, dtype=float)
        record: dict[str, Any] = {"stage": stage, "target_m": [round(float(v), 4) for v in planner.centre]}
        cand = None
        azimuth = planner.side_azimuth_deg
        for elev in elevations_deg:
            e, a = np.radians(elev), np.radians(azimuth)
            camera = planner.centre + distance_m * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            cand = planner.check_candidate(Candidate(0, elev, azimuth, distance_m, camera), q_now)
            if cand.ok:
                break
        if cand is None or not cand.ok:
            record.update(ok=False, reason="unreachable", detail=f"{cand.reason}: {cand.detail}" if cand else "")
            result.views.append(record)
            self.events("view_skipped", arm=arm_id, **record)
            return None
        try:
            checked_move(self.backend, planner.model, cand.joints_rad, self.motion)
        except UnsafeMoveError as err:
            record.update(ok=False, reason="unreachable", detail=str(err))
            result.views.append(record)
            self.events("view_skipped", arm=arm_id, **record)
            return None
        frames = capture_view(self.backend, self.rig, arm_id, self.calibration, self.settings)
        obs = estimate_from_depth(frames, self.rig, arm_id, self.settings)
        if obs.estimate is not None:
            obs.estimate.stage = stage
        if obs.candidate is not None:
            obs.candidate.stage = stage
        record.update(elevation_deg=cand.elevation_deg, distance_m=round(distance_m, 4),
                      q_rad=[round(float(v), 5) for v in cand.joints_rad], **obs.to_record())
        result.views.append(record)
        self.events("observation", arm=arm_id, **record)
        return obs

    def _grown(self, est: ObjectEstimate) -> Any:
        return envelope_obstacle(est.centre_m, est.radius_m + 0.03, est.height_m + 0.03, self.rig.table.height_m)

    def retreat(self, arm_id: str, near: ObjectEstimate | None) -> None:
        """Back to park, keeping clear of the (grown) estimate ``near`` if given, else of the workspace."""
        q_park = np.asarray(self.rig.arms[arm_id].park_q_rad, dtype=float)
        q_now = np.asarray(self.backend.arms[arm_id].read_state().q_rad, dtype=float)
        if np.max(np.abs(q_now - q_park)) < self.motion.start_tolerance_rad:
            return
        obstacle = workspace_obstacle(self.rig) if near is None else self._grown(near)
        model = ArmCollisionModel(self.rig, arm_id, calibration=self.calibration, obstacle=obstacle,
                                  margins=self.margins)
        checked_move(self.backend, model, q_park, self.motion, settle=False)
        self.events("parked", arm=arm_id)

    def look_at_estimate(self, arm_id: str, result: LocalisationResult, est: ObjectEstimate,
                         stage: str) -> Observation | None:
        """Look straight at an estimate from the arm's side, at its standoff plus a little."""
        s = self.settings
        planner = self._planner(arm_id, est.centre_m, est.radius_m, est.height_m, self._grown(est))
        distance = standoff_for_radius(est.radius_m) + s.refine_extra_standoff_m
        elevations = (s.refine_elevation_deg, s.refine_elevation_deg + 15.0, s.refine_elevation_deg - 15.0)
        return self._view(arm_id, result, stage, planner, distance, elevations)

    def refine(self, arm_id: str, result: LocalisationResult, first: ObjectEstimate, first_valid: bool,
               stage: str = "refine") -> None:
        """Look straight at the estimate until its centre moves less than the tolerance. The result's
        estimate is the last valid one (``first`` counts only if ``first_valid``: not truncated)."""
        s = self.settings
        current, target = (first if first_valid else None), first
        for _ in range(s.max_refinements):
            obs = self.look_at_estimate(arm_id, result, target, stage)
            if obs is None or obs.estimate is None:
                if obs is not None and obs.reason in ("outside_workspace", "too_tall"):
                    current = None
                    result.reason, result.detail, result.candidate = obs.reason, obs.detail, obs.candidate
                elif obs is not None and obs.reason == "no_object" and current is None:
                    # A closer look at a rejected estimate found nothing there: it was noise (a far, noisy
                    # stretch of table), not the object; forget it so that the search goes on.
                    result.reason = result.detail = ""
                    result.candidate = None
                break
            moved = float(np.linalg.norm(obs.estimate.centre_m[:2] - target.centre_m[:2]))
            current = target = obs.estimate
            if moved < s.refine_tolerance_m:
                break
        self.retreat(arm_id, target)
        result.estimate = current
        if current is not None:
            result.reason = result.detail = ""
            result.candidate = None
        elif not result.reason:
            result.reason, result.detail = "unreliable", "no view of the object gave a complete, supported estimate"

    def localise(self, arm_id: str, hint: ObjectEstimate | None = None, stage: str = "search") -> LocalisationResult:
        """Estimate the object with ``arm_id`` (the other arm parked): straight at ``hint`` first if given,
        else (or if that fails) the pan-based search sweep, then refinement."""
        result = LocalisationResult(arm_id, None)
        self.events("localise_start", arm=arm_id, stage=stage, hint=None if hint is None else hint.to_record())
        if hint is not None:
            obs = self.look_at_estimate(arm_id, result, hint, stage)
            if obs is not None and obs.estimate is not None:
                self.refine(arm_id, result, obs.estimate, True, stage)
                if result.estimate is not None:
                    return self._done(result)
            else:
                self.retreat(arm_id, hint)
        last: Observation | None = None
        workspace = workspace_obstacle(self.rig)
        for target in search_targets(self.rig, arm_id, self.calibration):
            planner = self._planner(arm_id, target, 0.01, 0.01, workspace)
            obs = self._view(arm_id, result, "search", planner, self.settings.search_distance_m,
                             (self.settings.search_elevation_deg, self.settings.search_elevation_deg + 15.0))
            if obs is None:
                continue
            last = obs
            first = obs.estimate or (obs.candidate if obs.reason in HINT_REASONS else None)
            if first is None:
                continue
            if obs.estimate is None:
                result.reason, result.detail, result.candidate = obs.reason, obs.detail, obs.candidate
            self.refine(arm_id, result, first, obs.estimate is not None, "refine" if stage == "search" else stage)
            if result.estimate is not None or result.reason in ("outside_workspace", "too_tall"):
                break
        if result.estimate is None and not result.reason:
            if last is None:
                result.reason, result.detail = "unreachable", "no search view was reachable"
            elif last.reason in ("no_object", "no_depth"):
                result.reason, result.detail = "no_object", "the search found no object on the table"
            else:
                result.reason, result.detail = last.reason, last.detail
        self.retreat(arm_id, None)
        return self._done(result)

    def _done(self, result: LocalisationResult) -> LocalisationResult:
        record = result.to_record()
        record.pop("views")
        self.events("localise_end", **record)
        return result


__all__ = [  # the estimator's names are re-exported: localise is the stage's entry point
    "HINT_REASONS", "REJECTION_REASONS", "LocalisationResult", "LocaliseSettings", "Localiser", "ObjectEstimate",
    "Observation", "capture_view", "estimate_from_depth", "search_targets",
]
