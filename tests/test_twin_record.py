"""Twin surveys end to end: files that darp's readers and pyrealsense2 accept, timing, ground truth,
IMU, determinism, contacts, atomic output and the ``darp twin`` command."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import darp
from darp.errors import ConfigError, TwinError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.envelope import read_envelope
from darp.formats.realsense.recording import open_recording
from darp.formats.survey import open_survey
from darp.kinematics.camera_poses import camera_poses
from darp.kinematics.rig import load_rig
from darp.kinematics.transforms import pose_error
from darp.twin.camera.spec import UnitCalibration, make_camera_spec
from darp.twin.objects.model import make_object
from darp.twin.record import record_survey
from darp.twin.rig_backend import TwinRig
from darp.twin.settings import TwinSettings
from darp.twin.truth import draw_true_rig, read_truth
from darp.twin.waypoints import Waypoint, WaypointPlan
from helpers.realsense_playback import play_back
from helpers.twin_surveys import PLACEMENT, SMALL, record

GRAVITY = 9.80665


@pytest.fixture(scope="module")
def ideal(tmp_path_factory) -> Path:
    return record(tmp_path_factory.mktemp("ideal") / "cube", "ideal", 1, 6)


@pytest.fixture(scope="module")
def realistic(tmp_path_factory) -> Path:
    return record(tmp_path_factory.mktemp("realistic") / "cube", "realistic", 2, 6)


def files_digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def test_survey_folder_is_complete_and_readable(ideal: Path) -> None:
    names = sorted(p.name for p in ideal.iterdir())
    assert names == [".darp-written", "arm_poses.csv", "cam348522076490.bag", "cam405622074504.bag",
                     "manip_envelope.json", "truth"]  # .darp-written: --overwrite may replace this folder
    assert not ideal.with_name(ideal.name + ".partial").exists()
    survey = open_survey(ideal)
    assert survey.arms == ("arm110", "arm111")
    env = read_envelope(ideal / "manip_envelope.json")
    cube = make_object("cube")
    assert env.object_name == "cube" and env.radius_m == pytest.approx(cube.radius_m)
    assert env.center_m == pytest.approx((PLACEMENT.x_m, PLACEMENT.y_m, cube.height_m / 2))
    truth = read_truth(ideal)
    assert truth.object_info["name"] == "cube" and truth.object_mesh_path is not None
    assert truth.settings == TwinSettings.from_profile("ideal", seed=1).with_camera(fps=6, **SMALL)
    assert (ideal / "truth" / "contacts.json").read_text().strip() == "[]"  # a normal survey touches nothing


def test_bags_play_back_in_pyrealsense2(ideal: Path) -> None:
    truth = read_truth(ideal)
    spec = make_camera_spec(UnitCalibration(), depth_resolution=(424, 240), colour_resolution=(424, 240), fps=6,
                            colour_fps=6)
    for arm, cal in truth.calibration.arms.items():
        path = ideal / f"cam{cal.serial}.bag"
        played = play_back(path)
        ours = open_recording(path)
        assert played.info["serial_number"] == cal.serial
        assert played.depth_scale == pytest.approx(0.001)
        n_frames = len(truth.camera_poses[arm]["frame_number"])
        assert n_frames > 20
        for key in ("depth", "color", "ir1", "ir2"):
            assert len(played.frames[key]) == ours.frame_count(key) == n_frames, key
        assert len(played.frames["accel"]) == ours.frame_count("accel") > 200
        d = spec.depth
        w, h, fx, fy, ppx, ppy, _, _ = played.profiles["depth"]["intrinsics"]
        assert (w, h) == (424, 240)
        np.testing.assert_allclose([fx, fy, ppx, ppy], [d.fx, d.fy, d.ppx, d.ppy], rtol=1e-6)
        depth = played.frames["depth"]
        np.testing.assert_allclose([f.timestamp_ms for f in depth], truth.camera_poses[arm]["timestamp_ms"], atol=1e-3)
        assert [f.frame_number for f in depth] == truth.camera_poses[arm]["frame_number"].tolist()
        assert {f.domain for f in depth} == {"Global Time"}
        k = n_frames // 2
        np.testing.assert_array_equal(depth[k].data, ours.read_frame("depth", k).data)
        assert np.count_nonzero(depth[k].data) > 0.5 * depth[k].data.size


def test_depth_pixels_back_project_onto_the_table_with_the_true_pose(ideal: Path) -> None:
    truth = read_truth(ideal)
    for arm, cal in truth.calibration.arms.items():
        rec = open_recording(ideal / f"cam{cal.serial}.bag")
        intr = rec.stream("depth").intrinsics
        k = 5
        depth_m = rec.read_frame("depth", k).data.astype(float) * 0.001
        v, u = np.nonzero(depth_m > 0)
        z = depth_m[v, u]
        pts = np.stack([(u - intr.ppx) / intr.fx * z, (v - intr.ppy) / intr.fy * z, z, np.ones_like(z)])
        world = (truth.camera_poses[arm]["T_world_cam"][k] @ pts)[:3]
        near_table = np.abs(world[2]) < 0.05
        assert near_table.mean() > 0.5
        # 1 mm depth units: a table point is off the plane by well under 2 mm; a pose error of
        # a few tenths of a degree would tilt the plane by centimetres across the image
        assert np.mean(np.abs(world[2][near_table]) < 0.002) > 0.99


def test_joint_log_and_camera_timing(realistic: Path) -> None:
    log = read_arm_poses(realistic / "arm_poses.csv")
    truth = read_truth(realistic)
    for arm, cal in truth.calibration.arms.items():
        dt = np.diff(log.times(arm))
        assert np.median(dt) == pytest.approx(1 / 33, rel=0.05)
        assert 0.001 < np.std(dt) < 0.004  # about 2 ms of jitter
        stamps = open_recording(realistic / f"cam{cal.serial}.bag").timestamps_ms("depth")
        np.testing.assert_allclose(np.diff(stamps), 1000 / 6, atol=1e-3)
        t0, t1 = log.span(arm)
        assert t0 < stamps[0] / 1e3 - 0.3 and stamps[-1] / 1e3 + 0.3 < t1  # camera interval inside the log


def test_eq1_with_the_true_calibration_reproduces_the_true_poses(ideal: Path) -> None:
    log = read_arm_poses(ideal / "arm_poses.csv")
    truth = read_truth(ideal)
    for arm, cal in truth.calibration.arms.items():
        p = truth.camera_poses[arm]
        poses = camera_poses(log.times(arm), log.joints(arm), p["timestamp_ms"] / 1e3, T_world_base=cal.T_world_base,
                             T_wrist_cam=cal.T_wrist_cam, joint_offsets_rad=cal.joint_offsets_rad)
        assert poses.posed.all()
        t_err, r_err = pose_error(poses.T_world_cam, p["T_world_cam"])
        still = poses.joint_speed_rad_s == 0
        assert still.sum() > 10 and (~still).sum() > 5
        assert np.max(t_err[still]) < 1e-6 and np.max(r_err[still]) < 1e-6
        assert np.max(t_err) < 5e-4  # linear interpolation of a 33 Hz log during motion


def test_realistic_errors_are_in_the_data_and_the_truth_explains_them(realistic: Path) -> None:
    log = read_arm_poses(realistic / "arm_poses.csv")
    truth = read_truth(realistic)
    nominal = load_rig()
    for arm, cal in truth.calibration.arms.items():
        p = truth.camera_poses[arm]
        t = p["timestamp_ms"] / 1e3
        true_cal = camera_poses(log.times(arm), log.joints(arm), t, T_world_base=cal.T_world_base,
                                T_wrist_cam=cal.T_wrist_cam, joint_offsets_rad=cal.joint_offsets_rad)
        nom = nominal.arms[arm]
        nominal_cal = camera_poses(log.times(arm), log.joints(arm), t, T_world_base=nom.T_world_base,
                                   T_wrist_cam=nom.T_wrist_cam)
        err_true = pose_error(true_cal.T_world_cam, p["T_world_cam"])[0]
        err_nominal = pose_error(nominal_cal.T_world_cam, p["T_world_cam"])[0]
        assert np.max(err_true) < 1e-3
        assert np.median(err_nominal) > 3e-3


def test_imu_measures_gravity_when_still(ideal: Path) -> None:
    truth = read_truth(ideal)
    for arm, cal in truth.calibration.arms.items():
        played = play_back(ideal / f"cam{cal.serial}.bag")
        poses = truth.camera_poses[arm]
        unmoved = np.all(np.abs(poses["T_world_cam"] - poses["T_world_cam"][0]) < 1e-12, axis=(1, 2))
        still_until_ms = poses["timestamp_ms"][np.argmin(unmoved) - 1]  # last frame before the first move
        still = [f.data for f in played.frames["accel"] if f.timestamp_ms <= still_until_ms]
        assert len(still) > 20
        R = poses["T_world_cam"][0][:3, :3]
        expected = R.T @ np.array([0.0, 0.0, GRAVITY])  # specific force of a body at rest: -g, in camera axes
        np.testing.assert_allclose(np.mean(still, axis=0), expected, atol=1e-3)
        gyro = [f.data for f in played.frames["gyro"] if f.timestamp_ms <= still_until_ms]
        assert np.max(np.abs(gyro)) < 1e-6


# Records the small survey in a child interpreter (argv: folder, tests folder, workers 0/1), then prints
# a digest of a float64 matrix product, which depends on the OpenBLAS kernel (FMA or not).
RECORD_SCRIPT = """
import hashlib, sys
from pathlib import Path
import numpy as np
sys.path.insert(0, sys.argv[2])
from helpers.twin_surveys import record
record(Path(sys.argv[1]), 'realistic', 2, 6, workers=sys.argv[3] == '1')
a, b = np.random.default_rng(0).standard_normal((2, 4, 4))
print('blas-probe', hashlib.sha256((a @ b).tobytes()).hexdigest())
"""


def record_in_child(folder: Path, workers: bool, **env: str) -> subprocess.CompletedProcess[str]:
    """Record the small survey in a fresh interpreter with this process's environment plus ``env``.

    The environment is inherited, not made up: variables that choose library code paths (OpenBLAS's
    ``OPENBLAS_CORETYPE`` and ``OPENBLAS_L2_SIZE`` pick its kernel) must be the ones this process has.
    """
    src = str(Path(darp.__file__).resolve().parents[1])  # the child must import the same darp as this one
    pythonpath = os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p)
    return subprocess.run([sys.executable, "-c", RECORD_SCRIPT, str(folder), str(Path(__file__).parent),
                           "1" if workers else "0"], capture_output=True, text=True, check=False,
                          env={**os.environ, "MUJOCO_GL": "egl", "PYTHONPATH": pythonpath, **env})


@pytest.mark.slow
def test_identical_seeds_give_byte_identical_surveys(realistic: Path, tmp_path: Path) -> None:
    """The same recording made again in a fresh interpreter (other hash seed), with each camera rendered
    in its own worker process this time, is byte-identical."""
    again = tmp_path / "cube"
    result = record_in_child(again, workers=True, PYTHONHASHSEED="123")
    assert result.returncode == 0, result.stderr
    assert files_digest(again) == files_digest(realistic)
    assert files_digest(again / "truth") == files_digest(realistic / "truth")


@pytest.mark.slow
def test_surveys_are_byte_identical_across_openblas_kernels(tmp_path: Path) -> None:
    """docs/determinism.md: the twin's files do not depend on the OpenBLAS kernel. Haswell uses FMA,
    Sandybridge does not; the children's matrix-product probe shows that the choice took effect."""
    folders, probes = {}, {}
    for kernel, workers in (("Haswell", False), ("Sandybridge", True)):
        folders[kernel] = tmp_path / kernel / "cube"
        result = record_in_child(folders[kernel], workers=workers, OPENBLAS_CORETYPE=kernel)
        if result.returncode == -4:  # SIGILL: this CPU cannot run that kernel
            pytest.skip(f"this CPU cannot run the OpenBLAS {kernel} kernel")
        assert result.returncode == 0, result.stderr
        probes[kernel] = [line for line in result.stdout.splitlines() if line.startswith("blas-probe")]
    if probes["Haswell"] == probes["Sandybridge"]:
        pytest.skip("OPENBLAS_CORETYPE had no effect (numpy without a dynamic-arch OpenBLAS?)")
    haswell, sandybridge = folders["Haswell"], folders["Sandybridge"]
    assert files_digest(haswell) == files_digest(sandybridge)
    assert files_digest(haswell / "truth") == files_digest(sandybridge / "truth")


