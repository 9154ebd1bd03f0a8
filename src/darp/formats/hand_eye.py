"""A known hand-eye transform (flange-from-camera, ``T_wrist_cam``) in the forms other tools write it.

:func:`read_hand_eye` reads, for ``darp import --hand-eye FILE``:

- **easy_handeye** YAML (``eye_on_hand: true``, ``transformation: {x, y, z, qx, qy, qz, qw}``, metres; the
  transform of ``tracking_base_frame`` in ``robot_effector_frame``);
- **MoveIt Calibration** launch file (a ``static_transform_publisher`` whose ``args`` are
  ``x y z qx qy qz qw parent child`` or ``x y z yaw pitch roll parent child``);
- a ``geometry_msgs`` ``Transform``/``Pose`` in YAML or JSON (``translation``/``position`` +
  ``rotation``/``orientation`` with ``x y z w``), optionally under ``transform``/``transformation``;
- a bare 4x4 (or 3x4): text (whitespace/commas), ``.npy``, or JSON (a nested list, or under ``T_wrist_cam``,
  ``T_flange_cam``, ``matrix``, ``transform``); its translation is in ``unit`` (``--hand-eye-unit``);
- darp's own calibration JSON (``darp calib handeye``'s output: the named arm's ``T_wrist_cam``).

The camera frame must be the **optical** frame (x right, y down, z forward). When a ROS file names a camera
frame that is not an optical frame (``camera_link``: x forward), the reader says so in ``notes`` and the
import's pairing check also tries the ROS body-to-optical rotation. The transform must be rigid by
:mod:`darp.geometry.rigid`'s rule (a slightly off rotation is re-orthonormalised with a warning).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.poses import PoseConventions, quat_pose, read_matrix_file
from darp.formats.text import read_utf8_text
from darp.geometry.rigid import orthonormalised, warn_orthonormalised

MAX_HAND_EYE_M = 1.0  # a camera further than this from the flange: the unit is wrong
# ROS body frame (x forward, y left, z up) -> optical frame (x right, y down, z forward)
T_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


@dataclass
class HandEye:
    """A hand-eye read from a file: flange-from-camera (metres) and what the file said about it."""

    T_wrist_cam: np.ndarray
    source: Path
    form: str
    camera_frame: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def optical(self) -> bool:
        """False when the file names a camera frame that is not an optical one (a ROS body frame)."""
        return not self.camera_frame or "optical" in self.camera_frame.lower()


def _xyzq(d: dict[str, Any]) -> np.ndarray | None:
    if all(k in d for k in ("x", "y", "z", "qx", "qy", "qz", "qw")):
        return quat_pose([d[k] for k in ("x", "y", "z", "qx", "qy", "qz", "qw")], PoseConventions())
    pos = d.get("translation", d.get("position"))
    rot = d.get("rotation", d.get("orientation"))
    if isinstance(pos, dict) and isinstance(rot, dict) and all(k in rot for k in "xyzw"):
        return quat_pose([pos["x"], pos["y"], pos["z"], rot["x"], rot["y"], rot["z"], rot["w"]], PoseConventions())
    return None


def _from_mapping(d: dict[str, Any], unit: str, path: Path, arm: str) -> HandEye:
    if "arms" in d and isinstance(d["arms"], dict):  # darp's calibration JSON
        from darp.formats.calibration import read_calibration

        cal = read_calibration(path)
        name = arm or next(iter(cal.arms))
        if name not in cal.arms:
            raise FormatError(f"arm {name!r} is not in this calibration (has {', '.join(cal.arms)}); give --arm", path)
        return HandEye(cal.arms[name].T_wrist_cam.copy(), path, "darp calibration", "optical")
    if d.get("eye_on_hand") is False:
        raise FormatError("easy_handeye eye_on_hand: false (an eye-to-hand calibration: the camera is fixed); "
                          "darp import needs the camera on the flange", path)
    for k in ("transformation", "transform", "T_wrist_cam", "T_flange_cam", "T_tool_cam", "hand_eye", "matrix",
              "pose"):
        if k in d:
            inner = d[k]
            frame = str(d.get("tracking_base_frame", d.get("child_frame_id", "")))
            if isinstance(inner, dict):
                T = _xyzq(inner)
                if T is not None:
                    form = "easy_handeye YAML" if "tracking_base_frame" in d else "Transform/Pose mapping"
                    return HandEye(T, path, form, frame)
            else:
                M = np.asarray(inner, np.float64)
                M = M.reshape(4, 4) if M.size == 16 else M
                return HandEye(_scaled(M, unit), path, "4x4 matrix", frame)
    T = _xyzq(d)
    if T is not None:
        return HandEye(T, path, "Transform/Pose mapping", str(d.get("child_frame_id", "")))
    raise FormatError("no hand-eye found: expected easy_handeye's 'transformation', a Transform/Pose "
                      "(translation + rotation), a 4x4 under 'T_wrist_cam', or darp's calibration JSON", path)


def _scaled(M: np.ndarray, unit: str) -> np.ndarray:
    M = np.array(M, np.float64)
    if M.shape == (3, 4):
        M = np.vstack([M, [0, 0, 0, 1]])
    if M.shape == (4, 4):
        M[:3, 3] *= 1e-3 if unit == "mm" else 1.0
    return M


def _from_launch(text: str, path: Path) -> HandEye:
    m = re.search(r'args\s*=\s*"([^"]+)"', text)
    if m is None:
        raise FormatError("no static_transform_publisher args in this launch file", path)
    parts = m.group(1).split()
    nums = []
    for p in parts:
        try:
            nums.append(float(p))
        except ValueError:
            break
    frames = parts[len(nums):len(nums) + 2]
    if len(nums) == 7:
        T = quat_pose(nums, PoseConventions())
    elif len(nums) == 6:
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("ZYX", nums[3:6]).as_matrix()  # tf's yaw pitch roll
        T[:3, 3] = nums[:3]
    else:
        raise FormatError(f"static_transform_publisher args have {len(nums)} numbers; expected 7 (x y z qx qy qz qw) "
                          "or 6 (x y z yaw pitch roll)", path)
    return HandEye(T, path, "MoveIt Calibration launch file", frames[1] if len(frames) > 1 else "")


def read_hand_eye(path: str | Path, unit: str = "m", arm: str = "") -> HandEye:
    """Flange-from-camera from any supported file (module docstring); ``unit`` for bare matrices."""
    p = Path(path)
    if not p.is_file():
        raise FormatError("hand-eye file not found", p)
    text = "" if p.suffix == ".npy" else read_utf8_text(p, "a hand-eye file")
    try:
        if p.suffix == ".npy" or (p.suffix == ".txt" and not text.lstrip().startswith("{")):
            he = HandEye(_scaled(read_matrix_file(p), unit), p, "4x4 matrix")
        elif p.suffix in (".launch", ".xml"):
            he = _from_launch(text, p)
        else:
            if p.suffix == ".json":
                d = json.loads(text)
            else:
                from darp.formats.text import read_yaml_mapping

                d = read_yaml_mapping(p)
            if isinstance(d, list):
                he = HandEye(_scaled(np.asarray(d, np.float64), unit), p, "4x4 matrix")
            else:
                he = _from_mapping(d, unit, p, arm)
    except (ValueError, KeyError, TypeError) as err:
        raise FormatError(f"cannot read the hand-eye ({type(err).__name__}: {err})", p) from None
    T, off = orthonormalised(he.T_wrist_cam, "hand-eye", p, error=FormatError)
    warn_orthonormalised([off], p, "hand-eye")
    he.T_wrist_cam = T
    dist = float(np.linalg.norm(T[:3, 3]))
    if dist > MAX_HAND_EYE_M:
        raise FormatError(f"the camera is {dist:.3g} m from the flange: the translation looks like millimetres; "
                          "give --hand-eye-unit mm", p)
    if not he.optical:
        he.notes.append(f"camera frame {he.camera_frame!r} is not an optical frame: darp needs the optical frame "
                        "(x right, y down, z forward); the pairing check also tries the ROS body-to-optical rotation")
    return he


__all__ = ["MAX_HAND_EYE_M", "T_BODY_OPTICAL", "HandEye", "read_hand_eye"]
