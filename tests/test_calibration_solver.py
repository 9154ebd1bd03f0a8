"""The calibration math on synthetic observations: exact projections through a known true rig plus noise.

The true rig is drawn by the twin's error model (joint-zero biases up to 1 deg, mounts 3 mm / 1 deg off,
second base 4 mm / 0.3 deg off); corners are projected exactly and perturbed with pixel noise, joint
readings with encoder noise. No rendering: these tests isolate the solver.
"""

from __future__ import annotations

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD
from darp.calibration.evaluate import fold_assignment, kfold_heldout, summarise, truth_errors
from darp.calibration.handeye import HAND_EYE_METHODS, best, opencv_hand_eye
from darp.calibration.jacobian import residuals_and_jacobian
from darp.calibration.model import build_observations
from darp.calibration.refine import Layout, _residuals, imitators, numeric_jacobian
from darp.calibration.solve import calibrate_observations, opencv_chain, to_calibration
from darp.calibration.world_frame import world_from_reference
from darp.errors import CalibrationError
from helpers.calibration_synthetic import board_pose, random_poses, synthetic_detections, true_rig

ARMS = ("arm110", "arm111")


def make_obs(seed: int, n: int = 20, noise_px: float = 0.1, encoder_deg: float = 0.002, profile: str = "realistic"):
    truth, settings = true_rig(seed, profile)
    rig = truth.nominal
    T_wb = board_pose(rig)
    poses = {a: random_poses(rig, a, n, T_wb, seed) for a in ARMS}
    dets = synthetic_detections(truth, poses, T_wb, noise_px=noise_px, encoder_noise_deg=encoder_deg, seed=seed)
    return build_observations(dets, DEFAULT_BOARD, ARMS), truth, settings


@pytest.fixture(scope="module")
def seed0():
    return make_obs(0)


@pytest.fixture(scope="module")
def core0(seed0):
    return calibrate_observations(seed0[0])


def _calibration(params, truth):
    T_ref_world = world_from_reference(params.T_ref_base, params.T_ref_board, ARMS)
    serials = {a: truth.arms[a].serial for a in ARMS}
    return to_calibration(params, T_ref_world, serials, epoch="test", date="2024-01-01", board=DEFAULT_BOARD)


def test_analytic_jacobian_matches_central_differences(seed0) -> None:
    obs, _, _ = seed0
    p0 = opencv_chain({a: opencv_hand_eye(obs, a) for a in ARMS}, ARMS, None)
    layout = Layout(ARMS, {a: np.ones(6, bool) for a in ARMS})
    x = np.random.default_rng(3).normal(0.0, 0.02, layout.size)  # away from the start: exercises Jr(w)
    r, J = residuals_and_jacobian(x, layout, p0, obs, 0.3)
    n = len(r)
    Jn = numeric_jacobian(lambda v: _residuals(v, layout, p0, obs, 0.3, np.inf, "flange")[:n], x, 1e-6)
    assert np.allclose(r, _residuals(x, layout, p0, obs, 0.3, np.inf, "flange")[:n], atol=1e-9)
    rel = np.abs(J - Jn).max(axis=0) / np.abs(Jn).max(axis=0)
    assert rel.max() < 1e-6


def test_imitators_rank_tied_coefficients_in_parameter_order() -> None:
    """Two parameters with the same effect share a degenerate offset's coefficient equally; their last
    bits (which change with the BLAS kernel) must not decide which one is listed."""
    names = ["a", "b", "c", "d", "e"]
    for ulp in (-1e-16, 0.0, 1e-16):
        coef = np.array([0.02, -1.8, 0.47 + ulp, 1.07, -0.47])
        assert imitators(coef, names) == ["b", "d", "c"]
        assert imitators(coef[::-1], names[::-1]) == ["b", "d", "e"]
    assert imitators(np.array([0.01, 0.04]), ["a", "b"]) == []


def test_opencv_hand_eye_is_exact_on_noiseless_data_without_joint_offsets() -> None:
    obs, truth, _ = make_obs(5, n=12, noise_px=0.0, encoder_deg=0.0, profile="ideal")
    for arm in ARMS:
        estimates = opencv_hand_eye(obs, arm)
        assert len(estimates) == len(HAND_EYE_METHODS) + 2
        for e in estimates:
            assert e.ok and e.median_px < 0.01, e.method
            assert np.allclose(e.T_wrist_cam, truth.arms[arm].T_wrist_cam, atol=1e-5), e.method


def test_identifiability_finds_joint1_and_joint6_degenerate_and_the_rest_identifiable(core0) -> None:
    core = core0
    ident = core.identifiability
    for arm in ARMS:
        rho = ident.rho[arm]
        assert rho[0] < 1e-6 and rho[5] < 1e-6, rho  # exact degeneracies, found numerically
        assert np.all(rho[1:5] > 1e-2), rho
        assert list(ident.identifiable[arm]) == [False, True, True, True, True, False]
        assert np.all(core.params.dq[arm][[0, 5]] == 0.0)
    assert f"{ARMS[1]}.joint1" in ident.degenerate_with and f"{ARMS[0]}.joint6" in ident.degenerate_with
    # joint 6 is imitated by the same arm's hand-eye, joint 1 of the second arm by its base
    assert any(n.startswith(f"handeye:{ARMS[0]}") for n in ident.degenerate_with[f"{ARMS[0]}.joint6"])
    assert any(n.startswith(f"base:{ARMS[1]}") for n in ident.degenerate_with[f"{ARMS[1]}.joint1"])
    sv = ident.singular_values
    # four null directions among the twelve offsets: numerically ~1e-6 of the largest (finite differences,
    # BLAS-dependent), the next one five orders of magnitude above them
    assert np.sum(sv < 1e-4 * sv[0]) == 4 and sv[-5] > 1e-2 * sv[0], sv


