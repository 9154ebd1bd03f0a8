#!/usr/bin/env python3
"""Completeness of the seeable surface over random placements: issue 14's target, survey by survey.

For every object and placement ``k`` the twin draws the placement itself (``darp collect --twin`` without
``--placement``: centre and yaw random, seeded, checked against the workspace) from the survey's seed
``seed * 1000 + object index * 100 + k`` (a paper object's index among the ten, so its surveys do not
depend on which other objects are listed; mesh files follow, 10, 11, ...). The survey runs the whole
acquisition (coverage planner with next best views unless ``--viewpoints orbit``), then ``darp process``
with ``--corrections`` (default ``fusion``: darp's fusion rules) and the optional ``--settings`` file.
Each row reads the survey's results.json: seeable completeness at 5 mm (``truth.seeable``: the share of
the true surface that any feasible camera pose of either arm can see which lies within 5 mm of the fused
cloud; docs/processing.md), the fused cloud's accuracy against the true mesh, the held-out median and the
cross-arm co-observed share per direction, and the co-seeable share (``truth.seeable.co_seeable_pct``: how much of
the seeable surface feasible poses of *both* arms can see at 60 deg incidence or less). The co-observed share also
counts surface one arm saw more obliquely, so it is often the higher; where the co-seeable share is about 0 (a thin
plate whose faces point at the arms) the arms share only rims.

The commands are darp's own command line (subprocesses that inherit this environment, OPENBLAS_* too), so
a row is exactly what a user gets. A survey already processed in ``--out`` is read again, not redone, so a
campaign cut short goes on where it stopped. After processing, a survey's bags and keyframes are deleted
unless ``--keep-recordings`` (a 26-survey run at 424x240 otherwise fills about 30 GB).

The default image size is darp's (640x480). At 424x240 a survey takes about half the CPU time, but a pixel
covers more than fusion's 1.5 mm voxel at the planner's standoffs, and surface seen only at 45-55 deg
incidence (a picture frame's faces between the arms) loses fusion's support: 81.8 % of the seeable surface
there against 99.8 % at 640x480 (docs/acquisition.md).

    MUJOCO_GL=egl .venv/bin/python studies/completeness.py [--objects mug,cup] [--placements 4]
        [--first-placement 0] [--seed 0] [--profile realistic] [--fps 6] [--resolution 640x480] [--corrections fusion]
        [--settings FILE] [--calibration FILE] [--viewpoints coverage] [--out DIR] [--json FILE] [--gallery PNG]
    .venv/bin/python studies/completeness.py --from-json a.json b.json [--gallery PNG]

``--from-json`` merges the rows of runs made side by side (a campaign split over workers) and prints their
table and summary without running anything. ``--gallery`` draws, per object, the fused clouds of its least
complete survey coloured by who saw each point (arm110 only, arm111 only, both: the co-observed band, in the
cross-arm table's 5 mm cells), so that what the numbers say can be looked at.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from darp.twin.objects.model import OBJECT_NAMES  # the paper's ten objects


def darp(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m darp ARGS`` with this interpreter and environment (OPENBLAS_* and MUJOCO_GL inherited)."""
    return subprocess.run([sys.executable, "-m", "darp", *args], capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})


