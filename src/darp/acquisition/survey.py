"""The autonomous object survey: localise, confirm, plan, record, verify, write the episode.

One procedure drives the twin and real hardware through :class:`~darp.backend.RigBackend`:

1. park both arms;
2. **localise** with the searching arm (the other parked) and **confirm** with the other arm looking
   straight at that estimate (:mod:`~darp.acquisition.localise`, :mod:`~darp.acquisition.confirm`);
3. **plan** each arm's views about the confirmed envelope: by default for coverage of the envelope's
   surface with a co-observed band between the arms (:mod:`~darp.acquisition.coverage`; a side no
   feasible view reaches is warned about by name), or the paper's fixed orbit
   (``viewpoint_strategy="orbit"``, :mod:`~darp.acquisition.viewpoints`);
4. **record**: start the joint log, then both cameras; each arm in turn visits its views (non-blocking
   moves, waiting on the rig clock, a settling interval at every view) and parks while the other
   waits parked; stop the cameras, keep logging a little, stop the log. So the camera interval lies
   inside the log's. With the coverage strategy every view's live depth updates the achieved coverage,
   and after an arm's planned views the next best views (those that see the most surface still
   unobserved, at most ``coverage.nbv_max_views``, within ``coverage.nbv_time_fraction`` of the time its
   planned views took) are added before it parks;
5. **verify** the written files (:mod:`~darp.acquisition.verify`) and accept or reject the episode
   (:mod:`~darp.acquisition.episode`), writing ``manip_envelope.json`` with the envelope, the
   standoff, the park and view configurations and the localisation/confirmation record.

A fault the rig reports during motion (a contact on the twin, a controller that left joint control on
hardware: :meth:`~darp.backend.RigBackend.fault`) stops both arms at once, closes the recordings and
the log, parks each arm not involved in the fault whose path to park is clear, and rejects the
episode with reason ``fault`` (``REJECTED.txt`` names the fault and where each arm was left); no
planned move is commanded after it.

A KeyboardInterrupt or a backend error at any point stops both arms, closes the recordings and the
log, and leaves ``<NAME>.partial/`` marked with ``PARTIAL.txt``; the KeyboardInterrupt is re-raised,
a backend error becomes an :class:`AcquisitionError` naming the folder.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.acquisition.confirm import ConfirmSettings, Decision, decide, settings_from_calibration
from darp.acquisition.coverage import CoverageSettings
from darp.acquisition.coverage_plan import (
    CoveragePlan,
    coverage_of_plans,
    plan_coverage,
    survey_feasible_poses,
)
from darp.acquisition.coverage_track import CoverageTracker, coverage_record, observe_live, visit_next_best_views
from darp.acquisition.episode import Episode
from darp.acquisition.localise import LocalisationResult, Localiser, LocaliseSettings, ObjectEstimate
from darp.acquisition.motion_check import (
    ArmCollisionModel,
    ClearanceMargins,
    MotionFault,
    MotionSettings,
    checked_move,
    envelope_obstacle,
    park_after_fault,
    stop_all_arms,
    workspace_obstacle,
)
from darp.acquisition.verify import VerificationReport, VerifySettings, verify_survey
from darp.acquisition.viewpoints import (
    ViewPlan,
    ViewpointPlanner,
    ViewpointSettings,
    calibration_table_problem,
    feasibility_summary,
    min_depth_from_intrinsics,
    standoff_for_radius,
)
from darp.backend import RigBackend
from darp.errors import AcquisitionError, DarpWarning
from darp.formats.calibration import Calibration
from darp.formats.envelope import ENVELOPE_FILE, Envelope, write_envelope
from darp.formats.survey import ARM_POSES_FILE
from darp.kinematics.rig import Rig

ProgressFn = Callable[[str, float, str], None]
"""``progress(phase, fraction, message)``: phase is localise, confirm, plan, record, verify or done."""


@dataclass(frozen=True)
class SurveySettings:
    """Every setting of a survey, grouped by stage."""

    localise: LocaliseSettings = field(default_factory=LocaliseSettings)
    confirm: ConfirmSettings = field(default_factory=ConfirmSettings)
    viewpoints: ViewpointSettings = field(default_factory=ViewpointSettings)
    coverage: CoverageSettings = field(default_factory=CoverageSettings)
    viewpoint_strategy: str = "orbit"  # the paper's fixed orbit per arm; or "coverage" (see docs/acquisition.md)
    record_feasible_poses: bool = True  # the coverage grid's feasible camera poses in manip_envelope.json
    confirm_from_calibration: bool = True  # confirmation thresholds from the calibration's stated uncertainty
    motion: MotionSettings = field(default_factory=MotionSettings)
    verify: VerifySettings = field(default_factory=VerifySettings)
    envelope_margin_m: float = 0.04  # arm and camera keep this far from the object envelope
    min_required_views: int = 4  # fewer feasible views than this for an arm terminates the survey
    searching_arm: str | None = None  # default: the rig's first arm
    derive_min_depth: bool = True  # the minimum depth from the depth stream's focal length
    log_lead_s: float = 0.5  # joint log before the cameras start
    camera_lead_s: float = 0.3  # cameras before the first move
    camera_tail_s: float = 0.3  # cameras after the last park
    log_tail_s: float = 0.5  # joint log after the cameras stop


@dataclass
class SurveyOutcome:
    """How a survey ended and what it produced."""

    status: str  # accepted | rejected | partial
    folder: Path
    reason: str = ""
    message: str = ""
    envelope: Envelope | None = None
    decision: Decision | None = None
    localisation: dict[str, LocalisationResult] = field(default_factory=dict)
    plans: dict[str, ViewPlan] = field(default_factory=dict)
    report: VerificationReport | None = None
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def accepted(self) -> bool:
        return self.status == "accepted"


class _Terminated(Exception):
    """Internal: the survey ends early with a reason (rejected, not an error)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason, self.message = reason, message


