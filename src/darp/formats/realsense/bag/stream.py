"""The per-message loops behind :meth:`BagRecording.iter_frames` and its frame table, made cheap.

Per message these loops need the data span in its chunk, the frame number and timestamp of the image's
header, a view of its pixels and the ``timestamp_domain`` among its KeyValue metadata messages. The general
path (:meth:`~darp.formats.realsense.bag.walk.Walk.visit`, then the reader's frame decoding) parses each of these
with small helper functions and objects. Here the usual case is parsed inline with precompiled ``struct``
formats and no intermediate objects (about 4 instead of 7 us of darp's own work per frame): the record fits
its chunk, the image has its stream's known layout (one byte comparison, :meth:`ImageDecoder.layout`),
the frame's metadata lies in one chunk and its records up to the domain parse cleanly. Every check is
the condition under which the general path would succeed with the same result, so anything else goes
down the general path, which gives exactly the frame, or raises exactly the error, that it always gave.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Generator

import numpy as np

from darp.formats.realsense.bag.frames import (
    DEFAULT_DOMAIN,
    DOMAIN_KEY,
    BagFrame,
    ChunkMetadata,
    ImageDecoder,
    MetadataError,
    MetadataSource,
)
from darp.formats.realsense.bag.walk import Visit, Walk, metadata_source
from darp.formats.realsense.types import FrameInfo

_U32 = struct.Struct("<I").unpack_from
_TWO_U32 = struct.Struct("<II").unpack_from
_HEAD = struct.Struct("<IIII").unpack_from  # a message's data length, then std_msgs/Header: seq, sec, nsec
_DOMAIN_FIELD = 4 + len(DOMAIN_KEY)  # the key's length field and the key
_MISSING = ""  # no timestamp_domain among the records read (an empty value goes to the general path)


def _scan(buf: memoryview, size: int, offsets: list[int], first: int, stop: int,
          texts: dict[bytes, str]) -> str | None:
    """The ``timestamp_domain`` among the KeyValue message records at ``offsets[first:stop]`` of the chunk
    bytes ``buf``, read as ``MetadataSource.domain`` reads them: the first record with that key. None where
    a record up to it does not parse cleanly (the general path then raises the error), ``_MISSING`` where
    none has the key or its value is empty (the general path gives that value)."""
    for i in range(first, stop):
        offset = offsets[i]
        if offset + 4 > size:
            return None
        start = offset + 8 + _U32(buf, offset)[0]
        if start + 4 > size:
            return None
        data_len, key_len = _TWO_U32(buf, start - 4)
        end, key_end = start + data_len, start + 4 + key_len
        if end > size or key_end + 4 > size:
            return None
        value_end = key_end + 4 + _U32(buf, key_end)[0]
        if value_end > end:
            return None
        if key_end - start == _DOMAIN_FIELD and buf[start + 4:key_end] == DOMAIN_KEY:
            raw = buf[key_end + 4:value_end].tobytes()
            text = texts.get(raw)
            if text is None:
                text = texts[raw] = str(raw, "utf-8", "replace")
            return text if text else None
    return _MISSING


def _domain(buf: memoryview, size: int, offsets: list[int], first: int, stop: int,
            texts: dict[bytes, str]) -> str | None:
    """The frame's ``timestamp_domain`` (librealsense's default without one) from its metadata records
    ``offsets[first:stop]`` in one chunk, or None: let the general path read it."""
    found = _scan(buf, size, offsets, first, stop, texts)
    return DEFAULT_DOMAIN if found == _MISSING else found


def _domain_across(source: MetadataSource, texts: dict[bytes, str]) -> str | None:
    """:func:`_domain` for metadata records spread over chunks (``source`` holds their chunks' bytes)."""
    buffers, chunks, offsets = source.buffers, source.chunks, source.offsets
    for i, chunk in enumerate(chunks):
        buf = buffers[chunk]
        found = _scan(buf, len(buf), offsets, i, i + 1, texts)
        if found != _MISSING:
            return found
    return DEFAULT_DOMAIN


def frames(walk: Walk, keys: list[str], decoders: dict[str, ImageDecoder],
           general: Callable[[str, Visit], BagFrame], check_open: Callable[[], None],
           on_error: MetadataError) -> Generator[BagFrame, None, None]:
    """The frames of ``walk``'s messages (streams ``keys``): the usual ones inline, the others through
    ``general(key, visit)``. ``check_open`` runs before each frame; ``on_error`` turns a metadata parsing
    error into the reader's error when a frame's metadata is read."""
    coders = [decoders.get(key) for key in keys]
    layouts = [None if coder is None else coder.layout() for coder in coders]
    texts: dict[bytes, str] = {}
    current, buf, size = -1, memoryview(b""), 0
    for block in walk.blocks():
        metadata = block.metadata
        for i, (code, position, time_ns, chunk, offset, lo, hi, step) in enumerate(zip(
                block.codes, block.positions, block.times, block.chunks, block.offsets, block.lo, block.hi,
                block.steps, strict=True)):
            check_open()
            if chunk != current:
                buf = walk.enter(chunk, step)
                current, size = chunk, len(buf)
            frame = None
            layout = layouts[code]
            if layout is not None and offset + 4 <= size:
                start = offset + 8 + _U32(buf, offset)[0]
                pattern, pixel_bytes, dtype, shape = layout
                pixel = start + 12 + len(pattern)
                # (a message too short for the header fails the next test: data length -1)
                data_len, seq, sec, nsec = _HEAD(buf, start - 4) if pixel <= size else (-1, 0, 0, 0)
                domain: str | None = None
                if pixel + pixel_bytes <= start + data_len <= size and buf[start + 12:pixel] == pattern:
                    domain = DEFAULT_DOMAIN
                    if lo < hi:
                        base, meta_chunks, meta_offsets = metadata[code]
                        first, stop = lo - base, hi - base
                        meta_chunk = meta_chunks[first]
                        if meta_chunk == meta_chunks[stop - 1]:  # in one chunk: this one, or often the next
                            meta_buf = buf if meta_chunk == chunk else walk.get(meta_chunk)
                            domain = _domain(meta_buf, len(meta_buf), meta_offsets, first, stop, texts)
                            source: ChunkMetadata | MetadataSource = ChunkMetadata(meta_buf, meta_offsets)
                        else:  # spread over chunks
                            source = metadata_source(walk.get, chunk, buf, meta_chunks[first:stop],
                                                     meta_offsets[first:stop])
                            domain, first, stop = _domain_across(source, texts), 0, None
                if domain is not None:
                    stamp_ms = (float(sec) + 1e-9 * float(nsec)) * 1000.0  # as ros_messages.ms_from_stamp
                    info = FrameInfo(keys[code], position, seq, stamp_ms, domain, time_ns)
                    data = np.ndarray(shape, dtype, buf, pixel)
                    frame = (BagFrame(info, data, {}) if lo == hi else
                             BagFrame.lazy(info, data, source, first, stop, on_error))
            if frame is None:
                frame = general(keys[code], walk.visit(block, i, buf))
                if coders[code] is not None:
                    layouts[code] = coders[code].layout()
            yield frame


def table(walk: Walk, columns: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
          general: Callable[[Visit], None]) -> None:
    """Frame number, timestamp and (for frames with metadata) domain of ``walk``'s messages into
    ``columns[code]`` at each message's position: the usual ones inline, the others by ``general(visit)``."""
    texts: dict[bytes, str] = {}
    current, buf, size = -1, memoryview(b""), 0
    for block in walk.blocks():
        metadata = block.metadata
        for i, (code, position, chunk, offset, lo, hi, step) in enumerate(zip(
                block.codes, block.positions, block.chunks, block.offsets, block.lo, block.hi, block.steps,
                strict=True)):
            if chunk != current:
                buf = walk.enter(chunk, step)
                current, size = chunk, len(buf)
            start = offset + 8 + _U32(buf, offset)[0] if offset + 4 <= size else size
            if start + 12 <= size:
                data_len, seq, sec, nsec = _HEAD(buf, start - 4)
                domain: str | None = DEFAULT_DOMAIN if start + data_len <= size else None
                if domain is not None and lo < hi:
                    base, meta_chunks, meta_offsets = metadata[code]
                    first, stop = lo - base, hi - base
                    meta_chunk = meta_chunks[first]
                    if meta_chunk == meta_chunks[stop - 1]:
                        meta_buf = buf if meta_chunk == chunk else walk.get(meta_chunk)
                        domain = _domain(meta_buf, len(meta_buf), meta_offsets, first, stop, texts)
                    else:
                        domain = _domain_across(metadata_source(walk.get, chunk, buf, meta_chunks[first:stop],
                                                                meta_offsets[first:stop]), texts)
                if domain is not None:
                    numbers, stamps, domains = columns[code]
                    numbers[position], stamps[position] = seq, (float(sec) + 1e-9 * float(nsec)) * 1000.0
                    if lo < hi:
                        domains[position] = domain
                    continue
            general(walk.visit(block, i, buf))
