"""Diagnostics: why a survey failed or looks wrong, in one line that names the input to blame.

:func:`no_keyframe_error` explains an empty keyframe selection per arm (no frame inside the joint log,
joint values outside the Z1's range, nothing settled, the envelope centre never in view);
:func:`low_floor_hint` adds to an empty fusion when the crop's floor cut most of a low object; and
:func:`plausibility_warnings` lists what is implausible in a completed survey's results (``results.json``
``warnings``: empty arm clouds, too few keyframes, an almost empty fused cloud, held-out or truth figures
beyond their bounds, a partial survey).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import ReconstructionError
from darp.processing.job import SurveyJob
from darp.reconstruction.crop import EnvelopeCrop


def no_keyframe_error(job: SurveyJob, selections: dict[str, Any]) -> ReconstructionError:
    """Why no keyframe was selected, blaming the input that explains it (joint log, envelope, ...)."""
    survey = job.survey
    log_file = survey.arm_poses_path or survey.path
    env_file = survey.envelope_path or survey.path
    parts = []
    blame: Path = survey.path
    for arm, sel in selections.items():
        c = sel.counts
        traj = job.poses().trajectories[arm]
        if c.get("posed", 0) == 0:
            span = traj.camera_span_s
            cam = "no frames" if span is None else f"camera frames {span[0]:.3f} .. {span[1]:.3f} s"
            parts.append(f"{arm}: none of {c.get('frames', 0)} frames lies inside the joint log (log "
                         f"{traj.log_span_s[0]:.3f} .. {traj.log_span_s[1]:.3f} s, {cam}; time_s must be host-clock "
                         "seconds, increasing)")
            blame = log_file
        elif outside_range(traj.poses.q_rad[traj.poses.posed]) > 0.5:
            q = traj.poses.q_rad[traj.poses.posed]
            parts.append(f"{arm}: the joint log's values (up to {float(np.nanmax(np.abs(q))):.3g} rad) are outside "
                         "the Z1's joint range in most frames (radians expected)")
            blame = log_file
        elif c.get("settled", 0) == 0:
            parts.append(f"{arm}: of {c['posed']} posed frames none is settled (stillness threshold "
                         f"{sel.still_threshold_rad_s:.3f} rad/s, measured joint-speed noise "
                         f"{sel.speed_noise_rad_s:.3f} rad/s)")
            blame = log_file
        elif c.get("in_view", 0) == 0:
            centre = job.envelope().center_m
            where = "unknown" if centre is None else "(" + ", ".join(f"{1000 * v:.0f}" for v in centre) + ") mm"
            parts.append(f"{arm}: {c['settled']} settled frames but none sees the envelope centre {where}")
            if blame == survey.path:
                blame = env_file if job.envelope_record().get("source") != "estimated" else survey.path
        else:
            parts.append(f"{arm}: {c.get('in_view', 0)} frames in view gave no keyframe")
    detail = "; ".join(parts) or "the survey has no arm"
    return ReconstructionError(f"no keyframe selected: {detail}", blame)


def outside_range(q_rad: np.ndarray, tol_rad: float = 0.2) -> float:
    """Share of the rows of ``q_rad`` (N, 6) outside the Z1's joint limits (by more than ``tol_rad``)."""
    from darp.kinematics.z1 import within_limits

    q = np.asarray(q_rad, np.float64).reshape(-1, 6)
    if q.size == 0:
        return 0.0
    inside = np.asarray(within_limits(np.nan_to_num(q, nan=0.0, posinf=1e9, neginf=-1e9), tol_rad=tol_rad))
    return float(1.0 - inside.mean())


def low_floor_hint(crop: EnvelopeCrop) -> str:
    """When the crop's floor (its table margin, which grows with the calibration's stated error) cuts at least
    half of the object's height, the reason an empty fusion gives (one clause, '' otherwise)."""
    if crop.table_margin_m < 0.5 * crop.height_m:
        return ""
    return (f"; the crop keeps only points {crop.table_margin_m * 1000:.0f} mm above the table (it grows with the "
            f"calibration's held-out error), {100 * crop.table_margin_m / crop.height_m:.0f} % of the object's "
            f"{crop.height_m * 1000:.0f} mm height: a better calibration, or --corrections table, is needed for "
            "an object this low")




