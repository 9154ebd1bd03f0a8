"""Camera trajectories at every frame for the exports: darp's own (``poses/`` of a processed survey) and the
twin's true one (``truth/camera_poses_<arm>.npz`` of the raw survey), on the host clock."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from darp.dataset import ProcessedSurvey
from darp.errors import FormatError
from darp.formats.io_input import LIMITS, npz_input
from darp.formats.text import read_utf8_text
from darp.formats.truth import read_camera_poses

POSES_DIR = "poses"  # darp process's eq. 1 poses of every frame (darp.reconstruction.poses)


def estimated_poses(survey: ProcessedSurvey, arm: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(host times (N,), T_world_cam (N, 4, 4)) of every posed frame of ``arm`` as processing posed them
    (eq. 1 with its calibration, or the twin's truth for ``--truth-poses``); None without ``poses/``."""
    folder = survey.folder / POSES_DIR
    files = sorted(folder.glob(f"*_{arm}.npz"))
    if not files:
        return None
    try:
        summary = json.loads(read_utf8_text(folder / "summary.json", "a JSON file", limit=LIMITS["json"]))
        offset_s = float(summary.get("clock_offset_s", 0.0))
        with npz_input(files[0], "a poses .npz") as data:
            t_s = np.asarray(data["timestamps_ms"], np.float64) / 1000.0 - offset_s
            T = np.asarray(data["T_world_cam"], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise FormatError(f"cannot read darp's poses: {err}", files[0]) from err
    posed = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    return t_s[posed], T[posed]


def true_poses(survey: ProcessedSurvey, arm: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(host times, T_world_cam) of every frame from the twin's truth; None for a survey without it."""
    truth = survey.truth_dir
    path = None if truth is None else Path(truth) / f"camera_poses_{arm}.npz"
    if path is None or not path.is_file():
        return None
    arrays = read_camera_poses(path)
    return np.asarray(arrays["t_host_s"], np.float64), np.asarray(arrays["T_world_cam"], np.float64)


__all__ = ["POSES_DIR", "estimated_poses", "true_poses"]
