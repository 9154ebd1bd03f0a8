"""The Z1 control loop's trajectory planner: limits, synchronisation, continuity on re-plans, stops."""

from __future__ import annotations

import numpy as np
import pytest

from darp.hardware.trajectory import plan_move, plan_stop
from darp.kinematics import z1

LOWER = np.maximum(z1.JOINT_LOWER, z1.SDK_JOINT_LOWER)
UPPER = np.minimum(z1.JOINT_UPPER, z1.SDK_JOINT_UPPER)
PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
ZERO = np.zeros(6)


def dense(plan, t0: float, n: int = 1201):
    t = np.linspace(t0, plan.end_s + 0.1, n)
    q, qd, qdd = (np.array(v) for v in zip(*(plan.sample(x) for x in t), strict=True))
    return t, q, qd, qdd


@pytest.mark.parametrize("speed, accel", [(0.6, 2.0), (1.0, 0.5), (np.pi, 10.0)])
def test_rest_to_rest_is_the_shortest_synchronised_move(speed, accel):
    target = PARK + np.array([0.9, -0.3, 0.5, 0.2, -1.0, 2.0])
    plan = plan_move(10.0, PARK, ZERO, ZERO, target, speed, accel, LOWER, UPPER)
    _, q, qd, qdd = dense(plan, 10.0)
    D = np.max(np.abs(target - PARK))
    assert plan.end_s - 10.0 == pytest.approx(max(1.875 * D / speed, np.sqrt(5.7735027 * D / accel)), rel=1e-6)
    peak_v, peak_a = np.max(np.abs(qd)), np.max(np.abs(qdd))
    assert peak_v <= speed * (1 + 1e-6) and peak_a <= accel * (1 + 1e-3)
    assert peak_v == pytest.approx(speed, rel=1e-3) or peak_a == pytest.approx(accel, rel=1e-2)  # one limit binds
    assert np.allclose(q[0], PARK) and np.allclose(q[-1], target)
    assert np.allclose(qd[0], 0) and np.allclose(qd[-1], 0)
    # synchronised: every joint is the same fraction of its way at every instant
    frac = (q - PARK) / (target - PARK)
    assert np.allclose(frac, frac[:, :1], atol=1e-9)


def test_replanning_mid_move_keeps_position_and_speed_continuous():
    rng = np.random.default_rng(7)
    for _ in range(20):
        first = np.clip(PARK + rng.uniform(-0.8, 0.8, 6), LOWER + 0.05, UPPER - 0.05)
        second = np.clip(PARK + rng.uniform(-0.8, 0.8, 6), LOWER + 0.05, UPPER - 0.05)
        p1 = plan_move(0.0, PARK, ZERO, ZERO, first, 0.8, 3.0, LOWER, UPPER)
        t_switch = rng.uniform(0.05, p1.end_s)
        q, qd, qdd = p1.sample(t_switch)
        p2 = plan_move(t_switch, q, qd, qdd, second, 0.8, 3.0, LOWER, UPPER)
        q2, qd2, _ = p2.sample(t_switch)
        assert np.allclose(q2, q, atol=1e-12) and np.allclose(qd2, qd, atol=1e-12)
        _, Q, V, A = dense(p2, t_switch)
        assert np.max(np.abs(V)) <= 0.8 * 1.002
        assert np.max(np.abs(A)) <= 3.0 * 1.01
        assert np.all(Q >= LOWER - 1e-9) and np.all(Q <= UPPER + 1e-9)
        assert np.allclose(Q[-1], second)
        steps = np.abs(np.diff(Q, axis=0))
        assert np.all(steps <= 0.8 * 1.002 * np.diff(np.linspace(t_switch, p2.end_s + 0.1, len(Q)))[0] + 1e-12)


def test_reversing_near_a_limit_brakes_first_and_stays_inside():
    # joint 2 races towards its lower limit (0 rad); the new target is back up: a single blend would
    # dip below the limit, so the plan brakes inside the limits and then moves
    q = PARK.copy()
    q[1] = 0.06
    qd = np.zeros(6)
    qd[1] = -0.5
    plan = plan_move(0.0, q, qd, ZERO, PARK, 0.6, 2.0, LOWER, UPPER)
    _, Q, V, _ = dense(plan, 0.0)
    assert np.all(Q[:, 1] >= LOWER[1] - 1e-9)
    assert np.allclose(Q[-1], PARK)
    assert np.max(np.abs(V)) <= 0.6 * 1.002


def test_stop_brakes_monotonically_at_the_acceleration_limit():
    qd = np.array([0.5, -0.3, 0.2, 0.0, 0.1, -0.4])
    plan = plan_stop(0.0, PARK, qd, ZERO, 0.6, 2.0, LOWER, UPPER)
    _, Q, V, A = dense(plan, 0.0)
    assert plan.end_s == pytest.approx(1.5 * 0.5 / 2.0)
    assert np.max(np.abs(A)) <= 2.0 * (1 + 1e-6)
    assert np.all(V * np.sign(qd) >= -1e-12)  # never reverses
    assert np.all(np.abs(V[1:]) <= np.abs(V[:-1]) + 1e-12)  # speed only decreases
    assert np.allclose(Q[-1], PARK + 0.5 * qd * plan.end_s)


def test_stop_next_to_a_limit_brakes_harder_rather_than_cross_it():
    q = PARK.copy()
    q[1] = 0.01
    qd = np.zeros(6)
    qd[1] = -0.5  # 1 cm of room at 0.5 rad/s: the 2 rad/s^2 stop would need 0.094 rad
    plan = plan_stop(0.0, q, qd, ZERO, 0.6, 2.0, LOWER, UPPER)
    _, Q, _, _ = dense(plan, 0.0)
    assert np.min(Q[:, 1]) >= LOWER[1] - 1e-9
