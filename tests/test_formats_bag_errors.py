"""Bad and damaged .bag input, writer validation and interrupted writes: always a clear RecordingError."""

from __future__ import annotations

import contextlib
import struct
from pathlib import Path

import numpy as np
import pytest

from darp.errors import DarpError, RecordingError, SalvagedRecordingWarning
from darp.formats.realsense.bag.reader import BagRecording
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.recording import open_recording
from darp.formats.realsense.rosbag1.index import MAGIC, load_index, read_record
from darp.formats.realsense.types import StreamProfile
from helpers.bag_samples import DEVICE, profiles, write_sample

CHUNKED = 20_000  # small chunks: about one frame set each at 64x48


@pytest.fixture(scope="module")
def lz4_bag(tmp_path_factory: pytest.TempPathFactory):
    return write_sample(tmp_path_factory.mktemp("lz4") / "cam.bag", chunk_threshold=CHUNKED)


@pytest.fixture(scope="module")
def raw_bag(tmp_path_factory: pytest.TempPathFactory):
    return write_sample(tmp_path_factory.mktemp("raw") / "cam.bag", compression="none", chunk_threshold=CHUNKED)


def _layout(path: Path) -> tuple[list, dict[str, list[int]], int]:
    """Chunks, the chunk number of every depth/gyro frame, and the index position of a whole bag."""
    data = path.read_bytes()
    with BagRecording(path) as recording:
        chunks_of = {k: [int(c) for c in recording._data[k]["chunk"]] for k in ("depth", "gyro")}
    index = load_index(memoryview(data), path)
    fields, _, _ = read_record(data, len(MAGIC), len(data))
    return index.chunks, chunks_of, struct.unpack("<Q", fields["index_pos"])[0]


def _cut(source: Path, target: Path, length: int) -> Path:
    target.write_bytes(source.read_bytes()[:length])
    return target


def _read_everything(recording: BagRecording) -> int:
    count = 0
    for key in recording.streams:
        recording.frame_infos(key)
        for source in recording.streams:
            with contextlib.suppress(RecordingError):
                recording.extrinsics(source, key)
    for _ in recording.iter_frames():
        count += 1
    return count


# -- not a bag ----------------------------------------------------------------------------------
def test_empty_file(tmp_path: Path) -> None:
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    for opener in (open_recording, BagRecording):
        with pytest.raises(RecordingError, match="empty file") as err:
            opener(empty)
        assert str(empty) in str(err.value)


@pytest.mark.parametrize("content", [b"\x89PNG\r\n\x1a\n" + bytes(100), b"just some text\n" * 20,
                                     b"#ROSBAG V1.2\n" + bytes(64)])
def test_wrong_format(tmp_path: Path, content: bytes) -> None:
    fake = tmp_path / "fake.bag"
    fake.write_bytes(content)
    with pytest.raises(RecordingError, match="not a RealSense recording") as err:
        open_recording(fake)
    assert err.value.path == fake
    with pytest.raises(RecordingError, match="not a ROS1 bag"):
        BagRecording(fake)


