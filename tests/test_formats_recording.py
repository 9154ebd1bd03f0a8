"""The generic Recording behaviour (frame sets, nearest frames, duration) on genuine librealsense files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from darp.errors import RecordingError
from darp.formats.realsense.recording import open_recording

FIXTURES = Path(__file__).parent / "fixtures" / "recordings"
GENUINE = sorted(FIXTURES.glob("rs25*.*"))


@pytest.mark.parametrize("path", GENUINE, ids=lambda p: p.name)
def test_framesets_pair_depth_with_its_infrared_and_nearest_colour(path: Path) -> None:
    with open_recording(path) as rec:
        sets = list(rec.framesets())
        assert len(sets) == rec.frame_count("depth")
        colour_stamps = rec.timestamps_ms("color")
        for fs in sets:
            assert fs.ir1 is not None and fs.ir2 is not None, "infrared partner missing"
            assert fs.ir1.info.frame_number == fs.depth.info.frame_number
            assert fs.ir2.info.frame_number == fs.depth.info.frame_number
            nearest = np.min(np.abs(colour_stamps - fs.depth.info.timestamp_ms))
            assert abs(fs.color.info.timestamp_ms - fs.depth.info.timestamp_ms) == pytest.approx(nearest)


@pytest.mark.parametrize("path", GENUINE, ids=lambda p: p.name)
def test_duration_uses_one_clock_even_when_domains_differ(path: Path) -> None:
    with open_recording(path) as rec:
        recording_ns = [i.recording_time_ns for k in rec.streams for i in rec.frame_infos(k)]
        assert rec.duration_s == pytest.approx((max(recording_ns) - min(recording_ns)) / 1e9)
        assert 0.0 < rec.duration_s < 60.0


@pytest.mark.parametrize("path", GENUINE, ids=lambda p: p.name)
def test_frame_at_returns_the_nearest_frame(path: Path) -> None:
    with open_recording(path) as rec:
        stamps = rec.timestamps_ms("depth")
        for i, t in enumerate(stamps):
            assert rec.frame_at("depth", t + 0.1).info.index == i


def test_open_recording_rejects_empty_and_foreign_files(tmp_path: Path) -> None:
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="empty file"):
        open_recording(empty)
    text = tmp_path / "notes.bag"
    text.write_text("hello")
    with pytest.raises(RecordingError, match="not a RealSense recording"):
        open_recording(text)
    with pytest.raises(RecordingError, match="no such file"):
        open_recording(tmp_path / "missing.bag")
    with pytest.raises(RecordingError, match="folder"):
        open_recording(tmp_path)
