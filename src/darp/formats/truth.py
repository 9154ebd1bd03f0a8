"""The ``truth/`` folder a twin survey carries beside the DARP files: its layout and the readers the
processing pipeline needs (camera poses). Written by :mod:`darp.twin.truth`; processing and evaluation
read it from here, so they depend on the file contract, not on the simulator."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from darp.errors import FormatError
from darp.formats.atomic import atomic_path
from darp.formats.io_input import npz_input

TRUTH_DIR = "truth"
CALIBRATION_FILE = "calibration.json"
OBJECT_MESH_FILE = "object.ply"
OBJECT_JSON_FILE = "object.json"
SETTINGS_FILE = "settings.yaml"
README_FILE = "README.txt"
POSE_ARRAYS = ("frame_number", "timestamp_ms", "t_host_s", "T_world_cam", "q_true_rad")

README_TEXT = """darp digital twin: ground truth of this survey (not part of the DARP survey format).

calibration.json        the TRUE calibration in darp's calibration format (schema 1): per arm the true
                        T_world_base, the true hand-eye T_wrist_cam (wrist = Z1 flange, camera = depth /
                        left-IR optical frame) and the true joint-zero offsets with eq. 1's convention
                        q_true = q_logged + joint_offsets_rad. Recovering camera poses with eq. 1 from
                        arm_poses.csv and this file reproduces camera_poses_<arm>.npz up to encoder noise
                        and the linear interpolation of the joint log.
object.ply              the object's true surface, world frame, metres.
object.json             object name, T_world_object, placement (x_m, y_m, yaw_rad), scale, centre/radius/height.
camera_poses_<arm>.npz  per recorded depth frame of that arm's camera: frame_number, timestamp_ms (as in
                        the bag, host clock plus any simulated clock offset), t_host_s (true exposure time
                        on the host clock), T_world_cam (N, 4, 4) and the true joint angles q_true_rad (N, 6).
settings.yaml           the twin settings: profile, seed and every error magnitude (darp twin docs).
contacts.json           contacts the collision monitor saw during the recording (empty: none).
"""


def save_npz_deterministic(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez``-compatible archive with fixed zip timestamps (byte-identical for equal arrays)."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.ascontiguousarray(array), allow_pickle=False)
            zf.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), buffer.getvalue())


def read_camera_poses(path: str | Path) -> dict[str, np.ndarray]:
    """Arrays of ``truth/camera_poses_<arm>.npz`` (see :data:`POSE_ARRAYS`)."""
    path = Path(path)
    try:
        with npz_input(path, "a camera poses .npz") as data:
            arrays = {name: data[name] for name in data.files}
    except FileNotFoundError:
        raise FormatError("no such file", path) from None
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise FormatError(f"not a readable .npz archive: {err}", path) from err
    missing = [name for name in POSE_ARRAYS if name not in arrays]
    if missing:
        raise FormatError(f"missing array(s) {', '.join(missing)}", path)
    return arrays


__all__ = [
    "CALIBRATION_FILE",
    "OBJECT_JSON_FILE",
    "OBJECT_MESH_FILE",
    "POSE_ARRAYS",
    "README_FILE",
    "README_TEXT",
    "SETTINGS_FILE",
    "TRUTH_DIR",
    "read_camera_poses",
    "save_npz_deterministic",
]