def survey(name: str, obj: str, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """Collect (unless already collected) and process (unless already processed) one survey: its row."""
    surveys, processed = args.out / "surveys", args.out / "processed"
    row: dict[str, Any] = {"survey": name, "object": obj, "seed": seed, "processed": str(processed / name)}
    results = processed / name / "results.json"
    if not results.is_file():
        t0 = time.monotonic()
        if not (surveys / name / "arm_poses.csv").is_file():
            for stale in (surveys / name, surveys / f"{name}.partial", surveys / f"{name}.rejected"):  # again
                if stale.exists():
                    shutil.rmtree(stale)
            calib = ["--truth-calibration"] if args.calibration is None else ["--calibration", str(args.calibration)]
            done = darp("collect", name, "--twin", "--object", obj, "--seed", str(seed), "--profile", args.profile,
                        "--fps", str(args.fps), "--resolution", args.resolution, "--viewpoints", args.viewpoints,
                        *calib, "--out", str(surveys), "--quiet")
            row["collect_s"] = round(time.monotonic() - t0, 1)
            if done.returncode != 0:
                row.update(status="collect failed", exit=done.returncode, error=_last_error(done))
                return row
        t1 = time.monotonic()
        calibration = args.calibration or surveys / name / "truth" / "calibration.json"
        settings = ["--settings", str(args.settings)] if args.settings else []
        done = darp("process", str(surveys / name), "--calibration", str(calibration), "--corrections",
                    args.corrections, *settings, "--out", str(processed))
        row["process_s"] = round(time.monotonic() - t1, 1)
        if done.returncode != 0 or not results.is_file():
            row.update(status="process failed", exit=done.returncode, error=_last_error(done))
            return row
        if not args.keep_recordings:  # a 640x480 survey's two bags are hundreds of MB: keep what was measured
            for bag in (surveys / name).glob("*.bag"):
                bag.unlink()
            shutil.rmtree(processed / name / "keyframes", ignore_errors=True)
    r = json.loads(results.read_text(encoding="utf-8"))
    truth = r.get("truth") or {}
    seeable = (truth.get("seeable") or {}).get("completeness_pct") or {}
    row.update(status="ok", fused=r["clouds"]["fused"],
               seeable_5mm_pct=seeable.get("5mm"), co_seeable_pct=(truth.get("seeable") or {}).get("co_seeable_pct"),
               accuracy_median_mm=(truth.get("cloud") or {}).get("accuracy", {}).get("median_mm"),
               heldout_median_mm=r["heldout"]["aggregate"]["median_mm"],
               co_observed_pct=[d["co_observed_pct"] for d in (r.get("cross_arm") or {}).get("directions", [])])
    return row


def _last_error(done: subprocess.CompletedProcess[str]) -> str:
    lines = [line for line in (done.stderr or done.stdout or "").splitlines() if line.strip()]
    return lines[-1][:300] if lines else f"exit {done.returncode}"


def line(r: dict[str, Any]) -> str:
    if r["status"] != "ok":
        return f"| {r['survey']} | {r['object']} | {r['status']}: {r.get('error', '')} | | | | | |"
    co = " / ".join(f"{c:.1f}" for c in r["co_observed_pct"]) or "-"
    c5 = "-" if r["seeable_5mm_pct"] is None else f"{r['seeable_5mm_pct']:.1f} %"
    both = "-" if r.get("co_seeable_pct") is None else f"{r['co_seeable_pct']:.1f} %"
    return (f"| {r['survey']} | {r['object']} | {r['fused']:,} | {c5} | {r['accuracy_median_mm']:.3f} | "
            f"{r['heldout_median_mm']:.3f} | {co} % | {both} |")


HEADER = ("| survey | object | fused points | seeable @5 mm | accuracy median, mm | held-out median, mm | "
          "co-observed (arm110 / arm111) | co-seeable |\n|---|---|---|---|---|---|---|---|")


def merged_rows(files: list[Path]) -> list[dict[str, Any]]:
    """The rows of several ``--json`` files, each survey once (the last file's row wins), by seed (which orders
    the paper's objects as :data:`OBJECT_NAMES`, then mesh files, then placements).

    A row written before rows named their processed folder gets it from its file's ``--out``."""
    by_name: dict[str, dict[str, Any]] = {}
    for f in files:
        try:
            data = json.loads(f.read_text(encoding="utf-8"))
            out = Path(data["args"]["out"])
            for r in data["rows"]:
                r.setdefault("processed", str(out / "processed" / r["survey"]))
                by_name[r["survey"]] = r
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"completeness: {f}: not a --json file of this study ({exc})") from None
    return sorted(by_name.values(), key=lambda r: int(r["seed"]))


