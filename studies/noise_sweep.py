#!/usr/bin/env python3
"""Keyframe stillness and processing against an encoder-noise sweep: the fixed threshold versus the
survey's own measured noise floor.

For each encoder noise (degrees, white, on every logged joint angle) a tiny twin survey of a cube is
recorded (three views per arm, 424x240 at 6 fps, seed given; joint-zero bias up to ``--bias-deg``,
hand-eye mount error 10 mm / 3 deg, second base 15 mm: the settings of issue 12's failing example) and
processed twice with the twin's true calibration: once with the old fixed 0.02 rad/s stillness
threshold (``keyframes.noise_factor: 0``) and once with the defaults (threshold from the log's noise).
Printed per noise level and mode: measured speed noise, threshold, settled frames and keyframes per
arm, held-out median / RMSE / within 10 mm, or the failure line.

    .venv/bin/python studies/noise_sweep.py [--noise-deg 0.005,0.02,0.05,0.08] [--seed 11]
        [--bias-deg 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any


def record(folder: Path, noise_deg: float, seed: int, bias_deg: float) -> None:
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement, make_object
    from darp.twin.record import record_survey
    from darp.twin.settings import JointErrorSettings, MountErrorSettings, TwinSettings
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints

    obj, rig = make_object("cube"), load_rig()
    placement = ObjectPlacement(0.0, 0.0, 0.4)
    centre = (0.0, 0.0, 0.5 * obj.height_m)
    plan = WaypointPlan({arm: tuple(orbit_waypoints(rig, arm, centre, 0.33, azimuths_deg=(-25.0, 0.0, 25.0),
                                                    elevation_deg=40.0, dwell_s=0.8))
                         for arm in ("arm110", "arm111")}, ("arm110", "arm111"))
    settings = dataclasses.replace(
        TwinSettings.from_profile("realistic", seed=seed).with_camera(fps=6, width=424, height=240),
        joints=JointErrorSettings(zero_bias_max_deg=bias_deg, encoder_noise_std_deg=noise_deg),
        mounts=MountErrorSettings(10.0, 3.0, 15.0, 0.3, 0.05))
    record_survey(folder, plan, obj, placement, settings=settings)


def process(survey: Path, out: Path, fixed: bool) -> dict[str, Any]:
    args = [sys.executable, "-m", "darp", "process", str(survey),
            "-c", str(survey / "truth" / "calibration.json"), "--out", str(out)]
    if fixed:
        settings = out.parent / f"{out.name}.yaml"
        settings.write_text("keyframes: {noise_factor: 0}\nevaluation: {figures: false}\n")
        args += ["--settings", str(settings)]
    done = subprocess.run(args, capture_output=True, text=True, env={**os.environ}, check=False)
    row: dict[str, Any] = {"rc": done.returncode}
    errors = [line for line in done.stderr.splitlines() if line.startswith("darp: error:")]
    if errors:
        row["error"] = errors[0][:160]
    stages = out / survey.name / "stages.json"
    if stages.is_file():
        arms = json.loads(stages.read_text()).get("stages", {}).get("keyframes", {}).get("summary", {}).get("arms", {})
        row["arms"] = {a: {k: c.get(k) for k in ("settled", "keyframes", "still_threshold_rad_s", "speed_noise_rad_s")}
                       for a, c in arms.items()}
    results = out / survey.name / "results.json"
    if done.returncode == 0 and results.is_file():
        r = json.loads(results.read_text())
        h = r["heldout"]["aggregate"]
        row.update(median_mm=h.get("median_mm"), rmse_mm=h.get("rmse_mm"), within_10mm_pct=h.get("within_10mm_pct"),
                   status=r.get("status"), warnings=r.get("warnings"))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise-deg", default="0.005,0.02,0.05,0.08")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--bias-deg", type=float, default=3.0)
    parser.add_argument("--keep", type=Path, default=None, help="keep surveys and outputs here")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="darp-noise-"))
    print("noise deg | mode     | speed noise rad/s | threshold | settled | keyframes | median | RMSE | <=10mm % "
          "| note")
    for noise in (float(v) for v in args.noise_deg.split(",")):
        survey = root / f"noise{noise:g}" / "cube"
        if not survey.is_dir():
            record(survey, noise, args.seed, args.bias_deg)
        for mode in ("fixed", "adaptive"):
            row = process(survey, root / f"noise{noise:g}" / mode, mode == "fixed")
            arms = row.get("arms", {})

            def per_arm(key: str, fmt: str, arms: dict[str, Any] = arms) -> str:
                return "/".join(format(c[key], fmt) if c.get(key) is not None else "-" for c in arms.values()) or "-"

            def num(key: str, row: dict[str, Any] = row) -> str:
                return "-" if row.get(key) is None else f"{row[key]:.2f}"

            note = row.get("error") or "; ".join(row.get("warnings") or []) or "ok"
            print(f"{noise:9g} | {mode:8} | {per_arm('speed_noise_rad_s', '.4f'):17} | "
                  f"{per_arm('still_threshold_rad_s', '.3f'):9} | {per_arm('settled', 'd'):7} | "
                  f"{per_arm('keyframes', 'd'):9} | {num('median_mm'):6} | {num('rmse_mm'):4} | "
                  f"{num('within_10mm_pct'):8} | {note}", flush=True)
    print(f"surveys and outputs in {root}")


if __name__ == "__main__":
    main()