def test_seeds_change_the_rig_and_the_log(tmp_path: Path) -> None:
    logs = []
    for seed in (3, 4):
        settings = TwinSettings.from_profile("realistic", seed=seed).with_camera(**SMALL)
        with TwinRig(settings) as twin:
            twin.start_joint_log(tmp_path / f"log{seed}.csv")
            twin.clock.sleep(0.5)
            twin.stop_joint_log()
        logs.append(read_arm_poses(tmp_path / f"log{seed}.csv"))
    assert not np.allclose(logs[0].joints("arm110")[0], logs[1].joints("arm110")[0])


def test_collision_monitor_catches_a_move_through_the_table() -> None:
    settings = TwinSettings.from_profile("ideal", seed=0).with_camera(**SMALL)
    with TwinRig(settings) as twin:
        twin.arms["arm110"].move_to(np.array([0.0, 2.6, -0.3, 0.0, 0.0, 0.0]))
        twin.wait_until_still("arm110", timeout_s=20.0)
        hits = twin.contact_events
        assert hits and {e.contact.other for e in hits} == {"table"}
        assert {e.contact.arm_id for e in hits} == {"arm110"}
        # the contact stop halts both arms at the first contact: shallow, never carried on through the table
        assert -0.01 < min(e.contact.distance_m for e in hits) < 0.0
        fault = twin.fault()
        assert fault is not None and "contact during motion" in fault.message
        assert not np.allclose(twin.arms["arm110"].read_state().q_rad, [0.0, 2.6, -0.3, 0.0, 0.0, 0.0], atol=0.05)
        live = twin.cameras["arm111"].latest_frameset()
        assert live.depth_m.shape == (240, 424) and np.count_nonzero(live.depth_m) > 1000
        assert live.timestamp_s <= twin.clock.now()


