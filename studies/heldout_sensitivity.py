#!/usr/bin/env python3
"""What moves the held-out figures: processed surveys re-fused, re-meshed and re-evaluated with an error injected
into their keyframes (issue 12: which error the `paper` profile lacks).

An error is injected into the stored keyframes, never into the raw survey, then fusion, ball pivoting and the
held-out evaluation run exactly as ``darp process`` ran them (same keyframes, split, crop and settings):

- ``pose_mm`` / ``pose_deg``: one rigid error per view (every keyframe of a dwell shares it), in the camera frame,
  of RMS length ``pose_mm`` and RMS angle ``pose_deg`` (random directions): what an arm error that differs from
  view to view would add;
- ``pixel_px``: per-pixel disparity noise of RMS ``pixel_px`` (white noise blurred to about a pixel, as the D4's
  matching window correlates it), drawn anew for every keyframe: more per-pixel depth noise;
- ``field_px``: a smooth disparity error per keyframe (a 3 x 4 grid, bicubic), as the twin's per-frame field.

Disparity errors become depth errors as in the twin (``z -> z / (1 + z e / (fx B))``, B = 50 mm). Every case
is seeded per survey, arm, view and frame, so a run is reproducible. The baseline case (no error) reproduces
the survey's own ``evaluation/heldout_distances.npz``.

    .venv/bin/python studies/heldout_sensitivity.py DEMO/processed/mug DEMO/processed/ketchup ... \\
        --case pose=pose_mm:2,pose_deg:0.2 --case pixel=pixel_px:0.3 [--settings FILE] [--json OUT]

Surveys are pooled per parent folder (one demo's ``processed/``), as ``darp demo`` pools its objects; each pool
is printed with its figures over the paper's (median, RMSE, p90, within 5 and 10 mm) and how many are within
+-25 %. The survey and calibration are those its ``results.json`` names (the twin's true calibration when it was
processed with ``--truth-poses``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

FIGURES = ("median_mm", "rmse_mm", "p90_mm", "within_5mm_pct", "within_10mm_pct")  # of darp.paper.HELDOUT
BAND = 0.25
BASELINE_M = 0.05  # stereo baseline used to turn disparity errors into depth errors (D435: 50 mm)
BLUR_SIGMA_PX = 1.0
_UNIT_BLUR = 2.0 * np.sqrt(np.pi) * BLUR_SIGMA_PX  # white noise blurred by sigma has std 1 / (2 sqrt(pi) sigma)
KNOWN = ("pose_mm", "pose_deg", "pixel_px", "field_px")


class Case(NamedTuple):
    """One injected error (all zero: the baseline)."""

    name: str
    pose_mm: float = 0.0
    pose_deg: float = 0.0
    pixel_px: float = 0.0
    field_px: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Case:
        """``NAME=key:value,key:value`` (keys: pose_mm, pose_deg, pixel_px, field_px)."""
        name, _, spec = text.partition("=")
        if not name or not spec:
            raise SystemExit(f"--case {text!r}: expected NAME=key:value[,key:value] (keys: {', '.join(KNOWN)})")
        values: dict[str, float] = {}
        for item in spec.split(","):
            key, _, value = item.partition(":")
            if key not in KNOWN:
                raise SystemExit(f"--case {text!r}: unknown key {key!r} (keys: {', '.join(KNOWN)})")
            try:
                values[key] = float(value)
            except ValueError:
                raise SystemExit(f"--case {text!r}: {key} needs a number, got {value!r}") from None
            if not values[key] >= 0:
                raise SystemExit(f"--case {text!r}: {key} must be >= 0")
        return cls(name, **values)

    @property
    def is_baseline(self) -> bool:
        return not (self.pose_mm or self.pose_deg or self.pixel_px or self.field_px)


def _rng(*parts: object) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(repr(p).encode()) for p in parts])


def view_error(case: Case, survey: str, arm: str, view: int) -> np.ndarray:
    """The rigid camera-frame error (4x4) shared by every keyframe of one view."""
    from scipy.spatial.transform import Rotation

    g = _rng(case.name, survey, arm, view, "pose")
    T = np.eye(4)
    T[:3, 3] = g.normal(0.0, case.pose_mm * 1e-3 / np.sqrt(3.0), 3)
    T[:3, :3] = Rotation.from_rotvec(g.normal(0.0, np.radians(case.pose_deg) / np.sqrt(3.0), 3)).as_matrix()
    return T


def disparity_error(case: Case, survey: str, arm: str, frame: int, shape: tuple[int, int]) -> np.ndarray:
    """One keyframe's disparity error (px): blurred per-pixel noise plus a smooth per-frame field."""
    import cv2

    g = _rng(case.name, survey, arm, frame, "depth")
    h, w = shape
    e = np.zeros(shape, np.float64)
    if case.pixel_px > 0:
        noise = cv2.GaussianBlur(g.normal(0.0, 1.0, shape).astype(np.float32), (0, 0), BLUR_SIGMA_PX)
        e += noise.astype(np.float64) * _UNIT_BLUR * case.pixel_px
    if case.field_px > 0:
        nodes = g.normal(0.0, case.field_px, (3, 4)).astype(np.float32)
        e += cv2.resize(nodes, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)
    return e