@pytest.mark.parametrize("seed", [0, 1])
def test_refinement_recovers_the_true_rig_and_beats_opencv(seed: int, seed0, core0) -> None:
    obs, truth, settings = seed0 if seed == 0 else make_obs(seed)
    core = core0 if seed == 0 else calibrate_observations(obs)
    true_cal = truth.calibration(settings)
    q = {a: obs.q_rad[obs.for_arm(a)] for a in ARMS}
    err = truth_errors(_calibration(core.params, truth), true_cal, ARMS, core.identifiability.identifiable, q)
    base = truth_errors(_calibration(opencv_chain(core.opencv, ARMS, "calibrateHandEye"), truth), true_cal, ARMS,
                        None, q)
    for arm in ARMS:
        a = err["arms"][arm]
        assert a["hand_eye"]["translation_mm"] < 0.5 and a["hand_eye"]["rotation_deg"] < 0.05
        assert a["max_identifiable_joint_offset_error_deg"] < 0.05
        assert a["camera_pose"]["translation_mm_max"] < 0.5
        assert a["joint_offset_error_deg"][0] is None and a["joint_offset_error_deg"][5] is None
        # OpenCV alone, blind to the joint offsets, is several times worse
        assert base["arms"][arm]["camera_pose"]["translation_mm_median"] > 3 * a["camera_pose"]["translation_mm_median"]
    # over seeds 0-5: 0.26-0.97 mm and 0.005-0.052 deg (20 captures per arm, 0.1 px corner noise)
    assert err["base_to_base"]["translation_mm"] < 1.0 and err["base_to_base"]["rotation_deg"] < 0.06
    assert base["base_to_base"]["translation_mm"] > 5 * err["base_to_base"]["translation_mm"]


def test_reported_uncertainty_covers_the_actual_error(seed0, core0) -> None:
    _, truth, settings = seed0
    core = core0
    res = core.refined
    true_cal = truth.calibration(settings)
    for arm in ARMS:
        std = np.degrees(res.joint_offset_std(arm))
        err = np.degrees(core.params.dq[arm] - true_cal.arms[arm].joint_offsets_rad)
        free = core.identifiability.identifiable[arm]
        assert np.all(std[free] > 0) and np.all(std[~free] == 0)
        assert np.all(np.abs(err[free]) < 5 * std[free]), (err, std)
    # the clustered (per-capture) covariance is more cautious than the i.i.d. one
    assert np.trace(res.covariance) > np.trace(res.covariance_iid)


def test_world_frame_is_the_rig_convention_measured(seed0, core0) -> None:
    _, truth, _ = seed0
    core = core0
    cal = _calibration(core.params, truth)
    o110, o111 = (cal.arms[a].T_world_base[:3, 3] for a in ARMS)
    assert np.allclose(0.5 * (o110 + o111), 0.0, atol=1e-9)  # origin midway between the bases
    assert abs(o110[1]) < 1e-9 and abs(o111[1]) < 1e-9 and o111[0] > 0.6  # x from arm110 to arm111
    assert abs(o110[2]) < 1e-3  # bases on the table plane (up to their true tilt)
    T_world_board = np.linalg.inv(world_from_reference(core.params.T_ref_base, core.params.T_ref_board, ARMS)) \
        @ core.params.T_ref_board
    assert T_world_board[2, 2] == pytest.approx(-1.0, abs=1e-9)  # board face up: its z points down


def test_kfold_heldout_errors_are_small_for_darp_and_folds_are_stratified(seed0, core0) -> None:
    obs, _, _ = seed0
    folds = fold_assignment(obs, 4, seed=1)
    for a in range(2):
        counts = np.bincount(folds[obs.arm_index == a], minlength=4)
        assert counts.max() - counts.min() <= 1
    free = core0.identifiability.identifiable
    held = kfold_heldout(obs, lambda o: calibrate_observations(o, None, free).params, k=4)
    held_cv = kfold_heldout(obs, lambda o: opencv_chain({a: opencv_hand_eye(o, a) for a in ARMS}, ARMS,
                                                        "calibrateHandEye"), k=4)
    for arm in ARMS:
        mm = summarise(held["per_arm"][arm]["corner_3d_mm"])
        assert mm["n"] > 100 and mm["median"] < 0.5
        assert summarise(held_cv["per_arm"][arm]["corner_3d_mm"])["median"] > 3 * mm["median"]
    assert set(held["per_capture"]) == set(obs.capture_ids)


def test_too_few_captures_is_a_calibration_error(seed0) -> None:
    obs, _, _ = seed0
    small = obs.subset(np.flatnonzero(obs.for_arm("arm110"))[:2])
    with pytest.raises(CalibrationError, match="at least 3"):
        opencv_hand_eye(small, "arm110")
    with pytest.raises(CalibrationError, match="never|no capture|usable"):
        build_observations([], DEFAULT_BOARD, ARMS)
    est = opencv_hand_eye(obs, "arm110")
    for e in est:
        e.ok = False
    with pytest.raises(CalibrationError, match="every OpenCV hand-eye method failed"):
        best(est)
