"""LZ4 frames of ROS1 bag chunks, decoded into reusable memory.

Each LZ4 chunk of a bag is one LZ4 frame: librealsense writes independent 4 MiB blocks with a content
checksum (XXH32 of the uncompressed bytes), and its player verifies that checksum. darp decodes the
blocks with the LZ4 library that python-lz4 ships, called through ``ctypes``: the output goes straight
into a caller's buffer (no fresh allocation per chunk, whose page faults cost as much as the decoding)
and the GIL is released while it runs, so chunks can be decoded on other threads. The checksum is
checked with the XXH32 of the same library. Where python-lz4's build does not expose those entry points
(they are plain exported C symbols of its extension modules), python-lz4's public API does the same
work more slowly: :func:`native` says which path is in use.
"""

from __future__ import annotations

import ctypes
import struct
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import lz4.block
import lz4.frame
import numpy as np

from darp.errors import DecodeError

LZ4_MAGIC = 0x184D2204
_U32 = struct.Struct("<I")
_BUFFER_STEP = 256 << 10  # buffer capacities are rounded up to this, so that they can be reused


class Lz4Error(DecodeError):
    """The bytes are not a well-formed LZ4 frame, or they fail its checksum."""


@dataclass(frozen=True)
class _Native:
    # ctypes function pointers; their restype (c_int, c_uint) makes each call return a Python int
    decompress: Callable[..., int]  # LZ4_decompress_safe(src, dst, src_size, dst_capacity) -> size or < 0
    decompress_with_dict: Callable[..., int]  # LZ4_decompress_safe_usingDict(..., dict, dict_size)
    xxh32: Callable[..., int]  # XXH32(data, length, seed) -> hash


def _load_native() -> _Native | None:
    """python-lz4's bundled LZ4 and XXH32 entry points, checked on a known frame; None if unusable."""
    try:
        library = ctypes.CDLL(lz4.frame._frame.__file__)
        decompress, with_dict, xxh32 = (library.LZ4_decompress_safe, library.LZ4_decompress_safe_usingDict,
                                        library.XXH32)
    except (OSError, AttributeError):
        return None
    decompress.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int]
    with_dict.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_int]
    xxh32.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint]
    decompress.restype = with_dict.restype = ctypes.c_int
    xxh32.restype = ctypes.c_uint
    native = _Native(decompress, with_dict, xxh32)
    try:  # the same answers as python-lz4's own API, or do not use it
        sample = bytes(range(256)) * 64 + b"darp" * 1000
        for linked in (False, True):
            frame = lz4.frame.compress(sample, block_size=lz4.frame.BLOCKSIZE_MAX64KB, block_linked=linked,
                                       content_checksum=True, store_size=False)
            out = ChunkBuffer(len(sample))
            _decode_native(native, frame, out, len(sample), True)
            if bytes(out.data[:len(sample)]) != sample:
                return None
    except (Lz4Error, OSError, ValueError):
        return None
    return native


