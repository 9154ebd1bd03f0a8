"""Turning a bag's Image/Imu messages into darp frames, cheaply.

Per frame the reader needs the pixels (a view, no copy), ``header.seq`` and ``header.stamp``, and the
``timestamp_domain`` among the frame's KeyValue metadata messages. Everything else in the metadata is
parsed only when :attr:`BagFrame.metadata` is first read. Images of one stream share their layout
(frame id, size, encoding, step), so after the first frame it is recognised by one byte comparison.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import numpy as np

from darp.errors import DecodeError
from darp.formats.realsense import ros_messages as rm
from darp.formats.realsense.types import Frame, FrameInfo

DEFAULT_DOMAIN = "Hardware Clock"  # what librealsense reports for a frame without metadata
_U32 = struct.Struct("<I")
_TWO_U32 = struct.Struct("<II")
_STAMP = struct.Struct("<III")  # std_msgs/Header: seq, stamp sec, stamp nsec
DOMAIN_KEY = b"timestamp_domain"


def message_span(buf: memoryview, offset: int) -> tuple[int, int]:
    """(start, end) of the data of the message record at ``offset`` in an uncompressed chunk."""
    (header_len,) = _U32.unpack_from(buf, offset)
    start = offset + 8 + header_len
    (data_len,) = _U32.unpack_from(buf, start - 4)
    end = start + data_len
    if end > len(buf):
        raise DecodeError(f"message record at offset {offset} runs past its chunk")
    return start, end


def header_stamp(buf: memoryview, start: int) -> tuple[int, float]:
    """(frame number, timestamp ms) from the std_msgs/Header that Image and Imu messages start with."""
    seq, sec, nsec = _STAMP.unpack_from(buf, start)
    return seq, rm.ms_from_stamp(sec, nsec)


class ImageDecoder:
    """Decodes the Image messages of one stream; the layout of the first is kept and checked for the rest."""

    def __init__(self) -> None:
        self._layout: bytes = b""  # frame id .. data length, as in the last message decoded the slow way
        self._dtype: np.dtype[Any] = np.dtype(np.uint8)  # meaningful once _layout is set
        self._shape: tuple[int, ...] = ()
        self._data_len = 0

    def decode(self, buf: memoryview, start: int, end: int) -> tuple[int, float, np.ndarray]:
        """(frame number, timestamp ms, read-only pixel view) of the Image message ``buf[start:end]``."""
        layout = self._layout
        data_start = start + 12 + len(layout)
        if layout and buf[start + 12:data_start] == layout and data_start + self._data_len <= end:
            seq, sec, nsec = _STAMP.unpack_from(buf, start)
            pixels = np.frombuffer(buf, self._dtype, self._data_len // self._dtype.itemsize, data_start)
            return seq, rm.ms_from_stamp(sec, nsec), pixels.reshape(self._shape)
        head = rm.decode_image_head(buf, start, end)
        pixels = rm.image_pixels(buf, head)
        if pixels.base is not None and pixels.flags.c_contiguous and head.data_len == pixels.nbytes:
            self._layout = bytes(buf[start + 12:head.data_start])
            self._dtype, self._shape, self._data_len = pixels.dtype, pixels.shape, head.data_len
        else:  # padded rows or unknown encodings: always the general path
            self._layout = b""
        return head.seq, head.timestamp_ms, pixels

    def layout(self) -> tuple[bytes, int, np.dtype[Any], tuple[int, ...]] | None:
        """(layout bytes, pixel bytes, dtype, shape) of the stream as last decoded, or None (none known):
        what :mod:`darp.formats.realsense.bag.stream` compares a message with to view its pixels directly."""
        return (self._layout, self._data_len, self._dtype, self._shape) if self._layout else None


def imu_sample(buf: memoryview, start: int, accel: bool) -> tuple[int, float, np.ndarray]:
    """(frame number, timestamp ms, float32 xyz) of an Imu message: linear acceleration or angular velocity."""
    seq, stamp_ms, gyro, acceleration = rm.decode_imu(buf, start)
    with np.errstate(over="ignore", invalid="ignore"):  # a damaged sample becomes inf: the caller decides
        return seq, stamp_ms, np.array(acceleration if accel else gyro, dtype=np.float32)


def key_value(buf: memoryview, offset: int) -> tuple[bytes, int, int]:
    """(key bytes, value start, value end) of the KeyValue message record at ``offset``."""
    start, end = message_span(buf, offset)
    (key_len,) = _U32.unpack_from(buf, start)
    key_end = start + 4 + key_len
    (value_len,) = _U32.unpack_from(buf, key_end)
    if key_end + 4 + value_len > end:
        raise DecodeError(f"KeyValue record at offset {offset} runs past its message")
    return bytes(buf[start + 4:key_end]), key_end + 4, key_end + 4 + value_len


def _text(buf: memoryview, start: int, end: int) -> str:
    return str(buf[start:end], "utf-8", "replace")


class MetadataSource:
    """Where a frame's KeyValue metadata messages are: the (chunk, offset) of each, and the chunk buffers
    they lie in (held, so that they stay valid: pooled buffers are not reused while referenced)."""

    __slots__ = ("buffers", "chunks", "offsets")

    def __init__(self, buffers: dict[int, memoryview], chunks: list[int], offsets: list[int]) -> None:
        self.buffers, self.chunks, self.offsets = buffers, chunks, offsets

    def domain(self) -> str:
        """The ``timestamp_domain`` item (usually among the first few), or librealsense's default."""
        buffers = self.buffers
        for chunk, offset in zip(self.chunks, self.offsets, strict=True):
            buf = buffers[chunk]
            key, value_start, value_end = key_value(buf, offset)
            if key == DOMAIN_KEY:
                return _text(buf, value_start, value_end)
        return DEFAULT_DOMAIN

    def read(self, lo: int = 0, hi: int | None = None) -> dict[str, str]:
        """The metadata dict of messages ``lo:hi`` (all by default)."""
        buffers = self.buffers
        return _metadata_dict((buffers[chunk], offset)
                              for chunk, offset in zip(self.chunks[lo:hi], self.offsets[lo:hi], strict=True))


