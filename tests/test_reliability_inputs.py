"""Bad input where it enters darp (issue 15): truncations and bit flips of every text format darp reads, malformed
values per field, the sanity ranges of docs/reliability.md, and writes that fail half-way (ENOSPC, EROFS).

Each case asserts the one outcome darp allows: the value is read, or a DarpError whose message starts with the file
(and names the field or line) - never another exception - and the input file is unchanged. The fuzzing is
property-based (hypothesis, derandomized: the same examples every run, so a failure reruns as it failed).
"""

from __future__ import annotations

import errno
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from darp.errors import DarpError, FormatError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.atomic import write_json_atomic, write_text_atomic
from darp.formats.calibration import calibration_to_dict, read_calibration
from darp.formats.envelope import Envelope, envelope_to_dict, read_envelope
from darp.formats.limits import MAX_JSON_BYTES
from darp.kinematics.rig import default_rig_path, load_rig
from darp.twin.waypoints import load_waypoints

FUZZ = settings(max_examples=40, deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

ARM_POSES = ("time_s,arm,q1,q2,q3,q4,q5,q6\n"
             + "".join(f"{1700000000 + 0.03 * k:.6f},{arm},0.1,0.6,-1.2,1.2,0.0,{0.01 * k:.3f}\n"
                       for k in range(6) for arm in ("arm110", "arm111")))
WAYPOINTS = """schema: darp-twin-waypoints/1
dwell_s: 0.5
arms:
  arm110:
    - [0.0, 1.2, -1.0, 0.2, 0.0, 0.0]
    - {q_deg: [10, 70, -60, 15, 0, 0], dwell_s: 1.0}
  arm111:
    - {q_rad: [0.0, 1.2, -1.0, 0.2, 0.0, 0.0]}
"""


def _envelope() -> dict[str, Any]:
    return envelope_to_dict(Envelope(object_name="cube", center_m=(0.0, 0.02, 0.05), radius_m=0.05, height_m=0.1,
                                     standoff_m=0.35, park_q_rad={"arm110": (0.0, 0.6, -1.2, 1.2, 0.0, 0.0)},
                                     view_q_rad={"arm111": [(0.1, 1.0, -1.0, 0.5, 0.0, 0.0)]}))


def _calibration() -> dict[str, Any]:
    from darp.formats.schema import to_jsonable

    return dict(to_jsonable(calibration_to_dict(load_rig().nominal_calibration())))


# name -> (file name, valid bytes, reader)
FORMATS: dict[str, tuple[str, Callable[[], bytes], Callable[[Path], object]]] = {
    "arm_poses": ("arm_poses.csv", lambda: ARM_POSES.encode(), read_arm_poses),
    "envelope": ("manip_envelope.json", lambda: json.dumps(_envelope(), indent=2).encode(), read_envelope),
    "calibration": ("calibration.json", lambda: json.dumps(_calibration(), indent=2).encode(), read_calibration),
    "rig": ("rig.yaml", lambda: default_rig_path().read_bytes(), load_rig),
    "waypoints": ("waypoints.yaml", lambda: WAYPOINTS.encode(), load_waypoints),
}


def _outcome(path: Path, reader: Callable[[Path], object]) -> None:
    """Read ``path``: a value, or a one-line DarpError naming the file; the file is left as it was."""
    before = path.read_bytes()
    try:
        reader(path)
    except DarpError as err:
        message = str(err)
        assert message.startswith(str(path)), message
        assert "\n" not in message.strip(), message
    assert path.read_bytes() == before


@pytest.mark.parametrize("kind", sorted(FORMATS))
def test_every_format_reads_its_valid_file(kind: str, tmp_path: Path) -> None:
    name, valid, reader = FORMATS[kind]
    path = tmp_path / name
    path.write_bytes(valid())
    reader(path)  # the fuzzing below starts from a file darp accepts


@pytest.mark.parametrize("kind", sorted(FORMATS))
@FUZZ
@given(data=st.data())
def test_truncated_or_bit_flipped_files_are_read_or_refused_in_one_line(kind: str, data: st.DataObject,
                                                                          tmp_path: Path) -> None:
    name, valid, reader = FORMATS[kind]
    raw = bytearray(valid())
    how = data.draw(st.sampled_from(["truncate", "flip", "both", "splice"]))
    if how in ("flip", "both"):
        for _ in range(data.draw(st.integers(1, 4))):
            at = data.draw(st.integers(0, len(raw) - 1))
            raw[at] ^= 1 << data.draw(st.integers(0, 7))
    if how in ("truncate", "both"):
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    if how == "splice":  # a value replaced by something absurd
        at = data.draw(st.integers(0, len(raw)))
        junk = data.draw(st.sampled_from([b"1e300", b"-1e6", b"nan", b"[[[[[[", b"9" * 5001, b'"x"', b"null",
                                          b"\x00\xff", b"1.0e6", b"{}", b"inf"]))
        raw = raw[:at] + junk + raw[at:]
    path = tmp_path / name
    path.write_bytes(bytes(raw))
    _outcome(path, reader)


def _json_case(payload: dict[str, Any], edit: Callable[[dict[str, Any]], None]) -> bytes:
    edit(payload)
    return json.dumps(payload).encode()


def _set_q(payload: dict[str, Any], value: float) -> None:
    payload["arms"]["arm110"]["joint_offsets_rad"][0] = value


def _move_base(payload: dict[str, Any]) -> None:
    payload["arms"]["arm110"]["T_world_base"][0][3] *= 1e6


def _share_serial(payload: dict[str, Any]) -> None:
    payload["arms"]["arm112"] = dict(payload["arms"]["arm110"])


# (file kind, bytes, words the message must contain): every one is refused
BAD_VALUES: dict[str, tuple[str, Callable[[], bytes], str]] = {
    "joints 1e6 rad": ("arm_poses", lambda: ARM_POSES.replace(",0.6,", ",1e6,", 1).encode(), "line 2: q2"),
    "joints 1e300 rad": ("arm_poses", lambda: ARM_POSES.replace(",1.2,0.0", ",1e300,0.0", 1).encode(), "line 2: q4"),
    "time in milliseconds": ("arm_poses", lambda: ARM_POSES.replace("1700000000.", "1700000000000.").encode(),
                             "milliseconds"),
    "negative time": ("arm_poses", lambda: ARM_POSES.replace("1700000000.000000", "-1.0", 1).encode(),
                      "line 2: time_s"),
    "envelope radius 1e9": ("envelope", lambda: _json_case(_envelope(), lambda p: p.update(radius_m=1e9)),
                            "radius_m"),
    "envelope centre 1e9": ("envelope", lambda: _json_case(_envelope(), lambda p: p.update(center_m=[1e9, 0, 0])),
                            "center_m"),
    "views of an unknown arm": ("envelope", lambda: _json_case(
        _envelope(), lambda p: p.update(view_q_rad={"arm999": [[0, 1, -1, 0.5, 0, 0]]})), "view_q_rad.arm999"),
    "5,001-digit integer": ("envelope", lambda: json.dumps(_envelope())[:-1].encode() + b', "n": '
                            + b"9" * 5001 + b"}", "digits"),
    "deeply nested": ("envelope", lambda: json.dumps(_envelope())[:-1].encode() + b', "n": ' + b"[" * 50000
                      + b"]" * 50000 + b"}", "nested too deeply"),
    "joint offset 100 rad": ("calibration", lambda: _json_case(_calibration(), lambda p: _set_q(p, 100.0)),
                             "arms.arm110.joint_offsets_rad"),
    "base translation x1e6": ("calibration", lambda: _json_case(_calibration(), _move_base),
                              "arms.arm110.T_world_base"),
    "calibration unknown key": ("calibration", lambda: _json_case(_calibration(), lambda p: p.update(extra=1)),
                                "unknown key"),
    "two arms share a serial": ("calibration", lambda: _json_case(_calibration(), _share_serial),
                                "also on arms.arm110"),
    "calibration deeply nested": ("calibration", lambda: b'{"schema_version": 1, "report": ' + b"[" * 50000
                                  + b"]" * 50000 + b"}", "nested too deeply"),
    "rig unknown key": ("rig", lambda: default_rig_path().read_bytes() + b"colour: red\n", "unknown key"),
    "rig rpy 1e300": ("rig", lambda: default_rig_path().read_bytes().replace(b"rpy_deg: [0.0, 0.0, 178.4]",
                                                                           b"rpy_deg: [0.0, 0.0, 1e300]"),
                      "rpy_deg"),
    "dwell 1.0e+6 s": ("waypoints", lambda: WAYPOINTS.replace("dwell_s: 1.0", "dwell_s: 1.0e+6").encode(),
                       "dwell_s: 1000000.0 is more than"),
    "dwell 1.0e6 s (YAML 1.2 float)": ("waypoints", lambda: WAYPOINTS.replace("dwell_s: 1.0", "dwell_s: 1.0e6")
                                       .encode(), "dwell_s: 1000000.0 is more than"),
}


@pytest.mark.parametrize("case", sorted(BAD_VALUES))
def test_implausible_values_are_refused_naming_the_file_and_field(case: str, tmp_path: Path) -> None:
    kind, make, words = BAD_VALUES[case]
    name, _, reader = FORMATS[kind]
    path = tmp_path / name
    path.write_bytes(make())
    before = path.read_bytes()
    with pytest.raises(DarpError) as caught:
        reader(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and words in message, message
    assert path.read_bytes() == before


@pytest.mark.parametrize("kind", ["calibration", "envelope"])
def test_a_json_file_over_the_size_limit_is_refused_unread_in_one_line(kind: str, tmp_path: Path) -> None:
    """A sparse file one byte over MAX_JSON_BYTES (no disk used): refused from its size, naming the file."""
    name, valid, reader = FORMATS[kind]
    path = tmp_path / name
    with path.open("wb") as f:
        f.write(valid())
        f.truncate(MAX_JSON_BYTES + 1)
    with pytest.raises(FormatError) as caught:
        reader(path)
    message = str(caught.value)
    assert message == f"{path}: {MAX_JSON_BYTES + 1} bytes, over darp's limit for a JSON file (256 MiB)"
    path.write_bytes(valid())  # the same file at its real size is read
    reader(path)


def test_yaml_floats_are_read_the_same_in_both_spellings(tmp_path: Path) -> None:
    for spelling in ("1.0e+0", "1.0e0", "1e0", "1.0"):
        path = tmp_path / "w.yaml"
        path.write_text(WAYPOINTS.replace("dwell_s: 1.0", f"dwell_s: {spelling}"))
        assert load_waypoints(path).arms["arm110"][1].dwell_s == 1.0


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS])
def test_a_write_that_fails_names_the_output_and_leaves_no_temporary_file(code: int, tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "out.json"
    write_json_atomic(target, {"old": True})
    real_replace = os.replace

    def failing_replace(src: Any, dst: Any) -> None:
        raise OSError(code, os.strerror(code), str(src))

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError) as caught:
        write_text_atomic(target, "new")
    monkeypatch.setattr(os, "replace", real_replace)
    assert caught.value.errno == code and caught.value.filename == str(target)  # not the .partial name
    assert json.loads(target.read_text()) == {"old": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_arm_poses_ranges_accept_a_real_log(tmp_path: Path) -> None:
    path = tmp_path / "arm_poses.csv"
    path.write_text(ARM_POSES)
    log = read_arm_poses(path)
    assert log.rows("arm110") == 6 and np.all(np.abs(log.joints("arm111")) < 2.0)


@FUZZ
@given(data=st.binary(min_size=0, max_size=40), at=st.integers(0, len(ARM_POSES)), cut=st.integers(0, 8),
       chunk=st.integers(1, 97))
def test_the_streamed_joint_log_does_not_depend_on_its_piece_size(data: bytes, at: int, cut: int, chunk: int,
                                                                  tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 32: arm_poses.csv is parsed piece by piece. Any splice of bytes into a valid log reads the same
    (arrays, lines, a dropped tail) or fails with a FormatError, whether the pieces are 1 to 97 bytes or the file."""
    import darp.formats.arm_poses as arm_poses

    raw = ARM_POSES.encode()
    path = tmp_path / "arm_poses.csv"
    path.write_bytes(raw[:at] + data + raw[at + cut:])

    def outcome() -> Any:
        try:
            log = arm_poses.read_arm_poses(path)
        except FormatError as err:
            assert str(err).startswith(str(path))
            return "refused"
        return (log.truncated_tail_line, {a: (log.times(a).tobytes(), log.joints(a).tobytes(), log.lines(a).tolist())
                                          for a in log.arms})

    whole = outcome()
    monkeypatch.setattr(arm_poses, "CHUNK_BYTES", chunk)
    assert outcome() == whole
