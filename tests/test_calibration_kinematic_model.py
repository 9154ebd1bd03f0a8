"""The richer calibration model (issue 16 item 1): joint origin offsets, axis tilts, compliance.

Synthetic corner observations through a true rig drawn by the twin's ``paper`` profile (joint origins
0.9 mm, axis tilts 0.15 deg per axis) plus gravity sag (compliance 1e-3 rad/N m on joints 2-4), with
small pixel and encoder noise: the richer model must be identified, recover the compliance, and predict
boards seen from new poses far better than the paper's model.
"""

from __future__ import annotations

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD
from darp.calibration.evaluate import corner_errors
from darp.calibration.handeye import opencv_hand_eye
from darp.calibration.jacobian import residuals_and_jacobian
from darp.calibration.kinematic_ident import MODEL_CANDIDATES, analyse_kinematics
from darp.calibration.model import build_observations
from darp.calibration.refine import Layout, _residuals, numeric_jacobian
from darp.calibration.solve import calibrate_observations, opencv_chain
from darp.formats.calibration import calibration_from_dict, calibration_to_dict
from darp.kinematics import z1
from darp.kinematics.kinematic_model import (
    N_PARAMS,
    PARAM_NAMES,
    KinematicParams,
    chain_fk,
    fk_batch_params,
    gravity_torques,
)
from darp.twin.arm_errors import fk_batch_with_errors
from helpers.calibration_synthetic import board_pose, random_poses, synthetic_detections, true_rig

ARMS = ("arm110", "arm111")
COMPLIANCE = 1e-3  # rad / N m (the paper profile's 1000 N m/rad)


class _SaggingRig:
    """A true rig whose links sag under gravity (what the encoders do not see)."""

    def __init__(self, truth, compliance: float) -> None:
        self.truth, self.arms, self.c = truth, truth.arms, compliance

    def T_world_cam(self, arm: str, q_true: np.ndarray) -> np.ndarray:
        Q = np.atleast_2d(q_true)
        link = Q + self.c * gravity_torques(Q, 0.2)
        T = self.truth.T_world_cam(arm, link)
        return T[0] if np.ndim(q_true) == 1 else T


@pytest.fixture(scope="module")
def data():
    truth, _ = true_rig(3, "paper", unabsorbed_mm=0.0)  # the first direction draw, as these tests were set on
    rig = truth.nominal
    T_wb = board_pose(rig)
    sag = _SaggingRig(truth, COMPLIANCE)
    train = {a: random_poses(rig, a, 14, T_wb, 3) for a in ARMS}
    test = {a: random_poses(rig, a, 8, T_wb, 103) for a in ARMS}
    obs = build_observations(synthetic_detections(sag, train, T_wb, noise_px=0.1, encoder_noise_deg=0.002, seed=3),
                             DEFAULT_BOARD, ARMS)
    obs_test = build_observations(synthetic_detections(sag, test, T_wb, noise_px=0.1, encoder_noise_deg=0.002,
                                                       seed=4), DEFAULT_BOARD, ARMS)
    return truth, obs, obs_test


@pytest.fixture(scope="module")
def cores(data):
    _, obs, _ = data
    return {m: calibrate_observations(obs, model=m) for m in ("paper", "kinematic+compliance")}


def test_nominal_chain_and_the_twin_use_one_chain() -> None:
    Q = z1.random_configurations(7, 0)
    assert np.allclose(chain_fk(Q, z1.JOINT_ORIGINS_M, z1.JOINT_AXES), z1.fk_batch(Q), atol=1e-12)
    assert np.allclose(fk_batch_params(Q, KinematicParams()), z1.fk_batch(Q), atol=1e-12)
    truth, _ = true_rig(3, "paper", unabsorbed_mm=0.0)  # the first direction draw, as these tests were set on
    err = truth.arms["arm110"].kinematic_errors
    params = KinematicParams(err.origin_m, err.axis_tilt_rad, np.zeros(6))
    assert np.array_equal(fk_batch_params(Q, params), fk_batch_with_errors(Q, err))
    assert not np.allclose(fk_batch_params(Q, params), z1.fk_batch(Q), atol=1e-4)  # the errors matter
    back = KinematicParams.from_vector(params.to_vector())
    assert np.array_equal(back.origin_m, params.origin_m) and np.array_equal(back.axis_tilt_rad, params.axis_tilt_rad)


def test_kinematic_jacobian_matches_central_differences(data) -> None:
    _, obs, _ = data
    sub = obs.subset(np.r_[0:4, 14:18])
    p0 = opencv_chain({a: opencv_hand_eye(sub, a) for a in ARMS}, ARMS, None)
    cand = MODEL_CANDIDATES["kinematic+compliance"]
    layout = Layout(ARMS, {a: np.ones(6, bool) for a in ARMS}, free_kin={a: cand.copy() for a in ARMS})
    x = np.random.default_rng(1).normal(0.0, 0.01, layout.size)
    x[layout.kin_columns()] = 0.0  # at zero kinematic errors the columns are exact
    r, J = residuals_and_jacobian(x, layout, p0, sub, 0.3)
    Jn = numeric_jacobian(lambda v: _residuals(v, layout, p0, sub, 0.3, np.inf, "flange")[:len(r)], x, 1e-7)
    cols = layout.kin_columns()
    rel = np.abs(J[:, cols] - Jn[:, cols]).max(axis=0) / np.abs(Jn[:, cols]).max(axis=0)
    assert rel.max() < 1e-4