def test_missing_file_and_folder(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such file"):
        BagRecording(tmp_path / "absent.bag")
    with pytest.raises(RecordingError):
        open_recording(tmp_path)


def test_generic_bag_without_realsense_topics(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "other.bag"
    with Writer(path) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        message = store.types["std_msgs/msg/String"](data="hi")
        writer.write(conn, 5, store.serialize_ros1(message, "std_msgs/msg/String"))
    with pytest.raises(RecordingError, match="no /file_version"):
        BagRecording(path)


def test_bz2_chunks_are_refused(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "bz2.bag"
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.BZ2)
    with writer:
        conn = writer.add_connection("/file_version", "std_msgs/msg/UInt32", typestore=store)
        writer.write(conn, 1, store.serialize_ros1(store.types["std_msgs/msg/UInt32"](data=4), "std_msgs/msg/UInt32"))
    with pytest.raises(RecordingError, match="BZ2-compressed chunk at byte offset 4109") as err:
        open_recording(path)
    assert str(path) in str(err.value)


# -- truncated files ------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["mid-chunk", "after-chunk-data", "after-chunk-index", "inside-index"])
@pytest.mark.parametrize("which", [2, 5])
def test_truncated_bag_reads_complete_chunks(lz4_bag, tmp_path: Path, kind: str, which: int) -> None:
    chunks, chunks_of, index_pos = _layout(lz4_bag.path)
    assert len(chunks) > 8
    chunk, following = chunks[which], chunks[which + 1]
    length, complete = {
        "mid-chunk": (chunk.data_start + chunk.data_len // 2, which),
        "after-chunk-data": (chunk.data_start + chunk.data_len, which + 1),
        "after-chunk-index": (following.pos, which + 1),
        "inside-index": (index_pos + 40, len(chunks)),
    }[kind]
    cut = _cut(lz4_bag.path, tmp_path / "cut.bag", length)
    with pytest.warns(SalvagedRecordingWarning, match="cut.bag: .*recovered"):
        recording = open_recording(cut)
    with recording:
        assert recording.truncated and "complete chunks recovered" in recording.truncation_note
        assert recording.salvage is not None and recording.salvage.chunks == complete
        assert recording.salvage.frames["depth"] == len([c for c in chunks_of["depth"] if c < complete])
        for key in ("depth", "gyro"):
            expected = [f for f, c in zip(lz4_bag.frames[key], chunks_of[key], strict=True) if c < complete]
            assert [i.frame_number for i in recording.frame_infos(key)] == [f["number"] for f in expected]
            for i, frame in enumerate(expected):
                assert np.array_equal(recording.read_frame(key, i).data, frame["data"])
        assert recording.stream("color").intrinsics == lz4_bag.streams[3].intrinsics
        assert _read_everything(recording) > 0


def test_truncated_before_any_chunk(lz4_bag, tmp_path: Path) -> None:
    chunks, _, _ = _layout(lz4_bag.path)
    with pytest.raises(RecordingError, match="truncated bag header"):
        BagRecording(_cut(lz4_bag.path, tmp_path / "a.bag", 2000))
    with pytest.raises(RecordingError, match="no complete chunk"):
        BagRecording(_cut(lz4_bag.path, tmp_path / "b.bag", chunks[0].data_start + 10))


def test_corrupted_lz4_chunk_names_file_and_offset(lz4_bag, tmp_path: Path) -> None:
    chunks, chunks_of, _ = _layout(lz4_bag.path)
    data = bytearray(lz4_bag.path.read_bytes())
    bad = chunks[4]
    middle = bad.data_start + bad.data_len // 2
    data[middle:middle + 8] = bytes(b ^ 0x5A for b in data[middle:middle + 8])
    broken = tmp_path / "broken.bag"
    broken.write_bytes(bytes(data))
    with BagRecording(broken) as recording:  # the index is intact: opening works
        first = chunks_of["depth"].index(0)
        assert np.array_equal(recording.read_frame("depth", first).data, lz4_bag.frames["depth"][first]["data"])
        victim = chunks_of["depth"].index(4)
        with pytest.raises(RecordingError, match=f"corrupt LZ4 chunk at byte offset {bad.pos}") as err:
            recording.read_frame("depth", victim)
        assert str(broken) in str(err.value)
        with pytest.raises(RecordingError, match=f"byte offset {bad.pos}"):
            list(recording.iter_frames())


def test_corrupted_last_chunk_of_an_unindexed_bag_is_skipped(lz4_bag, tmp_path: Path) -> None:
    chunks, chunks_of, index_pos = _layout(lz4_bag.path)
    data = bytearray(lz4_bag.path.read_bytes()[:index_pos])  # no index: as an interrupted write leaves it
    last = chunks[-1]
    middle = last.data_start + last.data_len // 2
    data[middle:middle + 8] = bytes(8)
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(bytes(data))
    with BagRecording(damaged) as recording:
        assert recording.truncated and "unreadable and was skipped" in recording.truncation_note
        expected = [f["number"] for f, c in zip(lz4_bag.frames["depth"], chunks_of["depth"], strict=True)
                    if c < len(chunks) - 1]
        assert [i.frame_number for i in recording.frame_infos("depth")] == expected


@pytest.mark.parametrize("fixture", ["raw_bag", "lz4_bag"])
@pytest.mark.filterwarnings("ignore::darp.errors.SalvagedRecordingWarning")
def test_damage_anywhere_gives_only_recording_errors(request: pytest.FixtureRequest, tmp_path: Path,
                                                     fixture: str) -> None:
    """Flip bytes at 150 random places (and cut at 30 random lengths): every outcome is a readable
    recording or a RecordingError, never a raw struct/Key/Index error."""
    source = request.getfixturevalue(fixture).path
    original = source.read_bytes()
    rng = np.random.default_rng(7)
    target = tmp_path / "fuzz.bag"
    outcomes = {"ok": 0, "error": 0}
    cases = [("flip", int(p)) for p in rng.integers(0, len(original), 150)]
    cases += [("cut", int(n)) for n in rng.integers(0, len(original), 30)]
    for kind, where in cases:
        data = bytearray(original)
        if kind == "flip":
            data[where] ^= 0xFF
        else:
            del data[where:]
        target.write_bytes(bytes(data))
        try:
            with open_recording(target) as recording:
                _read_everything(recording)
            outcomes["ok"] += 1
        except RecordingError as err:
            assert str(target) in str(err)
            outcomes["error"] += 1
    assert outcomes["error"] > 0 and outcomes["ok"] > 0


# -- reader misuse -------------------------------------------------------------------------------
def test_reader_requests_outside_the_recording(raw_bag) -> None:
    recording = BagRecording(raw_bag.path)
    with pytest.raises(RecordingError, match="no stream 'fisheye'.*depth"):
        recording.read_frame("fisheye", 0)
    with pytest.raises(RecordingError, match="frame 12 of stream 'depth' does not exist"):
        recording.read_frame("depth", 12)
    with pytest.raises(RecordingError, match="does not exist"):
        recording.read_frame("depth", -1)
    recording.close()
    with pytest.raises(RecordingError, match="closed"):
        recording.read_frame("depth", 0)


def test_missing_extrinsics(tmp_path: Path) -> None:
    streams = [p for p in profiles(16, 8) if p.key in ("depth", "color")]
    with BagWriter(tmp_path / "x.bag", DEVICE, streams) as writer:
        writer.write_image("depth", np.zeros((8, 16), np.uint16), 10.0, 1)
    with BagRecording(tmp_path / "x.bag") as recording:
        with pytest.raises(RecordingError, match="no extrinsics for stream 'color'"):
            recording.extrinsics("depth", "color")
        assert recording.frame_count("color") == 0 and list(recording.iter_frames(["color"])) == []


# -- writer validation -------------------------------------------------------------------------------
def _writer(tmp_path: Path, **kwargs) -> BagWriter:
    streams = kwargs.pop("streams", profiles(16, 8))
    return BagWriter(tmp_path / kwargs.pop("name", "w.bag"), kwargs.pop("device", DEVICE), streams, **kwargs)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"name": "w.db3"}, "must have the .bag extension"),
    ({"streams": []}, "no streams"),
    ({"streams": profiles(16, 8) * 2}, "duplicate stream keys"),
    ({"streams": [StreamProfile("depth", "Infrared", 1, 0, "z16", 30, 16, 8, profiles(16, 8)[0].intrinsics)]},
     "must be \\('Depth', 0\\)"),
    ({"streams": [StreamProfile("depth", "Depth", 0, 0, "z16", 30, 16, 8)]}, "needs intrinsics"),
    ({"streams": [StreamProfile("depth", "Depth", 0, 0, "yuyv", 30, 16, 8, profiles(16, 8)[0].intrinsics)]},
     "format 'yuyv'"),
    ({"streams": [StreamProfile("gyro", "Gyro", 0, 2, "z16", 200)]}, "motion streams have format"),
    ({"depth_scale": 0.0}, "depth_scale"),
    ({"extrinsics": {"color": np.diag([1.0, 1.0, -1.0, 1.0])}}, "rigid transform"),
    ({"extrinsics": {"fisheye": np.eye(4)}}, "not a recorded stream"),
    ({"compression": "bz2"}, "compression must be"),
])
def test_writer_rejects_bad_setup(tmp_path: Path, kwargs: dict, message: str) -> None:
    with pytest.raises(RecordingError, match=message):
        _writer(tmp_path, **kwargs)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_writer_rejects_bad_frames(tmp_path: Path) -> None:
    with _writer(tmp_path) as writer:
        depth = np.zeros((8, 16), np.uint16)
        cases = [
            (lambda: writer.write_image("depth", depth.astype(np.int32), 10.0, 1), "takes uint16 \\(8, 16\\)"),
            (lambda: writer.write_image("depth", depth.T, 10.0, 1), "is uint16 \\(16, 8\\)"),
            (lambda: writer.write_image("color", np.zeros((8, 16), np.uint8), 10.0, 1), "takes uint8 \\(8, 16, 3\\)"),
            (lambda: writer.write_image("fisheye", depth, 10.0, 1), "no stream 'fisheye'"),
            (lambda: writer.write_image("gyro", depth, 10.0, 1), "takes write_motion"),
            (lambda: writer.write_motion("depth", [0, 0, 1], 10.0, 1), "takes write_image"),
            (lambda: writer.write_motion("gyro", [0, 1], 10.0, 1), "3 finite numbers"),
            (lambda: writer.write_motion("gyro", [0, 1, np.nan], 10.0, 1), "3 finite numbers"),
            (lambda: writer.write_image("depth", depth, float("nan"), 1), "not finite"),
            (lambda: writer.write_image("depth", depth, 10.0, -1), "unsigned 32-bit"),
            (lambda: writer.write_image("depth", depth, 10.0, 2**32), "unsigned 32-bit"),
            (lambda: writer.write_image("depth", depth, 10.0, 1, timestamp_domain="Local"), "timestamp domain"),
            (lambda: writer.write_image("depth", depth, 10.0, 1, recording_time_ns=1), "after the description"),
        ]
        for call, message in cases:
            with pytest.raises(RecordingError, match=message):
                call()
        writer.write_image("depth", depth, 10.0, 1)
        with pytest.raises(RecordingError, match="does not come after"):
            writer.write_image("depth", depth, 10.0, 2)
        with pytest.raises(RecordingError, match="earlier than the recording start"):
            writer.write_image("ir1", np.zeros((8, 16), np.uint8), 10.0 - 150.0, 1)
        writer.write_image("depth", depth, 43.0, 2)
    with pytest.raises(RecordingError, match="writer is closed"):
        writer.write_image("depth", depth, 80.0, 3)
    with BagRecording(tmp_path / "w.bag") as recording:  # the rejected frames left no trace
        assert [i.frame_number for i in recording.frame_infos("depth")] == [1, 2]
        assert recording.frame_count("ir1") == 0


