"""The autonomous survey on the digital twin (realistic profile): accuracy, safety and clean endings.

Reduced frame rate and resolution (6 fps, 424x240) keep the surveys short; the full sweep over the ten
objects at ten placements each is ``studies/acquisition.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from darp.acquisition.survey import run_survey
from darp.backend import JointState
from darp.formats.arm_poses import read_arm_poses
from darp.formats.envelope import read_envelope
from darp.formats.realsense.recording import open_recording
from darp.geometry import min_enclosing_circle
from darp.kinematics.rig import load_rig
from darp.twin.objects.model import ObjectPlacement, RectRegion, make_object, random_placement, to_world
from darp.twin.rig_backend import TwinRig
from darp.twin.settings import TwinSettings

RIG = load_rig()


def twin(name: str | None, seed: int, placement: ObjectPlacement | None = None,
         check_placement: bool = True) -> tuple[TwinRig, object, object]:
    settings = TwinSettings.from_profile("realistic", seed=seed).with_camera(width=424, height=240, fps=6, imu=False)
    if name is None:
        return TwinRig(settings, rig=RIG), None, settings
    obj = make_object(name)
    if placement is None:
        ws = RIG.workspace
        region = RectRegion(ws.x_range_m[0], ws.x_range_m[1], ws.y_range_m[0], ws.y_range_m[1], 0.0)
        placement = random_placement(np.random.default_rng([seed, 0x9A1]), region, clearance_m=obj.radius_m)
    return TwinRig(settings, rig=RIG, obj=obj, placement=placement, check_placement=check_placement), obj, settings


@pytest.mark.slow
@pytest.mark.parametrize("name, seed", [("cup", 11), ("controller", 12), ("picture_frame", 13)])
def test_survey_is_accepted_accurate_and_collision_free(tmp_path: Path, name: str, seed: int) -> None:
    rig_backend, obj, settings = twin(name, seed)
    with rig_backend:
        outcome = run_survey(rig_backend, RIG, tmp_path, name, calibration=rig_backend.true_rig.calibration(settings))
        contacts = list(rig_backend.contact_events)
        placement = rig_backend.placement
    assert outcome.status == "accepted", outcome.message
    assert contacts == []  # the twin's contact monitor checks every arm during every move
    env = read_envelope(outcome.folder / "manip_envelope.json")
    vertices = np.asarray(to_world(obj, placement).vertices)
    axis, _ = min_enclosing_circle(vertices[:, :2])
    # The acceptance bound is 1 cm. The frame's smallest enclosing circle is fixed by its strut's foot,
    # which the arm facing the frame's front cannot see: that arm's centre is 1-2 cm off and the
    # average can reach 12 mm (this placement: 11.4 mm; the 100-survey benchmark: max 9.5 mm).
    tolerance = 0.0125 if name == "picture_frame" else 0.01
    assert np.linalg.norm(np.array(env.center_m[:2]) - axis) <= tolerance
    # the conservative envelope holds the whole object
    inside = np.hypot(*(vertices[:, :2] - np.array(env.center_m[:2])).T) <= env.radius_m + 2e-3
    assert inside.all() and vertices[:, 2].max() <= env.height_m + 3e-3
    assert all(len(v) >= 4 for v in env.view_q_rad.values())
    assert outcome.report.passed


def test_empty_table_ends_cleanly_on_the_twin(tmp_path: Path) -> None:
    rig_backend, _, _ = twin(None, 21)
    with rig_backend:
        outcome = run_survey(rig_backend, RIG, tmp_path, "empty")
        assert rig_backend.contact_events == []
    assert outcome.status == "rejected" and outcome.reason == "no_object"
    assert (tmp_path / "empty.rejected" / "REJECTED.txt").is_file()


def test_object_outside_the_workspace_ends_cleanly_on_the_twin(tmp_path: Path) -> None:
    """The twin refuses such a placement up front; unchecked, the survey (as on hardware) still ends cleanly."""
    rig_backend, _, _ = twin("mug", 22, ObjectPlacement(0.0, 0.38, 0.4), check_placement=False)
    with rig_backend:
        outcome = run_survey(rig_backend, RIG, tmp_path, "far")
    assert outcome.status == "rejected" and outcome.reason == "outside_workspace"
    assert "outside the workspace" in outcome.message


def test_disagreeing_arms_end_cleanly_on_the_twin(tmp_path: Path) -> None:
    rig_backend, _, _ = twin("mug", 23, ObjectPlacement(0.0, 0.05, 0.4))
    with rig_backend:
        arm = rig_backend.arms["arm111"]
        honest = arm.read_state
        bias = np.array([0.12, 0.0, 0.0, 0.0, 0.0, 0.0])  # a faulty joint-1 encoder on arm111

        def biased() -> JointState:
            s = honest()
            return JointState(s.time_s, s.q_rad + bias, s.qd_rad_s)

        arm.read_state = biased  # type: ignore[method-assign]
        outcome = run_survey(rig_backend, RIG, tmp_path, "biased")
        assert rig_backend.contact_events == []
    assert outcome.status == "rejected" and outcome.reason == "conflict"
    assert outcome.decision.steps[1]["centre_distance_m"] > 0.05


def test_interrupted_twin_survey_leaves_a_readable_partial_episode(tmp_path: Path) -> None:
    rig_backend, _, settings = twin("cube", 24, ObjectPlacement(0.05, -0.05, 0.3))

    def progress(phase: str, fraction: float, message: str) -> None:
        if phase == "record" and fraction > 0.3:
            raise KeyboardInterrupt

    with rig_backend, pytest.raises(KeyboardInterrupt):
        run_survey(rig_backend, RIG, tmp_path, "cube", calibration=rig_backend.true_rig.calibration(settings),
                   progress=progress)
    folder = tmp_path / "cube.partial"
    assert (folder / "PARTIAL.txt").read_text().startswith("partial: interrupted")
    log = read_arm_poses(folder / "arm_poses.csv")
    for arm in ("arm110", "arm111"):
        with open_recording(folder / f"cam{RIG.arms[arm].camera_serial}.bag") as rec:
            stamps = rec.timestamps_ms("depth") / 1e3
            assert len(stamps) > 10
        assert log.span(arm)[0] < stamps[0] and stamps[-1] <= log.span(arm)[1] + 0.2
