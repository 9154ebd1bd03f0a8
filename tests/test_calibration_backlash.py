"""Backlash in the richer calibration model (issue 16): a rig whose ONLY unmodelled error is backlash.

Synthetic corner observations through the twin's ``realistic`` rig (joint zeros, mounts and bases off;
no link-side errors) whose links sit half a 0.22 deg dead band behind the direction each joint last
moved in, as :class:`darp.twin.arm_errors.LinkDeflection` does. The captures record that direction
(``extra.move_direction``, as :func:`darp.calibration.capture_run.run_capture_plan` writes it).
``kinematic+compliance+backlash`` must recover the half dead band and predict new views far better than
the model without it; without directions the term is "not estimated"; the paper model is unchanged by
the directions being there.
"""

from __future__ import annotations

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD
from darp.calibration.evaluate import corner_errors
from darp.calibration.model import build_observations
from darp.calibration.solve import calibrate_observations
from darp.kinematics.kinematic_model import KinematicParams, fk_batch_params, link_angles
from helpers.calibration_synthetic import board_pose, random_poses, synthetic_detections, true_rig

ARMS = ("arm110", "arm111")
HALF_BAND = np.radians(0.11)  # the paper profile's 0.22 deg dead band


class _BacklashRig:
    """A true rig whose links lag the motor by HALF_BAND against each joint's last move direction."""

    def __init__(self, truth, directions: dict[str, np.ndarray]) -> None:
        self.truth, self.arms = truth, truth.arms
        self._queue = {a: list(d) for a, d in directions.items()}  # consumed in capture order

    def T_world_cam(self, arm: str, q_true: np.ndarray) -> np.ndarray:
        d = self._queue[arm].pop(0)
        return self.truth.T_world_cam(arm, np.asarray(q_true) - HALF_BAND * d)


