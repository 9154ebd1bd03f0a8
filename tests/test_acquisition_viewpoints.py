"""Viewpoint planning: the standoff rule, orbit shapes, every feasibility check, paths and ordering."""

from __future__ import annotations

import numpy as np
import pytest

from darp.acquisition.motion_check import ArmCollisionModel, ClearanceMargins, envelope_obstacle
from darp.acquisition.tour import order_views, tour_cost
from darp.acquisition.viewpoints import (
    Candidate,
    ViewpointPlanner,
    ViewpointSettings,
    calibration_table_problem,
    feasibility_summary,
    orbit_shape,
    reason_words,
    shoulder_offsets_m,
    standoff_for_radius,
)
from darp.kinematics import collision
from darp.kinematics.collision_shapes import Primitive
from darp.kinematics.rig import load_rig, rig_from_dict

RIG = load_rig()
CENTRE = np.array([0.02, 0.05, 0.05])
RADIUS, HEIGHT = 0.05, 0.10
PAPER = {4.11: 34.1, 4.31: 34.3, 4.41: 34.4, 4.85: 34.8, 5.78: 35.8, 5.83: 35.8, 6.90: 36.9, 7.22: 37.2, 11.60: 52.2}


def planner(arm: str = "arm110", margins: ClearanceMargins | None = None, settings: ViewpointSettings | None = None,
            other_q: np.ndarray | None = None, centre: np.ndarray = CENTRE) -> ViewpointPlanner:
    obstacle = envelope_obstacle(centre, RADIUS, HEIGHT, 0.0)
    model = ArmCollisionModel(RIG, arm, obstacle=obstacle, margins=margins or ClearanceMargins.from_rig(RIG),
                              other_q_rad=other_q)
    return ViewpointPlanner(model, centre, RADIUS, HEIGHT, settings or ViewpointSettings())


def side_candidate(p: ViewpointPlanner, elevation: float = 40.0, distance: float = 0.37) -> Candidate:
    e, a = np.radians(elevation), np.radians(p.side_azimuth_deg)
    cam = p.centre + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return Candidate(0, elevation, p.side_azimuth_deg, distance, cam)


def test_standoff_rule_reproduces_the_paper_table() -> None:
    for radius_cm, standoff_cm in PAPER.items():
        assert standoff_for_radius(radius_cm / 100) * 100 == pytest.approx(standoff_cm, abs=0.06)


def test_larger_objects_get_broader_denser_orbits() -> None:
    small, medium, large = orbit_shape(0.04, 0.05), orbit_shape(0.07, 0.06), orbit_shape(0.116, 0.19)
    assert len(small.elevations_deg) < len(medium.elevations_deg) <= len(large.elevations_deg)
    assert small.azimuth_span_deg < medium.azimuth_span_deg < large.azimuth_span_deg
    assert small.n_azimuth < medium.n_azimuth < large.n_azimuth
    assert small.standoff_m < medium.standoff_m < large.standoff_m
    assert min(orbit_shape(0.04, 0.15).elevations_deg) < min(small.elevations_deg)  # tall: a low ring


def test_a_good_candidate_passes_and_looks_at_the_centre() -> None:
    p = planner()
    cand = p.check_candidate(side_candidate(p))
    assert cand.ok, cand.detail
    T = p.model.T_world_cam(cand.q_rad)
    rel = CENTRE - T[:3, 3]
    depth = rel @ T[:3, 2]
    assert np.linalg.norm(rel - depth * T[:3, 2]) < 1e-6  # the optical axis passes through the centre
    assert depth == pytest.approx(0.37, abs=1e-6)
    assert np.linalg.norm(T[:3, 3] - cand.camera_m) < 1e-6


@pytest.mark.parametrize("reason, kwargs", [
    ("ik", {"distance": 2.5}),
    ("joint_limits", {"margins": ClearanceMargins(joint_limit_rad=1.2)}),
    ("workspace", {"settings": ViewpointSettings(reach_limit_m=0.3)}),
    ("min_depth", {"settings": ViewpointSettings(min_depth_m=0.5)}),
    ("table", {"margins": ClearanceMargins(table_m=0.6)}),
    ("self", {"margins": ClearanceMargins(self_m=0.5)}),
    ("parked_arm", {"margins": ClearanceMargins(arm_arm_m=1.5)}),
    ("envelope", {"margins": ClearanceMargins(envelope_m=0.4)}),
])
def test_each_check_rejects_with_its_reason(reason: str, kwargs: dict) -> None:
    distance = kwargs.pop("distance", 0.37)
    p = planner(**kwargs)
    cand = p.check_candidate(side_candidate(p, distance=distance))
    assert not cand.ok
    assert cand.reason == reason, cand.detail
    assert cand.detail