class ChunkMetadata:
    """A frame's metadata messages when they all lie in one chunk: the chunk's bytes (held, so that a pooled
    buffer is not reused under the frame) and a list of record offsets of which the frame's are ``lo:hi``."""

    __slots__ = ("buf", "offsets")

    def __init__(self, buf: memoryview, offsets: list[int]) -> None:
        self.buf, self.offsets = buf, offsets

    def read(self, lo: int = 0, hi: int | None = None) -> dict[str, str]:
        """The metadata dict of messages ``lo:hi``."""
        buf = self.buf
        return _metadata_dict((buf, offset) for offset in self.offsets[lo:hi])


def _metadata_dict(records: Iterable[tuple[memoryview, int]]) -> dict[str, str]:
    """Key -> value of KeyValue message records given as (chunk bytes, record offset); a repeated key keeps
    its last value."""
    metadata = {}
    for buf, offset in records:
        key, value_start, value_end = key_value(buf, offset)
        metadata[str(key, "utf-8", "replace")] = _text(buf, value_start, value_end)
    return metadata


class MetadataReader(Protocol):
    """Where a frame's metadata is parsed from (:class:`MetadataSource`, :class:`ChunkMetadata`)."""

    def read(self, lo: int = 0, hi: int | None = None) -> dict[str, str]: ...


MetadataError = Callable[[FrameInfo, Exception], Exception]  # a metadata parsing error -> the reader's error

_new = object.__new__


class BagFrame(Frame):
    """A :class:`Frame` whose metadata dict is parsed from the bag on first access.

    Equal to, and pickled as, a plain :class:`Frame` with the same content. ``on_error`` turns a
    low-level parsing error into the reader's :class:`~darp.errors.RecordingError`.
    """

    _metadata: dict[str, str] | None
    _source: MetadataReader | None
    _on_error: MetadataError | None
    _lo: int
    _hi: int | None

    def __init__(self, info: FrameInfo, data: np.ndarray, metadata: dict[str, str] | None = None, *,
                 source: MetadataReader | None = None, on_error: MetadataError | None = None) -> None:
        self.info, self.data = info, data
        self._metadata, self._source, self._on_error, self._lo, self._hi = metadata, source, on_error, 0, None
        if metadata is None and source is None:
            self._metadata = {}

    @classmethod
    def lazy(cls, info: FrameInfo, data: np.ndarray, source: MetadataReader, lo: int, hi: int | None,
             on_error: MetadataError | None) -> BagFrame:
        """A frame whose metadata is ``source.read(lo, hi)``, parsed when first read (the streaming path's
        constructor: one object per frame, no keyword handling)."""
        frame = _new(cls)
        frame.info, frame.data, frame._metadata, frame._source = info, data, None, source
        frame._lo, frame._hi, frame._on_error = lo, hi, on_error
        return frame

    @property
    def metadata(self) -> dict[str, str]:
        if self._metadata is None:
            assert self._source is not None  # no metadata yet: there is a source to parse it from
            try:
                self._metadata = self._source.read(self._lo, self._hi)
            except (struct.error, ValueError, KeyError, IndexError) as err:
                if self._on_error is None:
                    raise
                raise self._on_error(self.info, err) from err
            self._source = None
        return self._metadata

    @metadata.setter
    def metadata(self, value: dict[str, str]) -> None:
        self._metadata, self._source = value, None

    def __reduce__(self) -> tuple[type[Frame], tuple[FrameInfo, np.ndarray, dict[str, str]]]:
        return Frame, (self.info, self.data, self.metadata)
