"""Post-capture verification: read the written survey back and check it before accepting it.

Checks (each passes or fails with a reason; ``required`` checks decide acceptance):

- ``files``: both recordings and ``arm_poses.csv`` are there and open;
- ``streams.<arm>``: depth, colour and both infrared streams have frames, equal counts (within
  ``max_count_mismatch``), and a measured rate within ``rate_tolerance`` of the stream profile's;
- ``dropped.<arm>``: frame-number gaps in the depth stream, at most ``max_dropped_fraction``;
- ``log.<arm>``: the joint log's rate and its longest gap (``max_log_gap_s``);
- ``interval.<arm>``: the camera interval (first to last depth timestamp) inside the joint log's
  interval for that arm, so no camera pose needs extrapolation;
- ``views.<arm>``: every planned view reached: a run of log samples within ``view_tolerance_rad`` of
  the view's joints (every joint) lasting at least ``min_settled_s``;
- ``depth.<arm>``: depth validity on the object: for one frame in the middle of each settled view the
  envelope is projected with the frame's pose (eq. 1 from the log and the calibration) and the
  fraction of valid depth pixels inside its silhouette is measured; the median over the views must
  reach ``min_object_valid_fraction``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from darp.acquisition.viewpoints import envelope_points
from darp.errors import DarpError
from darp.formats.arm_poses import ArmPoseLog
from darp.formats.calibration import Calibration
from darp.formats.realsense.recording import Recording
from darp.formats.survey import open_survey
from darp.kinematics.camera_poses import POSED, interpolate_joints
from darp.kinematics.rig import Rig

Array = NDArray[np.float64]
IMAGE_KEYS = ("depth", "color", "ir1", "ir2")


@dataclass(frozen=True)
class VerifySettings:
    """Acceptance thresholds of the verification."""

    rate_tolerance: float = 0.1  # measured frame rate within 10 % of the profile's
    max_count_mismatch: float = 0.02  # streams of one camera differ by at most 2 % in frame count
    max_dropped_fraction: float = 0.01
    min_log_rate_hz: float = 20.0
    max_log_gap_s: float = 0.2
    view_tolerance_rad: float = 0.01
    min_settled_s: float = 0.2
    min_object_valid_fraction: float = 0.4
    clock_offset_s: float = 0.0  # camera time = host time + offset


@dataclass
class Check:
    """One verification check."""

    name: str
    passed: bool
    detail: str
    values: dict[str, Any] = field(default_factory=dict)
    required: bool = True

    def to_record(self) -> dict[str, Any]:
        return {"name": self.name, "passed": self.passed, "required": self.required, "detail": self.detail,
                "values": self.values}


@dataclass
class VerificationReport:
    """Every check; the survey passes when every required check does."""

    folder: Path
    checks: list[Check] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks if c.required)

    @property
    def failures(self) -> list[Check]:
        return [c for c in self.checks if c.required and not c.passed]

    def check(self, name: str) -> Check:
        for c in self.checks:
            if c.name == name:
                return c
        raise KeyError(name)

    def summary(self) -> str:
        if self.passed:
            return f"all {len(self.checks)} checks passed"
        return "; ".join(f"{c.name}: {c.detail}" for c in self.failures)

    def to_record(self) -> dict[str, Any]:
        return {"folder": str(self.folder), "passed": self.passed, "checks": [c.to_record() for c in self.checks]}


def settled_windows(t_s: Array, q_rad: Array, q_view: Array, tolerance_rad: float,
                    min_s: float) -> list[tuple[float, float]]:
    """Time windows (start, end) in which the logged joints stay within ``tolerance_rad`` of ``q_view``
    for at least ``min_s``."""
    near = np.all(np.abs(q_rad - np.asarray(q_view)) <= tolerance_rad, axis=1)
    windows = []
    k, n = 0, len(near)
    while k < n:
        if not near[k]:
            k += 1
            continue
        j = k
        while j + 1 < n and near[j + 1]:
            j += 1
        if t_s[j] - t_s[k] >= min_s:
            windows.append((float(t_s[k]), float(t_s[j])))
        k = j + 1
    return windows


def _stream_checks(arm: str, rec: Recording, s: VerifySettings) -> list[Check]:
    counts = {k: rec.frame_count(k) for k in IMAGE_KEYS if k in rec.streams}
    missing = [k for k in IMAGE_KEYS if counts.get(k, 0) == 0]
    depth = rec.frame_infos("depth") if counts.get("depth") else []
    values: dict[str, Any] = {"counts": counts}
    if missing:
        return [Check(f"streams.{arm}", False, f"no frames in {', '.join(missing)}", values)]
    spread = (max(counts.values()) - min(counts.values())) / max(counts.values())
    stamps = np.array([f.timestamp_ms for f in depth]) / 1e3
    rate = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 and stamps[-1] > stamps[0] else 0.0
    fps = rec.streams["depth"].fps
    values.update(measured_fps=round(float(rate), 3), profile_fps=fps, count_spread=round(float(spread), 4))
    problems = []
    if spread > s.max_count_mismatch:
        problems.append(f"stream frame counts differ by {spread:.1%}")
    if abs(rate - fps) > s.rate_tolerance * fps:
        problems.append(f"depth runs at {rate:.2f} fps, profile says {fps}")
    checks = [Check(f"streams.{arm}", not problems, "; ".join(problems) or
                    f"{counts['depth']} depth frames at {rate:.2f} fps", values)]
    numbers = np.array([f.frame_number for f in depth])
    gaps = np.diff(numbers)
    dropped = int(np.sum(np.clip(gaps - 1, 0, None)))
    total = int(numbers[-1] - numbers[0] + 1) if len(numbers) else 0
    frac = dropped / total if total else 0.0
    checks.append(Check(f"dropped.{arm}", frac <= s.max_dropped_fraction and not np.any(gaps <= 0),
                        f"{dropped} of {total} depth frames dropped" + ("; frame numbers not increasing"
                                                                           if np.any(gaps <= 0) else ""),
                        {"dropped": dropped, "expected": total, "fraction": round(frac, 5)}))
    return checks


def _log_checks(arm: str, log: ArmPoseLog, s: VerifySettings) -> Check:
    t = log.times(arm)
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    rate = (len(t) - 1) / span if span > 0 else 0.0
    gap = float(np.max(np.diff(t))) if len(t) > 1 else float("inf")
    ok = rate >= s.min_log_rate_hz and gap <= s.max_log_gap_s
    return Check(f"log.{arm}", ok, f"{len(t)} rows at {rate:.1f} Hz, longest gap {gap * 1000:.0f} ms",
                 {"rows": len(t), "rate_hz": round(rate, 3), "max_gap_s": round(gap, 4)})


def _project_mask(shape: tuple[int, int], intr: Any, T_world_cam: Array, pts_world: Array) -> Array | None:
    import cv2

    T_cam_world = np.linalg.inv(T_world_cam)
    pc = pts_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    if np.any(pc[:, 2] <= 0.05):
        return None
    u = intr.fx * pc[:, 0] / pc[:, 2] + intr.ppx
    v = intr.fy * pc[:, 1] / pc[:, 2] + intr.ppy
    hull = cv2.convexHull(np.round(np.column_stack([u, v])).astype(np.int32))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def verify_survey(folder: str | Path, rig: Rig, *, planned_views: Mapping[str, Array],
                  envelope: tuple[Array, float, float] | None, calibration: Calibration | None = None,
                  settings: VerifySettings | None = None) -> VerificationReport:
    """Verify a written survey folder against the planned views and the object envelope
    (``(centre, radius, height)``; None skips the depth check)."""
    s = settings if settings is not None else VerifySettings()
    report = VerificationReport(Path(folder))
    try:
        survey = open_survey(folder)
        log = survey.arm_poses()
    except DarpError as err:
        report.checks.append(Check("files", False, str(err)))
        return report
    report.checks.append(Check("files", True, f"recordings for {', '.join(survey.arms)}, {log.n_rows} log rows"))
    for arm in survey.arms:
        try:
            rec = survey.open_recording(arm)
        except DarpError as err:
            report.checks.append(Check(f"streams.{arm}", False, str(err)))
            continue
        with rec:
            report.checks.extend(_stream_checks(arm, rec, s))
            if arm not in log.arms:
                report.checks.append(Check(f"log.{arm}", False, "no rows for this arm in arm_poses.csv"))
                continue
            report.checks.append(_log_checks(arm, log, s))
            t_log, q_log = log.times(arm), log.joints(arm)
            depth = rec.frame_infos("depth")
            if not depth:
                continue
            cam_t = np.array([f.timestamp_ms for f in depth]) / 1e3 - s.clock_offset_s
            inside = bool(cam_t[0] >= t_log[0] and cam_t[-1] <= t_log[-1])
            report.checks.append(Check(
                f"interval.{arm}", inside,
                f"camera {cam_t[0] - t_log[0]:+.2f} s .. {cam_t[-1] - t_log[-1]:+.2f} s relative to the log's "
                f"first and last rows" + ("" if inside else ": the camera interval leaves the log interval"),
                {"camera_s": [float(cam_t[0]), float(cam_t[-1])], "log_s": [float(t_log[0]), float(t_log[-1])]}))
            views = np.asarray(planned_views.get(arm, np.zeros((0, 6))), dtype=float).reshape(-1, 6)
            windows = [settled_windows(t_log, q_log, q, s.view_tolerance_rad, s.min_settled_s) for q in views]
            reached = [bool(w) for w in windows]
            report.checks.append(Check(
                f"views.{arm}", all(reached),
                f"{sum(reached)} of {len(views)} planned views reached and settled"
                + ("" if all(reached) else f" (missed: {[i for i, r in enumerate(reached) if not r]})"),
                {"planned": len(views), "reached": int(sum(reached))}))
            if envelope is not None:
                report.checks.append(_depth_check(arm, rec, rig, calibration, t_log, q_log, cam_t, windows,
                                                  envelope, s))
    return report


def _depth_check(arm: str, rec: Recording, rig: Rig, calibration: Calibration | None, t_log: Array, q_log: Array,
                 cam_t: Array, windows: list[list[tuple[float, float]]], envelope: tuple[Array, float, float],
                 s: VerifySettings) -> Check:
    centre, radius, height = envelope
    pts = envelope_points(np.asarray(centre, float), radius, height, rig.table.height_m, n=24)
    intr = rec.stream("depth").intrinsics
    fractions = []
    for view_windows in windows:
        if not view_windows:
            continue
        t0, t1 = view_windows[0]
        k = int(np.argmin(np.abs(cam_t - 0.5 * (t0 + t1))))
        interp = interpolate_joints(t_log, q_log, cam_t[k:k + 1])
        if interp.status[0] != POSED:
            continue
        T_world_cam = rig.T_world_cam(arm, interp.q_rad[0], calibration=calibration)
        frame = rec.read_frame("depth", k)
        mask = _project_mask(frame.data.shape[:2], intr, T_world_cam, pts)
        if mask is None or not mask.any():
            continue
        fractions.append(float(np.mean(frame.data[mask] > 0)))
    if not fractions:
        return Check(f"depth.{arm}", False, "no settled frame shows the object envelope", {"views": 0})
    median = float(np.median(fractions))
    return Check(f"depth.{arm}", median >= s.min_object_valid_fraction,
                 f"{median:.0%} valid depth inside the envelope (median of {len(fractions)} views; "
                 f"minimum {s.min_object_valid_fraction:.0%})",
                 {"median": round(median, 4), "per_view": [round(f, 4) for f in fractions]})


__all__ = ["Check", "VerificationReport", "VerifySettings", "settled_windows", "verify_survey"]