def test_the_other_arm_in_the_way_is_rejected() -> None:
    # Bases 0.9 m apart (arm111 moved to x = 0.2): arm111 bent towards arm110 blocks arm110's view.
    data = RIG.to_dict()
    data["arms"]["arm111"]["T_world_base"]["xyz_m"] = [0.2, 0.0, 0.0]
    rig = rig_from_dict(data)
    centre = np.array([-0.15, 0.0, 0.05])
    q_other = np.array([-0.09, 2.62, -2.5, 0.9, -0.2, 1.32])
    obstacle = envelope_obstacle(centre, RADIUS, HEIGHT, 0.0)
    assert ArmCollisionModel(rig, "arm111", obstacle=obstacle).check_configuration(q_other).ok
    verdicts = []
    for other in (None, q_other):
        model = ArmCollisionModel(rig, "arm110", obstacle=obstacle, other_q_rad=other)
        p = ViewpointPlanner(model, centre, RADIUS, HEIGHT)
        verdicts.append(p.check_candidate(side_candidate(p)))
    assert verdicts[0].ok
    assert not verdicts[1].ok and verdicts[1].reason == "parked_arm"
    assert "arm111" in verdicts[1].detail


def test_excessive_joint_motion_between_views_is_dropped() -> None:
    plan = planner(settings=ViewpointSettings(max_joint_step_rad=0.05, min_views=1)).plan()
    # every move between views is too large; only the first view (reached from park) survives
    assert len(plan.views) <= 1
    assert any(c.reason == "joint_motion" for c in plan.candidates)


def test_plan_views_are_feasible_and_their_moves_clear() -> None:
    p = planner()
    plan = p.plan()
    assert len(plan.views) >= p.settings.min_views
    assert plan.attempts[0]["relaxation"] == "nominal"
    q_prev = p.q_park
    for view in plan.views:
        assert p.model.check_configuration(view.q_rad).ok
        assert p.model.check_path(q_prev, view.q_rad).ok
        q_prev = view.q_rad
    assert p.model.check_path(q_prev, p.q_park).ok
    assert plan.travel_rad == pytest.approx(tour_cost(p.q_park, plan.q_views, p.q_park))
    # views come from the arm's side of the object
    base_x = RIG.arms["arm110"].T_world_base[0, 3]
    for view in plan.views:
        assert np.sign(view.camera_m[0] - CENTRE[0]) == np.sign(base_x - CENTRE[0])


def test_too_few_views_regenerates_with_relaxed_parameters() -> None:
    plan = planner(settings=ViewpointSettings(min_views=200)).plan()
    names = [a["relaxation"] for a in plan.attempts]
    assert names == ["nominal", "wider span, lower ring", "larger standoff", "smaller standoff, lower rings",
                     "close"]
    spans = [a["shape"]["azimuth_span_deg"] for a in plan.attempts]
    assert spans[1] > spans[0]
    assert plan.attempts[2]["shape"]["standoff_m"] > plan.attempts[0]["shape"]["standoff_m"]
    assert plan.attempts[3]["shape"]["standoff_m"] < plan.attempts[0]["shape"]["standoff_m"]
    assert plan.attempts[4]["shape"]["standoff_m"] == pytest.approx(0.25 + RADIUS)
    assert len(plan.views) == max(a["views"] for a in plan.attempts)  # the best attempt is kept
    for a in plan.attempts:
        assert a["candidates"] == a["views"] + sum(a["rejected"].values())


def test_feasibility_summary_counts_every_refusal_by_reason() -> None:
    # A table margin no pose meets: every candidate that IK solves is refused for table clearance (or earlier).
    plan = planner(margins=ClearanceMargins(table_m=0.6), settings=ViewpointSettings(min_views=1)).plan()
    assert not plan.views
    counts: dict[str, int] = {}
    for c in plan.candidates:
        counts[c.reason] = counts.get(c.reason, 0) + 1
    assert counts.get("table", 0) > 0
    text = feasibility_summary(plan)
    n, tried = len(plan.candidates), len(plan.attempts)
    assert text.startswith(f"0 feasible of {n} candidates (the nominal orbit, best of {tried} tried): ")
    ranked = text.split(": ", 1)[1].split("; e.g. ")[0].split(", ")
    assert sum(int(part.split(" ", 1)[0]) for part in ranked) == len(plan.candidates)
    assert f"{counts['table']} table clearance" in ranked
    top_two = sorted(counts, key=lambda r: -counts[r])[:2]
    assert "table" in top_two
    for reason in top_two:  # the first refusal's detail of each of the two most frequent reasons
        example = next(c for c in plan.candidates if c.reason == reason)
        assert f"{reason_words(reason)}: {example.detail}" in text.split("; e.g. ", 1)[1]
    assert "mm above the table (margin 600 mm)" in text
    good = planner().plan()  # a feasible plan: nothing refused is listed when nothing was
    assert feasibility_summary(good).startswith(f"{len(good.views)} feasible of {len(good.candidates)} candidates")


