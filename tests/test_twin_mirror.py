"""Twin cameras that follow other arms (darp.twin.mirror): what they render is where the arms reported they were."""

from __future__ import annotations

import threading
import time

import numpy as np

from darp.backend import ArmBackend, JointState
from darp.kinematics.rig import load_rig
from darp.twin.mirror import MirrorCamera, MirrorClock, MirrorTwin
from darp.twin.settings import TwinSettings

PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
SPEED = np.array([0.3, 0.0, 0.0, 0.0, 0.2, -0.3])  # rad/s


class RampArm(ArmBackend):
    """An arm whose reported joints move at a constant speed from PARK on the wall clock (a stand-in for a
    hardware arm: only ``read_state`` matters here)."""

    def __init__(self, arm_id: str, t0: float) -> None:
        self.arm_id, self.t0 = arm_id, t0
        self.lock = threading.Lock()

    def q_at(self, t: float) -> np.ndarray:
        return PARK + SPEED * max(t - self.t0, 0.0)

    def read_state(self) -> JointState:
        t = time.time()
        return JointState(t, self.q_at(t), SPEED.copy())

    def move_to(self, q_target_rad: np.ndarray, max_speed_rad_s: float | None = None) -> None:
        raise NotImplementedError

    def is_moving(self) -> bool:
        return True

    def stop(self) -> None:
        raise NotImplementedError


def test_recorded_frames_are_rendered_where_the_arms_reported_they_were(tmp_path):
    rig = load_rig()
    settings = TwinSettings.from_profile("realistic", seed=4).with_camera(fps=6, width=424, height=240, imu=False)
    mirror = MirrorTwin(settings, rig=rig, q_initial_rad=dict.fromkeys(rig.arm_ids, PARK))
    try:
        t0 = time.time()
        arms = {a: RampArm(a, t0) for a in rig.arm_ids}
        mirror.follow(arms)
        clock = MirrorClock(mirror)
        cameras = {a: MirrorCamera(mirror, a) for a in rig.arm_ids}
        clock.sleep(0.2)
        for camera in cameras.values():
            camera.start_recording(tmp_path / f"cam{camera.serial}.bag")
        assert mirror.recording
        rendered = mirror.cameras["arm110"].frames_recorded
        clock.sleep(1.0)  # the arms move on; no recorded frame is rendered while recording
        assert mirror.cameras["arm110"].frames_recorded == rendered
        live = cameras["arm110"].latest_frameset()  # rendered at the wall clock even so
        assert abs(live.timestamp_s - time.time()) < 0.5
        for camera in cameras.values():
            camera.stop_recording()
        for arm_id, camera in mirror.cameras.items():
            truth = camera.truth
            assert 5 <= camera.frames_recorded <= 9  # about 1.2 s at 6 fps, both ending where the first stopped
            offsets = mirror.true_rig.arms[arm_id].joint_offsets_rad
            assert np.any(offsets != 0)  # the twin's seeded joint-zero errors are applied to reported joints
            for k in range(len(truth.q_true_rad)):
                expected = arms[arm_id].q_at(truth.t_host_s[k]) + offsets
                assert np.max(np.abs(truth.q_true_rad[k] - expected)) < 2e-3  # interpolated states: ~ms of motion
                T = mirror.true_rig.T_world_cam(arm_id, truth.q_true_rad[k])
                assert np.allclose(T, truth.T_world_cam[k], atol=1e-9)
        assert all((tmp_path / f"cam{c.serial}.bag").is_file() for c in cameras.values())
    finally:
        mirror.close()
