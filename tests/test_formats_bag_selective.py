"""Reading only what is needed from a .bag: the frame table reads the messages' headers (no image is paged
in from an uncompressed bag), ``read_frame`` and time windows decode only their frames; all of them give
exactly the frames that streaming the whole bag gives, and that pyrealsense2's playback gives."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from darp.formats.realsense.bag.reader import BagRecording
from darp.reconstruction.keyframe_io import frameset_at
from helpers.bag_samples import write_sample
from helpers.realsense_playback import play_back
from helpers.script_modules import load_study

IMAGES = ("depth", "color", "ir1", "ir2")


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_selective_reads_match_streaming_and_pyrealsense2(tmp_path: Path, compression: str) -> None:
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=20_000, framesets=9)
    played = play_back(sample.path)
    with BagRecording(sample.path) as selective, BagRecording(sample.path) as streamed:
        # the frame table alone (headers), against librealsense's playback
        infos = {key: selective.frame_infos(key) for key in IMAGES}
        for key in IMAGES:
            got = played.frames[key]
            assert [i.frame_number for i in infos[key]] == [f.frame_number for f in got], key
            assert [i.timestamp_ms for i in infos[key]] == [f.timestamp_ms for f in got], key
            assert [i.timestamp_domain for i in infos[key]] == [f.domain for f in got], key
        # random access, newest first (no streaming state to lean on), against the playback's pixels
        for key in IMAGES:
            for i in reversed(range(len(infos[key]))):
                frame = selective.read_frame(key, i)
                assert frame.info == infos[key][i]
                assert np.array_equal(frame.data, played.frames[key][i].data), (key, i)
        # the streaming path (every frame of every stream, recording order) gives the same frames
        seen = dict.fromkeys(IMAGES, 0)
        for frame in streamed.iter_frames():
            key = frame.info.stream
            if key in seen:
                assert frame.info == infos[key][frame.info.index]
                assert np.array_equal(frame.data, selective.read_frame(key, frame.info.index).data)
                seen[key] += 1
        assert seen == {key: len(infos[key]) for key in IMAGES}
        # one frame set decoded on its own (keyframe export) is the streamed grouping's
        for depth_index, whole in enumerate(streamed.framesets()):
            alone = frameset_at(selective, depth_index)
            for key in ("depth", "ir1", "ir2", "color"):
                a, b = getattr(alone, key), getattr(whole, key)
                assert a.info == b.info and np.array_equal(a.data, b.data), (key, depth_index)


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_frame_table_asks_for_no_uncompressed_chunk(tmp_path: Path, compression: str) -> None:
    """The kernel is asked for a chunk's bytes only where they are read in full: LZ4 chunks before decoding,
    uncompressed chunks when frames are read, never for the frame table of an uncompressed bag."""
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=20_000)
    with BagRecording(sample.path) as recording:
        store = recording._chunks
        assert store is not None and recording._random  # the mapping has no read-ahead on faults (Linux)
        asked: list[tuple[int, int]] = []
        store._willneed = lambda offset, length: asked.append((offset, length))
        store._advised.clear()
        recording.frame_infos("depth")
        recording.frame_infos("ir2")
        chunks = {(c.data_start, c.data_len) for c in recording._index.chunks}
        if compression == "none":
            assert asked == []
            assert "gyro" not in recording._tables  # IMU streams are not parsed along for nothing
        else:
            assert asked and set(asked) <= chunks
            assert "gyro" in recording._tables  # their chunks were decoded anyway
        asked.clear()
        frame = recording.read_frame("color", 5)
        assert np.array_equal(frame.data, sample.frames["color"][5]["data"])
        entry = recording._data["color"][5]
        chunk = recording._index.chunks[int(entry["chunk"])]
        assert (chunk.data_start, chunk.data_len) in asked
        np.testing.assert_array_equal(recording.timestamps_ms("gyro"), [f["ts"] for f in sample.frames["gyro"]])


def _evict(path: Path) -> None:
    load_study("process_io").evict([path])


def _cached_bytes(path: Path) -> int:
    return int(load_study("process_io").cached_bytes([path]))


@pytest.mark.skipif(shutil.which("fincore") is None or not hasattr(os, "posix_fadvise"), reason="needs fincore")
def test_frame_table_of_a_cold_bag_reads_a_small_part_of_it(tmp_path: Path) -> None:
    """With the page cache emptied of the bag, indexing every image stream brings in a small part of the file
    (headers and metadata; read-ahead of the images read 100 % of it before), and a frame read brings in its
    chunk. The kernel's page cache (util-linux ``fincore``) is the oracle."""
    sample = write_sample(tmp_path / "cold.bag", compression="none", width=424, height=240, framesets=24,
                          chunk_threshold=1 << 20)
    size = sample.path.stat().st_size
    _evict(sample.path)
    if _cached_bytes(sample.path) > size // 20:
        pytest.skip("this file system keeps the file cached (tmpfs?): nothing to measure")
    with BagRecording(sample.path) as recording:
        for key in IMAGES:
            recording.frame_infos(key)
        indexed = _cached_bytes(sample.path)
        assert indexed < 0.25 * size, f"{indexed} of {size} bytes read to index the frames"
        frame = recording.read_frame("depth", 12)
        assert np.array_equal(frame.data, sample.frames["depth"][12]["data"])  # its pages are read now
        assert _cached_bytes(sample.path) >= indexed + 424 * 240 * 2 // 2