class SurveyRunner:
    """Runs one survey on a backend; see :func:`run_survey`."""

    def __init__(self, backend: RigBackend, rig: Rig, episode: Episode, *, calibration: Calibration | None = None,
                 settings: SurveySettings | None = None, progress: ProgressFn | None = None,
                 object_name: str | None = None) -> None:
        self.backend, self.rig, self.episode = backend, rig, episode
        self.calibration = calibration
        self.s = settings if settings is not None else SurveySettings()
        self.progress = progress if progress is not None else (lambda phase, fraction, message: None)
        self.events = episode.events
        self.object_name = object_name
        self.primary = self.s.searching_arm or rig.arm_ids[0]
        if self.primary not in rig.arm_ids:
            raise AcquisitionError(f"searching arm {self.primary!r} is not in the rig ({', '.join(rig.arm_ids)})")
        self.secondary = next(a for a in rig.arm_ids if a != self.primary)
        self.margins = ClearanceMargins.from_rig(rig, envelope_m=self.s.envelope_margin_m)
        self.park = {a: np.array(rig.arms[a].park_q_rad, dtype=float) for a in rig.arm_ids}
        self.outcome = SurveyOutcome("running", episode.path)
        self.recording = False
        self.logging = False
        self.timings: dict[str, float] = {}
        self.estimate: ObjectEstimate | None = None
        self.coverage_plan: CoveragePlan | None = None
        self.feasible_poses: dict[str, list[list[float]]] | None = None
        self.tracker: CoverageTracker | None = None
        if self.s.viewpoint_strategy not in ("coverage", "orbit"):
            raise AcquisitionError(f"viewpoint strategy must be coverage or orbit, got {self.s.viewpoint_strategy!r}")

    # -- helpers ----------------------------------------------------------------------------------
    def _model(self, arm_id: str, obstacle: Any) -> ArmCollisionModel:
        return ArmCollisionModel(self.rig, arm_id, calibration=self.calibration, obstacle=obstacle,
                                 margins=self.margins)

    def _park(self, arm_id: str, obstacle: Any) -> None:
        q_now = np.asarray(self.backend.arms[arm_id].read_state().q_rad, dtype=float)
        if np.max(np.abs(q_now - self.park[arm_id])) < self.s.motion.start_tolerance_rad:
            return
        checked_move(self.backend, self._model(arm_id, obstacle), self.park[arm_id], self.s.motion)
        self.events("parked", arm=arm_id)

    def _stop_everything(self) -> None:
        """Stop the arms, close the recordings and the log; never raises."""
        stop_all_arms(self.backend)
        self._stop_recording()

    def _stop_recording(self) -> None:
        """Close the recordings and the log if they run; never raises."""
        if self.recording:
            for camera in self.backend.cameras.values():
                with contextlib.suppress(Exception):
                    camera.stop_recording()
            self.recording = False
        if self.logging:
            with contextlib.suppress(Exception):
                self.backend.stop_joint_log()
            self.logging = False

    # -- stages -----------------------------------------------------------------------------------
    def localise_and_confirm(self) -> Decision:
        loc = Localiser(self.backend, self.rig, self.calibration, settings=self.s.localise, motion=self.s.motion,
                        margins=self.margins, events=self.events)
        self.progress("localise", 0.0, f"searching with {self.primary}")
        a = loc.localise(self.primary, stage="search")
        self.outcome.localisation[self.primary] = a
        if a.reason in ("outside_workspace", "too_tall"):
            b = LocalisationResult(self.secondary, None, "skipped", f"{self.primary} found the object but {a.detail}")
        else:
            self.progress("confirm", 0.5, f"confirming with {self.secondary}")
            b = loc.localise(self.secondary, hint=a.estimate, stage="confirm")
        self.outcome.localisation[self.secondary] = b

        def reobserve(arm_id: str, hint: ObjectEstimate) -> ObjectEstimate | None:
            result = LocalisationResult(arm_id, None)
            obs = loc.look_at_estimate(arm_id, result, hint, "reobserve")
            if obs is not None and obs.estimate is not None:
                loc.refine(arm_id, result, obs.estimate, True, "reobserve")
            else:
                loc.retreat(arm_id, hint)
            self.events("reobserved", arm=arm_id, **{k: v for k, v in result.to_record().items() if k != "arm"})
            return result.estimate

        confirm = self.s.confirm
        if self.calibration is not None and self.s.confirm_from_calibration:
            confirm, how = settings_from_calibration(confirm, {arm: c.residuals for arm, c in
                                                               self.calibration.arms.items()})
            self.events("confirm_thresholds", **how)
        decision = decide(a, b, confirm, reobserve)
        self.events("confirmation", **decision.to_record())
        self.outcome.decision = decision
        if not decision.ok:
            raise _Terminated(decision.reason, decision.message)
        return decision

    def plan(self, est: ObjectEstimate) -> dict[str, ViewPlan]:
        self.progress("plan", 0.0, "planning views")
        t0 = time.perf_counter()
        vs = self.s.viewpoints
        obstacle = envelope_obstacle(est.centre_m, est.radius_m, est.height_m, self.rig.table.height_m)
        planners = {}
        for arm_id in self.rig.arm_ids:
            settings = vs
            if self.s.derive_min_depth:
                intr = self.backend.cameras[arm_id].depth_intrinsics
                settings = dataclasses.replace(vs, min_depth_m=min_depth_from_intrinsics(intr))
            planners[arm_id] = ViewpointPlanner(self._model(arm_id, obstacle), est.centre_m, est.radius_m,
                                                est.height_m, settings, self.park[arm_id])
        plans: dict[str, ViewPlan] = {}
        if self.s.viewpoint_strategy == "coverage":
            cov = plan_coverage(planners, self.s.coverage)
            self.coverage_plan = cov
            self.tracker = CoverageTracker(cov)
            plans = dict(cov.plans)
            for arm_id, plan in plans.items():
                if len(plan.views) < self.s.min_required_views:  # too few: the orbit with its relaxations
                    plans[arm_id] = planners[arm_id].plan()
                    self.events("coverage_fallback", arm=arm_id, coverage_views=len(plan.views))
            self.events("coverage_plan", **cov.prediction.to_record())
            for message in cov.prediction.warnings:
                warnings.warn(DarpWarning(f"coverage: {message}"), stacklevel=2)
        else:
            plans = {arm_id: planner.plan() for arm_id, planner in planners.items()}
            self.coverage_plan = coverage_of_plans(planners, plans, self.s.coverage)  # achieved coverage only
            self.tracker = CoverageTracker(self.coverage_plan)
        if self.s.record_feasible_poses:
            self.feasible_poses = survey_feasible_poses(planners, plans, self.coverage_plan, self.s.coverage,
                                                        self.s.viewpoint_strategy == "coverage")
        for plan in plans.values():
            self.events("view_plan", **plan.to_record(),
                        views=[c.to_record() for c in plan.views],
                        rejected=[c.to_record() for c in plan.candidates if not c.ok])
        self.timings["planning_s"] = time.perf_counter() - t0
        self.outcome.plans = plans
        short = {a: len(p.views) for a, p in plans.items() if len(p.views) < self.s.min_required_views}
        if short:
            what = " | ".join(f"{a}: {feasibility_summary(plans[a])}" for a in short)
            raise _Terminated("too_few_views", f"too few feasible views (at least {self.s.min_required_views} "
                              f"needed) even after relaxing the orbit: {what}")
        return plans

    def record(self, plans: dict[str, ViewPlan], obstacle: Any) -> None:
        folder = self.episode.path
        total = sum(len(p.views) for p in plans.values())
        done = 0
        clock = self.backend.clock
        self.backend.start_joint_log(folder / ARM_POSES_FILE)
        self.logging = True
        self.events("joint_log_started")
        clock.sleep(self.s.log_lead_s)
        self.recording = True  # from here on an error stops (closes) every camera
        for arm_id, camera in self.backend.cameras.items():
            camera.start_recording(folder / f"cam{camera.serial}.bag")
            self.events("camera_started", arm=arm_id, serial=camera.serial)
        clock.sleep(self.s.camera_lead_s)
        t_start = clock.now()
        for n_arm, arm_id in enumerate(self.rig.arm_ids):
            model = self._model(arm_id, obstacle)
            t_arm = clock.now()
            for k, view in enumerate(list(plans[arm_id].views)):
                self.progress("record", done / max(total, 1), f"{arm_id} view {k + 1}/{len(plans[arm_id].views)}")
                took = checked_move(self.backend, model, view.joints_rad, self.s.motion)
                state = self.backend.arms[arm_id].read_state()
                self.events("view_reached", arm=arm_id, view=k, move_s=round(took, 3),
                            q_rad=[round(float(v), 5) for v in state.q_rad])
                if self.tracker is not None:
                    observe_live(self.backend, self.tracker, arm_id, model)
                done += 1
            if self.tracker is not None:
                visit_next_best_views(self.backend, self.tracker, arm_id, plans[arm_id], model,
                                      list(self.rig.arm_ids[n_arm + 1:]), clock.now() - t_arm, self.s.coverage,
                                      self.s.motion, self.events)
            checked_move(self.backend, model, self.park[arm_id], self.s.motion, settle=False)
            self.events("parked", arm=arm_id)
        self.progress("record", 1.0, "stopping the cameras")
        clock.sleep(self.s.camera_tail_s)
        for arm_id, camera in self.backend.cameras.items():
            camera.stop_recording()
            self.events("camera_stopped", arm=arm_id)
        self.recording = False
        self.timings["recording_s"] = clock.now() - t_start
        if self.tracker is not None:
            achieved = self.tracker.achieved()
            self.events("coverage_achieved", **achieved.to_record(),
                        next_best_views={a: len(v) for a, v in self.tracker.extra.items()})
            check, warning = self.tracker.envelope_check()
            self.events("envelope_check", **check, warning=warning)
            if warning is not None:
                warnings.warn(DarpWarning(warning), stacklevel=2)
        clock.sleep(self.s.log_tail_s)
        self.backend.stop_joint_log()
        self.logging = False
        self.events("joint_log_stopped")

    def envelope(self, est: ObjectEstimate | None, plans: dict[str, ViewPlan]) -> Envelope:
        loc = {arm: r.to_record() for arm, r in self.outcome.localisation.items()}
        record = {"searching_arm": self.primary, "confirming_arm": self.secondary,
                  "calibration": None if self.calibration is None else self.calibration.epoch,
                  "arms": loc, "confirmation": None if self.outcome.decision is None
                  else self.outcome.decision.to_record()}
        extra: dict[str, Any] = {"planning": {a: p.to_record() for a, p in plans.items()}} if plans else {}
        coverage = self.coverage_record()
        if coverage is not None:
            extra["coverage"] = coverage
            if self.feasible_poses is not None:  # for "completeness of seeable" (evaluation, with the true mesh)
                extra["coverage"]["feasible_poses"] = self.feasible_poses
        center: tuple[float, float, float] | None = None
        if est is not None:
            x, y, z = (float(v) for v in est.centre_m)
            center = (x, y, z)
        return Envelope(
            object_name=self.object_name or self.episode.name,
            center_m=center,
            radius_m=None if est is None else float(est.radius_m),
            height_m=None if est is None else float(est.height_m),
            standoff_m=None if est is None else standoff_for_radius(est.radius_m),
            park_q_rad={a: tuple(float(v) for v in q) for a, q in self.park.items()},
            view_q_rad={a: [tuple(float(v) for v in c.joints_rad) for c in p.views] for a, p in plans.items()},
            localisation=record, extra=extra)

    def coverage_record(self) -> dict[str, Any] | None:
        """Predicted and achieved coverage of the envelope's surface (None for the orbit strategy)."""
        return coverage_record(self.s.viewpoint_strategy, self.coverage_plan, self.tracker)

    # -- the procedure ----------------------------------------------------------------------------
    def _acquire(self) -> tuple[ObjectEstimate, dict[str, ViewPlan]]:
        """Park, localise and confirm, plan, record; raises _Terminated for an early end."""
        if self.calibration is not None:  # before any move: the clearance checks stand on the calibration
            problem = calibration_table_problem(self.rig, self.calibration, self.margins.table_m)
            if problem:
                raise _Terminated("calibration_inconsistent", problem)
        workspace = workspace_obstacle(self.rig)
        for arm_id in self.rig.arm_ids:
            self._park(arm_id, workspace)
        t0 = time.perf_counter()
        est = self.localise_and_confirm().estimate
        self.timings["localisation_s"] = time.perf_counter() - t0
        assert est is not None  # a decision without an estimate terminates
        self.estimate = est
        plans = self.plan(est)
        self.record(plans, envelope_obstacle(est.centre_m, est.radius_m, est.height_m, self.rig.table.height_m))
        return est, plans

    def _terminated(self, end: _Terminated, before_finalise: Callable[[Path], None] | None) -> SurveyOutcome:
        o = self.outcome
        self.events("terminated", reason=end.reason, message=end.message)
        o.envelope = self.envelope(self.estimate if end.reason == "too_few_views" else None, o.plans)
        write_envelope(self.episode.path / ENVELOPE_FILE, o.envelope)
        if before_finalise is not None:
            before_finalise(self.episode.path)
        o.status, o.reason, o.message, o.timings = "rejected", end.reason, end.message, self.timings
        o.folder = self.episode.reject(end.reason, f"survey terminated: {end.message}", extra={"timings": self.timings})
        self.progress("done", 1.0, f"rejected: {end.message}")
        return o

    def _park_after_fault(self, arm_id: str) -> str:
        """Park one arm not involved in the fault if its path is clear; says what happened."""
        est = self.estimate

        def model() -> ArmCollisionModel:
            obstacle = (workspace_obstacle(self.rig) if est is None
                        else envelope_obstacle(est.centre_m, est.radius_m, est.height_m, self.rig.table.height_m))
            return self._model(arm_id, obstacle)

        return park_after_fault(self.backend, arm_id, model, self.park[arm_id], self.s.motion, self.events)

    def _faulted(self, err: MotionFault, before_finalise: Callable[[Path], None] | None) -> SurveyOutcome:
        """Both arms stopped, recordings closed, safe arms parked, the episode rejected with the fault."""
        o, fault = self.outcome, err.fault
        stop_all_arms(self.backend)
        self.events("fault", message=fault.message, arms=list(fault.arms))
        self._stop_recording()
        where = [f"{a} left where it stopped (involved in the fault)" if a in fault.arms else self._park_after_fault(a)
                 for a in self.rig.arm_ids]
        message = f"motion stopped by a fault: {fault.message}; " + "; ".join(where)
        self.events("terminated", reason="fault", message=message)
        o.envelope = self.envelope(self.estimate, o.plans)
        write_envelope(self.episode.path / ENVELOPE_FILE, o.envelope)
        if before_finalise is not None:
            before_finalise(self.episode.path)
        o.status, o.reason, o.message, o.timings = "rejected", "fault", message, self.timings
        o.folder = self.episode.reject("fault", message,
                                       extra={"timings": self.timings, "fault_arms": list(fault.arms)})
        self.progress("done", 1.0, f"rejected: {message}")
        return o

    def _verified(self, est: ObjectEstimate, plans: dict[str, ViewPlan],
                  before_finalise: Callable[[Path], None] | None) -> SurveyOutcome:
        o = self.outcome
        o.envelope = self.envelope(est, plans)
        write_envelope(self.episode.path / ENVELOPE_FILE, o.envelope)
        self.progress("verify", 0.0, "verifying the capture")
        t0 = time.perf_counter()
        report = verify_survey(self.episode.path, self.rig, planned_views={a: p.q_views for a, p in plans.items()},
                               envelope=(est.centre_m, est.radius_m, est.height_m), calibration=self.calibration,
                               settings=self.s.verify)
        self.timings["verification_s"] = time.perf_counter() - t0
        o.report, o.timings = report, self.timings
        self.events("verification", passed=report.passed, summary=report.summary())
        if before_finalise is not None:
            before_finalise(self.episode.path)
        coverage = self.coverage_record()
        if report.passed:
            self.episode.write_json("verification.json", {**report.to_record(),
                                                          **({"coverage": coverage} if coverage else {})})
            o.folder = self.episode.accept(report.summary(), extra={"timings": self.timings})
            o.status, o.message = "accepted", report.summary()
        else:
            o.status, o.reason, o.message = "rejected", "verification", report.summary()
            o.folder = self.episode.reject("verification", f"verification failed: {report.summary()}",
                                           report.to_record(), extra={"timings": self.timings})
        self.progress("done", 1.0, o.status)
        return o

    def run(self, before_finalise: Callable[[Path], None] | None = None) -> SurveyOutcome:
        """The whole survey; ``before_finalise(folder)`` may add files before the folder's rename."""
        o = self.outcome
        try:
            try:
                est, plans = self._acquire()
            except _Terminated as end:
                return self._terminated(end, before_finalise)
            except MotionFault as fault:
                return self._faulted(fault, before_finalise)
            return self._verified(est, plans, before_finalise)
        except KeyboardInterrupt:
            self._stop_everything()
            o.folder = self.episode.mark_partial("interrupted", "the survey was interrupted (KeyboardInterrupt)")
            o.status, o.reason = "partial", "interrupted"
            raise
        except Exception as err:  # a backend or library error: leave a readable, marked partial episode
            self._stop_everything()
            o.folder = self.episode.mark_partial("error", f"{type(err).__name__}: {err}")
            o.status, o.reason, o.message = "partial", "error", str(err)
            raise AcquisitionError(f"survey stopped by an error ({err}); partial episode left in {o.folder}") from err