class ChunkBuffer:
    """Memory that decoded chunks are written into, reused once nothing views it any more.

    Frames view a chunk through ``memoryview``\\ s of :attr:`data`; every such view (and every numpy array
    made from one) keeps a reference to the bytearray, so its reference count tells whether anything can
    still read it (:meth:`in_use`).
    """

    __slots__ = ("_holder", "_idle_refs", "address", "capacity", "data")

    def __init__(self, size: int) -> None:
        self.capacity = max(_BUFFER_STEP, -(-size // _BUFFER_STEP) * _BUFFER_STEP)
        self.data = bytearray(self.capacity)
        self._holder = (ctypes.c_char * self.capacity).from_buffer(self.data)  # pins the memory in place
        self.address = ctypes.addressof(self._holder)
        self._idle_refs = sys.getrefcount(self.data)

    def in_use(self) -> bool:
        return sys.getrefcount(self.data) > self._idle_refs

    def view(self, size: int) -> memoryview:
        """Read-only view of the first ``size`` bytes (what frames are made from)."""
        return memoryview(self.data)[:size].toreadonly()


def decode_frame(source: bytes | memoryview, out: ChunkBuffer, size: int, verify: bool = True) -> None:
    """Decode the LZ4 frame ``source`` into ``out``, which must hold ``size`` bytes: exactly ``size``
    must come out. ``verify`` checks the content checksum (and block checksums), as librealsense does.
    Raises :class:`Lz4Error` on any malformed or damaged frame."""
    if size > out.capacity:
        raise DecodeError(f"a buffer of {out.capacity} bytes cannot hold {size}")
    library = native()
    if library is not None:
        _decode_native(library, source, out, size, verify)
    else:
        _decode_portable(source, out, size, verify)


def _frame_header(source: bytes | memoryview, native: _Native | None) -> tuple[int, int, int]:
    """(flags, block size limit, offset of the first block) of an LZ4 frame; ``native`` checks the
    header checksum."""
    if len(source) < 7 or _U32.unpack_from(source, 0)[0] != LZ4_MAGIC:
        raise Lz4Error("no LZ4 frame magic")
    flags, descriptor = source[4], source[5]
    if flags >> 6 != 1 or flags & 0x02 or descriptor & 0x8F:
        raise Lz4Error("unsupported LZ4 frame version or reserved bits set")
    if flags & 0x01:
        raise Lz4Error("LZ4 frames with a dictionary ID are not supported")
    end = 6 + 8 * bool(flags & 0x08)
    if len(source) < end + 1:
        raise Lz4Error("the LZ4 frame header is cut short")
    if native is not None:
        header = np.frombuffer(source, np.uint8, end - 4, 4)
        if (native.xxh32(header.ctypes.data, end - 4, 0) >> 8) & 0xFF != source[end]:
            raise Lz4Error("LZ4 frame header checksum mismatch")
    block_id = (descriptor >> 4) & 0x7
    if block_id < 4:
        raise Lz4Error(f"invalid LZ4 block size id {block_id}")
    return flags, 1 << (8 + 2 * block_id), end + 1


class _Blocks:
    """The data blocks of an LZ4 frame from offset ``pos`` (just past the frame header), in order, as
    ``(offset, length, stored)``: ``stored`` blocks are uncompressed. Both decoders walk the frame with
    it; they differ in what they do with each block (the native one decodes straight into the chunk
    buffer and checks block checksums, the portable one goes through python-lz4's API). After the end
    mark, :attr:`end` is the offset past it (where the content checksum is, if any)."""

    def __init__(self, source: bytes | memoryview, pos: int, block_sums: bool) -> None:
        self.source, self.pos, self.block_sums = source, pos, block_sums
        self.end = -1

    def __iter__(self) -> Iterator[tuple[int, int, bool]]:
        source, pos, n, tail = self.source, self.pos, len(self.source), 4 * self.block_sums
        while True:
            if pos + 4 > n:
                raise Lz4Error("the LZ4 frame ends inside a block header")
            (length,) = _U32.unpack_from(source, pos)
            pos += 4
            if length == 0:
                break
            stored, length = bool(length >> 31), length & 0x7FFFFFFF
            if pos + length + tail > n:
                raise Lz4Error("an LZ4 block runs past the end of the frame")
            yield pos, length, stored
            pos += length + tail
        self.end = pos


def _decode_native(native: _Native, source: bytes | memoryview, out: ChunkBuffer, size: int, verify: bool) -> None:
    flags, block_max, pos = _frame_header(source, native if verify else None)
    independent, block_sums = bool(flags & 0x20), bool(flags & 0x10)
    src = np.frombuffer(source, np.uint8)  # holds the source (a file mapping) while C code reads it
    base, n = src.ctypes.data, len(source)
    written = 0
    blocks = _Blocks(source, pos, block_sums)
    for at, length, stored in blocks:
        if verify and block_sums and native.xxh32(base + at, length, 0) != _U32.unpack_from(source, at + length)[0]:
            raise Lz4Error("LZ4 block checksum mismatch")
        room = min(block_max, size - written)
        if stored:
            if length > room:
                raise Lz4Error("more data than the chunk size")
            out.data[written:written + length] = source[at:at + length]
            got = length
        elif independent or written == 0:
            got = native.decompress(base + at, out.address + written, length, room)
        else:  # linked blocks: the previous 64 KiB of output are the dictionary
            window = min(written, 65536)
            got = native.decompress_with_dict(base + at, out.address + written, length, room,
                                              out.address + written - window, window)
        if got < 0:
            raise Lz4Error("malformed LZ4 block (or more data than the chunk size)")
        written += got
    if written != size:
        raise Lz4Error(f"{written} bytes decompressed, the chunk header says {size}")
    if flags & 0x04:
        if blocks.end + 4 > n:
            raise Lz4Error("the LZ4 content checksum is missing")
        if verify and native.xxh32(out.address, size, 0) != _U32.unpack_from(source, blocks.end)[0]:
            raise Lz4Error("LZ4 content checksum mismatch")
    del src


def _decode_portable(source: bytes | memoryview, out: ChunkBuffer, size: int, verify: bool) -> None:
    """python-lz4's public API (a copy more per chunk): the frame decoder when verifying, else the blocks."""
    flags, block_max, pos = _frame_header(source, None)
    try:
        if verify or not flags & 0x20:
            data, _, complete = lz4.frame.decompress_chunk(lz4.frame.create_decompression_context(), source,
                                                           max_length=size + 1)
            if not complete:
                raise Lz4Error("the LZ4 frame ends early")
        else:
            parts: list[bytes] = []
            remaining = size
            for at, length, stored in _Blocks(source, pos, bool(flags & 0x10)):
                block = source[at:at + length]
                room = min(block_max, remaining)
                try:
                    parts.append(bytes(block) if stored else lz4.block.decompress(block, uncompressed_size=room))
                except lz4.block.LZ4BlockError as err:
                    raise Lz4Error("malformed LZ4 block (or more data than the chunk size)") from err
                remaining -= len(parts[-1])
            data = b"".join(parts)
    except (RuntimeError, lz4.block.LZ4BlockError) as err:
        raise Lz4Error(str(err)) from err
    if len(data) != size:
        raise Lz4Error(f"{len(data)} bytes decompressed, the chunk header says {size}")
    out.data[:size] = data


_UNSET = object()
NATIVE: _Native | None | object = _UNSET  # python-lz4's C entry points, looked up on first use


def native() -> _Native | None:
    """The native decoder (python-lz4's LZ4 and XXH32 through ctypes), or None: the portable path."""
    global NATIVE
    if NATIVE is _UNSET:
        NATIVE = _load_native()
    return NATIVE if isinstance(NATIVE, _Native) else None