def test_writer_does_not_overwrite(tmp_path: Path) -> None:
    _writer(tmp_path).close()
    with pytest.raises(RecordingError, match="already exists"):
        _writer(tmp_path)
    _writer(tmp_path, overwrite=True).close()
    (tmp_path / "w.bag.partial").write_bytes(b"stale")
    with pytest.raises(RecordingError, match="already exists") as err:
        _writer(tmp_path, name="w.bag")
    assert err.value.path == tmp_path / "w.bag"


# -- interrupted writes -------------------------------------------------------------------------------
def test_exception_inside_with_leaves_only_a_readable_partial(tmp_path: Path) -> None:
    target = tmp_path / "cam.bag"
    rng = np.random.default_rng(3)
    written = []
    with pytest.raises(RuntimeError, match="camera unplugged"), \
            BagWriter(target, DEVICE, profiles(64, 48)[:3], chunk_threshold=CHUNKED) as writer:
        for i in range(20):
            depth = rng.integers(0, 4000, (48, 64), dtype=np.uint16)
            writer.write_image("depth", depth, 1000.0 + 33.3 * i, i)
            written.append(depth)
        raise RuntimeError("camera unplugged")
    assert not target.exists()
    partial = tmp_path / "cam.bag.partial"
    with pytest.warns(SalvagedRecordingWarning, match="no index"):
        recording = open_recording(partial)
    with recording:
        assert recording.truncated and "no index (interrupted recording?)" in recording.truncation_note
        assert recording.salvage.missing == ("no index (interrupted recording?)",)
        assert recording.salvage.frames == {"depth": 20, "ir1": 0, "ir2": 0}
        frames = list(recording.iter_frames(["depth"]))
        assert [f.info.frame_number for f in frames] == list(range(20))
        assert all(np.array_equal(f.data, d) for f, d in zip(frames, written, strict=True))


