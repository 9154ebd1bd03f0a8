"""The ROS2 .db3 reader: formats, layout, time windows, extrinsics, bounded memory and bad files.

Recordings are made here with pyrealsense2's own recorder (>= 2.58 writes .db3) and played back with
pyrealsense2 as the oracle; damaged copies are made with sqlite3.
"""

from __future__ import annotations

import itertools
import shutil
import sqlite3
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from darp.errors import RecordingError
from darp.formats.realsense.db3.reader import Db3Recording, parse_key_values
from darp.formats.realsense.recording import open_recording
from helpers.realsense_playback import play_back

rs = pytest.importorskip("pyrealsense2")
FIXTURES = Path(__file__).parent / "fixtures" / "recordings"
PNG_DB3 = FIXTURES / "rs259_png.db3"
RAW_DB3 = FIXTURES / "rs259_uncompressed.db3"
CHANNELS = {"y8": 1, "y16": 1, "z16": 1, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


def record_db3(path: Path, *, compress: bool, color_fmt: str = "bgr8", ir_fmt: str = "y8", frames: int = 3,
               width: int = 32, height: int = 24, with_color: bool = True) -> dict[str, list[np.ndarray]]:
    """Record depth, IR1 (and colour) with librealsense's recorder; return the pixels sent."""
    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "Intel RealSense D435")
    dev.register_info(rs.camera_info.serial_number, "405622074504")
    stereo = dev.add_sensor("Stereo Module")
    rgb = dev.add_sensor("RGB Camera") if with_color else None

    def add(sensor, stream, index, uid, fmt):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps = stream, index, uid, width, height, 15
        vs.fmt = getattr(rs.format, fmt)
        vs.bpp = CHANNELS[fmt] * (2 if fmt in ("y16", "z16") else 1)
        i = rs.intrinsics()
        i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = width, height, 30.5, 31.25, width / 2 - 0.5, height / 2
        vs.intrinsics = i
        return sensor.add_video_stream(vs, True), vs.bpp

    depth, depth_bpp = add(stereo, rs.stream.depth, 0, 0, "z16")
    ir1, ir_bpp = add(stereo, rs.stream.infrared, 1, 1, ir_fmt)
    stereo.add_read_only_option(rs.option.depth_units, 0.001)
    streams = [(stereo, depth, depth_bpp, "depth"), (stereo, ir1, ir_bpp, "ir1")]
    extr = rs.extrinsics()
    c, s = np.cos(0.3), np.sin(0.3)
    extr.rotation = [c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0]  # column-major rotation about z
    extr.translation = [0.015, -0.002, 0.001]
    if rgb is not None:
        color, color_bpp = add(rgb, rs.stream.color, 0, 2, color_fmt)
        depth.register_extrinsics_to(color, extr)
        streams.append((rgb, color, color_bpp, "color"))
    recorder = rs.recorder(str(path), dev, compress)
    queue = rs.frame_queue(1000)
    stereo.open([depth, ir1])
    stereo.start(queue)
    if rgb is not None:
        rgb.open(color)
        rgb.start(queue)
    rng = np.random.default_rng(7)
    sent: dict[str, list[np.ndarray]] = {key: [] for *_, key in streams}
    for n in range(frames):
        for sensor, profile, bpp, key in streams:
            fmt = str(profile.format()).split(".")[-1]
            shape = (height, width) + ((CHANNELS[fmt],) if CHANNELS[fmt] > 1 else ())
            dtype = np.uint16 if bpp // CHANNELS[fmt] == 2 else np.uint8
            pixels = rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)
            sent[key].append(pixels)
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = pixels, bpp, bpp * width
            frame.timestamp, frame.frame_number = 5000.0 + 66.6 * n, 40 + n
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
        time.sleep(0.01)
    for sensor in [stereo] + ([rgb] if rgb is not None else []):
        sensor.stop()
        sensor.close()
    del recorder
    return sent


@pytest.mark.parametrize(
    "compress,color_fmt,ir_fmt",
    [(True, "rgb8", "y16"), (False, "rgb8", "y16"), (True, "bgra8", "y8"), (True, "rgba8", "y8"),
     (False, "bgra8", "y8")],
)
def test_pixel_formats_match_what_was_sent_and_librealsense(tmp_path, compress, color_fmt, ir_fmt):
    path = tmp_path / "formats.db3"
    sent = record_db3(path, compress=compress, color_fmt=color_fmt, ir_fmt=ir_fmt)
    played = play_back(path)
    with open_recording(path) as recording:
        assert isinstance(recording, Db3Recording)
        assert recording.compression == ("png" if compress else "none")
        assert recording.streams["color"].format == color_fmt and recording.streams["ir1"].format == ir_fmt
        for key, pixels in sent.items():
            frames = list(recording.iter_frames([key]))
            assert len(frames) == len(pixels) == len(played.frames[key])
            for frame, want, oracle in zip(frames, pixels, played.frames[key], strict=True):
                assert frame.data.dtype == want.dtype and np.array_equal(frame.data, want), key
                assert np.array_equal(frame.data, oracle.data), key
                assert frame.info.timestamp_ms == oracle.timestamp_ms
                assert frame.info.timestamp_domain == oracle.domain == "Hardware Clock"


