#!/usr/bin/env python3
"""Why an arm finds no feasible view: re-plan its orbit with the solved, the true and the nominal geometry.

A survey that ends ``too_few_views`` names the refusal reasons of its kept orbit; this script answers the next
question: is it the calibration (the solved joint zeros, base pose and hand-eye put the planned camera poses
where IK fails or a clearance check refuses) or the geometry (the object's place and size leave that arm no
view whatever its calibration)? For one envelope (a rejected survey's confirmed estimate, or the twin object's
true envelope at a placement) each arm's orbit, with all relaxations, is planned three times, exactly as the
survey plans it (:class:`darp.acquisition.viewpoints.ViewpointPlanner`, the survey's margins and minimum depth):

- ``solved``: with ``--calibration`` (what the survey used);
- ``truth``: with ``--truth`` (the twin's true calibration, ``captures/truth/calibration.json``);
- ``nominal``: the rig file alone;

and prints per arm and geometry the views found and the refusals by reason (each relaxation), plus the
calibration's differences from the nominal rig (base, the shoulder's height as the survey's calibration check
measures it, hand-eye, joint zeros).

    .venv/bin/python studies/feasibility.py --calibration CAL.json [--truth TRUTH.json]
        (--survey SURVEY.rejected | --object mug --placement X,Y,YAW) [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from darp.acquisition.motion_check import ArmCollisionModel, ClearanceMargins, envelope_obstacle  # noqa: E402
from darp.acquisition.survey import SurveySettings  # noqa: E402
from darp.acquisition.viewpoints import (  # noqa: E402
    ViewpointPlanner,
    feasibility_summary,
    min_depth_from_intrinsics,
    shoulder_offsets_m,
)
from darp.formats.calibration import Calibration, read_calibration  # noqa: E402
from darp.formats.realsense.types import Intrinsics  # noqa: E402
from darp.kinematics.rig import Rig, load_rig  # noqa: E402


def envelope_from_survey(folder: Path) -> tuple[np.ndarray, float, float, dict[str, Any]]:
    """The confirmed estimate of a (rejected) survey, from its events.jsonl."""
    for line in (folder / "events.jsonl").read_text().splitlines():
        event = json.loads(line)
        if event.get("kind") == "confirmation" and (event.get("estimate") or None):
            est = event["estimate"]
            return np.array(est["centre_m"], float), float(est["radius_m"]), float(est["height_m"]), event
    raise SystemExit(f"{folder}: no confirmed estimate in events.jsonl")


def envelope_from_object(rig: Rig, name: str, placement: str) -> tuple[np.ndarray, float, float]:
    """The twin object's true envelope standing at ``placement`` (x, y, yaw)."""
    from darp.twin.objects.model import make_object

    obj = make_object(name)
    x, y, _ = (float(v) for v in placement.split(","))
    return np.array([x, y, rig.table.height_m + obj.height_m / 2]), obj.radius_m, obj.height_m


def geometry_diff(rig: Rig, cal: Calibration) -> dict[str, dict[str, float]]:
    """Per arm: the calibration's base, hand-eye and joint-zero differences from the nominal rig."""
    out = {}
    shoulder = shoulder_offsets_m(rig, cal)
    for arm_id in rig.arm_ids:
        Tb0, Tc0, _ = rig.extrinsics(arm_id)
        Tb, Tc, dq = rig.extrinsics(arm_id, cal)
        rot = np.degrees(np.arccos(np.clip((np.trace(Tc0[:3, :3].T @ Tc[:3, :3]) - 1) / 2, -1, 1)))
        out[arm_id] = {"base_mm": float(np.linalg.norm(Tb[:3, 3] - Tb0[:3, 3]) * 1000),
                       "shoulder_height_mm": shoulder[arm_id] * 1000,
                       "hand_eye_mm": float(np.linalg.norm(Tc[:3, 3] - Tc0[:3, 3]) * 1000),
                       "hand_eye_deg": float(rot),
                       "joint_zero_max_deg": float(np.degrees(np.max(np.abs(dq))))}
    return out


