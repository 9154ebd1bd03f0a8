"""``arm_poses.csv``: the timestamped joint log of both arms (reader, validator, streaming writer).

Columns (header row required, any order, no others)::

    time_s  host-clock seconds (float; Unix epoch seconds with microsecond precision in practice)
    arm     arm id, e.g. ``arm110`` / ``arm111``
    q1..q6  the six joint angles in radians, as reported by the arm (no joint-zero correction)

Rows of both arms are interleaved in logging order; times must not decrease within an arm.
A last line cut short by a crash (no final newline and unparseable) is dropped and reported in
:attr:`ArmPoseLog.truncated_tail_line`; anywhere else a bad line is an error naming the line.
See docs/survey-format.md.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import NoReturn, Self

import numpy as np

from darp.errors import FormatError
from darp.formats.io_input import LIMITS, input_chunks
from darp.formats.limits import JOINT_ABS_MAX_RAD, TIME_MAX_S, TIME_MIN_S

JOINT_COLUMNS = ("q1", "q2", "q3", "q4", "q5", "q6")
COLUMNS = ("time_s", "arm", *JOINT_COLUMNS)
DEFAULT_ARMS = ("arm110", "arm111")
N_JOINTS = len(JOINT_COLUMNS)


@dataclass(frozen=True)
class ArmPoseLog:
    """The joint log, split per arm. Arrays are read-only; times in seconds, joints in radians."""

    path: Path
    _times: dict[str, np.ndarray]
    _joints: dict[str, np.ndarray]
    _lines: dict[str, np.ndarray]  # 1-based file line of every row, for diagnostics
    truncated_tail_line: int | None = None  # line number of a dropped, cut-short last line
    ignored_columns: tuple[str, ...] = field(default=())

    @property
    def arms(self) -> tuple[str, ...]:
        """Arms that have at least one row, in order of first appearance."""
        return tuple(self._times)

    @property
    def n_rows(self) -> int:
        """Rows of all arms together."""
        return sum(t.size for t in self._times.values())

    def _check(self, arm: str) -> None:
        if arm not in self._times:
            have = ", ".join(self._times) or "none"
            raise FormatError(f"no rows for arm {arm!r} (arms in the log: {have})", self.path)

    def times(self, arm: str) -> np.ndarray:
        """(N,) row times of ``arm`` in seconds, non-decreasing."""
        self._check(arm)
        return self._times[arm]

    def joints(self, arm: str) -> np.ndarray:
        """(N, 6) joint angles of ``arm`` in radians."""
        self._check(arm)
        return self._joints[arm]

    def lines(self, arm: str) -> np.ndarray:
        """(N,) 1-based line numbers of ``arm``'s rows in the file."""
        self._check(arm)
        return self._lines[arm]

    def rows(self, arm: str) -> int:
        """Number of rows of ``arm``."""
        return int(self.times(arm).size)

    def span(self, arm: str | None = None) -> tuple[float, float]:
        """(first, last) time in seconds of ``arm``, or of the whole log when ``arm`` is None."""
        if arm is not None:
            t = self.times(arm)
            return float(t[0]), float(t[-1])
        if not self._times:
            raise FormatError("the log has no rows", self.path)
        return (
            float(min(t[0] for t in self._times.values())),
            float(max(t[-1] for t in self._times.values())),
        )


def read_arm_poses(
    path: str | Path,
    known_arms: Iterable[str] | None = DEFAULT_ARMS,
    *,
    allow_extra_columns: bool = False,
    strict_tail: bool = False,
) -> ArmPoseLog:
    """Read and validate ``arm_poses.csv``, streamed: memory grows with the parsed rows (64 bytes a row), not
    with the text (about 100 bytes a row and many Python strings when read whole).

    ``known_arms=None`` accepts any arm id. ``allow_extra_columns`` ignores (and lists) unknown columns
    instead of refusing them. ``strict_tail`` makes a cut-short last line an error instead of dropping it.
    """
    path = Path(path)
    known = None if known_arms is None else tuple(known_arms)
    reader = _Reader(path, known, allow_extra_columns)
    with input_chunks(path, "a CSV file", limit=LIMITS["csv"], chunk_bytes=CHUNK_BYTES) as chunks:
        for text in _lines_of(chunks, path):
            reader.feed(text)
    return reader.finish(reader.pending_tail, strict_tail)


CHUNK_BYTES = 4 * 1024 * 1024  # text parsed per step (about 40,000 rows)


def _lines_of(chunks: Iterable[bytes], path: Path) -> Iterable[str]:
    """UTF-8 text (a leading BOM dropped) in pieces that end at a newline; the last piece may not."""
    carry = b""
    offset = 0  # bytes of the file before ``carry``
    first = True
    for block in chunks:
        data = carry + block
        cut = data.rfind(b"\n") + 1
        if cut == 0:
            carry = data
            continue
        yield _decode(data[:cut], offset, first, path)
        first = False
        offset += cut
        carry = data[cut:]
    if carry or first:
        yield _decode(carry, offset, first, path)