def summary(rows: list[dict[str, Any]], objects: list[str]) -> None:
    """Per object: seeable completeness and co-observed share over its placements; then the failure count."""
    ok = [r for r in rows if r["status"] == "ok" and r["seeable_5mm_pct"] is not None]
    print()
    for obj in objects:
        done = [r for r in ok if r["object"] == obj]
        if not done:
            continue
        values = [r["seeable_5mm_pct"] for r in done]
        co = [min(r["co_observed_pct"]) for r in done if r["co_observed_pct"]]
        # where feasible poses of both arms see little of the surface well (co_seeable_pct), the arms share rims
        geometry_bound = sum(1 for r in done if (r.get("co_seeable_pct") or 0.0) < 10.0
                             and min(r["co_observed_pct"] or [0.0]) < 10.0)
        text = (f"{obj}: seeable @5 mm min {min(values):.1f} / median {statistics.median(values):.1f} % over "
                f"{len(values)} placements (>= 95 %: {sum(v >= 95.0 for v in values)})")
        if co:
            text += (f"; co-observed, lower arm, min {min(co):.1f} % (>= 10 %: {sum(c >= 10.0 for c in co)}; "
                     f"below 10 % where both arms can see < 10 % of the seeable surface: {geometry_bound})")
        print(text)
    failed = [r for r in rows if r["status"] != "ok"]
    print(f"{len(ok)} of {len(rows)} surveys processed; {len(failed)} failed")