def run_survey(backend: RigBackend, rig: Rig, out: str | Path, name: str, *,
               calibration: Calibration | None = None, settings: SurveySettings | None = None,
               overwrite: bool = False, progress: ProgressFn | None = None, object_name: str | None = None,
               before_finalise: Callable[[Path], None] | None = None) -> SurveyOutcome:
    """Run one autonomous survey into ``<out>/<name>`` (see the module docstring).

    ``calibration``: the calibration used for live decisions (None: the rig's nominal transforms).
    ``before_finalise(folder)`` may add files (e.g. the twin's ``truth/``) before the folder is
    accepted or rejected. Returns the outcome; raises :class:`AcquisitionError` when an error stopped
    the survey (the partial folder is then left marked) and re-raises KeyboardInterrupt likewise.
    """
    episode = Episode(out, name, overwrite=overwrite, clock=backend.clock)
    runner = SurveyRunner(backend, rig, episode, calibration=calibration, settings=settings, progress=progress,
                          object_name=object_name)
    runner.events("survey_start", rig=rig.name, calibration=None if calibration is None else calibration.epoch,
                  searching_arm=runner.primary)
    return runner.run(before_finalise)


__all__ = ["ProgressFn", "SurveyOutcome", "SurveyRunner", "SurveySettings", "run_survey"]