def test_layout_is_the_documented_one():
    """The tables, topics and message types that docs/recordings-db3.md describes."""
    con = sqlite3.connect(PNG_DB3)
    columns = [row[1] for row in con.execute("PRAGMA table_info(messages)")]
    assert columns == ["id", "topic_id", "timestamp", "data"]
    types = dict(con.execute("SELECT name, type FROM topics").fetchall())
    assert types["/file_version"] == "std_msgs/msg/UInt32"
    assert types["/device_0/sensor_0/Depth_0/image/data/compressedDepth"] == "sensor_msgs/msg/CompressedImage"
    assert types["/device_0/sensor_1/Color_0/image/data/compressed"] == "sensor_msgs/msg/CompressedImage"
    assert types["/device_0/sensor_2/Gyro_0/imu/data"] == "sensor_msgs/msg/Imu"
    assert types["/device_0/sensor_0/Depth_0/tf/ref_1"] == "std_msgs/msg/String"
    raw_types = dict(sqlite3.connect(RAW_DB3).execute("SELECT name, type FROM topics").fetchall())
    assert raw_types["/device_0/sensor_0/Depth_0/image/data"] == "sensor_msgs/msg/Image"
    static_times = {t for (t,) in con.execute(
        "SELECT m.timestamp FROM messages m JOIN topics t ON t.id = m.topic_id WHERE t.name LIKE '%/info'")}
    assert static_times == {0}


def test_parse_key_values_keeps_equals_signs_in_values():
    assert parse_key_values("a=1;b=x=y;;c=;d") == {"a": "1", "b": "x=y", "c": "", "d": ""}


def test_frame_infos_windows_and_recording_order():
    with open_recording(PNG_DB3) as recording:
        infos = recording.frame_infos("depth")
        assert [i.index for i in infos] == [0, 1, 2, 3]
        assert all(a.recording_time_ns < b.recording_time_ns for a, b in itertools.pairwise(infos))
        everything = list(recording.iter_frames())
        assert len(everything) == sum(recording.frame_count(k) for k in recording.streams)
        times = [f.info.recording_time_ns for f in everything]
        assert times == sorted(times)
        start, stop = infos[1].timestamp_ms, infos[3].timestamp_ms
        window = list(recording.iter_frames(["depth", "ir2"], start_ms=start, stop_ms=stop))
        assert [(f.info.stream, f.info.index) for f in window] == [("depth", 1), ("ir2", 1), ("depth", 2), ("ir2", 2)]
        assert list(recording.iter_frames(["depth"], start_ms=1e18)) == []
        assert recording.nearest_index("color", infos[2].timestamp_ms + 4.0) == 2
        sets = list(recording.framesets())
        assert [s.depth.info.index for s in sets] == [0, 1, 2, 3]
        assert [s.color.info.index for s in sets] == [0, 1, 2, 3]


def test_extrinsics_map_points_like_librealsense(tmp_path):
    path = tmp_path / "extr.db3"
    record_db3(path, compress=True, frames=1)
    device = rs.context().load_device(str(path))
    profiles = {str(p.stream_type()): p for s in device.query_sensors() for p in s.get_stream_profiles()}
    rs_extr = profiles["stream.depth"].get_extrinsics_to(profiles["stream.color"])
    point = [0.1, -0.2, 1.3]
    expected = rs.rs2_transform_point_to_point(rs_extr, point)
    with open_recording(path) as recording:
        T_color_depth = recording.extrinsics("depth", "color")
        np.testing.assert_allclose(T_color_depth @ [*point, 1.0], [*expected, 1.0], atol=1e-6)
        np.testing.assert_allclose(recording.extrinsics("color", "depth") @ T_color_depth, np.eye(4), atol=1e-6)
        np.testing.assert_array_equal(recording.extrinsics("ir1", "ir1"), np.eye(4))


def _damaged_copy(tmp_path: Path, topic_pattern: str) -> Path:
    path = tmp_path / "damaged.db3"
    shutil.copy(RAW_DB3, path)
    with sqlite3.connect(path) as con:
        con.execute("DELETE FROM messages WHERE topic_id IN (SELECT id FROM topics WHERE name LIKE ?)",
                    (topic_pattern,))
    return path


