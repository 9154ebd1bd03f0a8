"""darp's ROS1 .bag writer and reader, with pyrealsense2 2.59 (real playback) and rosbags as oracles."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyrealsense2 as rs
import pytest

from darp.formats.realsense import ros_messages as rm
from darp.formats.realsense.bag.reader import BagRecording
from darp.formats.realsense.recording import open_recording
from darp.formats.realsense.types import DeviceInfo
from helpers.bag_samples import DEVICE, EXTRINSICS, IMU_INTRINSICS, Sample, write_sample
from helpers.rosbags_writing import message_putter, realsense_typestore

# -- pyrealsense2 as the oracle ----------------------------------------------------------------------
RS_KEYS = {("depth", 0): "depth", ("color", 0): "color", ("infrared", 1): "ir1", ("infrared", 2): "ir2",
           ("accel", 0): "accel", ("gyro", 0): "gyro"}
DOMAINS = {"global_time": "Global Time", "system_time": "System Time", "hardware_clock": "Hardware Clock"}


def _key(profile: rs.stream_profile) -> str:
    return RS_KEYS[(profile.stream_type().name, profile.stream_index())]


@dataclass
class Playback:
    frames: dict[str, list[dict]]
    fps: dict[str, int]
    intrinsics: dict[str, object]  # rs.intrinsics or rs.motion_device_intrinsic
    extrinsics: dict[tuple[str, str], np.ndarray]  # (source, target) -> T_target_source
    depth_scale: float
    info: dict[str, str]


def playback(path: Path) -> Playback:
    """Play a bag with librealsense: non-real-time, per-sensor, paused while the sensors start."""
    ctx = rs.context()
    device = ctx.load_device(str(path))
    player = device.as_playback()
    player.set_real_time(False)
    player.pause()
    queue = rs.frame_queue(100_000, keep_frames=True)
    sensors = device.query_sensors()
    profiles_by_key, depth_scale = {}, None
    for sensor in sensors:
        if sensor.is_depth_sensor():
            depth_scale = sensor.as_depth_sensor().get_depth_scale()
        for profile in sensor.get_stream_profiles():
            profiles_by_key[_key(profile)] = profile
        sensor.open(sensor.get_stream_profiles())
        sensor.start(queue)
    info = {name: device.get_info(getattr(rs.camera_info, attr)) for name, attr in
            (("Name", "name"), ("Serial Number", "serial_number"), ("Firmware Version", "firmware_version"),
             ("Product Id", "product_id"), ("Product Line", "product_line"))}
    player.resume()
    frames: dict[str, list[dict]] = {key: [] for key in profiles_by_key}
    stopped_waits = 0
    while stopped_waits < 3:  # after the player stops, drain until the queue stays empty
        ok, frame = queue.try_wait_for_frame(200)
        if ok:
            key = _key(frame.get_profile())
            if frame.is_motion_frame():
                m = frame.as_motion_frame().get_motion_data()
                data = np.array([m.x, m.y, m.z], dtype=np.float32)
            else:
                data = np.asanyarray(frame.get_data()).copy()
            counter = rs.frame_metadata_value.frame_counter
            frames[key].append({
                "number": frame.get_frame_number(), "ts": frame.get_timestamp(),
                "domain": DOMAINS[frame.get_frame_timestamp_domain().name], "data": data,
                "counter": frame.get_frame_metadata(counter) if frame.supports_frame_metadata(counter) else None,
            })
        elif player.current_status() == rs.playback_status.stopped:
            stopped_waits += 1
    intrinsics = {key: p.as_video_stream_profile().get_intrinsics() if p.is_video_stream_profile()
                  else p.as_motion_stream_profile().get_motion_intrinsics() for key, p in profiles_by_key.items()}
    extrinsics = {(a, b): rs_extrinsics(pa, pb)
                  for a, pa in profiles_by_key.items() for b, pb in profiles_by_key.items()}
    fps = {key: p.fps() for key, p in profiles_by_key.items()}
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    return Playback(frames, fps, intrinsics, extrinsics, depth_scale, info)


def rs_extrinsics(source: rs.stream_profile, target: rs.stream_profile) -> np.ndarray:
    """pyrealsense2's ``source.get_extrinsics_to(target)`` as a 4x4 ``T_target_source``."""
    e = source.get_extrinsics_to(target)
    T = np.eye(4)
    T[:3, :3] = np.array(e.rotation).reshape(3, 3, order="F")  # rs2_extrinsics.rotation is column-major
    T[:3, 3] = e.translation
    return T


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_pyrealsense2_plays_darp_bag(tmp_path: Path, compression: str) -> None:
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=20_000)
    played = playback(sample.path)
    with BagRecording(sample.path) as recording:
        assert played.depth_scale == pytest.approx(0.00025, rel=1e-7) and recording.depth_scale == played.depth_scale
        assert played.info == {"Name": DEVICE.name, "Serial Number": DEVICE.serial, "Firmware Version": DEVICE.firmware,
                               "Product Id": DEVICE.product_id, "Product Line": "D400"}
        for profile in sample.streams:
            key, expected = profile.key, sample.frames[profile.key]
            got = played.frames[key]
            assert [f["number"] for f in got] == [f["number"] for f in expected], key  # each frame exactly once
            assert [f["counter"] for f in got] == [f["number"] for f in expected], key
            assert [f["domain"] for f in got] == [f["domain"] for f in expected], key
            np.testing.assert_allclose([f["ts"] for f in got], [f["ts"] for f in expected], rtol=0, atol=1e-5)
            # darp's reader computes the timestamp exactly as the player does
            assert [f["ts"] for f in got] == recording.timestamps_ms(key).tolist(), key
            for g, e in zip(got, expected, strict=True):
                assert g["data"].dtype == e["data"].dtype and np.array_equal(g["data"], e["data"]), key
            assert played.fps[key] == profile.fps
            if profile.is_image:
                intr = played.intrinsics[key]
                mine = profile.intrinsics
                assert (intr.width, intr.height) == (mine.width, mine.height)
                np.testing.assert_allclose([intr.fx, intr.fy, intr.ppx, intr.ppy],
                                           [mine.fx, mine.fy, mine.ppx, mine.ppy], rtol=1e-6)
                assert str(intr.model).split(".")[-1].replace("_", " ").lower() == mine.model.lower()
                np.testing.assert_allclose(intr.coeffs, mine.coeffs, rtol=1e-6, atol=1e-9)
            else:
                mi = played.intrinsics[key]
                np.testing.assert_allclose(np.array(mi.data).ravel(), IMU_INTRINSICS.data, rtol=1e-6)
                np.testing.assert_allclose(mi.noise_variances, IMU_INTRINSICS.noise_variances, rtol=1e-6)
                np.testing.assert_allclose(mi.bias_variances, IMU_INTRINSICS.bias_variances, rtol=1e-6)
        for source in ("depth", "color", "ir2", "accel"):
            for target in ("depth", "color", "ir1", "ir2", "gyro"):
                T_rs = played.extrinsics[(source, target)]
                expected = EXTRINSICS.get(target, np.eye(4)) @ np.linalg.inv(EXTRINSICS.get(source, np.eye(4)))
                np.testing.assert_allclose(T_rs, expected, atol=2e-6)
                np.testing.assert_allclose(recording.extrinsics(source, target), T_rs, atol=2e-6)


