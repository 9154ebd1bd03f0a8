"""Damaged copies of complete darp bags, as recordings go wrong in the field, and the check that a command
said so: an interrupted recording (no index) and a cut copy (no index, last chunk incomplete)."""

from __future__ import annotations

import struct
from pathlib import Path

from darp.formats.realsense.rosbag1.index import MAGIC, bag_header_record, read_record


def index_pos(bag: Path) -> int:
    """Where a complete bag's index (its connection and chunk-info records) starts."""
    data = bag.read_bytes()
    fields, _, _ = read_record(data, len(MAGIC), len(data))
    return struct.unpack("<Q", fields["index_pos"])[0]


def unindexed_copy(bag: Path, target: Path) -> Path:
    """What :class:`BagWriter` leaves in ``<name>.bag.partial`` when the recording is interrupted: every
    chunk with its index data, a bag header saying ``index_pos = 0``, no index."""
    data = bag.read_bytes()
    header = bag_header_record(0, 0, 0)
    target.write_bytes(MAGIC + header + data[len(MAGIC) + len(header):index_pos(bag)])
    return target


def cut_copy(bag: Path, target: Path, length: int) -> Path:
    """The first ``length`` bytes of ``bag``: a copy cut short (its index and the end of its data lost)."""
    with open(bag, "rb") as source:
        target.write_bytes(source.read(length))
    return target


def salvage_warning(err: str, path: Path, *phrases: str) -> str:
    """The one ``darp: warning:`` line about ``path`` in a command's stderr; it must hold every phrase."""
    lines = [line for line in err.splitlines() if line.startswith("darp: warning: ") and str(path) in line]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"darp: warning: {path}: "), lines[0]
    for phrase in phrases:
        assert phrase in lines[0], (phrase, lines[0])
    return lines[0]
