"""darp.twin: the digital twin, a simulated rig behind the backend interface that writes byte-compatible surveys
plus their ground truth.

Settings and error profiles (:mod:`.settings`), the MuJoCo world (:mod:`.world`), simulated arms with kinematic
errors (:mod:`.arm_sim`, :mod:`.arm_errors`) and clock (:mod:`.clock`), the rig backend (:mod:`.rig_backend`;
a twin that mirrors a real rig in :mod:`.mirror`), object placement (:mod:`.placement`), waypoint plans
(:mod:`.waypoints`), recording a survey with its ``truth/`` folder (:mod:`.record`, :mod:`.truth`), calibration
captures (:mod:`.calib_capture`); the camera and the objects are subpackages (:mod:`.camera`, :mod:`.objects`).
MuJoCo loads only when a world is built.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".settings": ("TwinSettings", "paper_profile"),
    ".world": ("TwinWorld",),
    ".rig_backend": ("TwinRig",),
    ".arm_sim": ("SimArm",),
    ".clock": ("SimClock",),
    ".mirror": ("MirrorTwin",),
    ".placement": ("seeded_placements", "validate_placement"),
    ".waypoints": ("WaypointPlan", "load_waypoints", "orbit_waypoints", "save_waypoints"),
    ".record": ("RecordResult", "record_survey"),
    ".truth": ("TrueRig", "draw_true_rig", "write_truth"),
    ".calib_capture": ("capture_twin",),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.twin.arm_sim import SimArm
    from darp.twin.calib_capture import capture_twin
    from darp.twin.clock import SimClock
    from darp.twin.mirror import MirrorTwin
    from darp.twin.placement import seeded_placements, validate_placement
    from darp.twin.record import RecordResult, record_survey
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings, paper_profile
    from darp.twin.truth import TrueRig, draw_true_rig, write_truth
    from darp.twin.waypoints import WaypointPlan, load_waypoints, orbit_waypoints, save_waypoints
    from darp.twin.world import TwinWorld

__all__ = [
    "MirrorTwin",
    "RecordResult",
    "SimArm",
    "SimClock",
    "TrueRig",
    "TwinRig",
    "TwinSettings",
    "TwinWorld",
    "WaypointPlan",
    "capture_twin",
    "draw_true_rig",
    "load_waypoints",
    "orbit_waypoints",
    "paper_profile",
    "record_survey",
    "save_waypoints",
    "seeded_placements",
    "validate_placement",
    "write_truth",
]