def test_camera_clock_offset_shifts_the_bag_timestamps_only(tmp_path: Path) -> None:
    settings = TwinSettings.from_profile("ideal", seed=0).with_camera(fps=6, **SMALL).with_timing(
        camera_clock_offset_ms=25.0)
    with TwinRig(settings) as twin:
        twin.start_joint_log(tmp_path / "arm_poses.csv")
        twin.clock.sleep(0.2)
        camera = twin.cameras["arm110"]
        camera.start_recording(tmp_path / f"cam{camera.serial}.bag")
        twin.arms["arm110"].move_to(twin.park_q("arm110") + np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0]))
        twin.clock.sleep(1.0)
        camera.stop_recording()
        twin.clock.sleep(0.2)
        twin.stop_joint_log()
        poses = camera.truth.arrays()
    stamps = open_recording(tmp_path / f"cam{camera.serial}.bag").timestamps_ms("depth")
    np.testing.assert_allclose(stamps - 1e3 * poses["t_host_s"], 25.0, atol=1e-3)
    log = read_arm_poses(tmp_path / "arm_poses.csv")
    cal = draw_true_rig(load_rig(), settings).arms["arm110"]
    recovered = camera_poses(log.times("arm110"), log.joints("arm110"), stamps / 1e3, clock_offset_s=0.025,
                             T_world_base=cal.T_world_base, T_wrist_cam=cal.T_wrist_cam)
    assert np.max(pose_error(recovered.T_world_cam, poses["T_world_cam"])[0]) < 5e-4


