"""Small digital-twin surveys recorded by several test modules (each takes seconds to record)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from darp.kinematics.rig import load_rig
from darp.twin.objects.model import ObjectPlacement, make_object
from darp.twin.record import record_survey
from darp.twin.settings import TwinSettings
from darp.twin.waypoints import Waypoint, WaypointPlan, orbit_waypoints

# -- the twin-record tests' survey: one short move per arm -------------------------------------------
SMALL = {"width": 424, "height": 240}
PLACEMENT = ObjectPlacement(0.0, 0.02, 0.3)


def short_plan() -> WaypointPlan:
    """One short move per arm around its park pose (the camera keeps the table centre in view)."""
    park = load_rig().arms["arm110"].park_q_rad
    return WaypointPlan({
        "arm110": (Waypoint(park + np.array([0.15, 0.25, 0.0, -0.25, 0.0, 0.0]), 0.3),),
        "arm111": (Waypoint(park + np.array([-0.15, 0.2, 0.0, -0.2, 0.1, 0.0]), 0.3),),
    }, ("arm110", "arm111"))


def record(folder: Path, profile: str, seed: int, fps: int, workers: bool = False) -> Path:
    """The short survey of a cube at :data:`PLACEMENT`, 424x240, with the settings profile and seed given."""
    settings = TwinSettings.from_profile(profile, seed=seed).with_camera(fps=fps, **SMALL)
    record_survey(folder, short_plan(), make_object("cube"), PLACEMENT, settings=settings, camera_workers=workers)
    return folder


# -- the processing tests' survey: three views per arm --------------------------------------------------
TINY_PLACEMENT = ObjectPlacement(0.0, 0.0, 0.4)


def record_tiny_survey(folder: Path, name: str = "cube") -> Path:
    """Three views per arm around an object, 424x240 at 6 fps: about 25 simulated seconds."""
    obj = make_object(name)
    rig = load_rig()
    centre = (TINY_PLACEMENT.x_m, TINY_PLACEMENT.y_m, 0.5 * obj.height_m)
    plan = WaypointPlan({arm: tuple(orbit_waypoints(rig, arm, centre, 0.33, azimuths_deg=(-25.0, 0.0, 25.0),
                                                    elevation_deg=40.0, dwell_s=0.8))
                         for arm in ("arm110", "arm111")}, ("arm110", "arm111"))
    settings = TwinSettings.from_profile("realistic", seed=11).with_camera(fps=6, width=424, height=240)
    record_survey(folder, plan, obj, TINY_PLACEMENT, settings=settings)
    return folder