def test_missing_metadata_falls_back_like_librealsense(tmp_path):
    """Without its metadata librealsense reports a frame as number 0 at 0 ms on the hardware clock."""
    path = _damaged_copy(tmp_path, "%Depth_0/image/metadata")
    played = play_back(path)
    with open_recording(path) as recording:
        for info, oracle in zip(recording.frame_infos("depth"), played.frames["depth"], strict=True):
            assert (info.frame_number, info.timestamp_ms, info.timestamp_domain) == (
                oracle.frame_number, oracle.timestamp_ms, oracle.domain) == (0, 0.0, "Hardware Clock")
        assert recording.read_frame("depth", 0).metadata == {}
        assert recording.frame_infos("ir1")[1].frame_number == 1001  # other streams untouched
        assert recording.depth_scale == played.depth_scale


def test_missing_depth_units_option_uses_the_frames_depth_units(tmp_path):
    """librealsense falls back to 1 mm there (wrong for this file); darp uses the per-frame depth_units."""
    path = _damaged_copy(tmp_path, "%option/Depth_Units/%")
    with open_recording(path) as recording:
        assert recording.depth_scale == pytest.approx(0.000125, rel=1e-6)
    path = _damaged_copy(tmp_path, "%/image/metadata")
    with sqlite3.connect(path) as con:
        con.execute("DELETE FROM messages WHERE topic_id IN (SELECT id FROM topics WHERE name LIKE ?)",
                    ("%option/Depth_Units/%",))
    with open_recording(path) as recording:
        assert recording.depth_scale == play_back(path).depth_scale == pytest.approx(0.001)


def test_iteration_memory_is_bounded(tmp_path):
    """Streaming 20 VGA depth frames (12 MB of pixels) holds about one frame at a time."""
    path = tmp_path / "vga.db3"
    record_db3(path, compress=False, frames=20, width=640, height=480, with_color=False)
    with open_recording(path) as recording:
        tracemalloc.start()
        count = 0
        for frame in recording.iter_frames(["depth", "ir1"]):
            count += 1
            del frame
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert count == 40
    assert peak < 4 * 640 * 480 * 2, peak  # a few frames' worth, not 12 MB


def _copy(tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    shutil.copy(PNG_DB3, path)
    return path


def test_bad_files_raise_one_line_recording_errors(tmp_path):
    truncated = _copy(tmp_path, "truncated.db3")
    truncated.write_bytes(truncated.read_bytes()[:6000])
    with pytest.raises(RecordingError, match="truncated.db3"), open_recording(truncated) as recording:
        list(recording.iter_frames())
    garbage = tmp_path / "garbage.db3"
    garbage.write_bytes(b"SQLite format 3\x00" + bytes(range(256)) * 20)
    with pytest.raises(RecordingError, match="garbage.db3"):
        open_recording(garbage)
    other = tmp_path / "other.db3"
    with sqlite3.connect(other) as con:
        con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT, type TEXT)")
        con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INT, timestamp INT, data BLOB)")
        con.execute("INSERT INTO topics VALUES (1, '/chatter', 'std_msgs/msg/String')")
    with pytest.raises(RecordingError, match="no /file_version"):
        open_recording(other)
    empty = tmp_path / "empty.db3"
    sqlite3.connect(empty).execute("CREATE TABLE x(a)").connection.close()
    with pytest.raises(RecordingError, match="no topics/messages"):
        open_recording(empty)


def test_corrupt_frames_raise_on_read_naming_file_and_frame(tmp_path):
    path = _copy(tmp_path, "corrupt.db3")
    with sqlite3.connect(path) as con:
        (depth_id,) = con.execute("SELECT id FROM topics WHERE name LIKE '%Depth_0/image/data%'").fetchone()
        (color_id,) = con.execute("SELECT id FROM topics WHERE name LIKE '%Color_0/image/data%'").fetchone()
        first = con.execute("SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id", (depth_id,)).fetchone()
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (first[1][:40], first[0]))
        row = con.execute("SELECT id, data FROM messages WHERE topic_id = ? ORDER BY id", (color_id,)).fetchone()
        broken_png = bytearray(row[1])
        broken_png[-60:-20] = b"\x00" * 40
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (bytes(broken_png), row[0]))
    with open_recording(path) as recording:
        assert recording.frame_count("depth") == 4  # the index does not need pixels
        with pytest.raises(RecordingError, match=r"corrupt.db3: Depth_0 frame 0"):
            recording.read_frame("depth", 0)
        with pytest.raises(RecordingError, match=r"Color_0 frame 0"):
            recording.read_frame("color", 0)
        assert recording.read_frame("depth", 1).data.shape == (48, 64)


def test_bad_requests(tmp_path):
    recording = open_recording(PNG_DB3)
    with pytest.raises(RecordingError, match="no stream 'fisheye'.*depth"):
        recording.frame_infos("fisheye")
    with pytest.raises(RecordingError, match="no frame 4"):
        recording.read_frame("depth", 4)
    with pytest.raises(RecordingError, match="no frame -1"):
        recording.read_frame("depth", -1)
    assert recording.size_bytes == PNG_DB3.stat().st_size
    recording.close()
    recording.close()  # idempotent
    with pytest.raises(RecordingError, match="closed"):
        recording.read_frame("depth", 0)