def test_failed_recording_leaves_no_folder(tmp_path: Path) -> None:
    plan = WaypointPlan({"arm112": (Waypoint(np.zeros(6)),)}, ("arm112",))
    out = tmp_path / "cube"
    with pytest.raises(TwinError, match="unknown arm"):
        record_survey(out, plan, make_object("cube"), PLACEMENT,
                      settings=TwinSettings.from_profile("ideal").with_camera(fps=6, **SMALL))
    assert list(tmp_path.iterdir()) == []


def test_cli_record_and_bad_input(tmp_path: Path, capsys) -> None:
    from darp.cli._app import run

    park = load_rig().arms["arm110"].park_q_rad
    q = ",".join(f"{v:.3f}" for v in park + np.array([0.1, 0.1, 0.0, -0.1, 0.0, 0.0]))
    waypoints = tmp_path / "w.csv"
    waypoints.write_text(f"arm,q1,q2,q3,q4,q5,q6,dwell_s\narm110,{q},0.1\n")
    out = tmp_path / "survey"
    args = ["twin", "record", "--waypoints", str(waypoints), "--object", "cube", "--placement", "0,0,30",
            "--seed", "5", "--profile", "ideal", "--fps", "6", "--resolution", "424x240", "--no-workers",
            "--out", str(out), "-q"]
    assert run(args) == 0
    assert (out / "arm_poses.csv").is_file() and read_truth(out).object_info["placement"]["yaw_rad"] == pytest.approx(
        np.pi / 6)
    assert run(args) == 2  # exists
    assert "already exists" in capsys.readouterr().err
    waypoints.write_text("arm,q1,q2\narm110,0,1\n")
    assert run([*args[:-3], "--out", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "w.csv" in err[0] and "missing column" in err[0]


@pytest.mark.slow
def test_full_resolution_thirty_fps(tmp_path: Path) -> None:
    park = load_rig().arms["arm110"].park_q_rad
    plan = WaypointPlan({"arm110": (Waypoint(park + np.array([0.05, 0.05, 0.0, 0.0, 0.0, 0.0]), 0.0),)}, ("arm110",))
    settings = TwinSettings.from_profile("realistic", seed=7)
    result = record_survey(tmp_path / "cube", plan, make_object("cube"), PLACEMENT, settings=settings)
    played = play_back(tmp_path / "cube" / "cam348522076490.bag")
    depth = played.frames["depth"]
    assert len(depth) == result.frames["arm110"] > 30
    assert depth[0].data.shape == (480, 640) and played.frames["color"][0].data.shape == (480, 640, 3)
    np.testing.assert_allclose(np.diff([f.timestamp_ms for f in depth]), 1000 / 30, atol=1e-3)


def test_lighting_setting_changes_the_colour_images_and_stays_out_of_default_settings() -> None:
    from darp.twin.settings import LightingSettings

    base = TwinSettings.from_profile("ideal", seed=0).with_camera(**SMALL)
    assert "lighting" not in base.to_dict()  # default lights: settings files (and surveys) as before
    means = []
    for level in (0.1, 0.9):
        lit = dataclasses.replace(base, lighting=LightingSettings(ambient=level, key=level, fill=level,
                                                                  key_yaw_deg=90.0))
        assert TwinSettings.from_dict(lit.to_dict()).lighting == lit.lighting  # round trip through YAML
        with TwinRig(lit) as twin:
            frame = twin.cameras["arm110"].latest_frameset()
            assert frame.colour_bgr is not None
            means.append(float(frame.colour_bgr.mean()))
    assert means[1] > means[0] + 40  # brighter lights, brighter images
    with pytest.raises(ConfigError, match=r"lighting\.key"):
        LightingSettings(key=1.5)
