"""darp.acquisition: autonomous object surveys on any rig backend (the twin or the real rig).

Localise an object placed anywhere (:mod:`.localise`, depth estimates in :mod:`.estimate`), confirm it from both arms
(:mod:`.confirm`), plan the views (:mod:`.coverage`: the coverage model; :mod:`.coverage_plan`: coverage planning;
:mod:`.coverage_track`: achieved coverage and next best views; :mod:`.viewpoints`: candidate checks and the fixed orbit;
:mod:`.tour`: the views' order), move safely (:mod:`.motion_check`: clearances, fault stop), record the survey
(:mod:`.survey`, its event log in :mod:`.episode`) and verify it (:mod:`.verify`). Everything here drives a
:class:`darp.backend.RigBackend`; nothing knows which rig it is.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".survey": ("SurveySettings", "SurveyOutcome", "SurveyRunner", "run_survey"),
    ".verify": ("VerifySettings", "VerificationReport", "verify_survey"),
    ".localise": ("Localiser", "LocalisationResult"),
    ".estimate": ("LocaliseSettings", "ObjectEstimate", "estimate_from_depth"),
    ".confirm": ("ConfirmSettings", "Decision", "decide"),
    ".coverage": ("CoverageSettings",),
    ".coverage_plan": ("CoveragePlan", "plan_coverage"),
    ".coverage_track": ("CoverageTracker",),
    ".viewpoints": ("ViewpointSettings", "ViewpointPlanner", "ViewPlan", "Candidate"),
    ".motion_check": (
        "MotionSettings", "ClearanceMargins", "UnsafeMoveError", "MotionFault", "checked_move", "stop_all_arms"
    ),
    ".episode": ("Episode", "EventLog", "read_events"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.acquisition.confirm import ConfirmSettings, Decision, decide
    from darp.acquisition.coverage import CoverageSettings
    from darp.acquisition.coverage_plan import CoveragePlan, plan_coverage
    from darp.acquisition.coverage_track import CoverageTracker
    from darp.acquisition.episode import Episode, EventLog, read_events
    from darp.acquisition.estimate import LocaliseSettings, ObjectEstimate, estimate_from_depth
    from darp.acquisition.localise import LocalisationResult, Localiser
    from darp.acquisition.motion_check import (
        ClearanceMargins,
        MotionFault,
        MotionSettings,
        UnsafeMoveError,
        checked_move,
        stop_all_arms,
    )
    from darp.acquisition.survey import SurveyOutcome, SurveyRunner, SurveySettings, run_survey
    from darp.acquisition.verify import VerificationReport, VerifySettings, verify_survey
    from darp.acquisition.viewpoints import Candidate, ViewPlan, ViewpointPlanner, ViewpointSettings

__all__ = [
    "Candidate",
    "ClearanceMargins",
    "ConfirmSettings",
    "CoveragePlan",
    "CoverageSettings",
    "CoverageTracker",
    "Decision",
    "Episode",
    "EventLog",
    "LocalisationResult",
    "LocaliseSettings",
    "Localiser",
    "MotionFault",
    "MotionSettings",
    "ObjectEstimate",
    "SurveyOutcome",
    "SurveyRunner",
    "SurveySettings",
    "UnsafeMoveError",
    "VerificationReport",
    "VerifySettings",
    "ViewPlan",
    "ViewpointPlanner",
    "ViewpointSettings",
    "checked_move",
    "decide",
    "estimate_from_depth",
    "plan_coverage",
    "read_events",
    "run_survey",
    "stop_all_arms",
    "verify_survey",
]
