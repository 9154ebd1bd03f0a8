"""The one way darp opens a user's input file: a regular file only, and never more than its format's limit.

A named pipe, ``/dev/zero``, a socket or a folder given where a file is expected is refused with one line
naming it (a pipe would block the read forever, ``/dev/zero`` would fill memory). The file is opened with
``O_NONBLOCK`` and checked with ``fstat`` on the open descriptor, so neither the check nor the open can hang
and nothing can be swapped in between. Reads stop one byte past the limit, so a file that grows while it is
read is still bounded. The limits per format are in :data:`LIMITS` and in docs/reliability.md.
"""

from __future__ import annotations

import contextlib
import os
import stat
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from darp.errors import DarpError, FormatError

MiB = 1024 * 1024
# Largest file darp reads, per format (bytes). None of darp's own files comes near them.
LIMITS: dict[str, int] = {
    "json": 256 * MiB,  # captures.json, transforms.json, calibration, envelope, stages.json
    "yaml": 16 * MiB,  # rig, settings, waypoints, capture metadata
    "text": 256 * MiB,  # trajectories (TUM, trajectory.log), pose and intrinsics text files
    "image": 512 * MiB,  # one colour, depth or board image (PNG, JPEG, TIFF, ...)
    "npz": 1024 * MiB,  # intrinsics.npz, pose .npy/.npz, keyframes, observations, evaluation distances
    "cloud": 16 * 1024 * MiB,  # a PLY point cloud or mesh (read whole)
    "marker": MiB,  # PARTIAL.txt, UNFINISHED.txt (their first line is shown)
    "csv": 1 << 40,  # arm_poses.csv is streamed: memory does not grow with it
}
MAX_IMAGE_PIXELS = 1 << 28  # 268 Mpx (16384 x 16384): far above any RGB-D camera


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a special file"


def _refuse(mode: int, what: str, path: Path, error: type[DarpError]) -> DarpError:
    if stat.S_ISDIR(mode):
        return error(f"is a folder, not {what}", path)
    return error(f"is {_kind(mode)}, not a regular file ({what} expected)", path)


def _check_size(size: int, limit: int, what: str, path: Path, error: type[DarpError]) -> None:
    if size > limit:
        raise error(f"{size} bytes, over darp's limit for {what} ({limit // MiB} MiB)", path)


def open_input(path: str | Path, what: str = "a file", error: type[DarpError] = FormatError, *,
               limit: int = LIMITS["text"]) -> BinaryIO:
    """Open ``path`` for binary reading after checking that it is a regular file of at most ``limit`` bytes;
    every failure is one ``error`` naming ``path`` (``what`` names the expected kind: "a JSON file")."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise error("no such file", path) from None
    except IsADirectoryError:
        raise error(f"is a folder, not {what}", path) from None
    except PermissionError:
        raise error("permission denied", path) from None
    except OSError as err:
        raise error(f"cannot open: {err.strerror or err}", path) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise _refuse(info.st_mode, what, path, error)
        _check_size(info.st_size, limit, what, path, error)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def check_input(path: str | Path, what: str = "a file", error: type[DarpError] = FormatError, *,
                limit: int = LIMITS["text"]) -> Path:
    """:func:`open_input`'s checks alone, for a path handed to a library that opens it itself."""
    with open_input(path, what, error, limit=limit):
        return Path(path)


