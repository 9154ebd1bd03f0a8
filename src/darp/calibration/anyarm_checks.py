"""The any-arm hand-eye's checks of the data: why a board was not detected, whether captures are paired with
the right poses, and which captures place the board far from the others (docs/any-arm.md, "What each
hand-eye error means")."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from darp.formats.io_input import decode_image
from darp.formats.pairing import natural_key
from darp.kinematics.transforms import invert_transform

if TYPE_CHECKING:
    from darp.calibration.anyarm import GenericDetection
    from darp.calibration.board import Board
    from darp.calibration.model import Observations
    from darp.formats.captures import CaptureFolder


def marker_diagnosis(board: Board, image: str) -> str:
    """Why OpenCV's ChArUco detection kept no corner although markers are visible: ``""`` when no marker of the
    board's dictionary is seen, else the markers found and the real reason (a duplicated marker id, markers of
    ids the board does not have), as a suffix for the rejection reason."""
    grey = decode_image(image, cv2.IMREAD_GRAYSCALE, "a board image")
    if grey is None:
        return ""
    params = cv2.aruco.DetectorParameters()
    dictionary = board.cv_charuco().getDictionary()
    _, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(grey)
    if ids is None or len(ids) == 0:
        return ": no marker of the board's dictionary is seen"
    ids = ids.reshape(-1)
    uniq, counts = np.unique(ids, return_counts=True)
    dup = uniq[counts > 1]
    n_board = len(board.cv_charuco().getIds())
    foreign = uniq[uniq >= n_board]
    if len(dup):
        return (f": OpenCV finds {len(ids)} markers but marker id {int(dup[0])} appears {int(counts[counts > 1][0])} "
                "times (a second board, a reflection or a printed duplicate), and its ChArUco board check then "
                "drops the board; cover or remove the duplicate")
    if len(foreign):
        return (f": OpenCV finds {len(ids)} markers, {len(foreign)} with ids this board does not have (e.g. "
                f"{int(foreign[0])}): check the board's size and dictionary in handeye.yaml")
    return (f": OpenCV finds {len(ids)} markers but interpolates no ChArUco corner from them: check squares_x / "
            "squares_y (their order), the marker size and `legacy`")


def check_capture_pairing(folder: CaptureFolder[Board], obs: Observations, arm: str, force: bool = False
                          ) -> tuple[dict[str, float], str | None]:
    """The pairing check of one arm's captures: the boards' disagreement (median mm, after a PARK solve) as
    paired and with every image paired with its neighbour's pose (shifted by one either way).

    Raise :func:`darp.formats.pairing.judge_alternatives`' one-line error when a shift agrees much better
    (with ``force``: return its text as a warning); also with the other quaternion order when the poses were
    quaternions (any table form; a CSV's is also :func:`darp.calibration.diagnose.check_pose_conventions`'
    part, which checks the inversions)."""
    from darp.calibration.diagnose import consistency_mm
    from darp.formats.pairing import judge_alternatives

    sel = np.flatnonzero(obs.for_arm(arm))
    ids = [obs.capture_ids[i].split("/")[-1] for i in sel]
    order = sel[sorted(range(len(sel)), key=lambda j: natural_key(ids[j]))]
    F, B = np.asarray(obs.T_base_flange)[order], obs.T_depth_board_pnp[order]
    scores = {"as given": consistency_mm(F, B), "shift+1": consistency_mm(F[1:], B[:-1]),
              "shift-1": consistency_mm(F[:-1], B[1:])}
    caps = next(a for a in folder.arms if a.arm == arm)
    if caps.swapped is not None and all(i in caps.swapped for i in ids):  # quaternions, any table form
        Fq = np.array([caps.swapped[ids[j]] for j in sorted(range(len(sel)), key=lambda j: natural_key(ids[j]))])
        scores["quaternion order"] = consistency_mm(invert_transform(Fq) if folder.eye_to_hand else Fq, B)
    source = caps.pose_source
    return scores, judge_alternatives(scores, source or folder.root, "back-projected boards", force=force)


def disagreeing_captures(obs: Observations, dets: list[GenericDetection], centre_mm: np.ndarray,
                         factor: float = 5.0, floor_mm: float = 10.0) -> list[str]:
    """A warning naming the captures whose board, placed in the base, lies far from the others' (more than
    ``factor`` x the median and ``floor_mm``): a bad pose, a wrong pairing or a bad detection there."""
    med = float(np.median(centre_mm))
    bad = [i for i in np.argsort(-centre_mm) if centre_mm[i] > max(factor * med, floor_mm)]
    if not bad:
        return []
    src = {(f"{d.arm}/{d.capture_id}" if len(obs.arms) > 1 else d.capture_id): d.source for d in dets if d.ok}
    names = ", ".join(f"{Path(src.get(obs.capture_ids[i], obs.capture_ids[i])).name} ({centre_mm[i]:.1f} mm)"
                      for i in bad[:5])
    return [f"{len(bad)} capture(s) place the board far from the others (median {med:.2f} mm): {names}; check "
            "those captures' poses, pairing and detection"]


__all__ = ["check_capture_pairing", "disagreeing_captures", "marker_diagnosis"]