def test_path_check_finds_a_collision_between_clear_views() -> None:
    model = ArmCollisionModel(RIG, "arm110")
    q_a = np.array([-0.6, 1.6, -1.2, 0.0, 0.0, 0.0])  # reaching forward, swinging across the table
    q_b = np.array([0.6, 1.6, -1.2, 0.0, 0.0, 0.0])
    q_mid = 0.5 * (q_a + q_b)
    cam_mid = model.T_world_cam(q_mid)[:3, 3]
    T = np.eye(4)
    T[:3, 3] = cam_mid
    blocked = model.with_obstacle(Primitive.box(T, [0.04, 0.04, 0.04], "post", "object"))
    assert blocked.check_configuration(q_a).ok and blocked.check_configuration(q_b).ok
    verdict = blocked.check_path(q_a, q_b)
    assert not verdict.ok and verdict.reason == "envelope"
    assert 0.2 < verdict.path_fraction < 0.8


def test_path_check_agrees_with_exact_checks_at_every_sample() -> None:
    """The bounding-capsule shortcut never passes a path that an exact check of its samples fails."""
    rng = np.random.default_rng(4)
    model = ArmCollisionModel(RIG, "arm110", obstacle=envelope_obstacle(CENTRE, RADIUS, HEIGHT, 0.0),
                              margins=ClearanceMargins(table_m=0.03, self_m=0.02, arm_arm_m=0.05, envelope_m=0.05,
                                                       joint_limit_rad=0.0))
    park = RIG.arms["arm110"].park_q_rad
    lower, upper = np.array([-1.0, 1.2, -2.6, -1.4, -1.2, -2.0]), np.array([1.0, 2.9, -0.3, 1.4, 1.2, 2.0])
    disagreements, reasons = 0, set()
    for _ in range(12):
        q_b = rng.uniform(lower, upper)
        fast = model.check_path(park, q_b, max_step_rad=0.1)
        exact = all(model.check_configuration(q).ok for q in model.path_samples(park, q_b, 0.1))
        reasons.add(fast.reason)
        disagreements += fast.ok != exact
    assert disagreements == 0
    assert {"", "table", "self"} <= reasons  # clear paths and two kinds of failure were exercised


def test_ordering_is_shorter_than_random_orders() -> None:
    p = planner()
    plan = p.plan()
    Q = plan.q_views
    rng = np.random.default_rng(4)
    shuffled = Q[rng.permutation(len(Q))]
    order = order_views(p.q_park, shuffled, p.q_park)
    assert sorted(order) == list(range(len(Q)))
    ordered = tour_cost(p.q_park, shuffled[order], p.q_park)
    randoms = [tour_cost(p.q_park, Q[rng.permutation(len(Q))], p.q_park) for _ in range(200)]
    assert ordered < np.percentile(randoms, 5)
    assert ordered <= min(randoms) + 1e-9
    greedy = order_views(p.q_park, shuffled, p.q_park, two_opt_rounds=0)
    assert ordered <= tour_cost(p.q_park, shuffled[greedy], p.q_park) + 1e-12


def test_ordering_breaks_near_ties_by_the_lower_index() -> None:
    """Mirror-image views equally far from the start: rounding noise (which depends on the BLAS kernel)
    must not choose the tour's direction."""
    start = np.zeros(6)
    for eps in (-4e-16, 0.0, 4e-16):
        Q = np.array([[0.5 + eps, 0, 0, 0, 0, 0], [-0.5, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0], [-1.0, 0, 0, 0, 0, 0]])
        assert order_views(start, Q, start, two_opt_rounds=0)[0] == 0
        assert order_views(start, Q[[1, 0, 3, 2]], start, two_opt_rounds=0)[0] == 0


