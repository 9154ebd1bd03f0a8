"""The ROS1 bag index's fast path (darp.formats.realsense.rosbag1.usual) against the general per-record path on
the same bytes: identical BagIndex contents, or the identical error, on genuine librealsense bags, darp's
own (LZ4 and uncompressed, many chunks) and damaged copies; and against rosbags' reader as an outside oracle."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Reader

from darp.errors import RecordingError
from darp.formats.realsense.rosbag1 import index as rosbag1
from darp.formats.realsense.rosbag1.index import MAGIC, ByteSource, load_index, read_record
from helpers.bag_samples import write_sample

FIXTURES = Path(__file__).parent / "fixtures" / "recordings"
GENUINE = sorted(FIXTURES.glob("*.bag"))


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("index")
    return {c: write_sample(folder / f"{c}.bag", compression=c, framesets=20, chunk_threshold=20_000).path
            for c in ("lz4", "none")}


def _load(data: bytes, path: Path, fast: bool, monkeypatch: pytest.MonkeyPatch, fd: int | None = None):
    """load_index's result (or its error as (type, message)), with the fast path allowed or not; and
    whether the fast path produced it."""
    used = []
    real = rosbag1.usual_index

    def spy(*args):
        result = real(*args) if fast else None
        used.append(result is not None)
        return result

    with monkeypatch.context() as patch:
        patch.setattr(rosbag1, "usual_index", spy)
        try:
            index = load_index(ByteSource(memoryview(data), fd), path)
        except RecordingError as err:
            return (type(err), str(err)), any(used)
    return index, any(used)


def _same(a, b) -> None:
    if isinstance(a, tuple) or isinstance(b, tuple):
        assert a == b
        return
    assert a.connections == b.connections
    assert a.chunks == b.chunks
    assert (a.truncated, a.note) == (b.truncated, b.note)
    assert list(a.entries) == list(b.entries)
    for conn in a.entries:
        assert a.entries[conn].dtype == b.entries[conn].dtype
        assert np.array_equal(a.entries[conn], b.entries[conn])


def _index_pos(data: bytes) -> int:
    fields, _, _ = read_record(data, len(MAGIC), len(data))
    return struct.unpack("<Q", fields["index_pos"])[0]


@pytest.mark.parametrize("name", [p.name for p in GENUINE] + ["lz4", "none"])
def test_fast_path_equals_general_path_and_rosbags(name: str, written, monkeypatch: pytest.MonkeyPatch) -> None:
    path = FIXTURES / name if name.endswith(".bag") else written[name]
    data = path.read_bytes()
    fast, used = _load(data, path, True, monkeypatch)
    general, _ = _load(data, path, False, monkeypatch)
    assert used, "the usual layout should take the fast path"
    _same(fast, general)
    with open(path, "rb") as handle:  # through pread on the file, as BagRecording reads it
        by_fd, used_fd = _load(data, path, True, monkeypatch, handle.fileno())
    assert used_fd
    _same(by_fd, general)
    # rosbags as an outside oracle: the same chunks, connections and messages per connection
    with Reader(path) as reader:
        assert [info.pos for info in reader.chunk_infos] == [c.pos for c in fast.chunks]
        assert {c.id: c.topic for c in reader.connections} == {k: c.topic for k, c in fast.connections.items()}
        times: dict[int, list[int]] = {}
        for connection, t_ns, _ in reader.messages():
            times.setdefault(connection.id, []).append(t_ns)
    assert {k: sorted(v) for k, v in times.items()} == {k: e["time"].tolist() for k, e in fast.entries.items()}
    if name in ("lz4", "none"):
        assert len(fast.chunks) > 5 and {c.compression for c in fast.chunks} == {name}


def _damaged(data: bytes, at: int, value: bytes) -> bytes:
    return data[:at] + value + data[at + len(value):]


def test_damage_gives_the_same_index_or_error(written, monkeypatch: pytest.MonkeyPatch) -> None:
    """Cuts, a missing index, and bytes changed in chunk heads, index-data records and chunk infos: the
    fast path declines (or agrees) so that the result is the general path's, error messages included."""
    fell_back = 0
    for path in written.values():
        data = path.read_bytes()
        general, _ = _load(data, path, False, monkeypatch)
        chunks, index_pos = general.chunks, _index_pos(data)
        second = chunks[1]
        index_data = chunks[0].data_start + chunks[0].data_len  # the first chunk's first index-data record
        variants = {
            "cut in the index": data[:index_pos + 40],
            "cut in the last index data": data[:chunks[-1].data_start + chunks[-1].data_len + 30],
            "chunk head compression": _damaged(data, second.pos + 4 + 4 + len("compression="), b"bz2"),
            "chunk head size field name": _damaged(data, second.pos + 8, b"X"),
            "chunk data length": _damaged(data, second.data_start - 4, struct.pack("<I", second.data_len + 7)),
            "index-data op": _damaged(data, index_data + 4 + 4 + 5 + 4 + 4 + 6 + 4 + 4 + 3, b"\x09"),
            "index-data count": _damaged(data, index_data + 4 + 4 + 5 + 4 + 4 + 6, struct.pack("<I", 10**6)),
            "index-data ver name": _damaged(data, index_data + 4 + 4 + 5 + 4 + 4 + 6 + 4 + 4 + 3 + 1 + 4, b"v3r="),
            "index-data length": _damaged(data, index_data + 51, struct.pack("<I", 2**31)),
            "last chunk moved": data[:chunks[-1].pos] + b"\0" * 8 + data[chunks[-1].pos:],
            "chunk info count": _damaged(data, len(data) - 8 * len(chunks[-1:]) - 4, struct.pack("<I", 2**32 - 1)),
        }
        # the index position zeroed (an interrupted write): the scan
        header_at = data.index(b"index_pos=") + len(b"index_pos=")
        variants["index_pos zero"] = _damaged(data, header_at, bytes(8))
        variants["index_pos past the end"] = _damaged(data, header_at, struct.pack("<Q", len(data) + 5))
        for what, damaged in variants.items():
            assert damaged != data, what
            fast, used = _load(damaged, path, True, monkeypatch)
            slow, _ = _load(damaged, path, False, monkeypatch)
            _same(fast, slow)
            fell_back += not used
    assert fell_back >= 10  # the damage was seen (the fast path declined), not silently read past


def test_unusual_order_of_index_records_takes_the_general_path(written, monkeypatch: pytest.MonkeyPatch) -> None:
    """A chunk's index-data records in another order than its chunk info lists them: still the same index."""
    path = written["none"]
    data = bytearray(path.read_bytes())
    general, _ = _load(bytes(data), path, False, monkeypatch)
    chunk = general.chunks[0]
    start = chunk.data_start + chunk.data_len
    records, pos = [], start
    while pos < general.chunks[1].pos:
        _, data_start, data_len = read_record(bytes(data), pos, len(data))
        records.append(bytes(data[pos:data_start + data_len]))
        pos = data_start + data_len
    assert len(records) > 1
    data[start:pos] = b"".join(reversed(records))
    fast, _ = _load(bytes(data), path, True, monkeypatch)
    slow, _ = _load(bytes(data), path, False, monkeypatch)
    _same(fast, slow)
    _same(fast, general)  # the same index entries, whatever the record order