def perturbed(keyframe: Any, case: Case, survey: str, colour: bool) -> Any:
    """The keyframe's ``PosedDepth`` with the case's errors (the keyframe itself is left alone)."""
    frame = keyframe.posed_depth(colour)
    if case.is_baseline:
        return frame
    pose = frame.T_world_cam @ view_error(case, survey, keyframe.arm, int(keyframe.view))
    depth = frame.depth
    if case.pixel_px > 0 or case.field_px > 0:
        z = depth.astype(np.float64) * frame.depth_scale
        e = disparity_error(case, survey, keyframe.arm, int(keyframe.frame_number), depth.shape)
        z = np.where(z > 0, z / np.maximum(1.0 + z * e / (frame.intrinsics.fx * BASELINE_M), 0.5), 0.0)
        depth = np.clip(np.round(z / frame.depth_scale), 0, 65535).astype(np.uint16)
    return dataclasses.replace(frame, T_world_cam=pose, depth=depth)


def reevaluate(processed: Path, case: Case, settings: Any) -> np.ndarray:
    """Held-out point-to-mesh distances (mm) of one processed survey with ``case`` injected."""
    from darp.evaluation.heldout import heldout_points
    from darp.evaluation.point_to_mesh import MeshDistance
    from darp.reconstruction.fusion import VoxelFusion
    from darp.reconstruction.keyframe_io import DEPTH_ONLY, FOR_FUSION, iter_keyframes
    from darp.reconstruction.keyframes import FUSE, HELDOUT
    from darp.reconstruction.mesh import ball_pivoting_mesh

    job = _job(processed, settings)
    name, keyframes, crop, fusion_settings = job.survey.name, processed / "keyframes", job.crop(), settings.fusion_used
    fusion = VoxelFusion(fusion_settings, crop)
    for keyframe in iter_keyframes(keyframes, FUSE, skip=FOR_FUSION):
        fusion.add(perturbed(keyframe, case, name, colour=True))
    cloud = fusion.result().fused
    if len(cloud.points) == 0:
        raise SystemExit(f"{processed}: case {case.name!r} left no fused point")
    normals = cloud.normals / np.linalg.norm(cloud.normals, axis=1, keepdims=True)  # as the mesh stage reads them
    mesh = ball_pivoting_mesh(cloud.points, normals, cloud.colours, settings.mesh_used)
    if len(mesh.triangles) == 0:
        raise SystemExit(f"{processed}: case {case.name!r} left no mesh triangle")
    distance = MeshDistance.from_open3d(mesh)
    parts = [distance.distances(points) for keyframe in iter_keyframes(keyframes, HELDOUT, skip=DEPTH_ONLY)
             if len(points := heldout_points(perturbed(keyframe, case, name, colour=False), fusion_settings, crop))]
    return np.concatenate(parts).astype(np.float64) * 1000.0 if parts else np.empty(0)


