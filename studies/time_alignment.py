#!/usr/bin/env python3
"""Camera time alignment (issue 16 item 2) on a twin survey: the estimate and what it changes in the poses.

Estimates each camera's offset from the survey (:mod:`darp.reconstruction.time_align`, as
``darp process --corrections time`` does), then compares eq. 1 poses against the twin's true camera
poses (``truth/camera_poses_<arm>.npz``, evaluation only) for moving frames (largest joint speed above
0.15 rad/s) and settled frames, with the offset at 0 (paper mode), at the estimate, and at each
``--offset-ms`` given (e.g. the twin's true latency, 5 ms on the paper profile).

    .venv/bin/python studies/time_alignment.py SURVEY CALIBRATION [--offset-ms 5] [--json out.json]

Without arguments it says what it needs and exits: recording a paper-profile survey
takes several minutes (``darp collect mug --twin --profile paper --fps 6``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def pose_errors(survey: Any, calibration: Any, offsets: dict[str, float], moving_rad_s: float = 0.15
                ) -> dict[str, dict[str, float]]:
    """Median/p90 translation (mm) and rotation (deg) error vs truth, moving and settled frames, per arm."""
    from darp.formats.truth import read_camera_poses
    from darp.reconstruction.poses import recover_survey_poses

    poses = recover_survey_poses(survey, calibration, time_offsets_s=offsets)
    out = {}
    for arm, traj in poses.trajectories.items():
        truth = read_camera_poses(survey.truth_path / f"camera_poses_{arm}.npz")
        lookup = {int(n): i for i, n in enumerate(truth["frame_number"])}
        speed = traj.poses.joint_speed_rad_s
        rows = {"moving": [], "still": []}
        for i, n in enumerate(traj.frame_numbers.tolist()):
            T = traj.poses.T_world_cam[i]
            if n not in lookup or not np.all(np.isfinite(T)) or not np.isfinite(speed[i]):
                continue
            Tt = truth["T_world_cam"][lookup[n]]
            dt = 1e3 * float(np.linalg.norm(T[:3, 3] - Tt[:3, 3]))
            cos = (np.trace(T[:3, :3].T @ Tt[:3, :3]) - 1) / 2
            dr = float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
            rows["moving" if speed[i] > moving_rad_s else "still"].append((dt, dr))
        out[arm] = {}
        for kind, vals in rows.items():
            a = np.array(vals).reshape(-1, 2)
            out[arm][kind] = {"frames": len(a),
                              "translation_median_mm": float(np.median(a[:, 0])) if len(a) else float("nan"),
                              "translation_p90_mm": float(np.percentile(a[:, 0], 90)) if len(a) else float("nan"),
                              "rotation_median_deg": float(np.median(a[:, 1])) if len(a) else float("nan")}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("survey", type=Path, nargs="?")
    ap.add_argument("calibration", type=Path, nargs="?")
    ap.add_argument("--offset-ms", type=float, action="append", default=[])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.survey is None or args.calibration is None:
        print("time_alignment: skipped (give a twin SURVEY and its CALIBRATION; see the docstring)")
        return
    from darp.formats.calibration import read_calibration
    from darp.formats.survey import open_survey
    from darp.processing.job import SurveyJob
    from darp.processing.settings import CorrectionSettings, ProcessSettings

    survey = open_survey(args.survey)
    cal = read_calibration(args.calibration)
    job = SurveyJob(survey=survey, out=Path("/nonexistent"), calibration=cal, calibration_path=args.calibration,
                    settings=ProcessSettings(corrections=CorrectionSettings(time=True)))
    tick = time.perf_counter()
    try:
        record = job.time_alignment_record()
    finally:
        job.close()
    seconds = time.perf_counter() - tick
    report: dict[str, Any] = {"estimate": record, "estimate_seconds": seconds, "errors": {}}
    for arm, entry in record["arms"].items():
        est, std = entry.get("offset_s"), entry.get("std_s")
        shown = "none" if est is None else f"{1e3 * est:+.2f} ms +- {1e3 * (std or float('nan')):.2f}"
        print(f"{arm}: estimate {shown}  {entry.get('applied', '') or entry.get('not_applied', '')}")
    if "pooled" in record:
        p = record["pooled"]
        print(f"pooled: {1e3 * (p['offset_s'] or float('nan')):+.2f} ms +- {1e3 * (p['std_s'] or float('nan')):.2f}")
    print(f"applied: { {a: round(1e3 * v, 2) for a, v in record['applied_s'].items()} } ms ({seconds:.0f} s)")
    cases = {"paper (0 ms)": {}, "estimate (applied)": record["applied_s"]}
    for ms in args.offset_ms:
        cases[f"{ms:g} ms"] = dict.fromkeys(survey.arms, ms / 1000.0)
    with contextlib.suppress(KeyboardInterrupt):
        for name, offsets in cases.items():
            errs = pose_errors(survey, cal, offsets)
            report["errors"][name] = errs
            for arm, e in errs.items():
                m, s = e["moving"], e["still"]
                print(f"{name:>20} {arm}: moving {m['frames']:4d} frames {m['translation_median_mm']:.3f} mm "
                      f"(p90 {m['translation_p90_mm']:.3f}) {m['rotation_median_deg']:.4f} deg | still "
                      f"{s['frames']:4d} {s['translation_median_mm']:.3f} mm {s['rotation_median_deg']:.4f} deg")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
