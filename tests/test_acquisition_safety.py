"""Placement and motion safety: invalid twin placements refused before anything moves (exit 2), and a contact
(twin) or a controller fault (hardware fakes) stops both arms, parks what is safe and rejects the episode."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from darp.acquisition.motion_check import ArmCollisionModel, MotionFault, checked_move
from darp.acquisition.survey import run_survey
from darp.backend import RigFault
from darp.cli._app import run
from darp.errors import TwinError
from darp.kinematics.rig import load_rig
from darp.twin.objects.model import ObjectPlacement, make_object
from darp.twin.placement import validate_placement
from helpers.acquisition_fakes import Cylinder, FakeRig

RIG = load_rig()
FAST = ["--fps", "6", "--resolution", "424x240", "--quiet"]


@pytest.mark.parametrize("placement, message", [
    ("0.69,0,0", "the object is inside arm111's base"),  # the issue's cup inside arm111's base
    ("-0.62,0.02,0", "mm from arm110's shoulder_motor"),
    ("1.5,0,0", "is not on the table"),
    ("0,0.44,0", "is not on the table"),  # centre on the table, footprint over its edge
    # non-finite values are refused where the option enters (issue 32), before any placement check
    ("inf,0,0", "'--placement': expected finite x,y within +-10 m and yaw_deg within +-360, got 'inf,0,0'"),
    ("0,nan,0", "'--placement': expected finite x,y within +-10 m and yaw_deg within +-360, got '0,nan,0'"),
    ("0,0,inf", "'--placement': expected finite x,y within +-10 m and yaw_deg within +-360, got '0,0,inf'"),
    ("0,0.37,0", "outside the reachable workspace"),
])
def test_invalid_placements_are_refused_before_anything_moves(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                              placement: str, message: str) -> None:
    argv = ["collect", "s", "--twin", "--object", "cup", f"--placement={placement}", "--out", str(tmp_path), *FAST]
    assert run(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("darp: error:") and message in err and "\n" not in err
    assert not any(tmp_path.iterdir())  # no episode folder: nothing was built, nothing moved


def test_a_placement_just_inside_the_clearance_names_a_distance_below_it() -> None:
    # the mushroom-like mesh of studies/safety.py at 19.6 mm from arm111's shoulder motor read "20 mm from"
    import re

    cup = make_object("cup")
    base = RIG.arms["arm111"].T_world_base[0, 3]
    def near(x: float) -> bool:
        return any(w in _refusal(cup, x) for w in ("mm from", "inside"))

    clear, touching = base - 0.3, base  # bisect for the placement just inside the 20 mm clearance
    assert not near(clear) and near(touching)
    for _ in range(20):
        mid = 0.5 * (clear + touching)
        clear, touching = (clear, mid) if near(mid) else (mid, touching)
    x = touching
    message = _refusal(cup, x)
    distance = float(re.search(r"is ([0-9.]+) mm from", message).group(1))  # type: ignore[union-attr]
    assert 19.0 < distance < 20.0 and "must keep 20 mm" in message


def _refusal(obj, x: float) -> str:  # type: ignore[no-untyped-def]
    try:
        validate_placement(RIG, obj.radius_m, obj.height_m, ObjectPlacement(x, 0.0, 0.0))
    except TwinError as err:
        return str(err)
    return ""


def test_valid_placements_pass_and_a_tall_object_is_refused() -> None:
    cup = make_object("cup")
    for x, y in ((0.0, 0.0), (0.2, 0.25), (-0.2, -0.25)):
        validate_placement(RIG, cup.radius_m, cup.height_m, ObjectPlacement(x, y, 0.3))
    with pytest.raises(TwinError, match="taller than the workspace's 300 mm"):
        validate_placement(RIG, 0.05, 0.35, ObjectPlacement(0.0, 0.0, 0.0))


# -- contact stop on the twin ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def contact_twin():  # type: ignore[no-untyped-def]
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    settings = TwinSettings.from_profile("ideal", seed=5).with_camera(width=424, height=240, fps=6, imu=False)
    twin = TwinRig(settings, rig=RIG, obj=make_object("cup"), placement=ObjectPlacement(-0.2, 0.0, 0.0))
    with twin:
        yield twin


def test_a_contact_during_motion_stops_both_arms_and_refuses_further_moves(contact_twin) -> None:  # type: ignore[no-untyped-def]
    twin = contact_twin
    into_object = np.array([0.0, 2.4, -1.5, 0.0, 0.0, 0.0])  # arm110's wrist through the cup
    twin.arms["arm110"].move_to(into_object)
    twin.arms["arm111"].move_to(np.array(RIG.arms["arm111"].park_q_rad) + [2.5, 0, 0, 0, 0, 0])
    assert not twin.wait_until_still("arm110", timeout_s=20.0)  # ended by the fault, not by arriving
    fault = twin.fault()
    assert fault is not None and "arm110" in fault.arms and "contact during motion" in fault.message
    twin.clock.sleep(2.0)
    assert not any(arm.is_moving() for arm in twin.arms.values())  # both arms stopped at once
    q110 = twin.arms["arm110"].read_state().q_rad
    assert np.max(np.abs(q110 - into_object)) > 0.05  # never carried on to its target
    q111 = twin.arms["arm111"].read_state().q_rad
    assert abs(q111[0] - RIG.arms["arm111"].park_q_rad[0]) < 2.4  # arm111 stopped short as well
    n_contacts = len(twin.contact_events)
    ticks = {e.time_s for e in twin.contact_events}
    assert 0 < len(ticks) <= 45  # monitor ticks (60 Hz) while braking at 2 rad/s^2 and settling, not thousands
    model = ArmCollisionModel(RIG, "arm111")
    with pytest.raises(MotionFault, match="contact during motion"):
        checked_move(twin, model, np.array(RIG.arms["arm111"].park_q_rad))
    twin.clock.sleep(1.0)
    assert len(twin.contact_events) == n_contacts and not twin.arms["arm111"].is_moving()  # nothing moved


# -- fault during a survey (analytic fake rig) -------------------------------------------------------------
class FaultingRig(FakeRig):
    """Reports a fault of ``arm`` once it has made ``after_moves`` moves during the recording."""

    def __init__(self, arm: str, after_moves: int) -> None:
        super().__init__([Cylinder(0.05, 0.08, 0.05, 0.10)])
        self.fault_arm, self.after_moves = arm, after_moves
        self.moves_at_fault: dict[str, int] | None = None

    def fault(self) -> RigFault | None:
        arm = self.arms[self.fault_arm]
        recording = self.cameras["arm110"].writer is not None
        if self.moves_at_fault is None and recording and len(arm.moves) >= self.after_moves:
            self.moves_at_fault = {a: len(x.moves) for a, x in self.arms.items()}
        if self.moves_at_fault is None:
            return None
        message = f"{self.fault_arm}: the controller left joint control (collision protection)"
        return RigFault(message, (self.fault_arm,))


def test_a_fault_during_the_survey_stops_parks_the_other_arm_and_rejects(tmp_path: Path) -> None:
    from darp.acquisition.episode import read_events

    rig = FaultingRig("arm111", after_moves=3)
    outcome = run_survey(rig, rig.rig, tmp_path, "s")
    assert outcome.status == "rejected" and outcome.reason == "fault"
    assert rig.moves_at_fault is not None
    assert all(a.stops >= 1 for a in rig.arms.values())  # both arms told to stop
    # arm111 (faulted) was not commanded again; arm110 (already parked before its turn ended) stays parked
    assert len(rig.arms["arm111"].moves) == rig.moves_at_fault["arm111"]
    folder = tmp_path / "s.rejected"
    text = (folder / "REJECTED.txt").read_text()
    assert text.startswith("rejected: fault") and "collision protection" in text
    assert "arm111 left where it stopped (involved in the fault)" in text and "arm110 parked" in text
    assert all(c.writer is None for c in rig.cameras.values()) and rig.log is None  # files closed
    kinds = [e["kind"] for e in read_events(folder)]
    assert "fault" in kinds and kinds[-1] == "episode_rejected"


def test_a_fault_of_the_moving_arm_parks_the_other_when_its_path_is_clear(tmp_path: Path) -> None:
    rig = FaultingRig("arm110", after_moves=4)  # arm110 records first; arm111 is parked meanwhile
    outcome = run_survey(rig, rig.rig, tmp_path, "s")
    assert outcome.reason == "fault"
    assert len(rig.arms["arm110"].moves) == rig.moves_at_fault["arm110"]
    assert len(rig.arms["arm111"].moves) == rig.moves_at_fault["arm111"]  # already parked: no move needed
    assert "arm111 parked" in outcome.message


# -- the same guard on the hardware path (fake Z1 controllers) ---------------------------------------------
def test_a_controller_fault_on_hardware_stops_both_arms_and_raises(fake_z1, fake_rs, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from darp.hardware.rig import HardwareRig
    from darp.hardware.settings import HardwareSettings
    from darp.hardware.z1_arm import Z1Arm

    park = np.array(RIG.arms["arm110"].park_q_rad)
    settings = HardwareSettings.defaults(RIG.arm_ids)
    fake_z1.reset(multi_arm=True)
    controllers = {a: fake_z1.add_controller(park, port=p) for a, p in zip(RIG.arm_ids, (8071, 8073), strict=True)}
    arms = {a: Z1Arm(a, settings.arms[a], motion=settings.motion) for a in RIG.arm_ids}
    stops = dict.fromkeys(RIG.arm_ids, 0)
    for a, arm in arms.items():
        original = arm.stop

        def counted(a: str = a, original=original) -> None:  # type: ignore[no-untyped-def]
            stops[a] += 1
            original()

        arm.stop = counted  # type: ignore[method-assign]
    rig = HardwareRig(RIG, settings, arms=arms, cameras={})
    rig.connect(timeout_s=2.0)
    try:
        assert rig.fault() is None
        target = park + np.array([0.8, 0.0, 0.0, 0.0, 0.0, 0.0])
        threading.Timer(0.3, controllers["arm110"].trip).start()  # collision protection mid-move
        with pytest.raises(MotionFault, match="arm110.*left joint control") as err:
            checked_move(rig, ArmCollisionModel(RIG, "arm110"), target)
        assert err.value.fault.arms == ("arm110",)
        assert stops["arm111"] >= 1  # the other arm was told to stop at once
        with pytest.raises(MotionFault):  # no further move is commanded
            checked_move(rig, ArmCollisionModel(RIG, "arm111"), park)
    finally:
        rig.close()


@pytest.mark.parametrize(("values", "named"), [((float("inf"), 0.0, 0.0), "x=inf"), ((0.0, float("nan"), 0.0), "y=nan"),
                                                ((0.0, 0.0, float("inf")), "yaw=inf")])
def test_the_library_refuses_non_finite_placements_too(values: tuple[float, float, float], named: str) -> None:
    """Callers that bypass the CLI (batches, scripts) get the same refusal, naming the value."""
    with pytest.raises(TwinError, match=f"placement must be finite numbers, got {named}"):
        validate_placement(RIG, 0.04, 0.1, ObjectPlacement(*values))
