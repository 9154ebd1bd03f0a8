"""darp reads what librealsense writes: the committed genuine recordings against pyrealsense2 playback.

The fixtures (tests/fixtures/recordings/, made by scripts/make_recording_fixtures.py) were written by
librealsense's own recorder: ROS1 .bag by pyrealsense2 2.57, ROS2 .db3 by 2.59. For each, darp's
reader must return what pyrealsense2 returns when it plays the same file: device, profiles,
intrinsics, depth scale, extrinsics, and every frame's number, timestamp, domain and pixels.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from darp.errors import RecordingError
from darp.formats.realsense.recording import open_recording
from helpers.realsense_playback import Played, play_back

FIXTURES = Path(__file__).parent / "fixtures" / "recordings"
FILES = ["rs257_lz4.bag", "rs257_uncompressed.bag", "rs259_png.db3", "rs259_uncompressed.db3"]
STREAMS = ["depth", "color", "ir1", "ir2", "accel", "gyro"]
_played: dict[str, Played] = {}


def _generator():
    """The fixture script, whose functions say what content was recorded."""
    path = Path(__file__).parent.parent / "scripts" / "make_recording_fixtures.py"
    spec = importlib.util.spec_from_file_location("make_recording_fixtures", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(params=FILES)
def pair(request):
    """(darp recording, pyrealsense2 playback) of one fixture file."""
    path = FIXTURES / request.param
    if request.param not in _played:
        _played[request.param] = play_back(path)
    with open_recording(path) as recording:
        yield recording, _played[request.param]


def test_fixtures_are_tiny_and_present():
    for name in FILES:
        assert 0 < (FIXTURES / name).stat().st_size < 300_000, name
    assert "pyrealsense2" in (FIXTURES / "README.md").read_text()


def test_device_info(pair):
    recording, played = pair
    assert recording.device.name == played.info["name"] == "Intel RealSense D435I"
    assert recording.device.serial == played.info["serial_number"] == "348522076490"
    assert recording.device.firmware == played.info["firmware_version"]
    assert recording.device.product_id == played.info["product_id"]


def test_stream_profiles_and_intrinsics(pair):
    recording, played = pair
    assert sorted(recording.streams) == sorted(played.profiles) == sorted(STREAMS)
    for key, profile in recording.streams.items():
        expected = played.profiles[key]
        assert profile.format == expected["format"], key
        assert profile.fps == expected["fps"], key
        if "intrinsics" in expected:
            i = profile.intrinsics
            width, height, fx, fy, ppx, ppy, model, coeffs = expected["intrinsics"]
            assert (profile.width, profile.height) == (i.width, i.height) == (width, height)
            assert (i.fx, i.fy, i.ppx, i.ppy) == (fx, fy, ppx, ppy), key
            assert i.model.lower().replace(" ", "_") == model, key
            assert i.coeffs == coeffs, key
        else:
            m = profile.motion_intrinsics
            data, noise, bias = expected["motion_intrinsics"]
            assert (m.data, m.noise_variances, m.bias_variances) == (data, noise, bias), key


def test_depth_scale(pair):
    recording, played = pair
    assert recording.depth_scale == played.depth_scale
    assert recording.depth_scale == pytest.approx(0.000125, rel=1e-6)


def test_extrinsics_match_librealsense(pair):
    """Same pairs as librealsense (none to the IMU: the recorder stores only image-stream extrinsics).

    librealsense composes poses in float32 (and inverts twice on the way), darp in float64 from the
    same stored numbers, so they agree to float32 precision, not bit for bit."""
    recording, played = pair
    for source in recording.streams:
        for target in recording.streams:
            if (source, target) in played.extrinsics:
                T = recording.extrinsics(source, target)
                np.testing.assert_allclose(T, played.extrinsics[(source, target)], atol=1e-7, rtol=0,
                                           err_msg=f"{source}->{target}")
            else:
                with pytest.raises(RecordingError, match="no extrinsics"):
                    recording.extrinsics(source, target)
    T_color_depth = recording.extrinsics("depth", "color")
    assert T_color_depth[:3, 3] == pytest.approx([0.0147123, 0.0002345, 0.0003456], abs=1e-6)


def test_every_frame_matches_librealsense(pair):
    recording, played = pair
    for key in STREAMS:
        expected = played.frames[key]
        infos = recording.frame_infos(key)
        assert len(infos) == len(expected) == recording.frame_count(key), key
        frames = list(recording.iter_frames([key]))
        assert [f.info for f in frames] == infos
        for frame, want in zip(frames, expected, strict=True):
            assert frame.info.frame_number == want.frame_number, key
            assert frame.info.timestamp_ms == want.timestamp_ms, key
            assert frame.info.timestamp_domain == want.domain, key
            assert frame.data.dtype == want.data.dtype and frame.data.shape == want.data.shape, key
            assert np.array_equal(frame.data, want.data), (key, frame.info.index)
            for name, value in want.metadata.items():
                if name in frame.metadata:
                    assert int(float(frame.metadata[name])) == value, (key, name)
            assert np.array_equal(recording.read_frame(key, frame.info.index).data, frame.data)


def test_content_is_what_the_generator_recorded(pair):
    """Guards the oracle itself: both the SDK and darp return the pixels the script sent."""
    recording, _ = pair
    gen = _generator()
    for n in range(gen.N_FRAMES):
        assert np.array_equal(recording.read_frame("depth", n).data, gen.depth_pixels(n))
        assert np.array_equal(recording.read_frame("ir1", n).data, gen.infrared_pixels(n, 1))
        assert np.array_equal(recording.read_frame("ir2", n).data, gen.infrared_pixels(n, 2))
        color = recording.read_frame("color", n)
        assert np.array_equal(color.data, gen.color_pixels(n))
        assert color.data[0, 0].tolist() == [255, 0, 0]  # blue stays blue in BGR
        assert color.info.frame_number == 500 + n and color.info.timestamp_domain == "System Time"
    gyro = recording.read_frame("gyro", 3)
    assert gyro.info.timestamp_domain == "Hardware Clock"
    assert gyro.data == pytest.approx([0.1 * (0.1 + 1 + 0.25), -0.05, 0.1 * 1.01], rel=1e-6)
    accel = recording.read_frame("accel", 0)
    assert accel.data == pytest.approx([9.81 * 0.1, -9.81 * 0.5, 9.81], rel=1e-6)


def test_bag_and_db3_agree():
    """Both SDK generations recorded the same content; darp reads it the same from either format
    (up to the formats' own timestamp resolution)."""
    with open_recording(FIXTURES / "rs257_lz4.bag") as bag, open_recording(FIXTURES / "rs259_png.db3") as db3:
        assert bag.streams.keys() == db3.streams.keys()
        for key in STREAMS:
            assert bag.streams[key].intrinsics == db3.streams[key].intrinsics
            for a, b in zip(bag.iter_frames([key]), db3.iter_frames([key]), strict=True):
                assert (a.info.frame_number, a.info.timestamp_domain) == (b.info.frame_number, b.info.timestamp_domain)
                # ROS1 stores the stamp in whole nanoseconds, ROS2 as text with 6 decimals of a millisecond
                assert a.info.timestamp_ms == pytest.approx(b.info.timestamp_ms, abs=1e-6)
                assert np.array_equal(a.data, b.data)
