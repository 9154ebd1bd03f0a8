#!/usr/bin/env python3
"""Error budget of the richer calibration model (issue 16): the twin's ``paper`` profile with ONE error
source zeroed at a time, captured on the twin and solved with each calibration model.

Per seed and source: ``capture_twin`` (20 ChArUco captures per arm by default, 640x480, the same plan
and the same joint-zero, mount and kinematic draws in every variant) into ``WORK/<source>_s<seed>_n<N>``,
then ``solve_captures`` with each ``--models`` entry (5-fold held-out; no OpenCV comparison); one JSON
per solve (``solve_<model>.json``: held-out median 3-D corner error per arm of the paper model, "darp",
and of the richer one, "darp_model") and a table on stdout. Existing captures and solves are reused.

    MUJOCO_GL=egl .venv/bin/python studies/error_budget.py --work /tmp/budget --seeds 0,1 \\
        --sources paper,no_backlash,no_unmodelled --models kinematic+compliance,kinematic+compliance+backlash

Results: docs/accuracy.md, "Error budget of the richer model, and backlash".
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from darp.calibration.captures import read_captures
from darp.calibration.solve import SolveSettings, solve_captures
from darp.twin.calib_capture import capture_twin
from darp.twin.settings import TwinSettings, paper_profile

SOURCES = ("paper", "no_backlash", "no_repeat", "no_encoder", "no_intrinsics", "no_images", "no_sync",
           "no_compliance", "no_geometry", "no_unmodelled")


def variant(name: str, seed: int) -> TwinSettings:
    """The paper profile of ``seed`` with the source ``name`` zeroed (``paper``: as it is)."""
    s = paper_profile(seed)
    R = dataclasses.replace
    arm, joints, depth, images, sync = s.arm_errors, s.joints, s.depth_errors, s.images, s.sync
    changes: dict[str, dict[str, Any]] = {
        "paper": {},
        "no_backlash": {"arm_errors": R(arm, backlash_deg=0.0)},
        "no_repeat": {"arm_errors": R(arm, repeatability_mm=0.0)},
        "no_encoder": {"joints": R(joints, encoder_noise_std_deg=0.0)},
        "no_intrinsics": {"depth_errors": R(depth, focal_std_pct=0.0, centre_std_px=0.0)},
        "no_images": {"images": R(images, blur_sigma_px=0.0, shading_pct=0.0, noise_dn=0.0)},
        "no_sync": {"sync": R(sync, latency_ms=0.0, jitter_ms=0.0, exposure_ms=0.0)},
        "no_compliance": {"arm_errors": R(arm, joint_stiffness_nm_per_rad=0.0)},
        "no_geometry": {"arm_errors": R(arm, link_origin_std_mm=0.0, axis_tilt_std_deg=0.0)},
        "no_unmodelled": {"arm_errors": R(arm, backlash_deg=0.0, repeatability_mm=0.0),
                          "joints": R(joints, encoder_noise_std_deg=0.0),
                          "depth_errors": R(depth, focal_std_pct=0.0, centre_std_px=0.0),
                          "images": R(images, blur_sigma_px=0.0, shading_pct=0.0, noise_dn=0.0),
                          "sync": R(sync, latency_ms=0.0, jitter_ms=0.0, exposure_ms=0.0)},
    }
    if name not in changes:
        raise SystemExit(f"unknown source {name!r} (choose from {', '.join(SOURCES)})")
    return R(s, **changes[name])


def run(work: Path, seeds: list[int], sources: list[str], models: list[str], n: int) -> list[dict[str, Any]]:
    rows = []
    for seed in seeds:
        for name in sources:
            out = work / f"{name}_s{seed}_n{n}"
            t0 = time.time()
            if not (out / "captures.json").exists():
                capture_twin(out, seed=seed, profile="paper", n_per_arm=n, settings=variant(name, seed),
                             overwrite=True)
            t1 = time.time()
            caps = read_captures(out)
            for model in models:
                res_file = out / f"solve_{model}.json"
                if not res_file.exists():
                    o = solve_captures(caps, SolveSettings(model=model, compare=False, folds=5))
                    row: dict[str, Any] = {"source": name, "seed": seed, "n": n, "model": model,
                                           "capture_s": t1 - t0, "solve_s": time.time() - t1}
                    for meth, h in o.heldout.items():
                        row[meth] = {a: float(np.median(v["corner_3d_mm"])) for a, v in h["per_arm"].items()}
                    res_file.write_text(json.dumps(row, indent=1))
                rows.append(json.loads(res_file.read_text()))
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--sources", default="paper,no_backlash,no_unmodelled")
    ap.add_argument("--models", default="kinematic+compliance,kinematic+compliance+backlash")
    ap.add_argument("--captures", type=int, default=20)
    args = ap.parse_args(argv)
    rows = run(args.work, [int(s) for s in args.seeds.split(",")], args.sources.split(","),
               args.models.split(","), args.captures)
    for r in rows:
        paper, rich = r.get("darp", {}), r.get("darp_model", {})
        print(f"seed {r['seed']} {r['source']:>14} {r['model']:>30}: paper model "
              + " / ".join(f"{v:.2f}" for v in paper.values()) + " mm, richer "
              + " / ".join(f"{v:.2f}" for v in rich.values()) + " mm")


if __name__ == "__main__":
    main()
