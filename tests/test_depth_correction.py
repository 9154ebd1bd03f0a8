"""Issue 16 item 3: per-camera depth correction from board captures, stored in calibration.json and applied
at keyframe export only when ``corrections.depth`` is on."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD, corners_board_m
from darp.calibration.captures import CaptureWriter, read_captures
from darp.calibration.depth_fit import BoardDepthSamples, DepthFitSettings, board_depth_samples, fit_depth_correction
from darp.errors import FormatError
from darp.formats.calibration import DepthCorrection, calibration_from_dict, calibration_to_dict
from darp.formats.realsense.types import Intrinsics
from darp.reconstruction.backproject import CORRECTED_DEPTH_SCALE, correct_raw_depth

INTR = Intrinsics(width=320, height=240, fx=230.0, fy=230.0, ppx=160.0, ppy=120.0, model="None",
                  coeffs=(0.0, 0.0, 0.0, 0.0, 0.0))


def _look_at_board(distance_m: float, tilt_deg: float, yaw_deg: float) -> np.ndarray:
    """T_depth_board: the board's centre on the optical axis at ``distance_m``, tilted and turned."""
    side = DEFAULT_BOARD.square_length_m
    w = (DEFAULT_BOARD.squares_x * side, DEFAULT_BOARD.squares_y * side)
    a, b = np.radians(tilt_deg), np.radians(yaw_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = Ry @ Rx
    T[:3, 3] = np.array([0.0, 0.0, distance_m]) - T[:3, :3] @ np.array([0.5 * w[0], 0.5 * w[1], 0.0])
    return T


def _board_depth(T: np.ndarray, scale: float, offset_m: float, quad: float, rng: np.random.Generator,
                 noise_m: float = 0.0005, outliers: float = 0.03) -> np.ndarray:
    """A depth image of the board plane as a camera with ``z_true = scale z + offset + quad z^2`` reads it."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width].astype(float)
    rays = np.stack([(u - INTR.ppx) / INTR.fx, (v - INTR.ppy) / INTR.fy, np.ones_like(u)], axis=-1)
    n = T[:3, 2]
    z_true = float(n @ T[:3, 3]) / (rays @ n)
    if quad:
        z = (-scale + np.sqrt(scale * scale - 4 * quad * (offset_m - z_true))) / (2 * quad)
    else:
        z = (z_true - offset_m) / scale
    z = z + rng.normal(0.0, noise_m, z.shape)
    bad = rng.random(z.shape) < outliers  # the printed texture's artefacts: a few pixels 8-20 mm off
    z[bad] += rng.uniform(0.008, 0.02, int(bad.sum()))
    return np.where(z > 0, z, 0.0)


def _samples(scale: float, offset_m: float, quad: float, distances: list[float],
             seed: int = 0) -> list[BoardDepthSamples]:
    rng = np.random.default_rng(seed)
    corners = corners_board_m(DEFAULT_BOARD)
    out = []
    for k, d in enumerate(distances):
        T = _look_at_board(d, 15.0 * np.sin(k), 20.0 * np.cos(1.3 * k))
        depth = _board_depth(T, scale, offset_m, quad, rng)
        out.append(board_depth_samples(depth, INTR, T, corners, capture_id=str(k), max_pixels=2000, rng=rng))
    return out


def test_the_fit_recovers_a_known_scale_and_offset_despite_texture_artefacts() -> None:
    samples = _samples(1.02, -0.004, 0.0, [0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.38, 0.52])
    assert all(len(s.measured_m) > 1000 for s in samples)
    corr = fit_depth_correction(samples, DepthFitSettings(bootstrap=100))
    assert corr.scale == pytest.approx(1.02, abs=0.002)
    assert corr.offset_m == pytest.approx(-0.004, abs=0.0008)
    assert corr.scale_std is not None and corr.offset_std_m is not None
    assert abs(corr.scale - 1.02) < 4 * corr.scale_std + 2e-4
    assert abs(corr.offset_m + 0.004) < 4 * corr.offset_std_m + 1e-4
    # without per-capture pose errors the distance term is identifiable here, and found to be ~0
    assert abs(corr.quad_per_m) < 0.003
    # the corrected depth of a measured 0.5 m is the truth's within 0.3 mm
    z = np.array([0.5])
    assert abs(float(corr.apply(z)[0]) - (1.02 * 0.5 - 0.004)) < 3e-4


def test_a_plain_least_squares_fit_is_pulled_by_the_artefacts_the_robust_one_ignores() -> None:
    samples = _samples(1.0, 0.0, 0.0, [0.3, 0.4, 0.5, 0.6, 0.45, 0.35])
    z = np.concatenate([s.measured_m for s in samples])
    t = np.concatenate([s.predicted_m for s in samples])
    plain = np.linalg.lstsq(np.stack([z, np.ones_like(z)], 1), t, rcond=None)[0]
    robust = fit_depth_correction(samples, DepthFitSettings(bootstrap=20))
    err_plain = abs(plain[0] * 0.45 + plain[1] - 0.45)
    err_robust = abs(float(robust.apply(np.array([0.45]))[0]) - 0.45)
    assert err_robust < 0.25 * err_plain and err_robust < 2e-4


def test_the_distance_term_is_kept_only_when_the_captures_identify_it() -> None:
    wide = _samples(1.0, 0.002, -0.02, [0.25, 0.4, 0.55, 0.7, 0.85, 1.0, 1.15, 0.3, 0.9, 0.6], seed=2)
    corr = fit_depth_correction(wide, DepthFitSettings(bootstrap=100, max_quad_std_per_m=0.004))
    assert corr.quad_identifiable, corr.notes
    assert corr.quad_per_m == pytest.approx(-0.02, abs=0.005)
    narrow = _samples(1.0, 0.002, -0.02, [0.40, 0.42, 0.44, 0.46, 0.41, 0.45], seed=3)
    corr = fit_depth_correction(narrow, DepthFitSettings(bootstrap=50))
    assert not corr.quad_identifiable and "span only" in corr.notes


def test_depth_correction_round_trips_through_calibration_json_and_old_files_read() -> None:
    from darp.formats.calibration import ArmCalibration, Calibration

    arm = ArmCalibration(serial="348522076490", T_world_base=np.eye(4), T_wrist_cam=np.eye(4),
                         depth_correction=DepthCorrection(1.01, -0.002, 0.0, 0.001, 0.0004, None, False, (0.3, 0.6),
                                                          20, 6000, 0.0009, "x"),
                         time_offset_s=0.005, time_offset_std_s=0.001)
    cal = Calibration(epoch="e", date="2026-12-01", arms={"arm110": arm})
    payload = json.loads(json.dumps(calibration_to_dict(cal)))
    back = calibration_from_dict(payload)
    assert back.arms["arm110"].depth_correction == arm.depth_correction
    assert back.arms["arm110"].time_offset_s == 0.005
    old = json.loads(json.dumps(payload))
    for key in ("depth_correction", "time_offset_s", "time_offset_std_s"):
        del old["arms"]["arm110"][key]
    plain = calibration_from_dict(old)
    assert plain.arms["arm110"].depth_correction is None and plain.arms["arm110"].time_offset_s is None
    payload["arms"]["arm110"]["depth_correction"]["scale"] = 3.0
    with pytest.raises(FormatError, match="plausible depth correction"):
        calibration_from_dict(payload)


def test_corrected_raw_depth_keeps_holes_and_uses_a_finer_unit() -> None:
    raw = np.array([[0, 500], [1000, 65535]], np.uint16)
    corr = DepthCorrection(scale=1.01, offset_m=-0.002)
    out, scale = correct_raw_depth(raw, 0.001, corr)
    assert scale == CORRECTED_DEPTH_SCALE and out.dtype == np.uint16
    assert out[0, 0] == 0
    assert out[0, 1] * scale == pytest.approx(1.01 * 0.5 - 0.002, abs=CORRECTED_DEPTH_SCALE)
    assert out[1, 1] == 0  # 66 m does not fit the finer unit: no depth rather than a wrong one


def test_captures_store_depth_and_folders_without_it_still_read(tmp_path: Path) -> None:
    writer = CaptureWriter(tmp_path / "c", DEFAULT_BOARD)
    img = np.zeros((INTR.height, INTR.width), np.uint8)
    depth = np.full((INTR.height, INTR.width), 0.4567)
    depth[0, 0] = 0.0
    writer.add(arm="arm110", camera_serial="348522076490", time_s=1.0, q_rad=np.zeros(6), image=img, intrinsics=INTR,
               T_depth_stream=np.eye(4), depth_m=depth, depth_intrinsics=INTR)
    writer.add(arm="arm110", camera_serial="348522076490", time_s=2.0, q_rad=np.zeros(6), image=img, intrinsics=INTR,
               T_depth_stream=np.eye(4))
    cs = read_captures(writer.close().folder)
    with_depth, without = cs.captures
    assert with_depth.has_depth and not without.has_depth
    back = cs.load_depth(with_depth)
    assert back[0, 0] == 0.0 and back[5, 5] == pytest.approx(0.457, abs=1e-9)
    with pytest.raises(FormatError, match="no depth"):
        cs.load_depth(without)


# -- on the twin: a small capture set whose cameras have known depth errors ---------------------------------
@pytest.fixture(scope="module")
def twin_depth_captures(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    from darp.twin.calib_capture import capture_twin
    from darp.twin.settings import DepthErrorSettings, TwinSettings

    settings = TwinSettings.from_profile("realistic", seed=5)
    settings = dataclasses.replace(settings, depth_errors=DepthErrorSettings(scale_std_pct=1.5, offset_std_mm=3.0))
    root = tmp_path_factory.mktemp("depthcaps")
    caps = capture_twin(root / "caps", seed=5, n_per_arm=8, resolution=(424, 240), settings=settings)
    return caps, settings


def _true_errors(settings, serial: str):  # type: ignore[no-untyped-def]
    from darp.twin.camera.sensor import TwinCameraSettings
    from darp.twin.camera.spec import draw_unit, make_camera_spec
    from darp.twin.rig_backend import camera_unit_errors

    c = settings.camera
    spec = make_camera_spec(draw_unit(settings.rng(f"unit:{serial}")), serial=serial,
                            depth_resolution=(c.width, c.height), colour_resolution=(c.width, c.height))
    cam, _ = camera_unit_errors(settings, serial, spec, TwinCameraSettings.from_profile(c.depth_noise))
    return cam.errors


@pytest.mark.slow
def test_twin_captures_give_each_camera_its_true_depth_correction(twin_depth_captures, tmp_path: Path) -> None:
    from darp.calibration.depth_fit import estimate_depth_corrections
    from darp.calibration.detect import detect_captures
    from darp.calibration.solve import SolveSettings, solve_captures

    caps, settings = twin_depth_captures
    assert all(c.has_depth for c in caps.captures)
    corrections, skipped = estimate_depth_corrections(caps, detect_captures(caps), DepthFitSettings(bootstrap=100))
    assert set(corrections) == {"arm110", "arm111"} and not skipped
    for arm, corr in corrections.items():
        serial = caps.for_arm(arm)[0].camera_serial
        e = _true_errors(settings.with_camera(width=424, height=240, imu=False), serial)
        for z in (0.3, 0.45, 0.6):
            measured = z * (1 + e.depth_scale) + e.depth_offset_m
            error = float(corr.apply(np.array([measured]))[0]) - z
            raw = measured - z
            assert abs(error) < max(0.0012, 0.25 * abs(raw)), (arm, z, raw, error)
    # the solver stores it; a folder whose records lack depth solves as before, without a correction
    quick = SolveSettings(folds=0, compare=False)
    cal = solve_captures(caps, quick).calibration
    assert all(cal.arms[a].depth_correction is not None for a in ("arm110", "arm111"))
    plain = tmp_path / "plain"
    shutil.copytree(caps.folder, plain)
    for meta in plain.glob("arm11*_0*.json"):
        record = json.loads(meta.read_text())
        for key in ("depth_image", "depth_unit_m", "depth_intrinsics"):
            record.pop(key, None)
        meta.write_text(json.dumps(record))
    for png in plain.glob("*_depth.png"):
        png.unlink()
    old = solve_captures(read_captures(plain), quick).calibration
    assert all(old.arms[a].depth_correction is None for a in ("arm110", "arm111"))
    assert np.allclose(old.arms["arm110"].T_wrist_cam, cal.arms["arm110"].T_wrist_cam)
    assert old.report["depth_correction"]["captures_with_depth"] == 0


def _with_corrections(cal_path: Path, out: Path, depth: DepthCorrection | None, time_s: float | None) -> Path:
    payload = json.loads(cal_path.read_text())
    for arm in payload["arms"].values():
        if depth is not None:
            arm["depth_correction"] = depth.to_dict()
        if time_s is not None:
            arm["time_offset_s"] = time_s
    out.write_text(json.dumps(payload))
    return out


@pytest.mark.slow
def test_switches_off_change_nothing_and_depth_on_corrects_what_keyframes_store(survey_path: Path,
                                                                                 tmp_path: Path) -> None:
    from darp.formats.calibration import read_calibration
    from darp.formats.survey import open_survey
    from darp.processing.job import SurveyJob
    from darp.processing.runner import process_survey
    from darp.processing.settings import CorrectionSettings, ProcessSettings
    from darp.processing.stages import RECONSTRUCTION_STAGES
    from darp.reconstruction.keyframe_io import load_keyframes, read_keyframe_index

    truth_cal = survey_path / "truth" / "calibration.json"
    corr = DepthCorrection(scale=1.02, offset_m=-0.003)
    with_fields = _with_corrections(truth_cal, tmp_path / "cal.json", corr, 0.004)
    runs = {}
    for name, cal, spec in (("plain", truth_cal, "paper"), ("fields", with_fields, "paper"),
                            ("on", with_fields, "depth,time")):
        out = tmp_path / name / survey_path.name
        job = SurveyJob(survey=open_survey(survey_path), out=out, calibration=read_calibration(cal),
                        calibration_path=cal, settings=ProcessSettings(corrections=CorrectionSettings.parse(spec)))
        # the corrected run needs poses and keyframes only; the paper-mode runs go on to fusion and meshing
        process_survey(job, RECONSTRUCTION_STAGES if spec == "paper" else RECONSTRUCTION_STAGES[:2])
        runs[name] = out
    # paper mode: a calibration carrying corrections gives byte-identical outputs
    for rel in ("fused.ply", "mesh.ply", "poses/cam348522076490_arm110.npz"):
        assert (runs["plain"] / rel).read_bytes() == (runs["fields"] / rel).read_bytes(), rel
    plain_kf = {(k.arm, k.frame_number): k for k in load_keyframes(runs["plain"] / "keyframes")}
    on_kf = {(k.arm, k.frame_number): k for k in load_keyframes(runs["on"] / "keyframes")}
    assert plain_kf.keys() == on_kf.keys()  # keyframes are settled frames: the time offset keeps them
    for key in plain_kf:
        a, b = plain_kf[key].depth_m, on_kf[key].depth_m
        ok = a > 0
        assert on_kf[key].depth_scale == CORRECTED_DEPTH_SCALE
        assert np.allclose(b[ok], 1.02 * a[ok] - 0.003, atol=CORRECTED_DEPTH_SCALE)
    record = read_keyframe_index(runs["on"] / "keyframes").extra["depth_correction"]
    assert record["arms"]["arm110"]["applied"] and record["arms"]["arm110"]["scale"] == 1.02
    assert "depth_correction" not in read_keyframe_index(runs["plain"] / "keyframes").extra
    # time: the calibration's offset shifts the moving frames' poses, and poses/summary.json records it
    summary = json.loads((runs["on"] / "poses" / "summary.json").read_text())
    assert "time_alignment" not in json.loads((runs["plain"] / "poses" / "summary.json").read_text())
    p0 = np.load(runs["plain"] / "poses/cam348522076490_arm110.npz")
    p1 = np.load(runs["on"] / "poses/cam348522076490_arm110.npz")
    moved = np.linalg.norm(p0["T_world_cam"][:, :3, 3] - p1["T_world_cam"][:, :3, 3], axis=1)
    assert np.nanmax(moved) > 1e-4 and np.nanmin(moved) < 1e-6  # moving frames move, still ones do not
    stages = json.loads((runs["on"] / "stages.json").read_text())["stages"]
    assert set(stages) == {"poses", "keyframes"}
    assert stages["poses"]["summary"]["time_alignment"]["applied_s"] == {"arm110": 0.004, "arm111": 0.004}
    assert summary["time_alignment"]["arms"]["arm110"]["source"] == "calibration"


def test_a_switched_on_correction_without_its_calibration_field_warns_once(
        capsys: pytest.CaptureFixture[str]) -> None:
    from darp.cli.process import _warn_corrections

    _warn_corrections("mug", {"mode": "depth", "depth": {"warning": "corrections.depth is on but cal.json has no "
                                                                    "depth_correction for arm111"}})
    _warn_corrections("mug", {"mode": "paper"})
    err = capsys.readouterr().err.splitlines()
    assert err == ["darp: warning: mug: corrections.depth is on but cal.json has no depth_correction for arm111"]