def test_ordering_small_cases() -> None:
    start = np.zeros(6)
    Q = np.array([[3.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0], [2.0, 0, 0, 0, 0, 0]])
    assert order_views(start, Q) == [1, 2, 0]
    assert order_views(start, Q[:1]) == [0]
    assert order_views(start, np.zeros((0, 6))) == []
    # the return leg counts when an end is given
    assert tour_cost(start, Q[[1, 2, 0]], start) == pytest.approx(6.0)


def test_collision_model_uses_the_calibration() -> None:
    nominal = ArmCollisionModel(RIG, "arm110")
    cal = RIG.nominal_calibration()
    cal.arms["arm110"].joint_offsets_rad = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    shifted = ArmCollisionModel(RIG, "arm110", calibration=cal)
    q = RIG.arms["arm110"].park_q_rad
    np.testing.assert_allclose(shifted.model_q(q), q + [0.1, 0, 0, 0, 0, 0])
    expected = collision.arm_primitives(q + [0.1, 0, 0, 0, 0, 0], RIG.arms["arm110"].T_world_base,
                                        RIG.camera_mount("arm110"))
    np.testing.assert_allclose(shifted.primitives(q).centre, expected.centre)
    assert not np.allclose(nominal.primitives(q).centre, expected.centre)


def _tilted_base_calibration(arm: str, dz_m: float, tilt_deg: float = 0.0) -> object:
    """The nominal calibration with one arm's base moved up by ``dz_m`` and tilted about the world x axis."""
    cal = RIG.nominal_calibration()
    T = np.array(cal.arms[arm].T_world_base, dtype=float)
    a = np.radians(tilt_deg)
    R = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    T[:3, :3] = R @ T[:3, :3]
    T[2, 3] += dz_m
    cal.arms[arm].T_world_base = T
    return cal


def test_a_calibration_that_moves_a_base_off_the_table_is_named() -> None:
    """The 4x sweep's case (docs/twin.md): a solved base 40 mm low puts the arm's own park pose in the table
    clearance, so every view is refused; 40 mm high passes every check that the real arm would fail."""
    margin = ClearanceMargins.from_rig(RIG).table_m
    assert calibration_table_problem(RIG, RIG.nominal_calibration(), margin) == ""
    park = RIG.arms["arm111"].park_q_rad
    low = _tilted_base_calibration("arm111", -0.040, tilt_deg=2.0)
    offsets = shoulder_offsets_m(RIG, low)
    assert offsets["arm110"] == pytest.approx(0.0, abs=1e-9) and -0.045 < offsets["arm111"] < -0.039
    assert ArmCollisionModel(RIG, "arm111").check_configuration(park).ok
    verdict = ArmCollisionModel(RIG, "arm111", calibration=low).check_configuration(park)
    assert not verdict.ok and verdict.reason == "table"  # the oracle: the collision model itself
    problem = calibration_table_problem(RIG, low, margin)
    assert "shoulder of arm111 4" in problem and "mm lower than the rig file" in problem and "arm110: +0 mm" in problem
    high = _tilted_base_calibration("arm110", 0.040)
    assert ArmCollisionModel(RIG, "arm110", calibration=high).check_configuration(RIG.arms["arm110"].park_q_rad).ok
    assert "shoulder of arm110 40 mm higher" in calibration_table_problem(RIG, high, margin)
    within = _tilted_base_calibration("arm111", -0.8 * margin)  # inside the clearance: planning is left to decide
    assert calibration_table_problem(RIG, within, margin) == ""


def test_a_large_object_near_an_arms_base_gets_views_closer_in() -> None:
    """The safety campaign's picture frame (envelope r 123 mm, h 194 mm) 0.58 m from arm110's base: the
    4.5 r standoff (0.554 m) puts arm110's cameras behind its own base (2 views in the first four attempts,
    4 needed); 25 cm from the envelope's surface (0.373 m) it has 10."""
    centre, radius, height = np.array([-0.1151, -0.0632, 0.0969]), 0.12316, 0.19371
    model = ArmCollisionModel(RIG, "arm110", obstacle=envelope_obstacle(centre, radius, height, 0.0))
    p = ViewpointPlanner(model, centre, radius, height)
    plan = p.plan()
    names = [a["relaxation"] for a in plan.attempts]
    assert names[-1] == "close" and all(a["views"] < 4 for a in plan.attempts[:-1])
    assert len(plan.views) >= 6 and plan.shape.standoff_m == pytest.approx(0.25 + radius, abs=1e-3)
    for v in plan.views:
        assert v.ok and np.linalg.norm(v.camera_m - centre) == pytest.approx(plan.shape.standoff_m)
        assert p.model.check_configuration(v.joints_rad).ok