def _directions(poses: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Each capture's move direction when the poses are visited in order from ``start``."""
    prev = np.vstack([start, poses[:-1]])
    return np.sign(poses - prev)


def _detections(truth, poses: dict[str, np.ndarray], T_wb: np.ndarray, seed: int, with_direction: bool):
    start = {a: poses[a].mean(axis=0) for a in ARMS}
    dirs = {a: _directions(poses[a], start[a]) for a in ARMS}
    dets = synthetic_detections(_BacklashRig(truth, dirs), poses, T_wb, noise_px=0.1, encoder_noise_deg=0.002,
                                seed=seed)
    if with_direction:
        count = dict.fromkeys(ARMS, 0)
        for d in dets:
            d.record.extra["move_direction"] = dirs[d.record.arm][count[d.record.arm]].astype(int).tolist()
            count[d.record.arm] += 1
    return dets


@pytest.fixture(scope="module")
def data():
    truth, _ = true_rig(5, "realistic")
    rig = truth.nominal
    T_wb = board_pose(rig)
    train = {a: random_poses(rig, a, 16, T_wb, 5) for a in ARMS}
    test = {a: random_poses(rig, a, 8, T_wb, 105) for a in ARMS}
    obs = build_observations(_detections(truth, train, T_wb, 5, True), DEFAULT_BOARD, ARMS)
    obs_plain = build_observations(_detections(truth, train, T_wb, 5, False), DEFAULT_BOARD, ARMS)
    obs_test = build_observations(_detections(truth, test, T_wb, 6, True), DEFAULT_BOARD, ARMS)
    return obs, obs_plain, obs_test


def test_backlash_term_moves_the_link_behind_the_last_move() -> None:
    Q = np.array([[0.1, 1.0, -1.0, 0.3, 0.2, 0.1]])
    d = np.array([[1, -1, 1, 0, 1, -1]])
    params = KinematicParams(backlash_rad=np.full(6, 0.002))
    assert np.allclose(link_angles(Q, params, d), Q - 0.002 * d)
    assert np.array_equal(link_angles(Q, params, None), Q)  # no direction: no backlash
    assert np.allclose(fk_batch_params(Q, params, direction=d), fk_batch_params(Q - 0.002 * d, KinematicParams()))
    back = KinematicParams.from_dict(params.to_dict())
    assert np.array_equal(back.backlash_rad, params.backlash_rad)
    assert "backlash_rad" not in KinematicParams().to_dict()  # files of the models without it are unchanged
    assert np.array_equal(KinematicParams.from_vector(params.to_vector()).backlash_rad, params.backlash_rad)


@pytest.mark.slow
def test_backlash_is_recovered_and_predicts_new_views(data) -> None:
    obs, _, obs_test = data
    assert obs.move_dir is not None and obs.move_dir.shape == (obs.n_captures, 6)
    cores = {m: calibrate_observations(obs, model=m) for m in ("kinematic+compliance", "kinematic+compliance+backlash")}
    held = {m: float(np.median(corner_errors(c.params, obs_test)["corner_3d_mm"])) for m, c in cores.items()}
    rich = cores["kinematic+compliance+backlash"]
    assert held["kinematic+compliance+backlash"] < 0.5 * held["kinematic+compliance"], held
    for arm in ARMS:
        table = {r["parameter"]: r for r in rich.kin_ident.table[arm]}
        est = [j for j in range(6) if table[f"joint{j + 1}.backlash"]["status"] == "estimated"]
        assert len(est) >= 4, table
        b = rich.params.kin[arm].backlash_rad
        assert np.all(np.abs(b[est] - HALF_BAND) < 0.25 * HALF_BAND), np.degrees(b)


@pytest.mark.slow
def test_without_directions_backlash_is_not_estimated_and_paper_mode_is_unchanged(data) -> None:
    obs, obs_plain, _ = data
    assert obs_plain.move_dir is None
    core = calibrate_observations(obs_plain, model="kinematic+compliance+backlash")
    rows = [r for r in core.kin_ident.table["arm110"] if r["parameter"].endswith("backlash")]
    assert len(rows) == 6 and all(r["status"] == "not estimated" and "move direction" in r["reason"] for r in rows)
    assert not core.params.kin["arm110"].has_backlash
    # the paper model ignores the directions: identical solutions with and without them
    a = calibrate_observations(obs, model="paper").params
    b = calibrate_observations(obs_plain, model="paper").params
    for arm in ARMS:
        assert np.array_equal(a.T_wrist_cam[arm], b.T_wrist_cam[arm])
        assert np.array_equal(a.dq[arm], b.dq[arm])


def test_motion_directions_from_a_noisy_joint_log() -> None:
    from darp.reconstruction.poses import motion_directions

    rng = np.random.default_rng(0)
    ramp = np.r_[np.zeros(50), np.linspace(0, 0.3, 100), np.full(80, 0.3), np.linspace(0.3, 0.1, 100), np.full(80, 0.1)]
    Q = np.zeros((ramp.size, 6))
    Q[:, 1] = ramp
    Q[:, 2] = -ramp
    Q[:, 3] = ramp * 0.0008 / 0.3  # a 0.05 deg move with joint 2 ...
    Q[230:330, 3] = 0.0008 - np.linspace(0, 0.0016, 100)  # ... and one back, under the noise per row
    Q[330:, 3] = -0.0008
    Q += rng.normal(0.0, np.radians(0.01), Q.shape)  # the paper profile's encoder noise
    d = motion_directions(Q)
    assert np.all(d[:50, 1] == 0) and np.all(d[:, 0] == 0)  # not moved yet / never moved
    assert np.all(d[160:230, 1] == 1) and np.all(d[160:230, 2] == -1)  # held after moving up: still +1
    assert np.all(d[260:, 1] == -1) and np.all(d[260:, 2] == 1)  # after the way back
    assert np.all(d[160:230, 3] == 1) and np.all(d[340:, 3] == -1)  # small moves count (backlash takes up)


def test_eq1_model_hands_the_backlash_to_the_log_and_paper_mode_ignores_it() -> None:
    from darp.formats.calibration import ArmCalibration
    from darp.kinematics import z1
    from darp.reconstruction.poses import eq1_model

    kin = {"model": "kinematic+compliance+backlash", **KinematicParams(backlash_rad=np.full(6, 0.002)).to_dict()}
    cal = ArmCalibration("s", np.eye(4), np.eye(4), kinematics=kin)
    _, _, _, fk, info = eq1_model(cal, "arm110", kinematics=True)
    assert info["applied"] and np.allclose(info["backlash_rad"], 0.002)
    Q = z1.random_configurations(3, 1)
    assert fk is not None and np.allclose(fk(Q), z1.fk_batch(Q), atol=1e-12)  # the log carries the backlash
    *_, fk_paper, info_paper = eq1_model(cal, "arm110", kinematics=False)
    assert fk_paper is None and info_paper == {}


@pytest.mark.slow
def test_twin_captures_record_the_direction_of_the_move_that_brought_the_arm(tmp_path) -> None:
    from darp.kinematics.rig import load_rig
    from darp.twin.calib_capture import capture_twin

    caps = capture_twin(tmp_path / "caps", seed=2, profile="ideal", n_per_arm=4, resolution=(424, 240))
    rig = load_rig()
    for arm in ARMS:
        park = np.asarray(rig.arms[arm].park_q_rad, float)
        prev = park
        for k, rec in enumerate(caps.for_arm(arm)):
            d = np.asarray(rec.extra["move_direction"], float)
            target = np.asarray(rec.extra["planned_q_rad"], float)
            assert set(np.unique(d)) <= {-1.0, 0.0, 1.0}
            direct, via_park = np.sign(target - prev), np.sign(target - park)
            assert np.array_equal(d, direct) or np.array_equal(d, via_park), (arm, k, d, direct, via_park)
            if k == 0:
                assert np.array_equal(d, via_park)  # the arms start at park
            prev = target
    obs = build_observations([_Ok(r) for r in caps.captures], caps.board, ARMS)
    assert obs.move_dir is not None and obs.move_dir.shape == (8, 6)


class _Ok:
    """A stand-in detection (every capture accepted) for building observations from records alone."""

    def __init__(self, record) -> None:
        self.record, self.arm, self.capture_id, self.ok = record, record.arm, record.capture_id, True
        self.ids = np.arange(4)
        self.K = np.eye(3)
        self.corners_ideal_px = np.zeros((4, 2))
        self.T_depth_board = np.eye(4)