def least_complete(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per object (in first-seen order), its processed survey with the lowest seeable completeness at 5 mm."""
    worst: dict[str, dict[str, Any]] = {}
    drawable = [r for r in rows if r["status"] == "ok" and r.get("seeable_5mm_pct") is not None and r.get("processed")]
    for r in drawable:
        if r["object"] not in worst or r["seeable_5mm_pct"] < worst[r["object"]]["seeable_5mm_pct"]:
            worst[r["object"]] = r
    return worst


GALLERY_COLOURS = (("tab:red", "arm110 only"), ("tab:blue", "arm111 only"), ("tab:purple", "both arms"))


def gallery(rows: list[dict[str, Any]], path: Path, *, max_points: int = 6000) -> None:
    """Per object, the least complete survey's two arm clouds, each point coloured by who saw it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    import open3d as o3d
    from matplotlib.lines import Line2D
    from PIL import Image

    from darp.evaluation.cross_arm import DEFAULT_CELL_M, co_observed

    worst = least_complete(rows)
    if not worst:
        raise SystemExit("completeness: --gallery: no processed survey with a seeable completeness to draw")
    cols = min(5, len(worst))
    nrows = -(-len(worst) // cols)
    fig = plt.figure(figsize=(3.2 * cols, 3.4 * nrows + 0.6))
    rng = np.random.default_rng(0)
    palette = np.array([colour for colour, _ in GALLERY_COLOURS])
    for k, (obj, r) in enumerate(worst.items()):
        clouds = []
        for arm in ("arm110", "arm111"):
            ply = Path(r["processed"]) / f"{arm}.ply"
            if not ply.is_file():
                raise SystemExit(f"completeness: --gallery: {ply} is missing (was the campaign's --out moved?)")
            clouds.append(np.asarray(o3d.io.read_point_cloud(ply).points))
        both = [co_observed(clouds[i], clouds[1 - i], DEFAULT_CELL_M) for i in (0, 1)]
        points = np.vstack(clouds)
        group = np.concatenate([np.where(both[0], 2, 0), np.where(both[1], 2, 1)])  # index into GALLERY_COLOURS
        # a readable density, drawn in random order: the groups keep their proportions and no colour is painted
        # over the others
        keep = rng.permutation(len(points))[:max_points]
        points, group = points[keep], group[keep]
        ax = fig.add_subplot(nrows, cols, k + 1, projection="3d")
        ax.scatter(*(1000.0 * points.T), s=0.5, c=palette[group], depthshade=False, linewidths=0)
        ax.set_box_aspect(np.maximum(np.ptp(np.vstack(clouds), axis=0), 1e-6))
        ax.view_init(elev=25, azim=-60)
        ax.set_axis_off()
        co = " / ".join(f"{c:.0f}" for c in r["co_observed_pct"]) or "-"
        ax.set_title(f"{Path(obj).stem} ({r['survey']})\nseeable {r['seeable_5mm_pct']:.1f} %, "
                     f"co-observed {co} %", fontsize=8)
    handles = [Line2D([], [], ls="", marker="o", color=c, label=label) for c, label in GALLERY_COLOURS]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle("Least complete survey per object: its clouds by the arm that saw each point (world frame)",
                 fontsize=10)
    fig.tight_layout(rect=(0.0, 0.04, 1.0, 0.95))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".partial" + path.suffix)
    fig.savefig(tmp, dpi=85)
    plt.close(fig)
    with Image.open(tmp) as drawn:  # 256 colours lose nothing visible here and make the file 4x smaller
        small = drawn.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE)
    small.save(tmp, optimize=True)
    tmp.replace(path)
    print(f"gallery: {path}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", default=",".join(OBJECT_NAMES),
                   help="comma-separated twin objects or mesh files (default: the paper's ten)")
    p.add_argument("--placements", type=int, default=4, help="random placements per object")
    p.add_argument("--first-placement", type=int, default=0,
                   help="start at placement K (0-based): extends a campaign whose first K are measured elsewhere")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--profile", default="realistic", choices=("ideal", "realistic", "paper"))
    p.add_argument("--fps", type=int, default=6)
    p.add_argument("--resolution", default="640x480")
    p.add_argument("--viewpoints", default="coverage", choices=("coverage", "orbit"))
    p.add_argument("--corrections", default="fusion", help="darp process --corrections (default: fusion)")
    p.add_argument("--settings", type=Path, default=None, help="darp process --settings file")
    p.add_argument("--calibration", type=Path, default=None,
                   help="calibration for live decisions and processing (default: each survey's true one)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / ".bench" / "completeness-run",
                   help="surveys and processed results (default: .bench/completeness-run, ignored by git)")
    p.add_argument("--keep-recordings", action="store_true",
                   help="keep each survey's bags and keyframes after processing (default: delete them, keep the "
                        "survey's records, clouds, mesh and results.json)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--gallery", type=Path, default=None,
                   help="PNG: per object, the least complete survey's clouds by the arm that saw each point")
    p.add_argument("--from-json", type=Path, nargs="+", default=None,
                   help="merge the rows of earlier runs' --json files: print and draw them, run nothing")
    args = p.parse_args(argv)
    if args.from_json:
        merged = merged_rows(args.from_json)
        print(HEADER)
        for r in merged:
            print(line(r))
        summary(merged, list(dict.fromkeys(r["object"] for r in merged)))
        if args.gallery:
            gallery(merged, args.gallery)
        return 0
    objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    rows: list[dict[str, Any]] = []
    print(HEADER)
    others = [o for o in objects if o not in OBJECT_NAMES]
    for obj in objects:  # a paper object keeps its seeds whatever the list: its index among the ten
        i = OBJECT_NAMES.index(obj) if obj in OBJECT_NAMES else len(OBJECT_NAMES) + others.index(obj)
        for k in range(args.first_placement, args.placements):
            seed = args.seed * 1000 + i * 100 + k
            name = f"{Path(obj).stem}_s{seed}"
            rows.append(survey(name, obj, seed, args))
            print(line(rows[-1]), flush=True)
            if args.json:
                args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows},
                                                indent=1), encoding="utf-8")
    summary(rows, objects)
    if args.gallery:
        gallery(rows, args.gallery)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
