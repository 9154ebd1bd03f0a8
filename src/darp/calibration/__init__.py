"""darp.calibration: ChArUco calibration of the dual-arm rig, and hand-eye for any arm (docs/calibration.md).

The board (:mod:`.board`: spec, OpenCV board, printable PDF); capture plans (:mod:`.plan`, extended for
identifiability by :mod:`.plan_model`), taking them (:mod:`.capture_run`) and the capture folder
(:mod:`.captures`); corners and board poses (:mod:`.detect`); OpenCV hand-eye per arm (:mod:`.handeye`); the joint
refinement's model, Jacobian and solver with identifiability and uncertainty (:mod:`.model`, :mod:`.jacobian`,
:mod:`.refine`, pose helpers in :mod:`.geometry`), kinematic identifiability (:mod:`.kinematic_ident`), depth
corrections from the board (:mod:`.depth_fit`); the world frame (:mod:`.world_frame`); the driver
(:mod:`.solve`); held-out and truth errors (:mod:`.evaluate`); figures (:mod:`.report`); staleness
(:mod:`.check`). Any arm: hand-eye from measured flange poses (:mod:`.anyarm`, its refinement in
:mod:`.anyarm_refine`, held-out split and scores in :mod:`.anyarm_heldout`, its report and exports in
:mod:`.anyarm_report` and :mod:`.anyarm_export`, checks of the data in :mod:`.anyarm_checks` and
:mod:`.diagnose`). OpenCV loads only when a board is built or detected.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".board": ("Board", "make_board_spec", "parse_board"),
    ".plan": ("CapturePlan", "PlanSettings", "plan_captures"),
    ".capture_run": ("CaptureRunSettings", "run_capture_plan"),
    ".captures": ("CaptureSet", "CaptureWriter", "read_captures"),
    ".detect": ("Detection", "DetectionSettings", "detect_captures"),
    ".handeye": ("HandEyeEstimate", "opencv_hand_eye"),
    ".solve": ("SolveOutcome", "SolveSettings", "solve_captures", "to_calibration"),
    ".world_frame": ("canonical_world",),
    ".evaluate": ("kfold_heldout", "truth_errors"),
    ".check": ("CheckResult", "CheckSettings", "check_calibration"),
    ".report": ("write_report",),
    ".depth_fit": ("estimate_depth_corrections",),
    ".kinematic_ident": ("analyse_kinematics",),
    ".anyarm": ("HandEyeOutcome", "solve_folder"),
    ".diagnose": ("check_pose_conventions",),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.calibration.anyarm import HandEyeOutcome, solve_folder
    from darp.calibration.board import Board, make_board_spec, parse_board
    from darp.calibration.capture_run import CaptureRunSettings, run_capture_plan
    from darp.calibration.captures import CaptureSet, CaptureWriter, read_captures
    from darp.calibration.check import CheckResult, CheckSettings, check_calibration
    from darp.calibration.depth_fit import estimate_depth_corrections
    from darp.calibration.detect import Detection, DetectionSettings, detect_captures
    from darp.calibration.diagnose import check_pose_conventions
    from darp.calibration.evaluate import kfold_heldout, truth_errors
    from darp.calibration.handeye import HandEyeEstimate, opencv_hand_eye
    from darp.calibration.kinematic_ident import analyse_kinematics
    from darp.calibration.plan import CapturePlan, PlanSettings, plan_captures
    from darp.calibration.report import write_report
    from darp.calibration.solve import SolveOutcome, SolveSettings, solve_captures, to_calibration
    from darp.calibration.world_frame import canonical_world

__all__ = [
    "Board",
    "CapturePlan",
    "CaptureRunSettings",
    "CaptureSet",
    "CaptureWriter",
    "CheckResult",
    "CheckSettings",
    "Detection",
    "DetectionSettings",
    "HandEyeEstimate",
    "HandEyeOutcome",
    "PlanSettings",
    "SolveOutcome",
    "SolveSettings",
    "analyse_kinematics",
    "canonical_world",
    "check_calibration",
    "check_pose_conventions",
    "detect_captures",
    "estimate_depth_corrections",
    "kfold_heldout",
    "make_board_spec",
    "opencv_hand_eye",
    "parse_board",
    "plan_captures",
    "read_captures",
    "run_capture_plan",
    "solve_captures",
    "solve_folder",
    "to_calibration",
    "truth_errors",
    "write_report",
]
