#!/usr/bin/env python3
"""Robustness sweep (issue 12): the whole pipeline at 0.5x / 1x / 2x / 4x the twin's ``paper`` error profile.

For each error scale and seed: the ``paper`` profile with every magnitude multiplied by the scale
(:meth:`darp.twin.settings.TwinSettings.scaled`) is saved as a settings file; the rig is calibrated from
simulated ChArUco images (``darp calib capture --twin --settings`` then ``darp calib solve``); each object is
surveyed autonomously with that calibration (``darp collect --twin --settings``, placements seeded as in
``darp demo``) and the accepted surveys are processed together (``darp process``). Every step is a darp
command run in its own interpreter, exactly as a user would run it; nothing is tuned per run.

Per scale, printed as a table and written to ``--json``:

- calibration: held-out 3-D corner error per arm (the paper's hand-eye figure) and hand-eye error against truth;
- survey acceptance (accepted / attempted) and processing success (surveys with a results.json / accepted;
  the exit code of ``darp process``; a failure's one-line message);
- held-out point-to-mesh median and % within 10 mm, pooled over the processed surveys;
- accuracy against truth: median distance of the fused cloud to the true mesh.

A plot (``--plot``) shows the held-out median, % within 10 mm and truth accuracy against the error scale,
with the paper's real-rig values as lines (default ``.bench/robustness/robustness.png``, ignored by git).

    .venv/bin/python studies/robustness.py [--scales 0.5,1,2,4] [--objects mug,ketchup,dumbbell,cup]
        [--seeds 0] [--fps 6] [--resolution 640x480] [--captures 20] [--work DIR] [--keep]
        [--json FILE] [--plot PNG]
    .venv/bin/python studies/robustness.py --from-json x1.json x4.json [--plot PNG]

The full sweep (4 scales x 4 objects x several seeds) takes hours on 2 cores; docs/twin.md reports
``--scales 4,1,2,0.5 --seeds 0 --resolution 424x240`` (6 fps), the reduced run made on a shared machine.
Processed surveys that processing flags as implausible are counted in ``flagged`` and listed with the reason.

On the final ``paper`` profile the calibration from board images fails at 4x (blur 3.2 px, 80 % shading: too few
ChArUco corners, named); ``--image-scale 1`` keeps the board images' errors at 1x while every other error is at the
sweep's scale, so that the surveys at 4x can still be tried (rows marked "(images 1x)", folders ``x4_img1_seed*``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from darp import paper

ROOT = Path(__file__).resolve().parents[1]
PAPER = {"handeye_mm": tuple(paper.HANDEYE_HELDOUT_MM.values()), "median_mm": paper.HELDOUT["median_mm"],
         "within_10mm_pct": paper.HELDOUT["within_10mm_pct"]}


def darp(args: list[str], log: Path) -> int:
    """Run one darp command in a child interpreter (the environment passed on); output appended to ``log``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
           "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    with log.open("a") as handle:
        handle.write(f"\n$ darp {' '.join(args)}\n")
        handle.flush()
        done = subprocess.run([sys.executable, "-m", "darp", *args], env=env,
                              stdout=handle, stderr=subprocess.STDOUT, check=False)
    return done.returncode


def last_error(log: Path) -> str:
    lines = [line for line in log.read_text().splitlines() if line.startswith("darp: ")]
    return lines[-1] if lines else ""


def placements(seed: int, count: int) -> list[tuple[float, float, float]]:
    """The demo's seeded placements (:func:`darp.twin.placement.seeded_placements`)."""
    sys.path.insert(0, str(ROOT / "src"))
    from darp.twin.placement import seeded_placements

    return seeded_placements(seed, count)


