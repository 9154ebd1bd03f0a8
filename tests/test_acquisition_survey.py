"""The survey runner end to end on the analytic fake rig: accepted, terminated, interrupted, rejected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from darp.acquisition.confirm import ConfirmSettings
from darp.acquisition.episode import read_events
from darp.acquisition.survey import SurveySettings, run_survey
from darp.acquisition.viewpoints import ViewpointSettings
from darp.errors import AcquisitionError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.envelope import read_envelope
from darp.formats.realsense.recording import open_recording
from helpers.acquisition_fakes import Cylinder, FakeRig

OBJECT = Cylinder(0.05, 0.08, 0.05, 0.10)


@pytest.fixture(scope="module")
def accepted(tmp_path_factory: pytest.TempPathFactory) -> tuple[FakeRig, object, list[tuple[str, float, float]]]:
    rig = FakeRig([OBJECT])
    seen: list[tuple[str, float, float]] = []
    outcome = run_survey(rig, rig.rig, tmp_path_factory.mktemp("out"), "cyl",
                         progress=lambda phase, fraction, message: seen.append((phase, fraction, rig.clock.now())))
    return rig, outcome, seen


def test_accepted_survey_writes_the_darp_folder(accepted: tuple) -> None:
    rig, outcome, _ = accepted
    assert outcome.status == "accepted", outcome.message
    folder = outcome.folder
    assert folder.name == "cyl" and not folder.with_name("cyl.partial").exists()
    names = {p.name for p in folder.iterdir()}
    assert {"cam348522076490.bag", "cam405622074504.bag", "arm_poses.csv", "manip_envelope.json",
            "events.jsonl", "verification.json", "outcome.json"} <= names
    env = read_envelope(folder / "manip_envelope.json")
    assert np.linalg.norm(np.array(env.center_m[:2]) - [OBJECT.x_m, OBJECT.y_m]) < 0.003
    assert env.radius_m == pytest.approx(OBJECT.radius_m, abs=0.004)
    assert env.height_m == pytest.approx(OBJECT.height_m, abs=0.003)
    assert env.standoff_m == pytest.approx(max(0.30 + env.radius_m, 4.5 * env.radius_m))
    for arm in ("arm110", "arm111"):
        np.testing.assert_allclose(env.park_q_rad[arm], rig.rig.arms[arm].park_q_rad)
        planned = outcome.plans[arm].q_views
        assert len(env.view_q_rad[arm]) == len(planned) >= 4
        # every planned view was commanded, in order, between leaving and returning to park
        moves = np.array(rig.arms[arm].moves)
        for q in planned:
            assert np.min(np.max(np.abs(moves - q), axis=1)) < 1e-12
    loc = env.localisation
    assert loc["searching_arm"] == "arm110" and loc["confirmation"]["status"] == "consistent"
    assert set(loc["arms"]) == {"arm110", "arm111"}


def test_the_envelope_records_the_feasible_camera_poses(accepted: tuple) -> None:
    """For "completeness of the seeable surface": the coverage grid's feasible poses and the planned views,
    per arm, as T_world_cam's top rows (the planned views' poses among them)."""
    from darp.acquisition.motion_check import ArmCollisionModel

    rig, outcome, _ = accepted
    env = read_envelope(outcome.folder / "manip_envelope.json")
    poses = env.extra["coverage"]["feasible_poses"]
    assert set(poses) == {"arm110", "arm111"}
    for arm, rows in poses.items():
        T = np.array(rows).reshape(-1, 3, 4)
        assert len(T) > len(outcome.plans[arm].views) >= 4  # the grid adds poses to the orbit's views
        np.testing.assert_allclose(np.einsum("nij,nkj->nik", T[:, :, :3], T[:, :, :3]),
                                   np.broadcast_to(np.eye(3), (len(T), 3, 3)), atol=1e-5)
        # every camera looks at the object (its optical axis passes within the envelope's radius of the centre)
        to_centre = np.array(env.center_m) - T[:, :, 3]
        along = np.einsum("ni,ni->n", to_centre, T[:, :, 2])
        miss = np.linalg.norm(to_centre - along[:, None] * T[:, :, 2], axis=1)
        assert np.all(along > 0.15) and np.median(miss) < env.radius_m
        model = ArmCollisionModel(rig.rig, arm)
        for view in outcome.plans[arm].views:
            planned = model.T_world_cam(view.joints_rad)[:3].reshape(-1)
            assert np.min(np.max(np.abs(T.reshape(len(T), -1) - planned), axis=1)) < 1e-5


def test_one_arm_moves_at_a_time_and_the_log_spans_the_cameras(accepted: tuple) -> None:
    rig, outcome, _ = accepted
    log = read_arm_poses(outcome.folder / "arm_poses.csv")
    a, b = rig.arms["arm110"].intervals, rig.arms["arm111"].intervals
    assert len(a) > 5 and len(b) > 5
    for s0, e0 in a:  # no move of one arm overlaps a move of the other
        assert all(e0 <= s1 or e1 <= s0 for s1, e1 in b)
    for arm, other in (("arm110", "arm111"), ("arm111", "arm110")):
        # in the log too: while one arm moves, the other sits at park (rows at a hand-over excepted)
        q, q_other = log.joints(arm), log.joints(other)
        moving = np.flatnonzero(np.any(np.abs(np.diff(q, axis=0)) > 1e-9, axis=1)) + 1
        away = np.max(np.abs(q_other[moving] - rig.rig.arms[other].park_q_rad), axis=1) > 1e-9
        assert len(moving) > 20 and away.sum() <= 2
    for arm, serial in (("arm110", "348522076490"), ("arm111", "405622074504")):
        with open_recording(outcome.folder / f"cam{serial}.bag") as rec:
            stamps = rec.timestamps_ms("depth") / 1e3
            assert rec.frame_count("depth") > 50
        first, last = log.span(arm)
        assert first < stamps[0] and stamps[-1] < last
    assert all(c.passed for c in outcome.report.checks)
    assert outcome.report.check("views.arm110").values["reached"] == len(outcome.plans["arm110"].views)


def test_events_and_progress_follow_the_procedure(accepted: tuple) -> None:
    _, outcome, seen = accepted
    kinds = [e["kind"] for e in read_events(outcome.folder)]
    order = ["episode_start", "survey_start", "localise_start", "confirmation", "view_plan", "joint_log_started",
             "camera_started", "view_reached", "camera_stopped", "joint_log_stopped", "verification",
             "episode_accepted"]
    positions = [kinds.index(k) for k in order]
    assert positions == sorted(positions)
    events = read_events(outcome.folder)
    assert all("rig_time_s" in e and "wall_time_s" in e for e in events)
    rig_times = [e["rig_time_s"] for e in events]
    assert rig_times == sorted(rig_times)
    phases = [p for p, _, _ in seen]
    assert phases[0] == "localise" and phases[-1] == "done"
    assert list(dict.fromkeys(phases)) == ["localise", "confirm", "plan", "record", "verify", "done"]


def test_same_inputs_give_the_same_survey(accepted: tuple, tmp_path: Path) -> None:
    _, outcome, _ = accepted
    rig = FakeRig([OBJECT])
    again = run_survey(rig, rig.rig, tmp_path, "cyl")
    for name in ("manip_envelope.json", "arm_poses.csv", "cam348522076490.bag", "cam405622074504.bag"):
        assert (again.folder / name).read_bytes() == (outcome.folder / name).read_bytes(), name


def test_existing_survey_is_not_overwritten(accepted: tuple) -> None:
    _, outcome, _ = accepted
    rig = FakeRig([OBJECT])
    with pytest.raises(AcquisitionError, match="already exists"):
        run_survey(rig, rig.rig, outcome.folder.parent, "cyl")
    assert (outcome.folder / "arm_poses.csv").is_file()


def _rejected(tmp_path: Path, rig: FakeRig, settings: SurveySettings | None = None) -> object:
    outcome = run_survey(rig, rig.rig, tmp_path, "s", settings=settings)
    assert outcome.status == "rejected"
    assert outcome.folder == tmp_path / "s.rejected"
    assert (outcome.folder / "REJECTED.txt").read_text().startswith(f"rejected: {outcome.reason}")
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.partial").exists()
    return outcome


def test_empty_table_ends_cleanly(tmp_path: Path) -> None:
    rig = FakeRig([])
    outcome = _rejected(tmp_path, rig)
    assert outcome.reason == "no_object"
    assert "no object" in outcome.message
    assert not list(outcome.folder.glob("*.bag"))
    env = read_envelope(outcome.folder / "manip_envelope.json")
    assert env.center_m is None and env.localisation["confirmation"]["status"] == "terminated"
    for arm in rig.arms.values():  # back at park
        np.testing.assert_allclose(arm.true_q(), rig.rig.arms[arm.arm_id].park_q_rad, atol=1e-12)


def test_object_outside_the_workspace_ends_cleanly(tmp_path: Path) -> None:
    outcome = _rejected(tmp_path, FakeRig([Cylinder(0.0, 0.36, 0.04, 0.1)]))
    assert outcome.reason == "outside_workspace"
    assert "outside the workspace" in outcome.message
    assert outcome.localisation["arm111"].reason == "skipped"


def test_disagreeing_arms_end_cleanly(tmp_path: Path) -> None:
    # arm111's encoder reports joint 1 off by 7 deg: its estimate lands ~9 cm away, and it keeps
    # re-confirming itself, so the two arms cannot agree.
    rig = FakeRig([OBJECT], biases={"arm111": np.array([0.12, 0, 0, 0, 0, 0])})
    outcome = _rejected(tmp_path, rig)
    assert outcome.reason == "conflict"
    assert "each re-confirms its own estimate" in outcome.message
    steps = [s["step"] for s in outcome.decision.steps]
    assert steps == ["estimates", "consistency", "reobserve"]
    terminated = _rejected(tmp_path / "t", FakeRig([OBJECT], biases={"arm111": np.array([0.12, 0, 0, 0, 0, 0])}),
                           SurveySettings(confirm=ConfirmSettings(conflict_policy="terminate")))
    assert terminated.reason == "conflict" and "not averaged" in terminated.message


def test_too_few_views_names_why_each_candidate_was_refused(tmp_path: Path) -> None:
    # A minimum depth no view meets: both arms find the object, then every candidate view is refused.
    settings = SurveySettings(viewpoints=ViewpointSettings(min_depth_m=1.5), derive_min_depth=False)
    outcome = _rejected(tmp_path, FakeRig([OBJECT]), settings)
    assert outcome.reason == "too_few_views"
    assert outcome.message.startswith("too few feasible views (at least 4 needed) even after relaxing the orbit: "
                                      "arm110: 0 feasible of ")
    for arm_id, plan in outcome.plans.items():
        counts = {r: sum(1 for c in plan.candidates if c.reason == r) for r in ("ik", "min_depth")}
        assert counts["min_depth"] > 0 and sum(counts.values()) == len(plan.candidates) and not plan.views
        ranked = sorted(counts.items(), key=lambda kv: -kv[1])  # the most frequent reason first
        words = {"ik": "IK", "min_depth": "minimum depth"}
        listed = ", ".join(f"{n} {words[r]}" for r, n in ranked if n)
        n, tried = len(plan.candidates), len(plan.attempts)
        assert f"{arm_id}: 0 feasible of {n} candidates (the nominal orbit, best of {tried} tried): " \
            f"{listed}; e.g. {words[ranked[0][0]]}: " in outcome.message
        if ranked[1][1]:  # an example of the second reason too
            assert f"; {words[ranked[1][0]]}: " in outcome.message.split(f"{arm_id}: ")[1]
    assert "(minimum depth 1.500 m)" in outcome.message  # an example refusal's detail
    assert "\n" not in outcome.message
    assert outcome.message in (outcome.folder / "REJECTED.txt").read_text()


def test_a_calibration_with_a_base_off_the_table_ends_before_any_move(tmp_path: Path) -> None:
    rig = FakeRig([OBJECT])
    cal = rig.rig.nominal_calibration()
    T = np.array(cal.arms["arm111"].T_world_base, dtype=float)
    T[2, 3] -= 0.045
    cal.arms["arm111"].T_world_base = T
    outcome = run_survey(rig, rig.rig, tmp_path, "s", calibration=cal)
    assert outcome.status == "rejected" and outcome.reason == "calibration_inconsistent"
    assert "the shoulder of arm111 45 mm lower than the rig file" in outcome.message
    kinds = [e["kind"] for e in read_events(outcome.folder / "events.jsonl")]
    assert "localise_start" not in kinds and "parked" not in kinds
    for arm in rig.arms.values():  # never moved
        np.testing.assert_allclose(arm.true_q(), rig.rig.arms[arm.arm_id].park_q_rad, atol=1e-12)


def test_a_one_off_bad_estimate_falls_back_to_the_reconfirmed_one(tmp_path: Path) -> None:
    rig = FakeRig([OBJECT])
    ghost = Cylinder(OBJECT.x_m + 0.12, OBJECT.y_m, OBJECT.radius_m, OBJECT.height_m)
    rig.cameras["arm111"].glitch = lambda n: ghost if n < 6 else None  # its first looks see a ghost
    outcome = run_survey(rig, rig.rig, tmp_path, "s")
    assert outcome.decision.status == "fallback" and outcome.decision.reason == "reconfirmed_primary"
    assert outcome.status == "accepted", outcome.message
    env = read_envelope(outcome.folder / "manip_envelope.json")
    assert np.linalg.norm(np.array(env.center_m[:2]) - [OBJECT.x_m, OBJECT.y_m]) < 0.005


def test_interrupted_survey_leaves_a_marked_readable_partial_episode(tmp_path: Path) -> None:
    rig = FakeRig([OBJECT])
    arm = rig.arms["arm111"]

    def interrupt(n_moves: int) -> None:
        if rig.cameras["arm110"].writer is not None and n_moves >= 3:  # a few views into arm111's turn
            raise KeyboardInterrupt

    arm.on_move = interrupt
    with pytest.raises(KeyboardInterrupt):
        run_survey(rig, rig.rig, tmp_path, "s")
    folder = tmp_path / "s.partial"
    assert (folder / "PARTIAL.txt").read_text().startswith("partial: interrupted")
    assert not (tmp_path / "s").exists()
    log = read_arm_poses(folder / "arm_poses.csv")
    assert log.rows("arm110") > 100
    for serial in ("348522076490", "405622074504"):
        with open_recording(folder / f"cam{serial}.bag") as rec:
            assert rec.frame_count("depth") > 10
    assert all(a.stops >= 1 for a in rig.arms.values())  # both arms told to stop
    assert all(c.writer is None for c in rig.cameras.values()) and rig.log is None
    kinds = [e["kind"] for e in read_events(folder)]
    assert kinds[-1] == "episode_partial"


def test_backend_error_leaves_a_partial_episode_and_raises(tmp_path: Path) -> None:
    rig = FakeRig([OBJECT])

    def broken(path: Path) -> None:
        raise RuntimeError("USB camera disconnected")

    rig.cameras["arm111"].start_recording = broken  # type: ignore[method-assign]
    with pytest.raises(AcquisitionError, match="USB camera disconnected") as err:
        run_survey(rig, rig.rig, tmp_path, "s")
    assert "s.partial" in str(err.value)
    folder = tmp_path / "s.partial"
    assert "RuntimeError: USB camera disconnected" in (folder / "PARTIAL.txt").read_text()
    assert read_arm_poses(folder / "arm_poses.csv").n_rows > 0  # the log was closed properly
    with open_recording(folder / "cam348522076490.bag") as rec:  # the camera that did start
        assert rec.frame_count("depth") >= 0


def test_dropped_frames_fail_verification_and_reject(tmp_path: Path) -> None:
    rig = FakeRig([OBJECT])
    rig.cameras["arm110"].drop_every = 10
    outcome = _rejected(tmp_path, rig)
    assert outcome.reason == "verification"
    failed = {c.name for c in outcome.report.failures}
    assert "dropped.arm110" in failed and "dropped.arm111" not in failed
    assert (outcome.folder / "verification.json").is_file()
    assert "failed check dropped.arm110" in (outcome.folder / "REJECTED.txt").read_text()
    assert (outcome.folder / "arm_poses.csv").is_file()  # the rejected capture is kept


@pytest.mark.slow
@pytest.mark.parametrize("fraction", [0.0, 1.0])
def test_next_best_views_stay_within_their_time_budget(tmp_path: Path, fraction: float) -> None:
    """Every sample stays a target (``nbv_support_views`` above any count), so only the budget or the view cap
    stops the loop: no view at 0, some at 1, and their rig time is within the budget plus one view."""
    from dataclasses import replace

    from darp.acquisition.coverage import CoverageSettings

    cov = replace(CoverageSettings(), nbv_support_views=1000, nbv_min_gain=0.0, nbv_max_views=4,
                  nbv_time_fraction=fraction)
    rig = FakeRig([OBJECT])
    outcome = run_survey(rig, rig.rig, tmp_path, "cyl", settings=SurveySettings(viewpoint_strategy="coverage",
                                                                                 coverage=cov))
    assert outcome.status == "accepted", outcome.message
    events = read_events(outcome.folder)
    record = read_envelope(outcome.folder / "manip_envelope.json").extra["coverage"]
    added, spent, budget = (record[k] for k in ("next_best_views", "next_best_views_s", "next_best_views_budget_s"))
    longest = max(e["move_s"] for e in events if e["kind"] in ("view_reached", "next_best_view"))
    for arm in rig.rig.arm_ids:
        stopped = [e for e in events if e["kind"] == "next_best_view_budget" and e["arm"] == arm]
        if fraction == 0.0:
            assert added[arm] == 0 and spent[arm] == 0.0 and budget[arm] == 0.0
            assert stopped and stopped[0]["per_view_s"] > 0  # the loop says why it added nothing
        else:
            assert added[arm] >= 1 and budget[arm] > 0  # the arm's planned views took time
            assert spent[arm] <= budget[arm] + longest + 1.0  # a view started within the budget is finished
            if stopped:  # stopped by the budget: the spent time plus one more view would exceed it
                assert stopped[0]["spent_s"] + stopped[0]["per_view_s"] > stopped[0]["budget_s"]
