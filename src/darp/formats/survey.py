"""The DARP survey folder: two camera recordings, the joint log and the envelope, opened read-only.

::

    <object>/
        cam348522076490.bag      arm110's camera (a ROS2 ``.db3`` is accepted too)
        cam405622074504.bag      arm111's camera
        arm_poses.csv            joint log of both arms (darp.formats.arm_poses)
        manip_envelope.json      object envelope and robot configuration (darp.formats.envelope)
        truth/                   the digital twin's ground truth (optional, never needed to read a survey)

Nothing here ever writes into the folder.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from pathlib import Path

from darp.errors import SurveyError
from darp.formats.arm_poses import ArmPoseLog, read_arm_poses
from darp.formats.envelope import ENVELOPE_FILE, Envelope, read_envelope
from darp.formats.io_input import marker_text
from darp.formats.realsense.recording import Recording, open_recording

DEFAULT_SERIAL_TO_ARM: dict[str, str] = {"348522076490": "arm110", "405622074504": "arm111"}
ARM_POSES_FILE = "arm_poses.csv"
PARTIAL_FILE = "PARTIAL.txt"  # an unfinished survey folder: written first and removed last by twin record and
#   collect (so a SIGKILLed run is marked too), rewritten with the reason by an interrupted or failed acquisition
REJECTED_FILE = "REJECTED.txt"  # a survey collect rejected or terminated (a fault, a conflict, a failed check)
PARTIAL_RECORDING_SUFFIX = ".partial"  # cam<serial>.bag.partial: a recording that was never finalised
WRITTEN_BY_FILE = ".darp-written"  # in a folder darp created whole: --overwrite may delete such a folder only
TRUTH_DIR = "truth"
RECORDING_SUFFIXES = (".bag", ".db3")
_RECORDING_NAME = re.compile(r"^cam(?P<serial>[0-9A-Za-z]+)\.(?:bag|db3)$")


class Survey:
    """An opened survey folder. Files are located on open; their contents are read on demand."""

    def __init__(
        self,
        path: Path,
        recording_paths: dict[str, Path],
        serials: dict[str, str],
        arm_poses_path: Path | None,
        envelope_path: Path | None,
        problems: tuple[str, ...],
        notes: tuple[str, ...],
        partial: str | None = None,
    ) -> None:
        self.path = path
        self.recording_paths = recording_paths  # by arm
        self.serials = serials  # camera serial by arm
        self.arm_poses_path = arm_poses_path
        self.envelope_path = envelope_path
        self.problems = problems  # what makes the survey incomplete (open_survey(strict=True) raises)
        self.notes = notes  # worth knowing, not blocking (e.g. no manip_envelope.json)
        self.partial = partial  # why the survey is partial (PARTIAL.txt, *.bag.partial), or None
        self._log: ArmPoseLog | None = None
        self._envelope: Envelope | None = None

    def __repr__(self) -> str:
        return f"Survey({str(self.path)!r}, arms={list(self.recording_paths)})"

    @property
    def name(self) -> str:
        """The folder name (the object's name in the DARP release)."""
        return self.path.name

    @property
    def arms(self) -> tuple[str, ...]:
        """Arms with a recording, in the order of the serial mapping."""
        return tuple(self.recording_paths)

    @property
    def truth_path(self) -> Path | None:
        """The digital twin's ``truth/`` folder, or None for a real survey."""
        truth = self.path / TRUTH_DIR
        return truth if truth.is_dir() else None

    @property
    def size_bytes(self) -> int:
        """Bytes of the survey's own files: the recordings, arm_poses.csv and manip_envelope.json."""
        files = [*self.recording_paths.values(), self.arm_poses_path, self.envelope_path]
        return sum(f.stat().st_size for f in files if f is not None)

    def arm_poses(self) -> ArmPoseLog:
        """The joint log (read and validated once, then cached)."""
        if self.arm_poses_path is None:
            raise SurveyError(f"no {ARM_POSES_FILE} in this survey", self.path)
        if self._log is None:
            self._log = read_arm_poses(self.arm_poses_path, known_arms=tuple(self.serials))
        return self._log

    def envelope(self) -> Envelope | None:
        """The envelope, or None when the survey has no manip_envelope.json (see :attr:`notes`)."""
        if self.envelope_path is None:
            return None
        if self._envelope is None:
            self._envelope = read_envelope(self.envelope_path)
        return self._envelope

    def open_recording(self, arm: str) -> Recording:
        """Open ``arm``'s camera recording (index only; pixels are decoded on demand)."""
        if arm not in self.recording_paths:
            have = ", ".join(self.recording_paths) or "none"
            raise SurveyError(f"no recording for arm {arm!r} (recordings for: {have})", self.path)
        recording = open_recording(self.recording_paths[arm])
        serial = getattr(recording.device, "serial", "")
        if serial and serial != self.serials[arm]:
            recording.close()
            raise SurveyError(
                f"recording says camera serial {serial}, but its name says {self.serials[arm]}",
                self.recording_paths[arm],
            )
        return recording


def _check_mapping(path: Path, mapping: dict[str, str], source: Path) -> None:
    """Blame ``source`` (a calibration) for a recorded camera it has no arm for, or for a DARP camera on the
    wrong arm (swapped serials)."""
    arms = ", ".join(f"{a} -> camera {s}" for s, a in mapping.items()) or "none"
    for serial, arm in mapping.items():
        expected = DEFAULT_SERIAL_TO_ARM.get(serial)
        if expected is not None and expected != arm:
            raise SurveyError(f"arms.{arm}.serial: camera {serial} is on {expected} in the DARP rig "
                              "(serials swapped?)", source)
    for entry in sorted(path.iterdir()) if path.is_dir() else []:
        match = _RECORDING_NAME.match(entry.name)
        if match is not None and entry.suffix in RECORDING_SUFFIXES and match["serial"] not in mapping:
            raise SurveyError(f"no arm carries camera {match['serial']} (recorded in {entry}; arms: {arms})",
                              source)


def open_survey(
    path: str | Path,
    serial_to_arm: Mapping[str, str] | None = None,
    *,
    strict: bool = True,
    mapping_source: str | Path | None = None,
) -> Survey:
    """Locate a survey's files and map camera serials to arms.

    ``serial_to_arm`` replaces the default DARP mapping (348522076490 -> arm110, 405622074504 -> arm111);
    ``mapping_source`` is the file it came from (a calibration): a recorded camera it lacks, or a DARP camera
    it puts on the other arm, is that file's error, not the survey's.
    With ``strict`` (the default) an incomplete survey raises :class:`SurveyError` listing every problem;
    otherwise the problems are kept in :attr:`Survey.problems`.
    """
    path = Path(path)
    if not path.exists():
        raise SurveyError("no such survey folder", path)
    if not path.is_dir():
        raise SurveyError("not a folder (a survey is a folder holding cam<serial>.bag files)", path)
    mapping = dict(DEFAULT_SERIAL_TO_ARM if serial_to_arm is None else serial_to_arm)
    if mapping_source is not None:
        _check_mapping(path, mapping, Path(mapping_source))
    arms_expected = list(dict.fromkeys(mapping.values()))
    problems: list[str] = []
    notes: list[str] = []

    found: dict[str, list[Path]] = {}
    unexpected: list[str] = []
    for entry in sorted(path.iterdir()):
        if not entry.is_file() or entry.suffix not in RECORDING_SUFFIXES:
            continue
        match = _RECORDING_NAME.match(entry.name)
        if match is None:
            unexpected.append(entry.name)
        elif match["serial"] not in mapping:
            known = ", ".join(f"{s} -> {a}" for s, a in mapping.items())
            serial = match["serial"]
            problems.append(f"{entry.name}: camera serial {serial} is not mapped to an arm ({known})")
        else:
            found.setdefault(mapping[match["serial"]], []).append(entry)
    if unexpected:
        problems.append(f"unexpected recording(s) {', '.join(unexpected)} (expected cam<serial>.bag or .db3)")

    recording_paths: dict[str, Path] = {}
    serials: dict[str, str] = {}
    for arm in arms_expected:
        files = found.get(arm, [])
        arm_serials = [s for s, a in mapping.items() if a == arm]
        if not files:
            names = " or ".join(f"cam{s}.bag/.db3" for s in arm_serials)
            partial = [f"cam{s}.bag.partial" for s in arm_serials if (path / f"cam{s}.bag.partial").is_file()]
            hint = f"; found {', '.join(partial)}: an interrupted recording" if partial else ""
            problems.append(f"no recording for {arm} (expected {names}{hint})")
        elif len(files) > 1:
            problems.append(f"{len(files)} recordings for {arm}: {', '.join(f.name for f in files)}")
        else:
            recording_paths[arm] = files[0]
            serials[arm] = _RECORDING_NAME.match(files[0].name)["serial"]  # type: ignore[index]
    for arm in arms_expected:  # known arms of the log even when a recording is missing
        serials.setdefault(arm, next(s for s, a in mapping.items() if a == arm))
    serials = {arm: serials[arm] for arm in arms_expected}

    arm_poses = path / ARM_POSES_FILE
    if not arm_poses.is_file():
        problems.append(f"missing {ARM_POSES_FILE}")
    envelope = path / ENVELOPE_FILE
    if not envelope.is_file():
        notes.append(f"no {ENVELOPE_FILE} (object envelope unknown)")

    partial_reason = partial_survey_reason(path)
    if partial_reason is not None:
        notes.append(f"partial survey: {partial_reason}")

    if strict and problems:
        if not found and not arm_poses.is_file() and not unexpected:
            message = f"not a survey folder (no cam<serial>.bag recordings, no {ARM_POSES_FILE})"
            raise SurveyError(message, path)
        raise SurveyError("incomplete survey: " + "; ".join(problems), path)
    return Survey(
        path=path,
        recording_paths=recording_paths,
        serials=serials,
        arm_poses_path=arm_poses if arm_poses.is_file() else None,
        envelope_path=envelope if envelope.is_file() else None,
        problems=tuple(problems),
        notes=tuple(notes),
        partial=partial_reason,
    )


def partial_survey_reason(path: str | Path) -> str | None:
    """Why a survey folder is partial, or None: its ``PARTIAL.txt`` (an interrupted or failed acquisition;
    its first line), its ``REJECTED.txt`` (collect rejected or terminated it; its first line) and any
    ``*.partial`` recordings (never finalised, e.g. after SIGKILL)."""
    path = Path(path)
    reasons = []
    marker = path / PARTIAL_FILE
    if marker.exists():  # whatever it is: a marker that cannot be read (a pipe, a folder) still marks
        first = marker_text(marker).strip().splitlines()
        reasons.append(f"{PARTIAL_FILE} says {first[0]!r}" if first else f"{PARTIAL_FILE} present")
    rejected = path / REJECTED_FILE
    if rejected.exists():  # collect ended the survey early or its verification failed: not a whole survey
        first = marker_text(rejected).strip().splitlines()
        reasons.append(f"{REJECTED_FILE} says {first[0]!r}" if first else f"{REJECTED_FILE} present")
    try:
        leftovers = sorted(p.name for p in path.iterdir() if p.name.endswith(PARTIAL_RECORDING_SUFFIX))
    except OSError:
        leftovers = []
    if leftovers:
        reasons.append(f"unfinalised recording(s) {', '.join(leftovers)}")
    return "; ".join(reasons) if reasons else None


def looks_like_survey(path: str | Path) -> bool:
    """True when ``path`` is a folder holding an arm_poses.csv or a cam<serial> recording."""
    path = Path(path)
    if not path.is_dir():
        return False
    if (path / ARM_POSES_FILE).is_file():
        return True
    return any(_RECORDING_NAME.match(p.name) and p.is_file() for p in path.iterdir())


def find_survey_folders(paths: Iterable[str | Path]) -> list[Path]:
    """Expand the given paths into survey folders: a survey stays itself; a folder that is not a survey
    but holds surveys becomes its survey sub-folders (sorted by name). Anything else is an error."""
    result: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise SurveyError("no such survey folder", path)
        if not path.is_dir():
            raise SurveyError("not a folder (a survey is a folder holding cam<serial>.bag files)", path)
        if looks_like_survey(path):
            result.append(path)
            continue
        children = sorted(child for child in path.iterdir() if looks_like_survey(child))
        if not children:
            raise SurveyError(
                f"not a survey folder and holds no survey folders (no {ARM_POSES_FILE}, no cam<serial>.bag)",
                path,
            )
        result.extend(children)
    return result
