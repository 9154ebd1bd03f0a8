#!/usr/bin/env python3
"""Accuracy beyond the paper (issue 16, item 5): paper mode vs each improvement alone vs all together.

On the twin's ``paper`` error profile, per seed: the rig is calibrated from simulated ChArUco images
(``darp calib capture --twin --profile paper`` then ``darp calib solve``; a mode that needs the richer
calibration model also gets ``darp calib solve --model kinematic+compliance+backlash`` when this darp's CLI offers
``--model``), each object is surveyed once (``darp collect --twin``, placements seeded as in ``darp demo``)
and the SAME surveys are processed once per mode (``darp process --corrections SPEC``). Every step is a darp
command in its own interpreter (the helpers of studies/robustness.py), timed.

Modes map to ``--corrections`` specs: ``paper`` (none: poses from calibration and kinematics, as the
paper), ``kinematics``, ``time``, ``depth``, ``refine``, ``table``, ``fusion``, ``mesh`` (one
improvement each), ``all``, and any
combination joined by ``+`` (``kinematics+depth+table`` runs ``--corrections kinematics,depth,table``). A mode whose
results.json records nothing for its correction and whose numbers equal paper mode's is reported as
"no effect" (its switch does nothing on this branch), never as an improvement.

Per mode, printed as a table and written to ``--json``: hand-eye held-out 3-D corner error (median, per
arm, of the calibration the mode used), held-out point-to-mesh pooled over the surveys (median, RMSE,
p90, % within 5 / 10 mm), the fused cloud's accuracy (median distance to the true mesh, raw and after
removing the world gauge: docs/accuracy.md "Accuracy against truth") and completeness
(% of the seen true surface within 5 mm), keyframe pose error against the true poses (median translation),
and the seconds of each step (calibration solve, processing, refinement). A plot (``--plot``) shows the
main figures per mode with the issue's targets. Both default to ``.bench/accuracy/`` (ignored by git).

    .venv/bin/python studies/accuracy.py [--objects mug,ketchup] [--seeds 0] [--fps 6]
        [--resolution 640x480] [--captures 20] [--modes paper,kinematics,time,depth,refine,all]
        [--reuse DIR] [--work DIR] [--json FILE] [--plot PNG]
    .venv/bin/python studies/accuracy.py --from-json a.json b.json [--plot PNG]

``--reuse DIR`` takes one seed's captures, calibration and surveys from ``DIR`` (``captures/``,
``calibration.json``, ``surveys/<object>``, as a seed folder of this script is laid out) instead of making them;
only processing (and a kinematic solve, when a mode needs one) runs, into ``--work``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from darp import paper

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robustness import ROOT, darp, fmt, last_error, placements, print_aligned  # the shared helpers

MODES = ("paper", "kinematics", "time", "depth", "refine", "table", "fusion", "mesh", "all")
CORRECTION_NAMES = ("kinematics", "time", "depth", "refine", "table", "fusion", "mesh")
# the richest model darp solves (its backlash needs captures that record their move directions)
KINEMATIC_MODEL = "kinematic+compliance+backlash"
NEEDS_MODEL = {"kinematics", "all"}
TARGETS = {"handeye_mm": 1.5, "median_mm": 1.0, "within_10mm_pct": 99.0, "truth_accuracy_median_mm": 1.0}
PAPER = {"handeye_mm": tuple(paper.HANDEYE_HELDOUT_MM.values()), "median_mm": paper.HELDOUT["median_mm"],
         "within_10mm_pct": paper.HELDOUT["within_10mm_pct"]}
# what each correction records under results.json's "corrections" when it did something
RECORD_KEY = {"kinematics": "kinematics", "time": "time", "depth": "depth", "refine": "refine", "table": "table"}


def mode_parts(mode: str) -> list[str]:
    """The corrections a mode switches on (``all``: every one; ``a+b``: a combination)."""
    if mode == "paper":
        return []
    return list(CORRECTION_NAMES) if mode == "all" else mode.split("+")


def parse_modes(spec: str) -> list[str]:
    """``paper,refine,kinematics+depth,...`` -> the modes, checked against :data:`MODES` or combinations of
    correction names joined by ``+`` (the listed modes first, in their order, then combinations)."""
    modes = [m.strip().lower() for m in spec.split(",") if m.strip()]
    unknown = [m for m in modes if m not in MODES and not all(p in CORRECTION_NAMES for p in m.split("+"))]
    if unknown or not modes:
        raise SystemExit(f"accuracy.py: unknown mode(s) {', '.join(unknown) or '(none)'}; modes: {', '.join(MODES)} "
                         f"or a '+'-joined combination of {', '.join(CORRECTION_NAMES)}")
    return sorted(dict.fromkeys(modes), key=lambda m: (MODES.index(m) if m in MODES else len(MODES), modes.index(m)))


def corrections_spec(mode: str) -> str:
    """The ``--corrections`` value of a mode (a combination's ``+`` becomes ``,``)."""
    return mode.replace("+", ",")


def model_supported(help_text: str) -> bool:
    """Whether ``darp calib solve --help`` offers ``--model``."""
    return "--model" in help_text


def calib_solve_help() -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    done = subprocess.run([sys.executable, "-m", "darp", "calib", "solve", "--help"],
                          env=env, capture_output=True, text=True, check=False)
    return done.stdout + done.stderr


def mode_model(mode: str, supported: bool) -> str | None:
    """The calibration model a mode solves with (None: the default model)."""
    return KINEMATIC_MODEL if (mode in NEEDS_MODEL or "kinematics" in mode_parts(mode)) and supported else None


def heldout_of(calibration: Path, model: str | None = None) -> dict[str, float | None]:
    """Per arm, the calibration's held-out median 3-D corner error (mm): the richer model's own when
    ``model`` is given and the file holds it (``arms.<arm>.kinematics.heldout``), else the paper model's."""
    data = json.loads(calibration.read_text())

    def median(arm: dict[str, Any]) -> float | None:
        held = (arm.get("kinematics") or {}).get("heldout") if model is not None else None
        held = held or (arm.get("residuals") or {}).get("heldout") or {}
        value = (held.get("corner_3d_mm") or {}).get("median")
        return None if value is None else float(value)

    return {name: median(arm) for name, arm in (data.get("arms") or {}).items()}


def summarise_processed(processed: Path, surveys: list[str]) -> dict[str, Any]:
    """The pooled and per-survey figures of one mode's ``darp process`` output folder."""
    row: dict[str, Any] = {"surveys": {}}
    summary = processed / "results.json"
    if summary.exists():
        data = json.loads(summary.read_text())
        agg = (data.get("heldout") or {}).get("aggregate") or {}
        for key in ("median_mm", "rmse_mm", "p90_mm", "within_5mm_pct", "within_10mm_pct", "count"):
            row[f"heldout_{key}"] = agg.get(key)
        truth = ((data.get("truth") or {}).get("aggregate") or {})
        row["truth_accuracy_median_mm"] = (truth.get("accuracy") or {}).get("median_mm")
        comp = truth.get("completeness") or {}
        row["truth_completeness_5mm_pct"] = comp.get("within_5mm_pct")
    records: dict[str, Any] = {}
    stage_seconds: dict[str, float] = {}
    pose_mm: list[float] = []
    aligned: list[float] = []
    for name in surveys:
        result = processed / name / "results.json"
        if not result.exists():
            row["surveys"][name] = {"processed": False}
            continue
        data = json.loads(result.read_text())
        agg = (data.get("heldout") or {}).get("aggregate") or {}
        truth = data.get("truth") or {}
        cloud = truth.get("cloud") or {}
        gauge = truth.get("world_gauge") or {}
        entry = {"processed": True, "heldout_median_mm": agg.get("median_mm"),
                 "truth_accuracy_median_mm": (cloud.get("accuracy") or {}).get("median_mm"),
                 # after removing the world gauge (the calibration's world vs the twin's; not observable)
                 "truth_aligned_median_mm": (gauge.get("accuracy_aligned") or {}).get("median_mm"),
                 "gauge_translation_mm": gauge.get("translation_mm"), "gauge_rotation_deg": gauge.get("rotation_deg"),
                 "pose_error": truth.get("pose_error")}
        if entry["truth_aligned_median_mm"] is not None:
            aligned.append(float(entry["truth_aligned_median_mm"]))
        for arm in (truth.get("pose_error") or {}).values():
            if arm.get("translation_median_mm") is not None:
                pose_mm.append(float(arm["translation_median_mm"]))
        corrections = data.get("corrections") or {}
        for key in RECORD_KEY.values():
            if key in corrections:
                records.setdefault(key, {})[name] = corrections[key]
        refine = corrections.get("refine")
        if isinstance(refine, dict):
            entry["refine"] = {"arms": refine.get("arms"), "counts": refine.get("counts"),
                               "seconds": refine.get("seconds"), "bound": refine.get("bound"),
                               "gate": refine.get("gate")}
            stage_seconds["refine"] = stage_seconds.get("refine", 0.0) + float(refine.get("seconds") or 0.0)
        for stage, seconds in (data.get("stages") or {}).items():
            stage_seconds[stage] = stage_seconds.get(stage, 0.0) + float(seconds or 0.0)
        row["surveys"][name] = entry
    row["records"] = sorted(records)
    row["stage_seconds"] = {k: round(v, 2) for k, v in stage_seconds.items()}
    row["pose_error_median_mm"] = round(sum(pose_mm) / len(pose_mm), 3) if pose_mm else None
    # the gauge-aligned accuracy: mean over the surveys of each survey's median (the figure the target is for)
    row["truth_aligned_median_mm"] = round(sum(aligned) / len(aligned), 3) if aligned else None
    return row


COMPARED = ("heldout_median_mm", "heldout_rmse_mm", "heldout_count", "truth_accuracy_median_mm")


def mark_effects(rows: list[dict[str, Any]]) -> None:
    """Per row: ``effect`` = "baseline" (paper), "no effect" (same numbers as paper and nothing recorded:
    the switch does nothing on this branch), "ran, nothing applied" (same numbers, but the step recorded
    what it decided, e.g. a time offset refused as too uncertain), or "applied"."""
    by_seed = {r["seed"]: r for r in rows if r["mode"] == "paper"}
    for r in rows:
        base = by_seed.get(r["seed"])
        if r["mode"] == "paper":
            r["effect"] = "baseline"
            continue
        wanted = mode_parts(r["mode"])
        recorded = [w for w in wanted if RECORD_KEY[w] in r.get("records", [])]
        same = base is not None and all(r.get(k) == base.get(k) for k in COMPARED) and r.get("model") is None
        if same and not recorded:
            r["effect"] = "no effect (switch does nothing on this branch)"
        elif same and r["mode"] != "all":  # the step ran and recorded why it changed nothing (e.g. time refused)
            r["effect"] = "ran, nothing applied"
        else:
            missing = [w for w in wanted if w not in recorded and w != "kinematics"]
            r["effect"] = "applied" + (f" (nothing recorded for {', '.join(missing)})" if missing else "")


def run_seed(seed: int, objects: list[str], modes: list[str], args: argparse.Namespace, work: Path,
             supported: bool) -> list[dict[str, Any]]:
    """Calibrate (or reuse), survey (or reuse) and process every mode for one seed; one row per mode."""
    case = work / f"seed{seed}"
    case.mkdir(parents=True, exist_ok=True)
    log = case / "log.txt"
    source = args.reuse if args.reuse is not None else case
    captures, calibration = source / "captures", source / "calibration.json"
    timing: dict[str, float] = {}
    if not calibration.exists():
        t0 = time.monotonic()
        code = darp(["calib", "capture", "--twin", "--profile", "paper", "--seed", str(seed), "--captures",
                     str(args.captures), "-o", str(captures), "--overwrite", "-q"], log)
        timing["calib_capture_s"] = round(time.monotonic() - t0, 1)
        t0 = time.monotonic()
        if code == 0:
            code = darp(["calib", "solve", str(captures), "-o", str(calibration),
                         "--truth", str(captures / "truth" / "calibration.json")], log)
        timing["calib_solve_s"] = round(time.monotonic() - t0, 1)
        if code != 0:
            return [{"seed": seed, "mode": m, "error": last_error(log) or f"exit {code}"} for m in modes]
    calibrations: dict[str | None, Path] = {None: calibration}
    if any(mode_model(m, supported) for m in modes):
        kinematic = case / f"calibration-{KINEMATIC_MODEL.replace('+', '-')}.json"
        t0 = time.monotonic()
        if not kinematic.exists():
            code = darp(["calib", "solve", str(captures), "-o", str(kinematic), "--model", KINEMATIC_MODEL,
                         "--truth", str(captures / "truth" / "calibration.json")], log)
            if code != 0:
                print(f"seed {seed}: kinematic solve failed: {last_error(log)}", flush=True)
        timing["calib_solve_kinematic_s"] = round(time.monotonic() - t0, 1)
        if kinematic.exists():
            calibrations[KINEMATIC_MODEL] = kinematic
    surveys_dir = source / "surveys"
    accepted = []
    for name, (x, y, yaw) in zip(objects, placements(seed, len(objects)), strict=True):
        folder = surveys_dir / name
        if not folder.exists() and args.reuse is None:
            t0 = time.monotonic()
            darp(["collect", name, "--twin", "--object", name, "--profile", "paper", "--seed", str(seed),
                  "--fps", str(args.fps), "--resolution", args.resolution, "--calibration", str(calibration),
                  "-o", str(surveys_dir), "--placement", f"{x:.4f},{y:.4f},{yaw:.1f}", "--viewpoints", "orbit",
                  "-q"], log)  # the paper's acquisition, as darp demo
            timing[f"collect_{name}_s"] = round(time.monotonic() - t0, 1)
        if folder.exists():
            accepted.append(folder)
        else:
            print(f"seed {seed}: {name}: no accepted survey ({last_error(log)})", flush=True)
    rows = []
    for mode in modes:
        model = mode_model(mode, supported)
        cal = calibrations.get(model, calibration)
        if model is not None and model not in calibrations:
            model = None
        processed = case / f"processed-{mode}"
        t0 = time.monotonic()
        code = darp(["process", *map(str, accepted), "--calibration", str(cal), "-o", str(processed),
                     "--corrections", corrections_spec(mode), "--resume"], log) if accepted else 1
        row = {"seed": seed, "mode": mode, "model": model, "calibration": str(cal),
               "handeye_heldout_mm": heldout_of(cal, model), "process_exit": code,
               "process_error": last_error(log) if code != 0 else "",
               "process_s": round(time.monotonic() - t0, 1), "timing": timing,
               **summarise_processed(processed, [f.name for f in accepted])}
        rows.append(row)
        print(f"seed {seed} {mode}: held-out median {fmt(row.get('heldout_median_mm'))} mm, truth accuracy "
              f"{fmt(row.get('truth_accuracy_median_mm'), 3)} mm ({row['process_s']} s)", flush=True)
    return rows


HEADER = ["seed", "mode", "effect", "hand-eye mm", "med mm", "RMSE", "p90", "<=5mm %", "<=10mm %",
          "truth raw mm", "truth aligned mm", "compl 5mm %", "pose mm", "process s", "refine s"]


def table_lines(rows: list[dict[str, Any]]) -> list[list[str]]:
    """The table's rows as strings (header first, the paper's real-rig row and the targets last)."""
    lines = [HEADER]
    for r in rows:
        he = r.get("handeye_heldout_mm") or {}
        lines.append([str(r["seed"]), r["mode"], r.get("effect", "?").split(" (")[0],
                      " / ".join(fmt(v) for v in he.values()) or "--", fmt(r.get("heldout_median_mm")),
                      fmt(r.get("heldout_rmse_mm")), fmt(r.get("heldout_p90_mm")), fmt(r.get("heldout_within_5mm_pct")),
                      fmt(r.get("heldout_within_10mm_pct")), fmt(r.get("truth_accuracy_median_mm"), 3),
                      fmt(r.get("truth_aligned_median_mm"), 3),
                      fmt(r.get("truth_completeness_5mm_pct"), 1), fmt(r.get("pose_error_median_mm")),
                      fmt(r.get("process_s"), 0), fmt((r.get("stage_seconds") or {}).get("refine"), 1)])
    he_paper = " / ".join(fmt(v) for v in paper.HANDEYE_HELDOUT_MM.values())
    lines.append(["-", "paper (real rig)", "-", he_paper, *(fmt(paper.HELDOUT[k]) for k in paper.HELDOUT_FIGURES),
                  "-", "-", "-", "-", "-", "-"])
    lines.append(["-", "target (issue 16)", "-", "<= 1.5", "<= 1.0", "-", "-", "-", ">= 99", "-", "<= 1.0", "-", "-",
                  "-", "-"])
    return lines


def print_table(rows: list[dict[str, Any]]) -> None:
    print_aligned(table_lines(rows))
    for r in rows:
        if r.get("error") or r.get("process_error"):
            print(f"seed {r['seed']} {r['mode']}: {r.get('error') or r.get('process_error')}")
        if str(r.get("effect", "")).startswith("no effect"):
            print(f"seed {r['seed']} {r['mode']}: {r['effect']}")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in MODES if any(r["mode"] == m for r in rows)]
    panels = [("held-out median (mm)", "heldout_median_mm", TARGETS["median_mm"]),
              ("held-out within 10 mm (%)", "heldout_within_10mm_pct", TARGETS["within_10mm_pct"]),
              ("fused cloud to true mesh, gauge removed, median (mm)", "truth_aligned_median_mm",
               TARGETS["truth_accuracy_median_mm"]),
              ("keyframe pose error vs truth, median (mm)", "pose_error_median_mm", None)]
    fig, axes = plt.subplots(1, len(panels), figsize=(16, 3.8))
    for ax, (title, key, target) in zip(axes, panels, strict=True):
        for k, mode in enumerate(modes):
            values = [float(r[key]) for r in rows if r["mode"] == mode and r.get(key) is not None]
            faded = any(str(r.get("effect", "")).startswith("no effect") for r in rows if r["mode"] == mode)
            ax.plot([k] * len(values), values, "o", color="tab:grey" if faded else "tab:blue")
        if target is not None:
            ax.axhline(target, color="tab:green", ls="--", lw=1)
        ax.set_xticks(range(len(modes)), modes, rotation=30, fontsize=8)
        ax.set_title(title, fontsize=9)
    fig.suptitle("darp accuracy by correction mode, twin paper profile (green: issue 16 target; grey: no effect)",
                 fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", default="mug,ketchup")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--fps", type=int, default=6)
    parser.add_argument("--resolution", default="640x480")
    parser.add_argument("--captures", type=int, default=20)
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--reuse", type=Path, default=None,
                        help="take captures/, calibration.json and surveys/<object> of ONE seed from this folder")
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one, kept)")
    parser.add_argument("--json", type=Path, default=ROOT / ".bench" / "accuracy" / "accuracy.json")
    parser.add_argument("--plot", type=Path, default=ROOT / ".bench" / "accuracy" / "accuracy.png")
    parser.add_argument("--from-json", type=Path, nargs="+", default=None,
                        help="no runs: table and plot of --json files")
    args = parser.parse_args(argv)
    if args.from_json:
        rows = [r for f in args.from_json for r in json.loads(f.read_text())]
        mark_effects(rows)  # against the paper rows of all the files (a later run may add modes to an earlier one)
        print_table(rows)
        plot(rows, args.plot)
        return
    modes = parse_modes(args.modes)
    seeds = [int(s) for s in args.seeds.split(",")]
    if args.reuse is not None and len(seeds) != 1:
        raise SystemExit("accuracy.py: --reuse takes one seed's data; give a single --seeds value")
    objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    supported = model_supported(calib_solve_help())
    work = args.work or Path(tempfile.mkdtemp(prefix="darp-accuracy-"))
    support = "supported" if supported else "not supported (kinematics mode runs with the default model)"
    print(f"work folder {work}; calib solve --model {support}", flush=True)
    rows: list[dict[str, Any]] = []
    for seed in seeds:
        rows += run_seed(seed, objects, modes, args, work, supported)
        mark_effects(rows)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))
    print(f"\npaper profile, fps {args.fps}, resolution {args.resolution}, {args.captures} captures per arm, "
          f"objects {', '.join(objects)}")
    print_table(rows)
    plot(rows, args.plot)
    print(f"json: {args.json}; plot: {args.plot}")


if __name__ == "__main__":
    main()
