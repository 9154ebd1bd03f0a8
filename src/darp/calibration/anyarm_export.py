"""A darp capture folder (twin or Z1) written as a generic any-arm captures folder.

Each arm becomes a sub-folder with its images (copied byte for byte), ``poses/<n>.txt`` (the Z1
model's base-from-flange pose at the logged joints, metres, 17 significant digits) and
``intrinsics.json`` (the capture stream's K and Brown-Conrady coefficients); ``handeye.yaml`` at the
top declares the board. Solving it with :func:`darp.calibration.anyarm.solve_folder` gives the
hand-eye of the *image stream*; darp's own solve gives it for the depth frame, so the two compare as
``X_depth @ T_depth_stream``. With joint offsets held at zero (a generic arm has no joint model) the
two solves are the same problem and agree to numerical precision (tests/test_anyarm_calibration.py).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from darp.calibration.captures import CaptureSet
from darp.errors import CalibrationError
from darp.formats.atomic import write_text_atomic
from darp.kinematics import z1


def export_captures(captures: CaptureSet, out: str | Path, wrist_frame: str = "flange") -> int:
    """Write ``captures`` as a generic folder at ``out``; returns the number of captures written."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise CalibrationError("output folder exists and is not empty", out)
    b = captures.board
    write_text_atomic(out / "handeye.yaml", (
        f"# exported from {captures.folder} by darp calib export\n"
        f"board: {{type: charuco, squares_x: {b.squares_x}, squares_y: {b.squares_y}, "
        f"square_mm: {b.square_length_m * 1e3!r}, marker_mm: {b.marker_length_m * 1e3!r}, "
        f"dictionary: {b.dictionary}}}\nunit: m\nmode: eye_in_hand\n"))
    n = 0
    for arm in captures.arms:
        recs = captures.for_arm(arm)
        if not recs:
            continue
        folder = out / arm
        (folder / "images").mkdir(parents=True, exist_ok=True)
        (folder / "poses").mkdir(exist_ok=True)
        intr = recs[0].intrinsics
        if intr.model != "Brown Conrady" and any(intr.coeffs):
            raise CalibrationError(f"{arm}: distortion model {intr.model!r} has no OpenCV equivalent", captures.folder)
        write_text_atomic(folder / "intrinsics.json", json.dumps(
            {"K": intr.K.tolist(), "dist": list(intr.coeffs), "width": intr.width, "height": intr.height}) + "\n")
        T_depth_stream = recs[0].T_depth_stream
        write_text_atomic(folder / "T_depth_stream.txt", _matrix_text(T_depth_stream))
        for k, rec in enumerate(recs):
            src = captures.image_path(rec)
            shutil.copyfile(src, folder / "images" / f"{k:04d}{src.suffix}")
            T = z1.fk(np.asarray(rec.q_rad, float), wrist_frame)
            write_text_atomic(folder / "poses" / f"{k:04d}.txt", _matrix_text(T))
            n += 1
    return n


def _matrix_text(T: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.17g}" for v in row) for row in np.asarray(T)) + "\n"


__all__ = ["export_captures"]
