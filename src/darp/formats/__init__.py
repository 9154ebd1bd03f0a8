"""darp.formats: the on-disk contracts. It reads and writes files, validates them, and raises
:class:`darp.errors.FormatError` subclasses that name the file and the problem; it knows nothing about robots.

The survey folder (:mod:`.survey`) with its joint log (:mod:`.arm_poses`), envelope (:mod:`.envelope`) and
RealSense recordings (:mod:`.realsense`); the calibration file (:mod:`.calibration`); the twin's ``truth/`` folder
(:mod:`.truth`); camera trajectories (:mod:`.trajectories`), intrinsics files (:mod:`.intrinsics`), per-capture
pose files (:mod:`.poses`), pose tables (:mod:`.pose_tables`), hand-eye files (:mod:`.hand_eye`), the pairing of
files with poses (:mod:`.pairing`) and the any-arm captures folder (:mod:`.captures`); and what they share:
atomic writes (:mod:`.atomic`), the one input-opening path (:mod:`.io_input`) and output path with its locks and
unfinished marks (:mod:`.io_output`), text and YAML reading (:mod:`.text`), JSON schema helpers (:mod:`.schema`) and
value ranges (:mod:`.limits`).
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".survey": ("Survey", "open_survey", "find_survey_folders"),
    ".arm_poses": ("ArmPoseLog", "ArmPoseWriter", "read_arm_poses"),
    ".envelope": ("Envelope", "read_envelope", "write_envelope"),
    ".calibration": ("ArmCalibration", "Calibration", "read_calibration", "write_calibration"),
    ".trajectories": ("read_trajectory", "read_tum", "write_tum"),
    ".atomic": ("atomic_path", "write_json_atomic", "write_text_atomic"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.formats.arm_poses import ArmPoseLog, ArmPoseWriter, read_arm_poses
    from darp.formats.atomic import atomic_path, write_json_atomic, write_text_atomic
    from darp.formats.calibration import ArmCalibration, Calibration, read_calibration, write_calibration
    from darp.formats.envelope import Envelope, read_envelope, write_envelope
    from darp.formats.survey import Survey, find_survey_folders, open_survey
    from darp.formats.trajectories import read_trajectory, read_tum, write_tum

__all__ = [
    "ArmCalibration",
    "ArmPoseLog",
    "ArmPoseWriter",
    "Calibration",
    "Envelope",
    "Survey",
    "atomic_path",
    "find_survey_folders",
    "open_survey",
    "read_arm_poses",
    "read_calibration",
    "read_envelope",
    "read_trajectory",
    "read_tum",
    "write_calibration",
    "write_envelope",
    "write_json_atomic",
    "write_text_atomic",
    "write_tum",
]