def test_pyrealsense2_plays_full_resolution_bag(tmp_path: Path) -> None:
    sample = write_sample(tmp_path / "vga.bag", width=640, height=480, framesets=4)
    played = playback(sample.path)
    for key, expected in sample.frames.items():
        got = played.frames[key]
        assert [f["number"] for f in got] == [f["number"] for f in expected], key
        assert all(np.array_equal(g["data"], e["data"]) for g, e in zip(got, expected, strict=True)), key
    assert played.intrinsics["color"].width == 640


# -- darp's reader on darp's writer ----------------------------------------------------------------
@pytest.fixture(scope="module", params=["lz4", "none"])
def sample(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Sample:
    path = tmp_path_factory.mktemp(request.param) / "cam.bag"
    return write_sample(path, compression=request.param, chunk_threshold=20_000)


def test_reader_round_trips_the_description(sample: Sample) -> None:
    with open_recording(sample.path) as recording:
        assert isinstance(recording, BagRecording)
        assert recording.file_version == 4 and not recording.truncated
        assert recording.device == DeviceInfo(DEVICE.name, DEVICE.serial, DEVICE.firmware, DEVICE.product_id,
                                              {"Name": DEVICE.name, "Serial Number": DEVICE.serial,
                                               "Firmware Version": DEVICE.firmware, "Product Id": DEVICE.product_id}
                                              | DEVICE.info)
        assert recording.depth_scale == pytest.approx(0.00025, rel=1e-7) and recording.depth_scale_source == "option"
        assert list(recording.streams) == ["depth", "color", "ir1", "ir2", "accel", "gyro"]
        for profile in sample.streams:
            got = recording.stream(profile.key)
            if profile.is_image:
                assert got == profile
            else:  # IMU intrinsics are float32 in the file
                assert got.motion_intrinsics.data == pytest.approx(profile.motion_intrinsics.data, rel=1e-6)
                assert (got.fps, got.format, got.sensor_index) == (profile.fps, profile.format, profile.sensor_index)
        assert recording.sensor_names == {0: "Stereo Module", 1: "RGB Camera", 2: "Motion Module"}
        for key, T in EXTRINSICS.items():
            np.testing.assert_allclose(recording.extrinsics("depth", key), T, atol=1e-12)
            np.testing.assert_allclose(recording.extrinsics(key, "depth"), np.linalg.inv(T), atol=1e-12)
        np.testing.assert_array_equal(recording.extrinsics("color", "color"), np.eye(4))


def test_reader_round_trips_every_frame(sample: Sample) -> None:
    with BagRecording(sample.path) as recording:
        for key, expected in sample.frames.items():
            assert recording.frame_count(key) == len(expected)
            infos = recording.frame_infos(key)
            assert [i.frame_number for i in infos] == [e["number"] for e in expected]
            assert [i.timestamp_domain for i in infos] == [e["domain"] for e in expected]
            np.testing.assert_allclose([i.timestamp_ms for i in infos], [e["ts"] for e in expected], rtol=0, atol=1e-5)
            # default recording time: timestamp minus (first frame - 100 ms), in ns
            rec_ns = [(e["ts"] - (sample.frames["depth"][0]["ts"] - 100.0)) * 1e6 for e in expected]
            np.testing.assert_allclose([i.recording_time_ns for i in infos], rec_ns, atol=1)
            for i, e in enumerate(expected):
                frame = recording.read_frame(key, i)
                assert frame.info == infos[i]
                assert frame.data.dtype == e["data"].dtype and np.array_equal(frame.data, e["data"])
                assert frame.metadata["Frame Counter"] == str(e["number"])
                assert frame.metadata["timestamp_domain"] == e["domain"]
                assert int(frame.metadata["Frame Timestamp"]) == round(e["ts"] * 1000)


def test_random_access_by_time(sample: Sample) -> None:
    with BagRecording(sample.path) as recording:
        stamps = [f["ts"] for f in sample.frames["color"]]
        for i in (0, 5, len(stamps) - 1):
            assert recording.frame_at("color", stamps[i] + 10.0).info.index == i
            assert recording.frame_at("color", stamps[i] - 10.0).info.index == i
            assert np.array_equal(recording.frame_at("color", stamps[i]).data, sample.frames["color"][i]["data"])
        assert recording.frame_at("color", 0.0).info.index == 0
        assert recording.frame_at("gyro", 1e15).info.index == len(sample.frames["gyro"]) - 1


def test_iter_frames_windows_and_order(sample: Sample) -> None:
    with BagRecording(sample.path) as recording:
        everything = list(recording.iter_frames())
        assert len(everything) == sum(len(v) for v in sample.frames.values())
        times = [f.info.recording_time_ns for f in everything]
        assert times == sorted(times)
        start, stop = sample.frames["depth"][3]["ts"], sample.frames["depth"][7]["ts"]
        window = list(recording.iter_frames(["depth", "gyro"], start_ms=start, stop_ms=stop))
        assert {f.info.stream for f in window} == {"depth", "gyro"}
        assert [f.info.frame_number for f in window if f.info.stream == "depth"] == [103, 104, 105, 106]
        expected_gyro = [f["number"] for f in sample.frames["gyro"] if start <= f["ts"] < stop]
        assert [f.info.frame_number for f in window if f.info.stream == "gyro"] == expected_gyro
        for frame in window:
            assert np.array_equal(frame.data, sample.frames[frame.info.stream][frame.info.index]["data"])
        assert list(recording.iter_frames(["ir1"], start_ms=1e15)) == []


def test_framesets_group_depth_infrared_and_nearest_colour(tmp_path: Path) -> None:
    # written infrared first: the generic grouping in Recording.framesets matches IR frames it has seen
    sample = write_sample(tmp_path / "sets.bag", image_order=("ir1", "ir2", "depth", "color"), imu=False)
    with BagRecording(sample.path) as recording:
        sets = list(recording.framesets())
        assert [s.depth.info.frame_number for s in sets] == [f["number"] for f in sample.frames["depth"]]
        for i, s in enumerate(sets):
            assert s.ir1.info.frame_number == s.ir2.info.frame_number == s.depth.info.frame_number
            assert s.color.info.index == i and np.array_equal(s.color.data, sample.frames["color"][i]["data"])
            assert np.array_equal(s.ir2.data, sample.frames["ir2"][i]["data"])


def test_writer_is_deterministic(tmp_path: Path) -> None:
    first = write_sample(tmp_path / "a.bag", chunk_threshold=30_000).path.read_bytes()
    assert first == write_sample(tmp_path / "b.bag", chunk_threshold=30_000).path.read_bytes()
    assert first != write_sample(tmp_path / "c.bag", chunk_threshold=30_000, seed=1).path.read_bytes()


def test_frames_are_views_of_the_file(tmp_path: Path) -> None:
    sample = write_sample(tmp_path / "raw.bag", compression="none", imu=False, framesets=2)
    recording = BagRecording(sample.path)
    frame = recording.read_frame("depth", 1)
    assert not frame.data.flags.writeable and not frame.data.flags.owndata
    recording.close()  # the frame keeps its pages alive
    assert np.array_equal(frame.data, sample.frames["depth"][1]["data"])


# -- independent parsers -------------------------------------------------------------------------
def test_message_definitions_match_rosbags() -> None:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    for msgtype in rm.ALL_TYPES:
        ros2_name = msgtype.name.replace("/", "/msg/")
        store.register(get_types_from_msg(msgtype.definition.split("=" * 80)[0], ros2_name))
        assert store.generate_msgdef(ros2_name)[1] == msgtype.md5sum, msgtype.name


def test_rosbags_reads_darp_bag(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_typestore

    sample = write_sample(tmp_path / "cam.bag", chunk_threshold=20_000)
    store = get_typestore(Stores.ROS1_NOETIC)
    with Reader(sample.path) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts["/device_0/sensor_0/Depth_0/image/data"] == len(sample.frames["depth"])
        assert counts["/device_0/sensor_2/Gyro_0/imu/metadata"] == 4 * len(sample.frames["gyro"])
        types = {c.topic: (c.msgtype, c.digest) for c in reader.connections}
        assert types["/device_0/sensor_1/Color_0/info"] == ("realsense_msgs/msg/StreamInfo", rm.STREAM_INFO.md5sum)
        accel = [c for c in reader.connections if c.topic.endswith("Accel_0/imu/data")]
        values = [store.deserialize_ros1(raw, "sensor_msgs/msg/Imu") for _, _, raw in reader.messages(accel)]
        assert [m.header.seq for m in values] == [f["number"] for f in sample.frames["accel"]]
        for message, expected in zip(values, sample.frames["accel"], strict=True):
            acc = message.linear_acceleration
            assert np.array_equal(np.float32([acc.x, acc.y, acc.z]), expected["data"])
        color_info = [c for c in reader.connections if c.topic.endswith("Color_0/info/camera_info")]
        info = store.deserialize_ros1(next(reader.messages(color_info))[2], "sensor_msgs/msg/CameraInfo")
        assert info.distortion_model == "Inverse Brown Conrady" and info.K[0] == pytest.approx(0.9 * 64)


def test_reads_2018_style_bag_written_by_rosbags(tmp_path: Path) -> None:
    """file_version 3, 'Depth Units' option with a space, frame_id "0" images without trailer, written by
    an independent writer (rosbags) with its own record layout."""
    from rosbags.rosbag1 import Writer
    store = realsense_typestore()
    types = store.types
    path = tmp_path / "old.bag"
    depth = [np.arange(12 * 16, dtype=np.uint16).reshape(12, 16) * (i + 1) for i in range(3)]
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    with writer:
        put = message_putter(writer, store)
        put("/file_version", "std_msgs/msg/UInt32", types["std_msgs/msg/UInt32"](data=3))
        put("/device_0/info", "diagnostic_msgs/msg/KeyValue",
            types["diagnostic_msgs/msg/KeyValue"](key="Name", value="Intel RealSense D415"))
        put("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32",
            types["std_msgs/msg/Float32"](data=0.0001))
        put("/device_0/sensor_0/Depth_0/info", "realsense_msgs/msg/StreamInfo",
            types["realsense_msgs/msg/StreamInfo"](fps=15, encoding="mono16", is_recommended=True))
        header = types["std_msgs/msg/Header"]
        time = types["builtin_interfaces/msg/Time"]
        camera_info = types["sensor_msgs/msg/CameraInfo"](
            header=header(seq=0, stamp=time(sec=0, nanosec=0), frame_id=""), height=12, width=16,
            distortion_model="Brown Conrady", D=np.zeros(5), K=np.array([20.0, 0, 8, 0, 21.0, 6, 0, 0, 1]),
            R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0,
            roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        put("/device_0/sensor_0/Depth_0/info/camera_info", "sensor_msgs/msg/CameraInfo", camera_info)
        for i, image in enumerate(depth):
            message = types["sensor_msgs/msg/Image"](
                header=header(seq=40 + i, stamp=time(sec=1500 + i, nanosec=250_000_000), frame_id="0"), height=12,
                width=16, encoding="mono16", is_bigendian=0, step=32, data=image.view(np.uint8).ravel())
            put("/device_0/sensor_0/Depth_0/image/data", "sensor_msgs/msg/Image", message, 10_000_000 * (i + 1))
    with BagRecording(path) as recording:
        assert recording.file_version == 3 and recording.device.name == "Intel RealSense D415"
        assert recording.depth_scale == pytest.approx(0.0001) and recording.depth_scale_source == "option"
        assert recording.stream("depth").intrinsics.fx == 20.0 and recording.stream("depth").fps == 15
        frames = list(recording.iter_frames())
        assert [f.info.frame_number for f in frames] == [40, 41, 42]
        assert [f.info.timestamp_ms for f in frames] == [1500250.0, 1501250.0, 1502250.0]
        assert all(np.array_equal(f.data, d) for f, d in zip(frames, depth, strict=True))
        assert frames[0].info.timestamp_domain == "Hardware Clock"  # librealsense's default without metadata


@pytest.mark.parametrize("path", ["darp", "fixtures/recordings/rs257_lz4.bag"])
def test_unverified_lz4_decoding_gives_the_same_frames(tmp_path: Path, path: str) -> None:
    """The fast block-level LZ4 path (no content checksum) decodes exactly what lz4.frame does,
    on darp's 4 MiB blocks and on librealsense's own 1 MiB-block chunks."""
    if path == "darp":
        source = write_sample(tmp_path / "cam.bag", width=640, height=480, framesets=2, imu=False).path
    else:
        source = Path(__file__).parent / path
    with BagRecording(source) as checked, BagRecording(source, verify_checksums=False) as fast:
        assert checked.compressions == ["lz4"]
        pairs = list(zip(checked.iter_frames(), fast.iter_frames(), strict=True))
        assert pairs and all(a.info == b.info and np.array_equal(a.data, b.data) for a, b in pairs)


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_streaming_drops_file_pages_without_harming_held_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                compression: str) -> None:
    """iter_frames releases the file pages it has streamed past (flat memory); frames still held keep
    reading correct pixels (their pages fault back in from the page cache)."""
    from darp.formats.realsense.bag import reader as bag_reader

    monkeypatch.setattr(bag_reader, "_RELEASE_STEP", 4096)
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=20_000)
    with BagRecording(sample.path) as recording:
        held = list(recording.iter_frames())
        assert recording._released > len(held) * 1000
        for frame in held:
            assert np.array_equal(frame.data, sample.frames[frame.info.stream][frame.info.index]["data"])


def test_closing_during_iteration_is_a_clear_error(tmp_path: Path) -> None:
    from darp.errors import RecordingError

    sample = write_sample(tmp_path / "cam.bag", imu=False)
    recording = BagRecording(sample.path)
    frames = recording.iter_frames()
    first = next(frames)
    recording.close()
    with pytest.raises(RecordingError, match="closed"):
        next(frames)
    with pytest.raises(RecordingError, match="closed"):
        recording.frame_infos("ir2")
    assert np.array_equal(first.data, sample.frames[first.info.stream][0]["data"])