def run_case(scale: float, seed: int, objects: list[str], args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Calibrate, survey and process at one error scale and seed; returns the row."""
    sys.path.insert(0, str(ROOT / "src"))
    from darp.formats.calibration import read_calibration
    from darp.twin.settings import TwinSettings

    image_scale = scale if args.image_scale is None else args.image_scale
    case = work / (f"x{scale:g}_seed{seed}" if image_scale == scale else f"x{scale:g}_img{image_scale:g}_seed{seed}")
    case.mkdir(parents=True, exist_ok=True)
    log = case / "log.txt"
    settings_file = case / "settings.yaml"
    settings = TwinSettings.from_profile("paper", seed=seed).scaled(scale)
    if image_scale != scale:  # the board images' errors (blur, shading, noise) at their own scale
        settings = dataclasses.replace(settings, images=TwinSettings.from_profile("paper", seed=seed)
                                       .scaled(image_scale).images)
    settings.save(settings_file)
    row: dict[str, Any] = {"scale": scale, "image_scale": image_scale, "seed": seed, "objects": objects,
                           "surveys": {}}
    started = time.monotonic()
    captures, calibration = case / "captures", case / "calibration.json"
    if not calibration.exists():
        code = darp(["calib", "capture", "--twin", "--settings", str(settings_file), "--captures", str(args.captures),
                     "-o", str(captures), "--overwrite", "-q"], log)
        if code == 0:
            code = darp(["calib", "solve", str(captures), "-o", str(calibration),
                         "--truth", str(captures / "truth" / "calibration.json")], log)
        if code != 0:
            row["calibration_error"] = last_error(log) or f"exit {code}"
            return row
    cal = read_calibration(calibration)
    truth = ((cal.report or {}).get("truth") or {}).get("darp") or {}
    row["handeye_heldout_mm"] = {arm: (e.residuals or {}).get("heldout", {}).get("corner_3d_mm", {}).get("median")
                                 for arm, e in cal.arms.items()}
    row["handeye_truth_mm"] = {arm: a.get("hand_eye", {}).get("translation_mm")
                               for arm, a in truth.get("arms", {}).items()}
    surveys = case / "surveys"
    accepted = []
    for name, (x, y, yaw) in zip(objects, placements(seed, len(objects)), strict=True):
        folder = surveys / name
        if not folder.exists():
            code = darp(["collect", name, "--twin", "--object", name, "--settings", str(settings_file),
                         "--fps", str(args.fps), "--resolution", args.resolution, "--calibration", str(calibration),
                         "-o", str(surveys), "--placement", f"{x:.4f},{y:.4f},{yaw:.1f}", "--viewpoints",
                         "orbit", "-q"], log)  # the paper's acquisition, as darp demo
        else:
            code = 0
        row["surveys"][name] = {"accepted": folder.exists(), "exit": code,
                                "message": "" if folder.exists() else last_error(log)}
        if folder.exists():
            accepted.append(folder)
    processed = case / "processed"
    if accepted:
        code = darp(["process", *map(str, accepted), "--calibration", str(calibration), "-o", str(processed),
                     "--resume"], log)
        row["process_exit"] = code
        row["process_error"] = last_error(log) if code != 0 else ""
        for folder in accepted:
            result = processed / folder.name / "results.json"
            entry = row["surveys"][folder.name]
            entry["processed"] = result.exists()
            if result.exists():
                data = json.loads(result.read_text())
                agg = (data.get("heldout") or {}).get("aggregate") or {}
                entry["heldout_median_mm"] = agg.get("median_mm")
                entry["within_10mm_pct"] = agg.get("within_10mm_pct")
                acc = (((data.get("truth") or {}).get("cloud") or {}).get("accuracy") or {})
                entry["truth_accuracy_median_mm"] = acc.get("median_mm")
                entry["warnings"] = list(data.get("warnings") or [])
        summary = processed / "results.json"
        if summary.exists():
            data = json.loads(summary.read_text())
            for failed in data.get("failed") or []:  # each failed survey's own stage and reason
                if failed.get("name") in row["surveys"]:
                    row["surveys"][failed["name"]]["failure"] = f"{failed.get('stage')}: {failed.get('reason')}"
            agg = (data.get("heldout") or {}).get("aggregate") or {}
            row["heldout_median_mm"] = agg.get("median_mm")
            row["heldout_rmse_mm"] = agg.get("rmse_mm")
            row["heldout_p90_mm"] = agg.get("p90_mm")
            row["within_5mm_pct"] = agg.get("within_5mm_pct")
            row["within_10mm_pct"] = agg.get("within_10mm_pct")
            tagg = (((data.get("truth") or {}).get("aggregate") or {}).get("accuracy") or {})
            row["truth_accuracy_median_mm"] = tagg.get("median_mm")
    row["accepted"] = len(accepted)
    row["processed"] = sum(1 for s in row["surveys"].values() if s.get("processed"))
    row["flagged"] = sum(1 for s in row["surveys"].values() if s.get("warnings"))
    row["seconds"] = round(time.monotonic() - started, 1)
    return row


def fmt(value: Any, digits: int = 2) -> str:
    return "--" if value is None else f"{float(value):.{digits}f}"


def print_aligned(lines: list[list[str]]) -> None:
    """Print rows of cells right-aligned in columns, the first row (the header) underlined."""
    widths = [max(len(line[i]) for line in lines) for i in range(len(lines[0]))]
    for k, line in enumerate(lines):
        print("  ".join(cell.rjust(w) for cell, w in zip(line, widths, strict=True)))
        if k == 0:
            print("  ".join("-" * w for w in widths))


def print_table(rows: list[dict[str, Any]]) -> None:
    header = ["scale", "seed", "hand-eye held-out mm", "accepted", "processed", "flagged", "exit",
              "held-out med mm", "<=10mm %", "truth acc. med mm", "s"]
    lines = [header]
    for r in rows:
        he = r.get("handeye_heldout_mm") or {}
        img = r.get("image_scale", r["scale"])
        label = f"{r['scale']:g}x" + ("" if img == r["scale"] else f" (images {img:g}x)")
        tried = "calibration failed" if r.get("calibration_error") else f"{r.get('accepted', 0)}/{len(r['objects'])}"
        lines.append([label, str(r["seed"]), " / ".join(fmt(v) for v in he.values()) or "--",
                      tried, f"{r.get('processed', 0)}/{r.get('accepted', 0)}",
                      str(r.get("flagged", "--")), str(r.get("process_exit", "--")),
                      fmt(r.get("heldout_median_mm")), fmt(r.get("within_10mm_pct")),
                      fmt(r.get("truth_accuracy_median_mm"), 3), fmt(r.get("seconds"), 0)])
    lines.append(["paper", "-", " / ".join(fmt(v) for v in PAPER["handeye_mm"]), "-", "-", "-", "-",
                  fmt(PAPER["median_mm"]), fmt(PAPER["within_10mm_pct"]), "-", "-"])
    print_aligned(lines)
    for r in rows:
        img = r.get("image_scale", r["scale"])
        case = f"{r['scale']:g}x" + ("" if img == r["scale"] else f" (images {img:g}x)") + f" seed {r['seed']}"
        if r.get("calibration_error"):
            print(f"{case}: calibration failed: {r['calibration_error']}")
        for name, s in r.get("surveys", {}).items():
            if not s.get("accepted"):
                print(f"{case}: {name} rejected: {s.get('message')}")
            elif not s.get("processed", False):
                print(f"{case}: {name} not processed: {s.get('failure') or r.get('process_error')}")
            elif s.get("warnings"):
                print(f"{case}: {name} flagged: {'; '.join(s['warnings'])}")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8))
    scales = sorted({r["scale"] for r in rows})

    def held(r: dict[str, Any]) -> bool:  # board images at their own scale (--image-scale)
        return bool(r.get("image_scale", r["scale"]) != r["scale"])

    def series(key: str, images_held: bool) -> tuple[list[float], list[float]]:
        xs, ys = [], []
        for r in rows:
            if held(r) == images_held:
                values = list((r.get(key) or {}).values()) if key == "handeye_heldout_mm" else [r.get(key)]
                for v in values:
                    if v is not None:
                        xs.append(r["scale"])
                        ys.append(float(v))
        return xs, ys

    panels = [
        ("hand-eye held-out median (mm)", "handeye_heldout_mm", list(PAPER["handeye_mm"])),
        ("held-out point-to-mesh median (mm)", "heldout_median_mm", [PAPER["median_mm"]]),
        ("held-out within 10 mm (%)", "within_10mm_pct", [PAPER["within_10mm_pct"]]),
        ("fused cloud to true mesh, median (mm)", "truth_accuracy_median_mm", []),
    ]
    for ax, (title, key, refs) in zip(axes, panels, strict=True):
        ax.plot(*series(key, False), "o", color="tab:blue", label="twin (paper profile x scale)")
        if any(held(r) for r in rows):
            ax.plot(*series(key, True), "s", mfc="none", color="tab:green",
                    label="same, board images at their own scale")
        for ref in refs:
            ax.axhline(ref, color="tab:red", ls="--", lw=1)
        ax.axvline(1.0, color="grey", lw=0.6)
        ax.set_xscale("log", base=2)
        ax.set_xticks(scales, [f"{s:g}x" for s in scales])
        ax.set_xlabel("error scale (paper profile = 1x)")
        ax.set_title(title, fontsize=9)
    axes[0].legend(fontsize=7, loc="upper left")
    acc = [f"seed {r['seed']} {r['scale']:g}x" + (f" (images {r['image_scale']:g}x)" if held(r) else "")
           + (": calibration failed" if r.get("calibration_error") else
              f": {r.get('accepted', 0)}/{len(r['objects'])} accepted, {r.get('processed', 0)} processed")
           for r in rows]
    fig.suptitle("darp robustness sweep (red: the paper's real-rig values)   " + "; ".join(acc), fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scales", default="0.5,1,2,4")
    parser.add_argument("--objects", default="mug,ketchup,dumbbell,cup")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--fps", type=int, default=6)
    parser.add_argument("--resolution", default="640x480")
    parser.add_argument("--captures", type=int, default=20)
    parser.add_argument("--image-scale", type=float, default=None,
                        help="scale of the board images' errors (blur, shading, noise; default: the error scale): "
                             "a calibration that fails on the images at 4x can be held at 1x images to survey")
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the work folder")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--plot", type=Path, default=ROOT / ".bench" / "robustness" / "robustness.png")
    parser.add_argument("--from-json", type=Path, nargs="+", default=None,
                        help="no runs: print the table and plot of earlier --json files (e.g. scales run in parallel)")
    args = parser.parse_args()
    if args.from_json:
        rows = sorted((r for f in args.from_json for r in json.loads(f.read_text())),
                      key=lambda r: (r["seed"], r["scale"]))
        print_table(rows)
        plot(rows, args.plot)
        print(f"plot: {args.plot}")
        return
    scales = [float(s) for s in args.scales.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    work = args.work or Path(tempfile.mkdtemp(prefix="darp-robustness-"))
    rows = []
    try:
        for seed in seeds:
            for scale in scales:
                print(f"-- {scale:g}x paper profile, seed {seed} ({work})", flush=True)
                rows.append(run_case(scale, seed, objects, args, work))
                if args.json:
                    args.json.write_text(json.dumps(rows, indent=1))
    finally:
        if args.work is None and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(f"\nfps {args.fps}, resolution {args.resolution}, {args.captures} calibration captures per arm")
    print_table(rows)
    if rows:
        plot(rows, args.plot)
        print(f"plot: {args.plot}")
    failed = [r for r in rows for s in r.get("surveys", {}).values() if s.get("accepted") and not s.get("processed")]
    medians = [r["heldout_median_mm"] for r in rows if r.get("heldout_median_mm") is not None]
    print(f"accepted surveys without results: {len(failed)}; mean held-out median "
          f"{fmt(np.mean(medians) if medians else None)} mm")


if __name__ == "__main__":
    main()
