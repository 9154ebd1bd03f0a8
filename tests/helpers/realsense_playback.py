"""The test oracle: what pyrealsense2 itself returns when it plays a recording back.

Non-real-time, per-sensor playback into one frame queue, paused while the sensors start, delivers
every frame exactly once (the pipeline API may drop or repeat the first frames). The result uses
darp's stream keys and names so that tests compare like with like.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

RS_KEYS = {("depth", 0): "depth", ("color", 0): "color", ("infrared", 1): "ir1", ("infrared", 2): "ir2",
           ("accel", 0): "accel", ("gyro", 0): "gyro"}
DOMAINS = {"hardware_clock": "Hardware Clock", "system_time": "System Time", "global_time": "Global Time"}


@dataclass
class PlayedFrame:
    frame_number: int
    timestamp_ms: float
    domain: str
    data: np.ndarray
    metadata: dict[str, int]  # librealsense metadata name ("Frame Counter") -> value


@dataclass
class Played:
    info: dict[str, str]
    depth_scale: float | None
    profiles: dict[str, dict]  # intrinsics model as librealsense's enum name: "brown_conrady"
    extrinsics: dict[tuple[str, str], np.ndarray]  # (source, target) -> T_target_source
    frames: dict[str, list[PlayedFrame]] = field(default_factory=dict)


def _key(profile) -> str | None:
    return RS_KEYS.get((str(profile.stream_type()).split(".")[-1], profile.stream_index()))


def _metadata_name(value) -> str:
    """``frame_metadata_value.actual_exposure`` -> ``Actual Exposure`` (librealsense's names)."""
    return " ".join(word.capitalize() for word in str(value).split(".")[-1].split("_"))


def play_back(path: str | Path) -> Played:
    """Everything pyrealsense2 reports about ``path``, every frame included."""
    import pyrealsense2 as rs

    device = rs.context().load_device(str(path))
    playback = device.as_playback()
    playback.set_real_time(False)
    info = {str(i).split(".")[-1]: device.get_info(i) for i in
            (rs.camera_info.name, rs.camera_info.serial_number, rs.camera_info.firmware_version,
             rs.camera_info.product_id) if device.supports(i)}
    played = Played(info=info, depth_scale=None, profiles={}, extrinsics={})
    sensors = device.query_sensors()
    profiles = {}
    for sensor in sensors:
        if sensor.is_depth_sensor():
            played.depth_scale = sensor.as_depth_sensor().get_depth_scale()
        for profile in sensor.get_stream_profiles():
            key = _key(profile)
            if key is None:
                continue
            profiles[key] = profile
            entry = {"format": str(profile.format()).split(".")[-1], "fps": profile.fps()}
            if profile.is_video_stream_profile():
                i = profile.as_video_stream_profile().get_intrinsics()
                entry["intrinsics"] = (i.width, i.height, i.fx, i.fy, i.ppx, i.ppy,
                                       str(i.model).split(".")[-1], tuple(i.coeffs))
            if profile.is_motion_stream_profile():
                m = profile.as_motion_stream_profile().get_motion_intrinsics()
                entry["motion_intrinsics"] = (tuple(np.array(m.data).reshape(-1)), tuple(m.noise_variances),
                                              tuple(m.bias_variances))
            played.profiles[key] = entry
    for source, p_source in profiles.items():
        for target, p_target in profiles.items():
            try:
                e = p_source.get_extrinsics_to(p_target)
            except RuntimeError:
                continue
            T = np.eye(4)
            T[:3, :3] = np.array(e.rotation).reshape(3, 3).T  # column-major
            T[:3, 3] = e.translation
            played.extrinsics[(source, target)] = T
    queue = rs.frame_queue(100000, keep_frames=True)
    playback.pause()
    for sensor in sensors:
        sensor.open(sensor.get_stream_profiles())
        sensor.start(queue)
    playback.resume()
    while True:
        ok, frame = queue.try_wait_for_frame(200)
        if not ok:
            if playback.current_status() == rs.playback_status.stopped:
                break
            continue
        key = _key(frame.get_profile())
        if key is None:
            continue
        if frame.is_motion_frame():
            v = frame.as_motion_frame().get_motion_data()
            data = np.array([v.x, v.y, v.z], dtype=np.float32)
        else:
            data = np.asanyarray(frame.get_data()).copy()
        metadata = {_metadata_name(m): frame.get_frame_metadata(m)
                    for m in rs.frame_metadata_value.__members__.values() if frame.supports_frame_metadata(m)}
        played.frames.setdefault(key, []).append(PlayedFrame(
            frame_number=frame.get_frame_number(), timestamp_ms=frame.get_timestamp(),
            domain=DOMAINS[str(frame.get_frame_timestamp_domain()).split(".")[-1]], data=data, metadata=metadata))
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    return played