def plan_all(rig: Rig, cal: Calibration | None, centre: np.ndarray, radius: float, height: float,
             min_depth_m: float) -> dict[str, Any]:
    s = SurveySettings()
    margins = ClearanceMargins.from_rig(rig, envelope_m=s.envelope_margin_m)
    obstacle = envelope_obstacle(centre, radius, height, rig.table.height_m)
    out = {}
    for arm_id in rig.arm_ids:
        model = ArmCollisionModel(rig, arm_id, calibration=cal, obstacle=obstacle, margins=margins)
        settings = dataclasses.replace(s.viewpoints, min_depth_m=min_depth_m)
        plan = ViewpointPlanner(model, centre, radius, height, settings, np.array(rig.arms[arm_id].park_q_rad)).plan()
        out[arm_id] = {"views": len(plan.views), "summary": feasibility_summary(plan),
                       "attempts": [{"relaxation": a["relaxation"], "views": a["views"], "candidates": a["candidates"],
                                     "rejected": a["rejected"]} for a in plan.attempts]}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calibration", type=Path, required=True)
    parser.add_argument("--truth", type=Path, default=None)
    parser.add_argument("--survey", type=Path, default=None, help="a survey folder (its confirmed estimate)")
    parser.add_argument("--object", default=None)
    parser.add_argument("--placement", default=None, help="x,y,yaw of the object (with --object)")
    parser.add_argument("--resolution", default="424x240", help="the depth stream's (for the minimum depth)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    rig = load_rig()
    record: dict[str, Any] = {}
    if args.survey is not None:
        centre, radius, height, event = envelope_from_survey(args.survey)
        record["confirmation"] = {k: event.get(k) for k in ("status", "reason", "message")}
    elif args.object and args.placement:
        centre, radius, height = envelope_from_object(rig, args.object, args.placement)
    else:
        raise SystemExit("give --survey, or --object and --placement")
    w, h = (int(v) for v in args.resolution.split("x"))
    fx = 0.5 * w  # a depth HFOV of about 90 deg (the twin's units: fx 211.7 px at 424x240)
    min_depth = min_depth_from_intrinsics(Intrinsics(w, h, fx, fx, w / 2, h / 2))
    record["envelope"] = {"centre_m": [round(float(v), 4) for v in centre], "radius_m": round(radius, 4),
                          "height_m": round(height, 4), "min_depth_m": round(min_depth, 4)}
    print(f"envelope: centre {np.round(centre, 3).tolist()} m, radius {radius * 100:.1f} cm, "
          f"height {height * 100:.1f} cm; minimum depth {min_depth:.3f} m")
    cals: dict[str, Calibration | None] = {"solved": read_calibration(args.calibration)}
    if args.truth is not None:
        cals["truth"] = read_calibration(args.truth)
    cals["nominal"] = None
    for name, cal in cals.items():
        if cal is not None:
            diff = geometry_diff(rig, cal)
            record.setdefault("geometry", {})[name] = diff
            print(f"{name} calibration against the nominal rig: " + "; ".join(
                f"{a}: base {d['base_mm']:.1f} mm (shoulder {d['shoulder_height_mm']:+.1f} mm), "
                f"hand-eye {d['hand_eye_mm']:.1f} mm / {d['hand_eye_deg']:.2f} deg, "
                f"joint zeros up to {d['joint_zero_max_deg']:.2f} deg" for a, d in diff.items()))
        plans = plan_all(rig, cal, centre, radius, height, min_depth)
        record.setdefault("plans", {})[name] = plans
        for arm_id, p in plans.items():
            print(f"  [{name}] {arm_id}: {p['summary']}")
            for a in p["attempts"]:
                print(f"      {a['relaxation']:<30} {a['views']:>2} views of {a['candidates']:>2}; "
                      f"refused {a['rejected']}")
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