def _decode(data: bytes, offset: int, first: bool, path: Path) -> str:
    try:
        return data.decode("utf-8-sig" if first else "utf-8")
    except UnicodeDecodeError as err:
        raise FormatError(f"not UTF-8 text (byte {offset + err.start})", path) from err


class _Grow:
    """An arm's rows, appended in blocks: arrays grown in place (``ndarray.resize``, a realloc that moves no
    data for large arrays), so the peak is the rows themselves and not twice them."""

    def __init__(self) -> None:
        self.n = 0
        self.t = np.empty(1024)
        self.q = np.empty((1024, N_JOINTS))
        self.lines = np.empty(1024, dtype=np.int64)

    def add(self, t: np.ndarray, q: np.ndarray, lines: np.ndarray) -> None:
        need = self.n + t.size
        if need > self.t.size:
            size = max(need, 2 * self.t.size)
            self.t.resize(size, refcheck=False)
            self.q.resize((size, N_JOINTS), refcheck=False)
            self.lines.resize(size, refcheck=False)
        self.t[self.n:need], self.q[self.n:need], self.lines[self.n:need] = t, q, lines
        self.n = need

    def frozen(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.t.resize(self.n, refcheck=False)
        self.q.resize((self.n, N_JOINTS), refcheck=False)
        self.lines.resize(self.n, refcheck=False)
        return _frozen(self.t), _frozen(self.q), _frozen(self.lines)


class _Reader:
    """The parse of one file, piece by piece (the rules of the whole-file reader, in the same order per piece)."""

    def __init__(self, path: Path, known: tuple[str, ...] | None, allow_extra: bool) -> None:
        self.path, self.known, self.allow_extra = path, known, allow_extra
        self.header: list[str] | None = None
        self.index: dict[str, int] = {}
        self.ignored: list[str] = []
        self.line_no = 0  # lines consumed
        self.blank_header = False
        self.pending_tail = ""  # the text after the last newline (a last line without one)
        self.arms: dict[str, _Grow] = {}
        self.last_t: dict[str, float] = {}
        self.rows = 0

    def feed(self, text: str) -> None:
        lines = text.split("\n")
        self.pending_tail = lines.pop()  # "" when the piece ends with a newline
        if self.header is None and lines:
            self._take_header(lines.pop(0))
        if self.header is None:
            return
        self._rows(lines, self.line_no + 1)
        self.line_no += len(lines)

    def _take_header(self, line: str) -> None:
        self.line_no = 1
        if not line.strip():
            self.blank_header = True  # an error unless the whole file is blank (finish says which)
        header = [name.strip() for name in line.rstrip("\r").split(",")]
        self.header = header
        self.index, self.ignored = _column_index(header, self.path, self.allow_extra) if not self.blank_header \
            else ({}, [])

    def _rows(self, lines: list[str], first_line: int) -> None:
        if self.blank_header:
            if any(line.strip() for line in lines):
                _column_index([""], self.path, self.allow_extra)  # "no header row"
            return
        assert self.header is not None
        numbers = list(range(first_line, first_line + len(lines)))
        body = [line.rstrip("\r") for line in lines]
        if any(not line.strip() for line in body):  # skip blank lines, keep true line numbers
            kept = [(n, line) for n, line in zip(numbers, body, strict=True) if line.strip()]
            numbers = [n for n, _ in kept]
            body = [line for _, line in kept]
        if body:
            self._parse(body, numbers)

    def _parse(self, body: list[str], line_numbers: list[int]) -> None:
        header, index, path = self.header, self.index, self.path
        assert header is not None
        n_columns = len(header)
        n_commas = n_columns - 1
        if any(line.count(",") != n_commas for line in body):
            bad = next(i for i, line in enumerate(body) if line.count(",") != n_commas)
            _row_error(body[bad].split(","), line_numbers[bad], header, index, path)
        cells = ",".join(body).split(",")  # one split for the whole piece: much faster than per row
        numeric_names = ("time_s", *JOINT_COLUMNS)
        numbers = np.empty((len(body), len(numeric_names)), dtype=np.float64)
        try:
            for k, name in enumerate(numeric_names):
                numbers[:, k] = list(map(float, cells[index[name] :: n_columns]))
        except ValueError:
            bad = next(i for i, line in enumerate(body) if not _row_ok(line.split(","), n_columns, index))
            _row_error(body[bad].split(","), line_numbers[bad], header, index, path)
        line_array = np.asarray(line_numbers, dtype=np.int64)
        finite = np.isfinite(numbers)
        if not finite.all():
            row, col = map(int, np.argwhere(~finite)[0])
            raise FormatError(f"line {line_array[row]}: {numeric_names[col]} is {numbers[row, col]} (must be finite)",
                              path)
        _check_ranges(numbers, line_array, path)
        arm_ids = np.array([cell.strip() for cell in cells[index["arm"] :: n_columns]], dtype=object)
        present = list(dict.fromkeys(arm_ids.tolist()))
        for arm in present:
            if not arm or (self.known is not None and arm not in self.known):
                first = int(np.nonzero(arm_ids == arm)[0][0])
                expected = f" (expected one of: {', '.join(self.known)})" if self.known else ""
                raise FormatError(f"line {line_array[first]}: unknown arm id {arm!r}{expected}", path)
        for arm in present:
            mask = arm_ids == arm
            t = numbers[mask, 0]
            last = self.last_t.get(arm)
            back = np.nonzero(np.diff(t) < 0.0)[0]
            if last is not None and t[0] < last:
                line = int(line_array[mask][0])
                raise FormatError(f"line {line}: time goes backwards for {arm} ({_fmt_pair(t[0], last)})", path)
            if back.size:
                k = int(back[0]) + 1
                line = int(line_array[mask][k])
                raise FormatError(f"line {line}: time goes backwards for {arm} ({_fmt_pair(t[k], t[k - 1])})", path)
            self.arms.setdefault(arm, _Grow()).add(t, numbers[mask, 1:], line_array[mask])
            self.last_t[arm] = float(t[-1])
        self.rows += len(body)

    def finish(self, tail: str, strict_tail: bool) -> ArmPoseLog:
        path = self.path
        if self.header is None:  # the file is one line without a newline (or empty)
            if not tail.strip():
                raise FormatError("empty file: expected a header row " + ",".join(COLUMNS), path)
            self._take_header(tail)
            tail = ""
        if self.blank_header:
            if tail.strip():
                _column_index([""], path, self.allow_extra)
            raise FormatError("empty file: expected a header row " + ",".join(COLUMNS), path)
        assert self.header is not None
        truncated: int | None = None
        line = tail.rstrip("\r")
        if line.strip():
            number = self.line_no + 1
            if _row_ok(line.split(","), len(self.header), self.index):
                self._parse([line], [number])
            elif strict_tail:
                _row_error(line.split(","), number, self.header, self.index, path, tail=True)
            else:
                truncated = number
        if not self.rows:
            dropped = f" (the only row, line {truncated}, is cut short)" if truncated else ""
            raise FormatError(f"no data rows after the header{dropped}", path)
        times: dict[str, np.ndarray] = {}
        joints: dict[str, np.ndarray] = {}
        arm_lines: dict[str, np.ndarray] = {}
        for arm, grow in self.arms.items():
            times[arm], joints[arm], arm_lines[arm] = grow.frozen()
        return ArmPoseLog(path, times, joints, arm_lines, truncated, tuple(self.ignored))


def _check_ranges(numbers: np.ndarray, line_array: np.ndarray, path: Path) -> None:
    """Refuse times and joint angles outside the plausible ranges (docs/reliability.md)."""
    t = numbers[:, 0]
    bad_t = np.nonzero((t < TIME_MIN_S) | (t > TIME_MAX_S))[0]
    if bad_t.size:
        row = int(bad_t[0])
        why = ("negative" if t[row] < TIME_MIN_S
               else f"beyond {TIME_MAX_S:.0e} s: milliseconds? the column is host-clock seconds")
        raise FormatError(f"line {line_array[row]}: time_s is {float(t[row])!r} ({why})", path)
    q = numbers[:, 1:]
    bad_q = np.argwhere(np.abs(q) > JOINT_ABS_MAX_RAD)
    if bad_q.size:
        row, col = map(int, bad_q[0])
        raise FormatError(f"line {line_array[row]}: {JOINT_COLUMNS[col]} is {float(q[row, col])!r} rad "
                          f"(outside +-{JOINT_ABS_MAX_RAD:.4f}: not a joint angle in radians)", path)


def _column_index(
    header: list[str], path: Path, allow_extra: bool
) -> tuple[dict[str, int], list[str]]:
    missing = [name for name in COLUMNS if name not in header]
    if len(missing) == len(COLUMNS):
        raise FormatError(f"line 1: no header row (the first line must be {','.join(COLUMNS)})", path)
    duplicated = sorted({name for name in header if header.count(name) > 1})
    if duplicated:
        raise FormatError(f"line 1: column(s) {', '.join(map(repr, duplicated))} appear twice", path)
    if missing:
        raise FormatError(f"line 1: missing column(s) {', '.join(missing)}", path)
    extra = [name for name in header if name not in COLUMNS]
    if extra and not allow_extra:
        raise FormatError(
            f"line 1: unexpected column(s) {', '.join(repr(n) for n in extra)} "
            f"(expected exactly {','.join(COLUMNS)})",
            path,
        )
    return {name: header.index(name) for name in COLUMNS}, extra


def _row_ok(row: list[str], n_columns: int, index: dict[str, int]) -> bool:
    if len(row) != n_columns or not row[index["arm"]].strip():
        return False
    try:
        for name in ("time_s", *JOINT_COLUMNS):
            float(row[index[name]])
    except ValueError:
        return False
    return True


def _row_error(
    row: list[str], line: int, header: list[str], index: dict[str, int], path: Path, tail: bool = False
) -> NoReturn:
    """Raise the most specific error for a row that failed the fast path."""
    suffix = " (last line cut short: the writer probably crashed)" if tail else ""
    if len(row) != len(header):
        joints_found = len(row) - (len(header) - N_JOINTS)
        detail = f" ({joints_found} joint values instead of {N_JOINTS})" if joints_found >= 0 else ""
        raise FormatError(
            f"line {line}: expected {len(header)} fields, found {len(row)}{detail}{suffix}", path
        )
    if not row[index["arm"]].strip():
        raise FormatError(f"line {line}: empty arm id{suffix}", path)
    for name in ("time_s", *JOINT_COLUMNS):
        cell = row[index[name]]
        try:
            float(cell)
        except ValueError:
            message = f"line {line}: {name} is not a number: {cell.strip()!r}{suffix}"
            raise FormatError(message, path) from None
    raise FormatError(f"line {line}: malformed row{suffix}", path)


def _fmt_pair(later: float, earlier: float) -> str:
    for digits in (3, 6, 9):
        a, b = f"{later:.{digits}f}", f"{earlier:.{digits}f}"
        if a != b:
            return f"{a} < {b}"
    return f"{later!r} < {earlier!r}"


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    array.flags.writeable = False
    return array


class ArmPoseWriter:
    """Streaming, thread-safe writer of ``arm_poses.csv`` for the joint logger.

    The header is written on open; rows are flushed to the OS every ``flush_every`` rows (so a crash of
    the process loses at most that many) and fsynced on :meth:`close`. Rows are validated with the
    reader's rules, so the writer cannot produce a file the reader refuses.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        known_arms: Iterable[str] | None = DEFAULT_ARMS,
        flush_every: int = 8,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        self.flush_every = max(1, int(flush_every))
        self._known = None if known_arms is None else tuple(known_arms)
        self._lock = threading.Lock()
        self._last_time: dict[str, float] = {}
        self._pending = 0
        self.rows_written = 0
        try:
            self._handle = open(self.path, "w" if overwrite else "x", encoding="utf-8",  # noqa: SIM115 (closed in close)
                                newline="\n")
        except FileExistsError:
            raise FormatError("already exists (refusing to overwrite a joint log)", self.path) from None
        except OSError as err:
            raise FormatError(f"cannot create: {err.strerror}", self.path) from err
        self._handle.write(",".join(COLUMNS) + "\n")
        self._handle.flush()

    def write(self, time_s: float, arm: str, q: Sequence[float] | np.ndarray) -> None:
        """Append one row: host time in seconds, arm id, six joint angles in radians."""
        values = [float(v) for v in np.asarray(q, dtype=np.float64).reshape(-1)]
        time_s = float(time_s)
        if len(values) != N_JOINTS:
            message = f"row for {arm}: expected {N_JOINTS} joint values, got {len(values)}"
            raise FormatError(message, self.path)
        if not math.isfinite(time_s) or not all(math.isfinite(v) for v in values):
            raise FormatError(f"row for {arm} at {time_s!r}: values must be finite", self.path)
        if not arm or "," in arm or "\n" in arm or (self._known is not None and arm not in self._known):
            raise FormatError(f"unknown arm id {arm!r}", self.path)
        line = f"{time_s:.6f},{arm}," + ",".join(f"{v:.9f}" for v in values) + "\n"
        with self._lock:
            if self._handle.closed:
                raise FormatError("write after close", self.path)
            last = self._last_time.get(arm)
            if last is not None and time_s < last:
                raise FormatError(f"time goes backwards for {arm} ({_fmt_pair(time_s, last)})", self.path)
            self._last_time[arm] = time_s
            self._handle.write(line)
            self.rows_written += 1
            self._pending += 1
            if self._pending >= self.flush_every:
                self._handle.flush()
                self._pending = 0

    def flush(self, sync: bool = False) -> None:
        """Push buffered rows to the OS (and to disk with ``sync``)."""
        with self._lock:
            if not self._handle.closed:
                self._handle.flush()
                self._pending = 0
                if sync:
                    os.fsync(self._handle.fileno())

    def close(self) -> None:
        """Flush, fsync and close; idempotent."""
        with self._lock:
            if self._handle.closed:
                return
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
