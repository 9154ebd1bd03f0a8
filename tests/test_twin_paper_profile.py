"""The twin's ``paper`` profile and its error sources (issue 12): each source has the stated magnitude, is
deterministic for a seed, and is absent from ``ideal`` and ``realistic``; ``--settings FILE`` on every twin
command."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from darp.cli._app import run
from darp.errors import ConfigError, DarpError
from darp.kinematics import z1
from darp.kinematics.rig import load_rig
from darp.twin.arm_errors import KinematicErrors, LinkDeflection, fk_batch_with_errors, gravity_torques
from darp.twin.arm_sim import SimArm
from darp.twin.camera.sensor import UnitErrors
from darp.twin.clock import SimClock
from darp.twin.settings import (
    OPTIONAL_GROUPS,
    ArmErrorSettings,
    TwinSettings,
)
from darp.twin.truth import draw_true_rig

FORWARD = np.array([0.0, 1.5, -1.0, -0.54, 0.0, 0.0])
SHOW_MID = np.array([0.0, 0.9, -1.2, 0.25, 0.0, 0.0])


# -- the profile -------------------------------------------------------------------------------------

def test_paper_profile_round_trips_through_yaml(tmp_path: Path) -> None:
    paper = TwinSettings.from_profile("paper", seed=5)
    paper.save(tmp_path / "paper.yaml")
    again = TwinSettings.load(tmp_path / "paper.yaml")
    assert again == paper and again.profile == "paper" and again.seed == 5
    text = (tmp_path / "paper.yaml").read_text()
    error_groups = [g for g in OPTIONAL_GROUPS if g != "lighting"]  # lighting: the studio lights, not an error
    for group in error_groups:
        assert f"\n{group}:" in text
    # every error source is on in the paper profile
    for group in error_groups:
        values = dataclasses.asdict(getattr(paper, group))
        assert all(v > 0 for k, v in values.items() if k != "thermal_tau_s"), group


@pytest.mark.parametrize("profile", ["ideal", "realistic"])
def test_default_profiles_hold_no_new_error_and_write_the_same_yaml(profile: str) -> None:
    settings = TwinSettings.from_profile(profile)
    text = settings.to_yaml()
    for group in OPTIONAL_GROUPS:
        assert getattr(settings, group) == type(getattr(settings, group))()
        assert f"{group}:" not in text
    assert TwinSettings.from_dict(settings.to_dict()) == settings


def test_a_partial_settings_file_keeps_the_profile_and_bad_keys_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("profile: paper\nseed: 3\nsync:\n  latency_ms: 12.0\n")
    s = TwinSettings.load(path)
    assert s.sync.latency_ms == 12.0 and s.sync.jitter_ms == TwinSettings.from_profile("paper").sync.jitter_ms
    path.write_text("profile: paper\narm_errors:\n  backlash: 1.0\n")
    with pytest.raises(ConfigError, match="mine.yaml") as err:
        TwinSettings.load(path)
    assert "backlash" in str(err.value)
    path.write_text("profile: paper\nimages:\n  blur_sigma_px: -1\n")
    with pytest.raises(ConfigError, match="blur_sigma_px"):
        TwinSettings.load(path)


def test_scaled_multiplies_every_magnitude() -> None:
    paper = TwinSettings.from_profile("paper")
    double = paper.scaled(2.0)
    assert double.joints.encoder_noise_std_deg == 2 * paper.joints.encoder_noise_std_deg
    assert double.arm_errors.backlash_deg == 2 * paper.arm_errors.backlash_deg
    assert double.arm_errors.joint_stiffness_nm_per_rad == paper.arm_errors.joint_stiffness_nm_per_rad / 2
    assert double.depth_errors.thermal_tau_s == paper.depth_errors.thermal_tau_s
    assert double.images.blur_sigma_px == 2 * paper.images.blur_sigma_px
    assert dataclasses.replace(paper.scaled(0.0).arm_errors, payload_kg=0.0) == ArmErrorSettings()


# -- robot ----------------------------------------------------------------------------------------

def test_kinematic_errors_move_the_flange_by_their_size_and_are_seeded() -> None:
    Q = np.array([FORWARD, SHOW_MID])
    zero = KinematicErrors(np.zeros((6, 3)), np.zeros((6, 3)))
    assert np.allclose(fk_batch_with_errors(Q, zero), z1.fk_batch(Q), atol=1e-12)
    s = ArmErrorSettings(link_origin_std_mm=0.3, axis_tilt_std_deg=0.05)
    errors = KinematicErrors.draw(s, np.random.default_rng(1))
    assert errors is not None
    again = KinematicErrors.draw(s, np.random.default_rng(1))
    assert again is not None and np.array_equal(errors.origin_m, again.origin_m)
    shift_mm = 1e3 * np.linalg.norm(fk_batch_with_errors(Q, errors)[:, :3, 3] - z1.fk_batch(Q)[:, :3, 3], axis=1)
    # six origins of 0.3 mm per axis plus 0.05 deg tilts at up to 0.5 m lever: around a millimetre
    assert np.all(shift_mm > 0.1) and np.all(shift_mm < 5.0)
    assert KinematicErrors.draw(ArmErrorSettings(), np.random.default_rng(1)) is None


def test_the_mujoco_arm_follows_the_true_chain_with_kinematic_errors() -> None:
    from darp.twin.world import TwinWorld

    settings = TwinSettings.from_profile("paper", seed=4)
    true_rig = draw_true_rig(load_rig(), settings)
    world = TwinWorld(true_rig.nominal, true_rig.arms)
    for arm_id in true_rig.arms:
        assert true_rig.arms[arm_id].kinematic_errors is not None
        world.set_arm_q(arm_id, SHOW_MID)
    world.forward()
    for arm_id in true_rig.arms:
        assert np.allclose(world.T_world_camera(arm_id), true_rig.T_world_cam(arm_id, SHOW_MID), atol=1e-9)


def test_gravity_torques_are_the_gradient_of_the_potential_energy() -> None:
    """Oracle: tau_j = -dU/dq_j with U = sum m g z over the same lumped masses (finite differences)."""
    from darp.twin.arm_errors import LINK_MASSES

    def potential(q: np.ndarray, payload: float) -> float:
        links = z1.link_transforms_batch(q[None])[0]
        u = sum(m * 9.81 * (links[i, :3, :3] @ np.asarray(c) + links[i, :3, 3])[2] for i, m, c in LINK_MASSES)
        tip = links[6, :3, :3] @ np.array([z1.WRIST_FRAMES["flange"] + 0.03, 0, 0]) + links[6, :3, 3]
        return float(u + payload * 9.81 * tip[2])

    for q in (FORWARD, SHOW_MID):
        tau = gravity_torques(q[None], 0.2)[0]
        for j in (1, 2, 3):
            h = 1e-6
            dq = np.zeros(6)
            dq[j] = h
            numeric = -(potential(q + dq, 0.2) - potential(q - dq, 0.2)) / (2 * h)
            assert tau[j] == pytest.approx(numeric, rel=1e-5, abs=1e-6)
    # the upper arm holding the forearm forward: about 5-15 N m at joint 2, a few tenths of a degree at 2000 N m/rad
    sag_deg = np.rad2deg(gravity_torques(FORWARD[None], 0.2)[0] / 2000.0)
    assert 0.05 < sag_deg[1] < 0.5 and sag_deg[0] == 0.0 and sag_deg[5] == 0.0


def _arm(settings: ArmErrorSettings, seed: int = 0) -> SimArm:
    clock = SimClock(0.0)
    return SimArm("arm110", clock, SHOW_MID, deflection=LinkDeflection(settings, np.random.default_rng(seed)))


def _settle(arm: SimArm) -> None:
    arm.clock.sleep(5.0)


def test_backlash_puts_the_link_half_the_dead_band_behind_the_last_motion() -> None:
    arm = _arm(ArmErrorSettings(backlash_deg=0.2))
    target = SHOW_MID + np.array([0.1, 0.1, -0.1, 0.1, 0.1, 0.1])
    arm.move_to(target)
    _settle(arm)
    lag = np.rad2deg(arm.true_q() - arm.read_state().q_rad)
    assert np.allclose(lag, -0.1 * np.sign(target - SHOW_MID), atol=1e-9)
    arm.move_to(SHOW_MID)
    _settle(arm)
    lag = np.rad2deg(arm.true_q() - arm.read_state().q_rad)
    assert np.allclose(lag, +0.1 * np.sign(target - SHOW_MID), atol=1e-9)


def test_repeatability_spreads_arrivals_by_the_stated_amount_and_is_seeded() -> None:
    def arrivals(seed: int) -> np.ndarray:
        arm = _arm(ArmErrorSettings(repeatability_mm=0.1), seed)
        out = []
        for k in range(40):
            arm.move_to(FORWARD if k % 2 == 0 else SHOW_MID)
            _settle(arm)
            if k % 2 == 0:
                out.append(z1.fk(arm.true_q())[:3, 3])
        return np.array(out)

    a = arrivals(3)
    assert np.array_equal(a, arrivals(3))
    spread_mm = 1e3 * np.linalg.norm(a - a.mean(axis=0), axis=1)
    assert 0.005 < np.median(spread_mm) < 0.1 and spread_mm.max() < 0.3


def test_sag_is_on_the_link_side_and_depends_on_the_configuration() -> None:
    arm = _arm(ArmErrorSettings(joint_stiffness_nm_per_rad=2000.0, payload_kg=0.2))
    lag_mid = arm.true_q() - arm.read_state().q_rad
    arm.move_to(FORWARD)
    _settle(arm)
    lag_fwd = arm.true_q() - arm.read_state().q_rad
    expected = gravity_torques(FORWARD[None], 0.2)[0] / 2000.0
    assert np.allclose(lag_fwd, expected, atol=1e-12)
    assert abs(lag_fwd[1] - lag_mid[1]) > np.deg2rad(0.05)  # not a constant joint offset a calibration absorbs


# -- camera ---------------------------------------------------------------------------------------

def test_depth_scale_offset_bias_and_thermal_drift() -> None:
    z = np.array([[0.0, 0.3, 0.6]], dtype=np.float32)
    e = UnitErrors(depth_scale=0.005, depth_offset_m=0.001, depth_bias_per_m=0.002, thermal_drift=0.002,
                   thermal_tau_s=600.0, session_start_s=100.0)
    cold = e.depth(z, 100.0)
    assert cold[0, 0] == 0.0  # invalid stays invalid
    assert cold[0, 2] == pytest.approx(0.6 * 1.005 + 0.001 + 0.002 * 0.36, abs=1e-6)
    warm = e.depth(z, 700.0)  # one time constant later: 63 % of the drift
    assert warm[0, 2] - cold[0, 2] == pytest.approx(0.6 * 0.002 * (1 - np.exp(-1)), abs=1e-6)
    assert UnitErrors().depth(z, 5.0) is z


def test_factory_intrinsics_differ_from_the_rendering_ones_by_the_stated_spread() -> None:
    from darp.twin.camera.sensor import TwinCameraSettings
    from darp.twin.camera.spec import make_camera_spec
    from darp.twin.rig_backend import camera_unit_errors

    spec = make_camera_spec(serial="1")
    base = TwinCameraSettings.from_profile("realistic")
    assert camera_unit_errors(TwinSettings.from_profile("realistic"), "1", spec, base) == (base, None)
    paper = TwinSettings.from_profile("paper", seed=2)
    ratios, shifts = [], []
    for serial in range(40):
        cam, factory = camera_unit_errors(paper, str(serial), spec, base)
        assert factory is not None and cam.errors is not None
        ratios.append(factory.color.fx / spec.color.fx - 1.0)
        shifts.append(factory.depth.ppx - spec.depth.ppx)
    assert np.std(ratios) == pytest.approx(paper.depth_errors.focal_std_pct / 100, rel=0.35)
    assert np.std(shifts) == pytest.approx(paper.depth_errors.centre_std_px, rel=0.35)
    again, _ = camera_unit_errors(paper, "0", spec, base)
    first, _ = camera_unit_errors(paper, "0", spec, base)
    assert again == first


# -- board images -----------------------------------------------------------------------------------

def _board_image() -> tuple[np.ndarray, cv2.aruco.CharucoDetector]:
    board = cv2.aruco.CharucoBoard((10, 7), 0.03, 0.022, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))
    grey = board.generateImage((640, 448), marginSize=20)
    # a slight perspective so corners fall between pixels
    H = np.array([[0.9, 0.05, 20.0], [-0.03, 0.92, 15.0], [0.0, 0.0001, 1.0]])
    grey = cv2.warpPerspective(grey, H, (640, 480), borderValue=255)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), cv2.aruco.CharucoDetector(board)


def test_photographic_errors_add_sub_pixel_corner_noise() -> None:
    """Oracle: OpenCV's ChArUco detector on a board image with and without blur, uneven light and noise."""
    bgr, detector = _board_image()
    clean, clean_ids, _, _ = detector.detectBoard(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    errors = UnitErrors(blur_sigma_px=0.8, shading=0.2, noise_dn=2.0)
    shots = []
    for seed in range(3):
        img = errors.photograph(bgr, np.random.default_rng(seed), None)
        assert np.array_equal(img, errors.photograph(bgr, np.random.default_rng(seed), None))
        corners, ids, _, _ = detector.detectBoard(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        assert ids is not None and len(ids) >= 0.9 * len(clean_ids)
        common = np.intersect1d(ids.ravel(), clean_ids.ravel())
        a = corners[np.searchsorted(ids.ravel(), common, sorter=np.argsort(ids.ravel()))]
        b = clean[np.searchsorted(clean_ids.ravel(), common, sorter=np.argsort(clean_ids.ravel()))]
        shots.append(np.linalg.norm((a - b).reshape(-1, 2), axis=1))
    err = np.concatenate(shots)
    assert 0.005 < np.median(err) < 0.5  # sub-pixel, as on real photographs


def test_motion_blur_smears_along_the_motion() -> None:
    img = np.zeros((60, 60, 3), np.uint8)
    img[:, 30:] = 255
    blurred = UnitErrors().photograph(img, np.random.default_rng(0), np.array([8.0, 0.0]))
    row = blurred[30, :, 0].astype(int)
    assert 0 < row[28] < 255 and 0 < row[32] < 255  # the edge spread over the motion
    column = blurred[:, 20, 0]
    assert np.all(column == 0)  # nothing moves vertically
    assert np.array_equal(UnitErrors().photograph(img, np.random.default_rng(0), np.array([0.1, 0.0])), img)


# -- timing ---------------------------------------------------------------------------------------

def test_frame_stamps_carry_latency_and_seeded_jitter() -> None:
    from darp.twin.camera.backend import TwinCameraBackend

    stamps = []
    for latency, jitter in ((0.0, 0.0), (5.0, 1.0)):
        backend = TwinCameraBackend.__new__(TwinCameraBackend)
        backend.clock = SimClock(1000.0)
        backend.clock_offset_ms = 0.0
        backend.latency_ms, backend.jitter_ms, backend.jitter_seed = latency, jitter, 9
        stamps.append(np.array([backend.frame_stamp_ms(n, n * 33_333_333) for n in range(200)]))
    assert backend.frame_stamp_ms(17, 5) == backend.frame_stamp_ms(17, 5)  # seeded per frame number
    delta = stamps[1] - stamps[0]
    assert delta.mean() == pytest.approx(5.0, abs=0.3) and delta.std() == pytest.approx(1.0, rel=0.2)


# -- --settings on every twin command -------------------------------------------------------------

BAD = "profile: paper\nsync:\n  latency: 3\n"


@pytest.mark.parametrize("argv", [
    ["collect", "s", "--twin"],
    ["calib", "capture", "--twin", "--captures", "1"],
    ["twin", "record", "--object", "cube"],
    ["demo"],
])
def test_every_twin_command_takes_settings_and_names_a_bad_file(argv: list[str], tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad_settings.yaml"
    bad.write_text(BAD)
    extra = ["-o", str(tmp_path / "out")]
    if argv[0] == "twin":
        waypoints = tmp_path / "w.yaml"
        waypoints.write_text("arm110: []\n")
        extra += ["--waypoints", str(waypoints)]
    code = run([*argv, *extra, "--settings", str(bad)])
    err = capsys.readouterr().err
    assert code == 2
    assert "bad_settings.yaml" in err and "latency" in err and "Traceback" not in err
    assert run([*argv, "--help"]) == 0
    assert "--settings" in capsys.readouterr().out


def test_a_settings_file_seed_is_used_unless_seed_is_given(tmp_path: Path) -> None:
    from darp.cli._options import Profile, twin_settings

    path = tmp_path / "s.yaml"
    TwinSettings.from_profile("paper", seed=7).save(path)
    assert twin_settings(Profile.realistic, 0, path) == TwinSettings.from_profile("paper", seed=7)
    assert twin_settings(Profile.paper, 3, None) == TwinSettings.from_profile("paper", seed=3)


def test_the_demo_table_shows_the_ratio_to_the_paper() -> None:
    from darp.cli._demo_tables import heldout_table

    results = {"heldout": {"objects": [], "aggregate": {"keyframes": 9, "count": 100, "median_mm": 2.0,
                                                         "rmse_mm": 6.0, "p90_mm": 6.38, "within_5mm_pct": 83.82,
                                                         "within_10mm_pct": 96.56}}}
    last = heldout_table(results).splitlines()[-1]
    assert last.startswith("darp / paper")
    assert "0.94" in last and "1.49 !" in last and last.count("1.00") == 3


@pytest.mark.slow
def test_a_paper_profile_survey_is_byte_identical_for_a_seed(tmp_path: Path) -> None:
    """Every new error source draws from named, seeded generators: the same seed gives the same files."""
    import hashlib

    from helpers.twin_surveys import record

    def digests(folder: Path) -> dict[str, str]:
        return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()}

    a = digests(record(tmp_path / "a" / "cube", "paper", 2, 6))
    b = digests(record(tmp_path / "b" / "cube", "paper", 2, 6, workers=True))
    assert a == b and "truth/settings.yaml" in a
    settings = TwinSettings.load(tmp_path / "a" / "cube" / "truth" / "settings.yaml")
    assert settings.profile == "paper" and settings.arm_errors == TwinSettings.from_profile("paper").arm_errors


def test_frame_disparity_field_is_seeded_zero_draws_nothing_and_is_in_the_paper_profile() -> None:
    z = np.full((48, 64), 0.4, np.float32)
    z[0, 0] = 0.0
    rng = np.random.default_rng(3)
    assert UnitErrors(focal_baseline_px_m=19.0).depth(z, 1.0, rng) is z  # zero: nothing drawn, same array
    assert rng.random() == np.random.default_rng(3).random()
    e = UnitErrors(field_disparity_px=0.2, focal_baseline_px_m=19.0)
    a, b = e.depth(z, 1.0, np.random.default_rng(7)), e.depth(z, 1.0, np.random.default_rng(7))
    assert np.array_equal(a, b) and a[0, 0] == 0.0
    assert not np.array_equal(a, e.depth(z, 1.0, np.random.default_rng(8)))
    assert 0.1e-3 < float(np.std(a[z > 0] - 0.4)) < 3e-3
    paper = TwinSettings.from_profile("paper")
    assert paper.depth_errors.frame_field_px > 0
    assert paper.scaled(2.0).depth_errors.frame_field_px == pytest.approx(2 * paper.depth_errors.frame_field_px)
    for name in ("ideal", "realistic"):
        assert TwinSettings.from_profile(name).depth_errors.frame_field_px == 0.0


def test_kinematic_errors_have_their_stated_size_in_a_random_direction() -> None:
    """Every arm's joint origins are off by exactly sqrt(3) x the per-axis std and its axes tilted by exactly
    sqrt(2) x the std, perpendicular to the nominal axis (so no seed draws a nearly exact or a 3-sigma arm)."""
    s = ArmErrorSettings(link_origin_std_mm=1.0, axis_tilt_std_deg=0.2)
    directions = []
    for seed in range(5):
        errors = KinematicErrors.draw(s, np.random.default_rng(seed))
        assert errors is not None
        assert np.allclose(np.linalg.norm(errors.origin_m, axis=1), np.sqrt(3.0) * 1e-3, rtol=1e-12)
        assert np.allclose(np.linalg.norm(errors.axis_tilt_rad, axis=1), np.sqrt(2.0) * np.deg2rad(0.2), rtol=1e-12)
        assert np.allclose(np.sum(errors.axis_tilt_rad * z1.JOINT_AXES, axis=1), 0.0, atol=1e-15)
        # the true axes really are tilted by that angle
        cos = np.sum(errors.axes() * z1.JOINT_AXES, axis=1)
        assert np.allclose(np.rad2deg(np.arccos(np.clip(cos, -1, 1))), np.sqrt(2.0) * 0.2, rtol=1e-6)
        directions.append(errors.origin_m[1] / np.linalg.norm(errors.origin_m[1]))
    assert min(np.linalg.norm(a - b) for i, a in enumerate(directions) for b in directions[i + 1:]) > 0.05


def test_per_unit_depth_errors_have_their_stated_size_and_a_random_sign() -> None:
    from darp.twin.camera.sensor import TwinCameraSettings
    from darp.twin.camera.spec import make_camera_spec
    from darp.twin.rig_backend import camera_unit_errors

    spec = make_camera_spec(serial="1")
    base = TwinCameraSettings.from_profile("realistic")
    paper = TwinSettings.from_profile("paper", seed=5)
    d = paper.depth_errors
    signs = []
    for serial in range(12):
        cam, factory = camera_unit_errors(paper, str(serial), spec, base)
        e = cam.errors
        assert abs(e.depth_scale) == pytest.approx(d.scale_std_pct / 100)
        assert abs(e.depth_offset_m) == pytest.approx(d.offset_std_mm * 1e-3)
        assert abs(e.depth_bias_per_m) == pytest.approx(d.bias_std_mm_per_m2 * 1e-3)
        assert abs(factory.color.fx / spec.color.fx - 1.0) == pytest.approx(d.focal_std_pct / 100)
        assert np.hypot(factory.color.ppx - spec.color.ppx, factory.color.ppy - spec.color.ppy) == pytest.approx(
            np.sqrt(2.0) * d.centre_std_px)
        signs.append(np.sign(e.depth_scale))
    assert -12 < sum(signs) < 12  # both signs occur


def test_a_sensor_fixed_depth_field_is_the_same_every_frame_and_leaves_the_other_draws_alone() -> None:
    """The static field: RMS of its nodes exactly as stated, the same depth error in every frame (no rng
    needed), z^2 growth, varying across the image, and drawn from its own stream (the unit's other errors,
    hence its colour images and the calibration, are the same with or without it)."""
    from darp.twin.camera.sensor import STATIC_FIELD_GRID, TwinCameraSettings, sensor_field_nodes
    from darp.twin.camera.spec import make_camera_spec
    from darp.twin.rig_backend import camera_unit_errors

    nodes = sensor_field_nodes(np.random.default_rng(1), 0.15)
    arr = np.asarray(nodes)
    assert arr.shape == STATIC_FIELD_GRID and float(np.sqrt(np.mean(arr**2))) == pytest.approx(0.15)
    fb = 383.0 * 0.05
    e = UnitErrors(static_field_px=nodes, focal_baseline_px_m=fb)
    for z0 in (0.4, 0.8):
        z = np.full((480, 640), z0, np.float32)
        z[0, 0] = 0.0
        a, b = e.depth(z, 1.0), e.depth(z, 2.0, np.random.default_rng(9))
        assert np.array_equal(a, b) and a[0, 0] == 0.0  # fixed to the sensor: every frame alike
        err = (a - z0)[z > 0]
        expected = z0 * z0 * 0.9 * 0.15 / fb  # depth std of the disparity field (bicubic: ~0.9 x the nodes' RMS)
        assert 0.5 * expected < float(np.std(err)) < 1.5 * expected
        # it varies across the image: one eighth of the width apart, the errors differ
        assert float(np.std(a[:, 80:] - a[:, :-80])) > 0.5 * expected
    # the camera's draw: own stream, other unit errors unchanged
    spec = make_camera_spec(serial="1")
    base = TwinCameraSettings.from_profile("realistic")
    paper = TwinSettings.from_profile("paper", seed=3)
    assert paper.depth_errors.static_field_px > 0
    without = dataclasses.replace(paper, depth_errors=dataclasses.replace(paper.depth_errors, static_field_px=0.0))
    with_cam, with_factory = camera_unit_errors(paper, "7", spec, base)
    without_cam, without_factory = camera_unit_errors(without, "7", spec, base)
    assert without_cam.errors.static_field_px == ()
    for stream in ("color", "depth"):
        a_i, b_i = getattr(with_factory, stream), getattr(without_factory, stream)
        assert (a_i.fx, a_i.fy, a_i.ppx, a_i.ppy) == (b_i.fx, b_i.fy, b_i.ppx, b_i.ppy)
    assert dataclasses.replace(with_cam.errors, static_field_px=()) == without_cam.errors
    other, _ = camera_unit_errors(paper, "8", spec, base)
    assert other.errors.static_field_px != with_cam.errors.static_field_px  # one field per unit
    for name in ("ideal", "realistic"):
        assert TwinSettings.from_profile(name).depth_errors.static_field_px == 0.0
    assert paper.scaled(2.0).depth_errors.static_field_px == pytest.approx(2 * paper.depth_errors.static_field_px)


def test_unabsorbable_size_matches_a_nonlinear_fit_of_the_calibration_model() -> None:
    """Oracle: scipy's nonlinear least squares of joint offsets, base and hand-eye corrections (18
    unknowns) to the true chain's camera points at the reference configurations."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from darp.kinematics.kinematic_model import chain_fk, tilted_axes
    from darp.twin.arm_errors import CALIBRATION_Q_RAD, unabsorbable_mm

    errors = KinematicErrors.draw(ArmErrorSettings(link_origin_std_mm=1.0, axis_tilt_std_deg=0.2),
                                  np.random.default_rng(3))
    assert errors is not None
    Q = CALIBRATION_Q_RAD
    T_fc = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.055], [0, 0, 0, 1.0]])
    pts = np.array([[0.0, 0.0, 0.4], [0.1, 0.0, 0.4], [-0.1, 0.0, 0.4], [0.0, 0.1, 0.4], [0.0, -0.1, 0.4]])

    def points(F: np.ndarray) -> np.ndarray:
        C = F @ T_fc
        return np.einsum("nij,pj->npi", C[:, :3, :3], pts) + C[:, None, :3, 3]

    def small(v: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(v[:3]).as_matrix()
        T[:3, 3] = v[3:]
        return T

    target = points(fk_batch_with_errors(Q, errors))
    nominal_o, nominal_a = np.asarray(z1.JOINT_ORIGINS_M, float), tilted_axes(np.zeros((6, 3)))

    def residual(p: np.ndarray) -> np.ndarray:
        F = small(p[:6])[None] @ chain_fk(Q + p[6:12], nominal_o, nominal_a) @ small(p[12:])[None]
        return (points(F) - target).ravel()

    fit = least_squares(residual, np.zeros(18), x_scale=0.01)
    nonlinear_mm = 1e3 * float(np.median(np.linalg.norm(fit.fun.reshape(-1, 3), axis=1)))
    assert nonlinear_mm > 0.3  # the draw is not absorbable
    assert unabsorbable_mm(errors) == pytest.approx(nonlinear_mm, rel=0.05)


def test_an_unabsorbed_target_picks_directions_of_that_size_and_keeps_every_magnitude() -> None:
    from darp.twin.arm_errors import unabsorbable_mm

    base = ArmErrorSettings(link_origin_std_mm=1.0, axis_tilt_std_deg=0.2)
    free = [KinematicErrors.draw(base, np.random.default_rng(s)) for s in range(8)]
    sizes = [unabsorbable_mm(e) for e in free if e is not None]
    assert max(sizes) - min(sizes) > 0.5  # without a target the unabsorbable part spreads widely
    aimed = dataclasses.replace(base, unabsorbed_mm=2.5)
    for s in range(8):
        e = KinematicErrors.draw(aimed, np.random.default_rng(s))
        assert e is not None
        assert unabsorbable_mm(e) == pytest.approx(2.5, rel=0.05)
        assert np.allclose(np.linalg.norm(e.origin_m, axis=1), np.sqrt(3.0) * 1e-3)
        assert np.allclose(np.linalg.norm(e.axis_tilt_rad, axis=1), np.sqrt(2.0) * np.deg2rad(0.2))
        assert np.allclose(np.sum(e.axis_tilt_rad * np.asarray(z1.JOINT_AXES, float), axis=1), 0.0, atol=1e-12)
    # no target: the first draw, as before the setting existed
    e0, f0 = KinematicErrors.draw(base, np.random.default_rng(0)), free[0]
    assert e0 is not None and f0 is not None and np.array_equal(e0.origin_m, f0.origin_m)
    paper = TwinSettings.from_profile("paper", seed=11)
    for arm in draw_true_rig(load_rig(), paper).arms.values():
        assert arm.kinematic_errors is not None
        assert unabsorbable_mm(arm.kinematic_errors) == pytest.approx(paper.arm_errors.unabsorbed_mm, rel=0.05)
    assert TwinSettings.from_profile("paper").scaled(2.0).arm_errors.unabsorbed_mm == pytest.approx(5.0)


def test_the_demo_surveys_with_the_papers_orbit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``darp collect`` plans for coverage by default; the demo reproduces the paper, so it asks for the orbit."""
    import darp.cli.demo as demo
    from darp.cli._options import Profile

    calls: list[list[str]] = []

    class Stop(Exception):
        pass

    def record(args: list[object]) -> None:
        calls.append([str(a) for a in args])
        if calls[-1][0] == "collect":
            raise Stop

    monkeypatch.setattr(demo, "_call", record)
    with pytest.raises(Stop):
        demo.demo_command(out=tmp_path, objects=None, seed=0, fps=6, captures=20, profile=Profile.paper,
                          settings_file=None)
    assert [c[0] for c in calls] == ["calib", "calib", "collect"]
    collect = calls[-1]
    assert collect[collect.index("--viewpoints") + 1] == "orbit"
    assert collect[collect.index("--profile") + 1] == "paper"


@pytest.mark.parametrize(("extra", "expected"), [([], "paper"), (["--profile", "realistic"], "realistic")])
def test_the_demo_runs_the_paper_profile_unless_told(extra: list[str], expected: str, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """``darp demo`` shows the real rig's error levels by default; ``--profile realistic`` is an option away."""
    import darp.cli.demo as demo

    calls: list[list[str]] = []

    def record(args: list[object]) -> None:
        calls.append([str(a) for a in args])
        raise DarpError("stop here")

    monkeypatch.setattr(demo, "_call", record)
    assert run(["demo", "-o", str(tmp_path / "demo"), *extra]) == 2
    capture = calls[0]
    assert capture[:2] == ["calib", "capture"] and capture[capture.index("--profile") + 1] == expected