def _job(processed: Path, settings: Any) -> Any:
    from darp.errors import DarpError
    from darp.formats.calibration import read_calibration
    from darp.processing.job import open_job

    try:
        record = json.loads((processed / "results.json").read_text())
        survey = Path(record["survey_path"])
        cal_path = (record.get("calibration") or {}).get("path")
        if cal_path:
            calibration = read_calibration(cal_path)
        else:
            from darp.twin.truth import read_truth

            calibration = read_truth(survey).calibration
        return open_job(survey, processed, calibration, calibration_path=Path(cal_path) if cal_path else None,
                        settings=settings)
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise SystemExit(f"{processed}: not a processed survey with its survey and calibration ({err})") from None
    except DarpError as err:
        raise SystemExit(f"{processed}: {err}") from None


def paper() -> dict[str, float]:
    """The paper's held-out figures this study compares with (darp's own record of them)."""
    from darp import paper

    return {key: float(paper.HELDOUT[key]) for key in FIGURES}


def figures(distances_mm: np.ndarray) -> dict[str, float]:
    """The paper's five held-out figures of ``distances_mm`` (NaN when empty), as the pipeline computes them."""
    from darp.evaluation.point_to_mesh import distance_stats

    stats = distance_stats(np.asarray(distances_mm, np.float64) * 1e-3, (0.005, 0.010))
    return {"median_mm": stats.median_m * 1000.0, "rmse_mm": stats.rmse_m * 1000.0, "p90_mm": stats.p90_m * 1000.0,
            "within_5mm_pct": stats.within_pct[0.005], "within_10mm_pct": stats.within_pct[0.010]}


def in_band(values: dict[str, float]) -> int:
    """How many of the figures are within +-25 % of the paper's."""
    return sum(1 - BAND <= values[k] / ref <= 1 + BAND for k, ref in paper().items())


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("processed", nargs="+", type=Path, help="processed survey folders (<out>/<survey>)")
    parser.add_argument("--case", action="append", default=[], help="NAME=key:value,... (repeatable)")
    parser.add_argument("--settings", type=Path, help="the processing settings file the surveys were processed with")
    parser.add_argument("--json", type=Path, help="write every pool's figures here")
    args = parser.parse_args(argv)

    from darp.errors import DarpError
    from darp.processing.settings import ProcessSettings, load_settings

    try:
        settings = ProcessSettings() if args.settings is None else load_settings(args.settings)
    except DarpError as err:
        raise SystemExit(f"{args.settings}: {err}") from None
    cases = [Case("baseline"), *(Case.parse(c) for c in args.case)]
    if len({c.name for c in cases}) != len(cases):
        raise SystemExit("--case names must differ from each other and from 'baseline'")
    reference = paper()
    pools: dict[str, list[Path]] = {}
    for folder in args.processed:
        pools.setdefault(str(folder.parent), []).append(folder)
    rows: list[dict[str, Any]] = []
    print(f"| pool | case | points | median | RMSE | p90 | <=5 mm | <=10 mm | in +-{BAND:.0%} |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for pool, folders in pools.items():
        for case in cases:
            d = np.concatenate([reevaluate(f, case, settings) for f in folders])
            values = figures(d)
            ratios = {k: values[k] / ref for k, ref in reference.items()}
            rows.append({"pool": pool, "surveys": [f.name for f in folders], "case": case._asdict(),
                         "points": int(d.size), **values, "ratios": ratios, "in_band": in_band(values)})
            cells = " | ".join(f"{values[k]:.2f} ({ratios[k]:.2f})" for k in FIGURES)
            print(f"| {Path(pool).parent.name or pool} | {case.name} | {d.size:,} | {cells} | "
                  f"{in_band(values)} / {len(FIGURES)} |", flush=True)
    if args.json:
        from darp.formats.atomic import write_json_atomic

        write_json_atomic(args.json, {"paper": reference, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
