#!/usr/bin/env python3
"""Where the held-out tail is: each held-out point farther than 10 mm from the measured mesh, classified with
the twin's truth (issues 12 and 16: the dumbbell's and the mug's tails).

For each held-out keyframe of a processed twin survey, its points are taken exactly as the evaluation takes
them (fusion's per-frame filters and the same region: the envelope crop, or the keyframe's fitted table crop
under ``corrections.table``) and moved into the twin's true world with that frame's true pose
(``T_true @ inv(T_used)``, so pose errors are removed and the depth errors stay). A point beyond 10 mm is

- ``table``: within 6 mm of the true table (z = 0) and more than 4 mm from the true object;
- ``object``: within 3 mm of the true object: a surface that the measured mesh lacks (a hole);
- ``other``: neither (depth error, mixed pixels, a misplaced view).

Per keyframe it also prints, in the world the pipeline used, where the true table points lie against the
crop's floor (paper mode) or against the keyframe's fitted plane by distance from the envelope axis (with
``corrections.table``): a table that the fitted plane misses inside the envelope shows there.

    .venv/bin/python studies/heldout_tail.py SURVEY PROCESSED_SURVEY CALIBRATION [--corrections C]
        [--truth-poses]

``PROCESSED_SURVEY`` is the survey's folder under ``darp process``'s output, processed with the same
calibration and corrections.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

TABLE_BAND_M = 0.006
OFF_OBJECT_M = 0.004
ON_OBJECT_M = 0.003
FAR_M = 0.01


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("survey", type=Path)
    parser.add_argument("processed", type=Path)
    parser.add_argument("calibration", type=Path)
    parser.add_argument("--corrections", default="paper")
    parser.add_argument("--truth-poses", action="store_true")
    parser.add_argument("--json", type=Path, help="write the per-keyframe records here")
    args = parser.parse_args()

    import trimesh

    from darp.evaluation.point_to_mesh import MeshDistance
    from darp.formats.calibration import read_calibration
    from darp.formats.truth import read_camera_poses
    from darp.processing.evaluate import read_truth_mesh
    from darp.processing.job import open_job
    from darp.processing.settings import CorrectionSettings, ProcessSettings
    from darp.reconstruction.backproject import PosedDepth, backproject
    from darp.reconstruction.keyframe_io import DEPTH_ONLY, HELDOUT, iter_keyframes, posed_frames
    from darp.reconstruction.table_plane import TableCrop

    settings = ProcessSettings(corrections=CorrectionSettings.parse(args.corrections))
    job = open_job(args.survey, args.processed, read_calibration(args.calibration), settings=settings,
                   truth_poses=args.truth_poses)
    crop = job.crop()
    outer = crop.radius_m + crop.margin_m
    tv, tt = read_truth_mesh(args.survey / "truth" / "object.ply")
    truth = MeshDistance(tv, tt)
    mesh = trimesh.load(args.processed / "mesh.ply", force="mesh", process=False)
    measured = MeshDistance(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    print(f"crop: radius {crop.radius_m * 1e3:.1f} + {crop.margin_m * 1e3:.1f} mm, floor "
          f"{crop.z_range_m[0] * 1e3:.1f} mm, top {crop.z_range_m[1] * 1e3:.1f} mm; corrections {args.corrections}")
    totals = {"points": 0, "far": 0, "table": 0, "object": 0, "other": 0}
    records: list[dict[str, Any]] = []
    true_poses: dict[str, Any] = {}
    for frame in posed_frames(iter_keyframes(job.keyframes_dir, HELDOUT, skip=DEPTH_ONLY), colour=False):
        region, plane_record = job.table_region(frame) if settings.corrections.table else (crop, {})
        if frame.arm not in true_poses:
            true_poses[frame.arm] = read_camera_poses(args.survey / "truth" / f"camera_poses_{frame.arm}.npz")
        tp = true_poses[frame.arm]
        index = int(np.flatnonzero(np.asarray(tp["frame_number"]) == frame.frame_id)[0])
        to_true = tp["T_world_cam"][index] @ np.linalg.inv(frame.T_world_cam)
        bare = PosedDepth(frame.arm, frame.frame_id, frame.depth, frame.depth_scale, frame.intrinsics,
                          frame.T_world_cam, None)
        pts = backproject(bare, settings.fusion.depth, None).points.astype(np.float64)
        r = np.hypot(pts[:, 0] - crop.center_m[0], pts[:, 1] - crop.center_m[1])
        pts, r = pts[r < outer + 0.06], r[r < outer + 0.06]
        p_true = pts @ to_true[:3, :3].T + to_true[:3, 3]
        d_true = truth.distances(p_true)
        table = (np.abs(p_true[:, 2]) < TABLE_BAND_M) & (d_true > OFF_OBJECT_M)
        kept = region.contains(pts)
        d_mesh = measured.distances(pts[kept]) if kept.any() else np.empty(0)
        far = d_mesh > FAR_M
        k_table, k_true = table[kept], d_true[kept]
        rec: dict[str, Any] = {
            "arm": frame.arm, "frame": int(frame.frame_id), "points": int(kept.sum()), "far": int(far.sum()),
            "table": int(np.sum(far & k_table)), "object": int(np.sum(far & (k_true < ON_OBJECT_M))),
            "far_z_mm": None if not far.any() else round(float(np.median(pts[kept][far, 2])) * 1e3, 1)}
        rec["other"] = rec["far"] - rec["table"] - rec["object"]
        line = (f"{frame.arm} {frame.frame_id}: {rec['points']} pts, >10 mm {rec['far']} (table {rec['table']}, "
                f"object {rec['object']}, other {rec['other']}; z med {rec['far_z_mm']} mm)")
        heights = (region.plane.height(pts[table]) if isinstance(region, TableCrop) else pts[table, 2])
        what = "above its fitted plane" if isinstance(region, TableCrop) else "world z"
        bins = {}
        for lo, hi in ((0.0, outer), (outer, outer + 0.03), (outer + 0.03, outer + 0.06)):
            m = (r[table] >= lo) & (r[table] < hi)
            if m.sum() >= 20:
                bins[f"{lo * 1e3:.0f}-{hi * 1e3:.0f}"] = [round(float(np.percentile(heights[m], q)) * 1e3, 2)
                                                          for q in (5, 50, 95)]
        rec["true_table_mm"] = bins
        if plane_record:
            rec["plane"] = plane_record
            line += f"\n   plane z {plane_record.get('table_z_mm')} mm, tilt {plane_record.get('tilt_deg')} deg"
        line += f"\n   true table, {what} (5/50/95 % by radius mm): " + "; ".join(
            f"r {k}: {v[0]:+.1f} / {v[1]:+.1f} / {v[2]:+.1f}" for k, v in bins.items())
        print(line)
        records.append(rec)
        totals["points"] += rec["points"]
        for key in ("far", "table", "object", "other"):
            totals[key] += rec[key]
    n = max(totals["points"], 1)
    print(f"held-out points {totals['points']}: beyond 10 mm {totals['far']} ({100 * totals['far'] / n:.2f} %): "
          f"table {totals['table']} ({100 * totals['table'] / n:.2f} %), object/mesh hole {totals['object']} "
          f"({100 * totals['object'] / n:.2f} %), other {totals['other']} ({100 * totals['other'] / n:.2f} %)")
    if args.json is not None:
        args.json.write_text(json.dumps({"totals": totals, "keyframes": records}, indent=1))


if __name__ == "__main__":
    main()
