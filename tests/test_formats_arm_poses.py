"""arm_poses.csv: reader validation (one clear error per defect), writer round trip, flushing, threads."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from darp.errors import FormatError
from darp.formats.arm_poses import COLUMNS, ArmPoseWriter, read_arm_poses

HEADER = ",".join(COLUMNS)


def _write(path: Path, *lines: str, newline_at_end: bool = True) -> Path:
    path.write_text("\n".join(lines) + ("\n" if newline_at_end else ""), encoding="utf-8")
    return path


def _row(t: float, arm: str = "arm110", q: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)) -> str:
    return ",".join([f"{t}", arm, *map(str, q)])


def _error(path: Path, **kwargs: object) -> str:
    with pytest.raises(FormatError) as info:
        read_arm_poses(path, **kwargs)  # type: ignore[arg-type]
    message = str(info.value)
    assert path.name in message, message  # every error names the file
    assert "\n" not in message
    return message


def test_writer_reader_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    path = tmp_path / "arm_poses.csv"
    t = 1718000000.0 + np.cumsum(rng.uniform(0.02, 0.04, 50))
    q110 = rng.uniform(-2.5, 2.5, (50, 6))
    q111 = rng.uniform(-2.5, 2.5, (50, 6))
    with ArmPoseWriter(path) as writer:
        for k in range(50):
            writer.write(t[k], "arm110", q110[k])
            writer.write(t[k] + 0.001, "arm111", q111[k])
    log = read_arm_poses(path)
    assert log.arms == ("arm110", "arm111")
    assert log.n_rows == 100 and log.rows("arm110") == 50 and log.rows("arm111") == 50
    np.testing.assert_allclose(log.times("arm110"), t, atol=1e-6, rtol=0)
    np.testing.assert_allclose(log.times("arm111"), t + 0.001, atol=1e-6, rtol=0)
    np.testing.assert_allclose(log.joints("arm110"), q110, atol=1e-9, rtol=0)
    np.testing.assert_allclose(log.joints("arm111"), q111, atol=1e-9, rtol=0)
    assert log.span("arm111") == pytest.approx((t[0] + 0.001, t[-1] + 0.001), abs=1e-6)
    assert log.span() == pytest.approx((t[0], t[-1] + 0.001), abs=1e-6)
    assert log.lines("arm111")[:2].tolist() == [3, 5]  # header is line 1, rows interleave
    assert log.truncated_tail_line is None
    with pytest.raises(ValueError):
        log.joints("arm110")[0, 0] = 1.0  # arrays are read-only


def test_columns_in_any_order_and_crlf_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "arm_poses.csv"
    path.write_bytes(b"arm,q1,q2,q3,q4,q5,q6,time_s\r\narm111,1,2,3,4,5,6,10.5\r\n\r\narm111,1,2,3,4,5,7,10.25\r\n")
    message = _error(path)
    assert "line 4: time goes backwards for arm111 (10.250 < 10.500)" in message  # blank line 3 counted
    path.write_bytes(b"arm,q1,q2,q3,q4,q5,q6,time_s\r\narm111,1,2,3,4,5,6,10.5\r\n")
    log = read_arm_poses(path)
    assert log.times("arm111").tolist() == [10.5]
    assert log.joints("arm111").tolist() == [[1, 2, 3, 4, 5, 6]]


def test_time_going_backwards_names_line_and_values(tmp_path: Path) -> None:
    lines = [HEADER] + [_row(12.0 + 0.034 * k, "arm111") for k in range(10)]
    lines.insert(6, _row(11.9, "arm110"))  # other arms do not interfere
    lines.insert(8, _row(12.1, "arm111"))  # line 9 goes back: line 8 (k=5) is at 12.170
    path = _write(tmp_path / "arm_poses.csv", *lines)
    message = _error(path)
    assert message.endswith("arm_poses.csv: line 9: time goes backwards for arm111 (12.100 < 12.170)")


def test_equal_times_are_allowed(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), _row(1.0), _row(1.5))
    assert read_arm_poses(path).times("arm110").tolist() == [1.0, 1.0, 1.5]


@pytest.mark.parametrize(
    ("cell", "column", "expected"),
    [("nan", "q3", "line 3: q3 is nan (must be finite)"),
     ("inf", "time_s", "line 3: time_s is inf (must be finite)"),
     ("-inf", "q6", "line 3: q6 is -inf (must be finite)")],
)
def test_non_finite_values(tmp_path: Path, cell: str, column: str, expected: str) -> None:
    values = {"time_s": "2.0", "arm": "arm110", "q1": "0", "q2": "0", "q3": "0", "q4": "0", "q5": "0", "q6": "0"}
    values[column] = cell
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), ",".join(values[c] for c in COLUMNS), _row(3.0))
    assert expected in _error(path)


def test_non_numeric_value(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), "2.0,arm110,0,0,zero,0,0,0", _row(3.0))
    assert "line 3: q3 is not a number: 'zero'" in _error(path)
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), ",arm110,0,0,0,0,0,0")
    assert "line 3: time_s is not a number: ''" in _error(path)


def test_missing_and_extra_columns(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", "time_s,arm,q1,q2,q3,q4,q5", "1.0,arm110,0,0,0,0,0")
    assert "line 1: missing column(s) q6" in _error(path)
    path = _write(tmp_path / "arm_poses.csv", HEADER + ",gripper", _row(1.0) + ",0.5")
    message = _error(path)
    assert "line 1: unexpected column(s) 'gripper'" in message
    log = read_arm_poses(path, allow_extra_columns=True)
    assert log.ignored_columns == ("gripper",)
    assert log.joints("arm110").tolist() == [[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]]
    path = _write(tmp_path / "arm_poses.csv", "1.0,arm110,0,0,0,0,0,0")  # no header at all
    assert "line 1: no header row (the first line must be time_s,arm,q1,q2,q3,q4,q5,q6)" in _error(path)
    path = _write(tmp_path / "arm_poses.csv", HEADER + ",q1", _row(1.0) + ",0")
    assert "line 1: column(s) 'q1' appear twice" in _error(path)


def test_unknown_arm(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), _row(1.1, "arm111"), _row(1.2, "arm112"))
    assert "line 4: unknown arm id 'arm112' (expected one of: arm110, arm111)" in _error(path)
    log = read_arm_poses(path, known_arms=None)
    assert log.arms == ("arm110", "arm111", "arm112")
    with pytest.raises(FormatError, match="no rows for arm 'arm113'"):
        log.times("arm113")


def test_wrong_number_of_joints(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), _row(1.1, q=(1, 2, 3, 4, 5)), _row(1.2))
    assert "line 3: expected 8 fields, found 7 (5 joint values instead of 6)" in _error(path)
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0, q=(1, 2, 3, 4, 5, 6, 7)), _row(1.2))
    assert "line 2: expected 8 fields, found 9 (7 joint values instead of 6)" in _error(path)


def test_empty_and_header_only(tmp_path: Path) -> None:
    path = _write(tmp_path / "arm_poses.csv", newline_at_end=False)
    assert "empty file" in _error(path)
    path = _write(tmp_path / "arm_poses.csv", HEADER)
    assert "no data rows after the header" in _error(path)
    assert "no such file" in _error(tmp_path / "missing.csv")


def test_truncated_last_line_is_dropped_and_flagged(tmp_path: Path) -> None:
    lines = [HEADER, _row(1.0), _row(1.1, "arm111"), "1.2,arm110,0.1,0.2,0.3"]
    path = _write(tmp_path / "arm_poses.csv", *lines, newline_at_end=False)
    log = read_arm_poses(path)
    assert log.truncated_tail_line == 4
    assert log.rows("arm110") == 1 and log.rows("arm111") == 1
    message = _error(path, strict_tail=True)
    assert "line 4: expected 8 fields, found 5" in message and "cut short" in message
    # the same line WITH a newline was written whole: it is a genuine error, not a crash
    path = _write(tmp_path / "arm_poses.csv", *lines)
    assert "line 4: expected 8 fields, found 5" in _error(path)
    # a complete last line without a final newline is kept
    path = _write(tmp_path / "arm_poses.csv", HEADER, _row(1.0), _row(1.2), newline_at_end=False)
    log = read_arm_poses(path)
    assert log.rows("arm110") == 2 and log.truncated_tail_line is None
    # a crash right after the first row began leaves nothing usable
    path = _write(tmp_path / "arm_poses.csv", HEADER, "1.0,arm1", newline_at_end=False)
    assert "no data rows after the header (the only row, line 2, is cut short)" in _error(path)


def test_writer_flushes_while_open(tmp_path: Path) -> None:
    path = tmp_path / "arm_poses.csv"
    with ArmPoseWriter(path, flush_every=4) as writer:
        for k in range(9):
            writer.write(100.0 + 0.03 * k, "arm110", np.full(6, 0.01 * k))
        visible = read_arm_poses(path)  # another reader, while the writer is still open
        assert visible.rows("arm110") == 8  # two flushes of four rows; the ninth is still buffered
        writer.flush()
        assert read_arm_poses(path).rows("arm110") == 9
    assert read_arm_poses(path).rows("arm110") == 9


def test_writer_refuses_what_the_reader_refuses(tmp_path: Path) -> None:
    path = tmp_path / "arm_poses.csv"
    with ArmPoseWriter(path) as writer:
        writer.write(1.0, "arm110", [0.0] * 6)
        with pytest.raises(FormatError, match="time goes backwards for arm110"):
            writer.write(0.5, "arm110", [0.0] * 6)
        writer.write(0.5, "arm111", [0.0] * 6)  # per-arm ordering only
        with pytest.raises(FormatError, match="expected 6 joint values, got 5"):
            writer.write(2.0, "arm110", [0.0] * 5)
        with pytest.raises(FormatError, match="must be finite"):
            writer.write(2.0, "arm110", [0.0, float("nan"), 0, 0, 0, 0])
        with pytest.raises(FormatError, match="unknown arm id 'arm9'"):
            writer.write(2.0, "arm9", [0.0] * 6)
    with pytest.raises(FormatError, match="write after close"):
        writer.write(3.0, "arm110", [0.0] * 6)
    with pytest.raises(FormatError, match="already exists"):
        ArmPoseWriter(path)
    log = read_arm_poses(path)
    assert (log.rows("arm110"), log.rows("arm111")) == (1, 1)


def test_writer_is_thread_safe(tmp_path: Path) -> None:
    path = tmp_path / "arm_poses.csv"
    n = 2000
    with ArmPoseWriter(path, flush_every=3) as writer:
        def log_arm(arm: str, offset: float) -> None:
            for k in range(n):
                writer.write(offset + 0.001 * k, arm, np.full(6, k * 1e-3))

        threads = [threading.Thread(target=log_arm, args=(arm, 5.0)) for arm in ("arm110", "arm111")]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    log = read_arm_poses(path)  # would fail on any interleaved, torn line
    for arm in ("arm110", "arm111"):
        assert log.rows(arm) == n
        np.testing.assert_allclose(log.joints(arm)[:, 0], np.arange(n) * 1e-3, atol=1e-9)
    assert writer.rows_written == 2 * n