@pytest.mark.slow
def test_identifiability_reports_redundant_and_no_effect_parameters(cores) -> None:
    table = {r["parameter"]: r for r in cores["kinematic+compliance"].kin_ident.table["arm111"]}
    assert len(table) == N_PARAMS - 6  # no backlash rows without the backlash model
    assert table["joint1.tilt.z"]["status"] == "no effect"  # a tilt about joint 1's own (z) axis
    # joint 1's origin is where the base is (arm111's base is estimated): redundant, named as such
    for axis in "xyz":
        row = table[f"joint1.origin.{axis}"]
        assert row["status"] == "redundant", row
        assert "base:arm111" in row["reason"], row
    # joint 6's origin along its own (x) axis moves the flange along that axis whatever q6: the hand-eye's
    row = {r["parameter"]: r for r in cores["kinematic+compliance"].kin_ident.table["arm110"]}["joint6.origin.x"]
    assert row["status"] == "redundant" and "handeye:arm110" in row["reason"], row
    estimated = [n for n, r in table.items() if r["status"] == "estimated"]
    assert "joint2.compliance" in estimated  # the joint with the largest gravity torque
    assert 5 <= len(estimated) <= 25


@pytest.mark.slow
def test_richer_model_recovers_compliance_and_predicts_new_views_better(data, cores) -> None:
    _, _, obs_test = data
    held = {m: float(np.median(corner_errors(c.params, obs_test)["corner_3d_mm"])) for m, c in cores.items()}
    assert held["kinematic+compliance"] < 0.4 * held["paper"], held
    assert held["kinematic+compliance"] < 0.5, held  # mm
    for arm in ARMS:
        c = cores["kinematic+compliance"].params.kin[arm].compliance_rad_per_nm
        assert abs(c[1] - COMPLIANCE) < 0.3 * COMPLIANCE, c  # joint 2 carries the largest torque


@pytest.mark.slow
def test_calibration_file_carries_the_model_and_old_files_still_read(data, cores) -> None:
    from darp.calibration.solve import _kinematics_entry, to_calibration
    from darp.calibration.world_frame import world_from_reference

    _, obs, _ = data
    paper = cores["paper"]
    ident = analyse_kinematics(paper.params, obs, paper.identifiability.identifiable, "kinematic",
                               paper.refined.sigma_px)
    assert not any(r["parameter"].endswith("compliance") for r in ident.table["arm110"])
    assert ident.table["arm110"][0]["parameter"] == "joint1.origin.x"
    core = cores["kinematic+compliance"]
    T_rw = world_from_reference(core.params.T_ref_base, core.params.T_ref_board, ARMS)
    cal = to_calibration(paper.params, T_rw, {a: a for a in ARMS}, epoch="t", date="2026-01-01", board=DEFAULT_BOARD)
    cal.arms["arm110"].kinematics = _kinematics_entry(core, "arm110", obs, T_rw, None)
    other = _kinematics_entry(core, "arm111", obs, T_rw, None)
    mid = 0.5 * (np.asarray(cal.arms["arm110"].kinematics["T_world_base"]) + np.asarray(other["T_world_base"]))
    assert np.allclose(mid[:3, 3], 0.0, atol=1e-9)  # the richer model's bases in the world it realises itself
    back = calibration_from_dict(calibration_to_dict(cal))
    kin = back.arms["arm110"].kinematics
    assert kin is not None and kin["model"] == "kinematic+compliance"
    assert set(kin["estimated"]) <= set(PARAM_NAMES)
    assert np.allclose(KinematicParams.from_dict(kin).origin_m, core.params.kin["arm110"].origin_m)
    assert np.allclose(kin["T_wrist_cam"], core.params.T_wrist_cam["arm110"])
    assert np.allclose(back.arms["arm110"].T_wrist_cam, paper.params.T_wrist_cam["arm110"])  # main: paper model
    assert back.arms["arm111"].kinematics is None  # absent: nothing to apply


@pytest.mark.slow
def test_d_optimal_extra_poses_carry_more_information_than_random_ones(data, cores) -> None:
    from darp.calibration.plan_model import _information, _kin_logdet, candidate_observations, select_extra_poses

    truth, obs, _ = data
    core = cores["paper"]
    T_wb = board_pose(truth.nominal)
    candidates = {a: random_poses(truth.nominal, a, 10, T_wb, 11) for a in ARMS}
    free = core.identifiability.identifiable
    picks = select_extra_poses(core.params, obs, DEFAULT_BOARD, candidates, free, 4, sigma_px=0.5)
    assert len(picks) == 4 and len(set(picks)) == 4
    # the criterion the selection maximises, for its picks and for random ones
    cand_obs, ids = candidate_observations(core.params, obs, DEFAULT_BOARD, candidates)
    cand = MODEL_CANDIDATES["kinematic+compliance"]
    layout = Layout(ARMS, {a: np.asarray(free[a], bool) for a in ARMS}, free_kin={a: cand.copy() for a in ARMS})
    _, J0 = residuals_and_jacobian(np.zeros(layout.size), layout, core.params, obs, 0.5)
    A0 = J0.T @ J0
    kin = layout.kin_columns()
    A0[kin, kin] += 1.0 / layout.kin_prior() ** 2
    other = np.setdiff1d(np.arange(layout.size), kin)
    info, _ = _information(layout, core.params, cand_obs, 0.5)

    def gain(sel: list[int]) -> float:
        return _kin_logdet(A0 + info[sel].sum(axis=0), kin, other)

    chosen = gain([ids.index(p) for p in picks])
    rng = np.random.default_rng(0)
    randoms = [gain(list(rng.choice(len(ids), 4, replace=False))) for _ in range(5)]
    assert chosen > max(randoms)