def read_input_bytes(path: str | Path, what: str = "a file", error: type[DarpError] = FormatError, *,
                     limit: int = LIMITS["text"]) -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes (a file growing past it while read is refused)."""
    parts: list[bytes] = []
    total = 0
    with open_input(path, what, error, limit=limit) as handle:
        expected = os.fstat(handle.fileno()).st_size
        try:
            while True:  # the size said, then whatever the file grew by, never past the limit
                block = handle.read(min(max(expected - total, 0), limit - total) + 1)
                if not block:
                    break
                parts.append(block)
                total += len(block)
                _check_size(total, limit, what, Path(path), error)
        except OSError as err:
            raise error(f"cannot read: {err.strerror or err}", path) from None
    return parts[0] if len(parts) == 1 else b"".join(parts)


@contextlib.contextmanager
def input_chunks(path: str | Path, what: str = "a file", error: type[DarpError] = FormatError, *,
                 limit: int = LIMITS["csv"], chunk_bytes: int = 8 * MiB) -> Iterator[Iterator[bytes]]:
    """Yield an iterator over the file's bytes in chunks (for streamed formats: memory flat in the length)."""
    handle = open_input(path, what, error, limit=limit)

    def chunks() -> Iterator[bytes]:
        total = 0
        while True:
            try:
                block = handle.read(chunk_bytes)
            except OSError as err:
                raise error(f"cannot read: {err.strerror or err}", path) from None
            if not block:
                return
            total += len(block)
            _check_size(total, limit, what, Path(path), error)
            yield block

    with handle:
        yield chunks()


def load_numpy(path: str | Path, what: str = "a NumPy file", error: type[DarpError] = FormatError
               ) -> dict[str, Any] | Any:
    """A ``.npy`` array or an ``.npz``'s arrays (as a dict, every array read) through the checked path; a
    truncated or damaged file is one ``error`` naming it (NumPy raises zipfile, EOF or value errors)."""
    import io
    import zipfile

    data = read_input_bytes(path, what, error, limit=LIMITS["npz"])
    try:
        loaded = np.load(io.BytesIO(data), allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded:
                return {k: loaded[k] for k in loaded.files}
        return loaded
    except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as err:
        detail = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise error(f"truncated or damaged {what} ({detail})", path) from None


@contextlib.contextmanager
def npz_input(path: str | Path, what: str = "an .npz file", error: type[DarpError] = FormatError) -> Iterator[Any]:
    """``np.load`` of an ``.npz`` (no pickle) opened through the checked path; the arrays are read lazily."""
    with open_input(path, what, error, limit=LIMITS["npz"]) as handle, np.load(handle, allow_pickle=False) as data:
        yield data


def marker_text(path: str | Path) -> str:
    """The text of a marker file (``PARTIAL.txt``, ``UNFINISHED.txt``), undecodable bytes replaced; "" when it
    cannot be read (a marker that is there says enough)."""
    try:
        return read_input_bytes(path, "a marker file", limit=LIMITS["marker"]).decode("utf-8", errors="replace")
    except DarpError:
        return ""


def image_too_large(width: int, height: int) -> bool:
    """True when a ``width`` x ``height`` image is beyond :data:`MAX_IMAGE_PIXELS` (or not positive)."""
    return width <= 0 or height <= 0 or width * height > MAX_IMAGE_PIXELS


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Send what C libraries print on stderr (libpng's "libpng error: ...", OpenCV's decoder warnings) to
    /dev/null for the block: darp reports the damaged file itself, in one line."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable fd 2: nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR, or None when ``data`` is not a PNG."""
    if len(data) >= 24 and data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def decode_image(path: str | Path, flags: int, what: str = "an image", error: type[DarpError] = FormatError,
                 ) -> np.ndarray | None:
    """Read and decode an image with OpenCV through the checked path: a regular file within the image limit,
    at most :data:`MAX_IMAGE_PIXELS` pixels (checked from a PNG's header before decoding). Returns the array,
    or None when OpenCV cannot decode it (the caller says what that means for its file)."""
    import cv2  # heavy: only when an image is read

    data = read_input_bytes(path, what, error, limit=LIMITS["image"])
    size = png_size(data)
    if size is not None and image_too_large(*size):
        raise error(f"{size[0]}x{size[1]} pixels, beyond darp's image limit ({MAX_IMAGE_PIXELS} pixels)", path)
    with native_stderr_silenced():
        image: np.ndarray | None = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is not None and image_too_large(image.shape[1], image.shape[0]):
        raise error(f"{image.shape[1]}x{image.shape[0]} pixels, beyond darp's image limit", path)
    return image


__all__ = ["LIMITS", "MAX_IMAGE_PIXELS", "check_input", "decode_image", "image_too_large", "input_chunks",
           "load_numpy", "marker_text", "npz_input", "open_input", "png_size", "read_input_bytes"]