def test_unindexed_copy_is_what_an_interrupted_writer_leaves(tmp_path: Path) -> None:
    """The tests' stand-in for an interrupted recording (damaged_recordings.unindexed_copy of a complete bag)
    is byte for byte the ``.partial`` the writer leaves."""
    from helpers.damaged_recordings import unindexed_copy

    def write(interrupt: bool) -> None:
        with BagWriter(tmp_path / "cam.bag", DEVICE, profiles(64, 48)[:3], chunk_threshold=CHUNKED) as writer:
            for i in range(20):
                writer.write_image("depth", np.full((48, 64), i, np.uint16), 1000.0 + 33.3 * i, i)
            if interrupt:
                raise RuntimeError("camera unplugged")

    with pytest.raises(RuntimeError, match="camera unplugged"):
        write(interrupt=True)
    partial = tmp_path / "cam.bag.partial"
    left = partial.read_bytes()
    partial.unlink()
    write(interrupt=False)
    assert unindexed_copy(tmp_path / "cam.bag", tmp_path / "copy.bag").read_bytes() == left


def test_killed_writer_leaves_complete_chunks(tmp_path: Path) -> None:
    """A process killed mid-write: the .partial holds some complete chunks and a cut one."""
    target = tmp_path / "cam.bag"
    writer = BagWriter(target, DEVICE, profiles(64, 48)[:1], chunk_threshold=CHUNKED)
    for i in range(30):
        writer.write_image("depth", np.full((48, 64), i, np.uint16), 1000.0 + 33.3 * i, i)
    writer._handle.flush()
    snapshot = (tmp_path / "cam.bag.partial").read_bytes()
    writer.abort()
    killed = tmp_path / "killed.bag"
    killed.write_bytes(snapshot[: len(snapshot) - 3000])  # the last chunk is cut
    with BagRecording(killed) as recording:
        numbers = [i.frame_number for i in recording.frame_infos("depth")]
        assert recording.truncated and 0 < len(numbers) < 30 and numbers == list(range(len(numbers)))
        assert all(int(f.data[0, 0]) == f.info.frame_number for f in recording.iter_frames())


def test_recording_errors_are_darp_errors() -> None:
    assert issubclass(RecordingError, DarpError)  # the CLI turns them into exit code 2
