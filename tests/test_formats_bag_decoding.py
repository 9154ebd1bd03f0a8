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

from darp.errors import RecordingError
from darp.formats.realsense.bag.reader import BagRecording
from darp.formats.realsense.rosbag1 import lz4 as bag_lz4
from darp.formats.realsense.rosbag1.index import MAGIC, ByteSource, load_index, read_record
from darp.formats.realsense.rosbag1.lz4 import ChunkBuffer, Lz4Error, decode_frame
from darp.formats.realsense.types import Frame
from helpers.bag_samples import write_sample
from helpers.rosbags_writing import message_putter, realsense_typestore


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
    from darp.formats.realsense.bag import chunks as bag_chunks

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


# -- the inline per-message loops (bag_stream) against the general path ----------------------------
def _everything(recording: BagRecording) -> tuple[list, object]:
    """What a reader hands out: every frame (info, pixels, metadata or its error) or the error that
    stopped the stream, and every stream's frame table (or its error)."""
    frames: list = []
    try:
        for frame in recording.iter_frames():
            try:
                metadata: object = frame.metadata
            except RecordingError as err:
                metadata = str(err)
            frames.append((frame.info, frame.data.shape, str(frame.data.dtype), frame.data.tobytes(),
                           frame.data.flags.writeable, metadata))
    except RecordingError as err:
        frames.append(str(err))
    try:
        tables: object = {key: recording.frame_infos(key) for key in recording.streams}
    except RecordingError as err:
        tables = str(err)
    return frames, tables


def _both_paths(path: Path, **options: object) -> tuple[tuple[list, object], tuple[list, object], int]:
    """(outcome with the inline loops, outcome with every message the general way, frames made inline)."""
    with BagRecording(path, **options) as inline:
        general_calls = []
        general = inline._frame
        inline._frame = lambda key, visit: general_calls.append(key) or general(key, visit)
        inline_outcome = _everything(inline)
    with BagRecording(path, **options) as reference:
        reference._inline = False
        reference_outcome = _everything(reference)
    made = sum(not isinstance(f, str) for f in inline_outcome[0]) - len(general_calls)
    return inline_outcome, reference_outcome, made


