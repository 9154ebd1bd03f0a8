"""darp's fast .bag reading path: native LZ4 decoding, pooled chunk buffers, decode threads, lazy
metadata and the fast index parser, each checked against an independent or slower reference."""

from __future__ import annotations

import os
import pickle
import signal
import struct
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
from test_formats_bag import write_sample

from darp.errors import RecordingError
from darp.formats import bag_lz4
from darp.formats.bag_lz4 import ChunkBuffer, Lz4Error, decode_frame
from darp.formats.bag_reader import BagRecording
from darp.formats.recording_types import Frame
from darp.formats.rosbag1 import MAGIC, ByteSource, load_index, read_record


def _payload(seed: int = 0, size: int = 300_000) -> bytes:
    """Compressible but not trivial bytes (a noisy ramp)."""
    rng = np.random.default_rng(seed)
    return (np.arange(size) // 7 + rng.integers(0, 3, size)).astype(np.uint8).tobytes()


@pytest.mark.parametrize("native", [True, False], ids=["native", "portable"])
@pytest.mark.parametrize("linked", [False, True], ids=["independent", "linked"])
@pytest.mark.parametrize("options", [{"content_checksum": True, "store_size": False},
                                     {"content_checksum": False, "store_size": True, "block_checksum": True}])
def test_lz4_frames_decode_like_python_lz4(monkeypatch: pytest.MonkeyPatch, native: bool, linked: bool,
                                          options: dict) -> None:
    if native and bag_lz4.native() is None:
        pytest.fail("python-lz4's bundled library is not reachable: the fast path is off on this machine")
    if not native:
        monkeypatch.setattr(bag_lz4, "NATIVE", None)
    data = _payload()
    frame = lz4.frame.compress(data, block_size=lz4.frame.BLOCKSIZE_MAX64KB, block_linked=linked, **options)
    assert lz4.frame.decompress(frame) == data
    out = ChunkBuffer(len(data))
    for verify in (True, False):
        out.data[:] = bytes(out.capacity)
        decode_frame(frame, out, len(data), verify)
        assert bytes(out.view(len(data))) == data
    with pytest.raises(Lz4Error, match="more data than the chunk size|chunk header says"):
        decode_frame(frame, out, len(data) - 1, False)


@pytest.mark.parametrize("native", [True, False], ids=["native", "portable"])
def test_lz4_damage_is_detected_when_verifying(monkeypatch: pytest.MonkeyPatch, native: bool) -> None:
    if not native:
        monkeypatch.setattr(bag_lz4, "NATIVE", None)
    data = _payload(1)
    frame = bytearray(lz4.frame.compress(data, block_linked=False, content_checksum=True, store_size=False))
    rng = np.random.default_rng(3)
    out = ChunkBuffer(len(data))
    caught = 0
    for where in rng.integers(7, len(frame) - 4, 40):
        bad = bytearray(frame)
        bad[where] ^= 0x10
        try:
            decode_frame(bytes(bad), out, len(data), True)
        except Lz4Error:
            caught += 1
    assert caught == 40  # every flipped bit fails a length check, the decoder or the content checksum
    with pytest.raises(Lz4Error, match="magic"):
        decode_frame(b"not an lz4 frame", out, len(data), True)


def test_pooled_buffers_are_reused_only_when_no_frame_views_them(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames kept by the consumer stay intact while the reader recycles buffers for later chunks."""
    from darp.formats import bag_chunks

    allocated = []
    monkeypatch.setattr(bag_chunks, "ChunkBuffer", lambda size: allocated.append(size) or ChunkBuffer(size))
    sample = write_sample(tmp_path / "cam.bag", width=96, height=64, framesets=40, imu=False, chunk_threshold=30_000)
    with BagRecording(sample.path) as recording:
        kept = []
        for n, frame in enumerate(recording.iter_frames(["depth", "color"])):
            if n % 5 == 0:
                kept.append(frame)  # the rest are dropped at once, so their buffers can be reused
        assert len(recording._index.chunks) > 20
        assert 0 < len(allocated) < len(recording._index.chunks) - 5  # buffers were recycled
        for frame in kept:
            assert not frame.data.flags.writeable
            assert np.array_equal(frame.data, sample.frames[frame.info.stream][frame.info.index]["data"])
            assert frame.metadata["timestamp_domain"] == sample.frames[frame.info.stream][frame.info.index]["domain"]


@pytest.mark.parametrize("threads", [0, 1, 2])
def test_decode_threads_give_the_same_frames(tmp_path: Path, threads: int) -> None:
    sample = write_sample(tmp_path / "cam.bag", width=96, height=64, framesets=20, chunk_threshold=25_000)
    with BagRecording(sample.path, decode_threads=0) as reference, \
            BagRecording(sample.path, decode_threads=threads) as recording:
        pairs = list(zip(reference.iter_frames(), recording.iter_frames(), strict=True))
        assert len(pairs) == sum(len(frames) for frames in sample.frames.values())
        for a, b in pairs:
            assert a.info == b.info and np.array_equal(a.data, b.data) and a.metadata == b.metadata
        # abandoning a stream half-way leaves the recording usable
        stream = recording.iter_frames(["depth"])
        next(stream)
        del stream
        assert recording.read_frame("depth", 19).info.frame_number == sample.frames["depth"][19]["number"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX only")
def test_a_forked_child_keeps_reading(tmp_path: Path) -> None:
    """A process forked while decode workers exist (multiprocessing's default on Linux) gets none of
    them: its reads must neither hang on the parent's pending work nor fail."""
    sample = write_sample(tmp_path / "cam.bag", width=96, height=64, framesets=12, chunk_threshold=25_000)
    with BagRecording(sample.path, decode_threads=2) as recording:
        stream = recording.iter_frames(["depth"])
        next(stream)  # the workers now exist and hold work in flight
        pid = os.fork()
        if pid == 0:  # the child: read everything again, report through the exit status
            signal.alarm(30)  # a hang ends the child (killed by SIGALRM) instead of the test run
            ok = [f.info.frame_number for f in recording.iter_frames(["depth"])] == \
                [f["number"] for f in sample.frames["depth"]]
            os._exit(0 if ok else 1)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert len(list(stream)) == len(sample.frames["depth"]) - 1


def test_lazy_metadata_frames_behave_like_frames(tmp_path: Path) -> None:
    sample = write_sample(tmp_path / "cam.bag", framesets=3, imu=False)
    with BagRecording(sample.path) as recording:
        frame = recording.read_frame("color", 2)
    assert isinstance(frame, Frame)
    expected = {"timestamp_domain": "System Time", "Frame Counter": "5002"}
    assert expected.items() <= frame.metadata.items()  # parsed after close: the frame holds its chunk
    copy = pickle.loads(pickle.dumps(frame))
    assert type(copy) is Frame and copy.info == frame.info and copy.metadata == frame.metadata
    assert np.array_equal(copy.data, frame.data)
    frame.metadata = {"replaced": "1"}
    assert frame.metadata == {"replaced": "1"}


def test_corrupt_metadata_surfaces_as_a_recording_error_when_read(tmp_path: Path) -> None:
    """A KeyValue whose length field is damaged: the frame (pixels, time) still reads, and its metadata
    gives a one-line RecordingError naming the file when it is parsed."""
    sample = write_sample(tmp_path / "cam.bag", compression="none", framesets=2, imu=False)
    data = bytearray(sample.path.read_bytes())
    with BagRecording(sample.path) as recording:
        entries = recording._metadata_entries["depth"]
        last = entries[entries["time"] == entries["time"][0]][-1]  # after timestamp_domain
        chunk = recording._index.chunks[int(last["chunk"])]
        record = chunk.data_start + int(last["offset"])
        header_len = int.from_bytes(data[record:record + 4], "little")
        key_len_at = record + 8 + header_len
    data[key_len_at:key_len_at + 4] = (10**6).to_bytes(4, "little")
    broken = tmp_path / "broken.bag"
    broken.write_bytes(bytes(data))
    with BagRecording(broken) as recording:
        frame = recording.read_frame("depth", 0)
        assert np.array_equal(frame.data, sample.frames["depth"][0]["data"])
        with pytest.raises(RecordingError, match="corrupt metadata of depth frame 0") as err:
            _ = frame.metadata
        assert str(broken) in str(err.value)


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_fast_index_equals_a_scan_of_the_chunks(tmp_path: Path, compression: str) -> None:
    """The one-read-per-chunk index parser finds the same chunks and entries as rebuilding the index
    from the chunks' own records."""
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=20_000)
    data = sample.path.read_bytes()
    fd = os.open(sample.path, os.O_RDONLY)
    try:
        indexed = load_index(ByteSource(memoryview(data), fd), sample.path)
    finally:
        os.close(fd)
    fields, _, _ = read_record(data, len(MAGIC), len(data))
    (index_pos,) = struct.unpack("<Q", fields["index_pos"])
    scanned = load_index(memoryview(data[:index_pos]), sample.path)  # as an interrupted write leaves it
    assert scanned.truncated and not indexed.truncated and len(indexed.chunks) > 5
    assert indexed.chunks == scanned.chunks
    assert indexed.entries.keys() == scanned.entries.keys()
    for conn, entries in indexed.entries.items():
        assert np.array_equal(entries, scanned.entries[conn])