RESULTS_FILE = "results.json"
SCHEMA = "darp-results/1"
SUMMARY_SCHEMA = "darp-results-summary/1"


def plausibility_warnings(results: dict[str, Any], job: SurveyJob) -> list[str]:
    """The implausible parts of one survey's results, each one line (empty when nothing is implausible)."""
    warnings: list[str] = []
    if job.survey.partial is not None:
        warnings.append(f"partial survey: {job.survey.partial}")
    min_kf = job.settings.keyframes.min_keyframes
    for arm, counts in (results["keyframes"].get("arms") or {}).items():
        n = int(counts.get("keyframes", 0) or 0)
        if n < min_kf:
            warnings.append(f"{arm}: {n} keyframes, fewer than the minimum {min_kf}")
    clouds = results.get("clouds") or {}
    for arm in job.arms:
        if int(clouds.get(arm, 0) or 0) == 0:
            warnings.append(f"{arm}: its fused cloud is empty (the arm adds nothing to the result)")
    sparse = sparse_cloud_warning(int(clouds.get("fused", 0) or 0), results.get("envelope") or {},
                                  job.settings.fusion_used.voxel_size_m, job.settings.evaluation.min_surface_pct)
    if sparse:
        warnings.append(sparse)
    median = (results["heldout"].get("aggregate") or {}).get("median_mm")
    bound = job.settings.evaluation.max_heldout_median_mm
    if median is None:
        warnings.append("no held-out point: the held-out evaluation measured nothing")
    elif median > bound:
        warnings.append(f"held-out median {median:.2f} mm above the plausible bound {bound:g} mm "
                        "(calibration or poses off?)")
    accuracy = (((results.get("truth") or {}).get("cloud") or {}).get("accuracy") or {}).get("median_mm")
    truth_bound = job.settings.evaluation.max_truth_accuracy_mm
    if accuracy is not None and accuracy > truth_bound:
        shown = "n/a" if median is None else f"{median:.2f} mm"
        warnings.append(f"fused cloud {accuracy:.2f} mm from the true surface (median), above the bound "
                        f"{truth_bound:g} mm, while the held-out median is {shown}: whole views are moved "
                        "together (calibration or kinematic error), which the held-out metric cannot see")
    return warnings


def sparse_cloud_warning(points: int, envelope: dict[str, Any], voxel_m: float, min_pct: float) -> str:
    """One line when ``points`` fused voxels of ``voxel_m`` cover less than ``min_pct`` % of the envelope's top and
    side (its bottom stands on the table), else "". A surface voxel holds one point, and a surface cuts at least
    one voxel per ``voxel_m^2`` of its area, so ``points * voxel_m^2`` over-estimates the surface covered: the rule
    flags only clouds that are almost empty (dark or specular parts dropping out, a low resolution)."""
    radius, height = envelope.get("radius_m"), envelope.get("height_m")
    if not (isinstance(radius, (int, float)) and isinstance(height, (int, float)) and radius > 0 and height > 0):
        return ""
    area_m2 = math.pi * radius * radius + 2.0 * math.pi * radius * height
    pct = 100.0 * points * voxel_m * voxel_m / area_m2
    if points == 0 or pct >= min_pct:
        return ""  # an empty cloud is named per arm above
    return (f"fused cloud almost empty: {points} points at {voxel_m * 1000:g} mm voxels cover about {pct:.1f} % of "
            f"the envelope's top and side ({area_m2 * 1e4:.0f} cm^2), below {min_pct:g} %: the held-out figures "
            "are measured against almost no surface (dark or specular object, low resolution?)")


__all__ = ["low_floor_hint", "no_keyframe_error", "outside_range", "plausibility_warnings", "sparse_cloud_warning"]