def _odd_metadata_bag(path: Path, compression: str) -> list[str]:
    """A bag (written by rosbags) whose depth frames carry unusual metadata and layouts; returns the
    timestamp domain librealsense gives each frame."""
    from rosbags.rosbag1 import Writer
    store = realsense_typestore()
    types = store.types
    header, time = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    metadata = [  # per frame: its KeyValues in order, and the domain they give
        ([("system_time", "1"), ("timestamp_domain", "System Time"), ("Frame Counter", "0")], "System Time"),
        ([], "Hardware Clock"),  # no metadata at all
        ([("Frame Counter", "2")], "Hardware Clock"),  # metadata without a domain
        ([("timestamp_domain", "Global Time"), ("timestamp_domain", "System Time")], "Global Time"),  # 1st
        ([("a", "1"), ("b", "2"), ("c", ""), ("d", "4"), ("timestamp_domain", "Zeit \u20ac")], "Zeit \u20ac"),
        ([("timestamp_domain", "System Time")], "System Time"),  # an 8-row image: another layout
        ([("timestamp_domain", "System Time")], "System Time"),  # padded rows (step 40)
        ([("timestamp_domain", "Global Time")], "Global Time"),
        ([("timestamp_domain", "Global Time")], "Global Time"),
    ]
    writer = Writer(path)
    if compression == "lz4":
        writer.set_compression(Writer.CompressionFormat.LZ4)
    with writer:
        put = message_putter(writer, store)

        put("/file_version", "std_msgs/msg/UInt32", types["std_msgs/msg/UInt32"](data=3))
        put("/device_0/sensor_0/Depth_0/info", "realsense_msgs/msg/StreamInfo",
            types["realsense_msgs/msg/StreamInfo"](fps=30, encoding="mono16", is_recommended=True))
        for i, (items, _) in enumerate(metadata):
            rows, step = (8 if i == 5 else 12), (40 if i == 6 else 32)
            pixels = (np.arange(rows * step, dtype=np.uint32) * (i + 3) % 251).astype(np.uint8)
            message = types["sensor_msgs/msg/Image"](
                header=header(seq=70 + i, stamp=time(sec=1700 + i, nanosec=123_456_789), frame_id="0"),
                height=rows, width=16, encoding="mono16", is_bigendian=0, step=step, data=pixels)
            time_ns = 1_000_000 * (i + 1)
            put("/device_0/sensor_0/Depth_0/image/data", "sensor_msgs/msg/Image", message, time_ns)
            for key, value in items:
                put("/device_0/sensor_0/Depth_0/image/metadata", "diagnostic_msgs/msg/KeyValue",
                    types["diagnostic_msgs/msg/KeyValue"](key=key, value=value), time_ns)
    return [domain for _, domain in metadata]


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_inline_frames_read_unusual_metadata_and_layouts_exactly(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "odd.bag"
    domains = _odd_metadata_bag(path, compression)
    inline, general, made = _both_paths(path)
    assert inline == general and made >= 4  # the rest took the general path, as they must
    frames = inline[0]
    assert [info.timestamp_domain for info, *_ in frames] == domains
    assert [info.frame_number for info, *_ in frames] == list(range(70, 79))
    assert frames[1][-1] == {}
    assert frames[3][-1]["timestamp_domain"] == "System Time"  # the dict keeps the last
    assert frames[5][1] == (8, 16) and frames[6][1] == (12, 16) and not any(f[4] for f in frames)


@pytest.mark.parametrize(("compression", "threshold"),
                         [("none", 20_000), ("none", 768 * 1024), ("lz4", 20_000)])
def test_inline_frames_equal_the_general_path_on_damaged_files(tmp_path: Path, compression: str,
                                                               threshold: int) -> None:
    """Bytes flipped in record headers, image headers and metadata records (and at random): the inline
    loops give the same frames, metadata, frame tables and errors as parsing every message the general
    way (LZ4 chunks read without their checksum, so that damage reaches the messages)."""
    sample = write_sample(tmp_path / "cam.bag", compression=compression, chunk_threshold=threshold,
                          framesets=4)
    original = sample.path.read_bytes()
    options = {"verify_checksums": False}
    intact, general, made = _both_paths(sample.path, **options)
    images = ("depth", "ir1", "ir2", "color")  # all inline but each stream's first (its layout is learnt)
    assert intact == general and made == sum(len(sample.frames[k]) - 1 for k in images)
    if compression == "none":  # places in the messages themselves
        with BagRecording(sample.path) as recording:
            chunks = recording._index.chunks
            tables = [t for key in ("depth", "color") for t in (recording._data[key],
                                                                recording._metadata_entries[key])]
            records = [chunks[int(e["chunk"])].data_start + int(e["offset"]) for t in tables for e in t[:3]]
        places = [r + d for r in records for d in (0, 1, 3, 4, 40, 41, 42, 45, 47, 50, 54, 58, 62, 66, 70)]
    else:  # LZ4 frames: their bytes decode to anything
        places = []
    rng = np.random.default_rng(11)
    places += rng.integers(0, len(original), 30 if compression == "none" else 120).tolist()
    target = tmp_path / "damaged.bag"
    differ = 0
    for place in places:
        data = bytearray(original)
        data[place] ^= 0x5A
        target.write_bytes(bytes(data))
        try:
            inline, general, _ = _both_paths(target, **options)
        except RecordingError as err:  # opening fails, the same way for both
            assert str(target) in str(err)
            continue
        assert inline == general, place
        differ += inline != intact
    assert differ > len(places) // 3  # the damage did reach what is read
