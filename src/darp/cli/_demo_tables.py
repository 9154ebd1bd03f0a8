"""Plain-text tables that ``darp demo`` prints: darp's numbers next to the paper's.

Ratios are darp / paper; ``!`` marks one outside +-25 % (the band the ``paper`` twin profile aims at).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from darp import paper
from darp.formats.calibration import read_calibration


def _fmt(value: Any, digits: int = 2, suffix: str = "") -> str:
    if value is None:
        return "--"
    try:
        return f"{float(value):.{digits}f}{suffix}"
    except (TypeError, ValueError):
        return str(value)


def _table(title: str, header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(str(row[i])) for row in [header, *rows]) for i in range(len(header))]
    line = "  ".join("-" * w for w in widths)

    def fmt(row: list[str]) -> str:
        return "  ".join(str(cell).ljust(w) if i == 0 else str(cell).rjust(w)
                         for i, (cell, w) in enumerate(zip(row, widths, strict=True)))

    return "\n".join([title, fmt(header), line, *(fmt(r) for r in rows)])


def calibration_table(calib_dir: Path) -> str:
    """Held-out hand-eye error per arm (paper's metric) and, on the twin, errors against truth."""
    cal = read_calibration(calib_dir / "calibration.json")
    truth = ((cal.report or {}).get("truth") or {}).get("darp") or {}
    rows = []
    for arm, entry in cal.arms.items():
        held = (entry.residuals or {}).get("heldout", {}).get("corner_3d_mm", {})
        arm_truth = truth.get("arms", {}).get(arm, {})
        he = arm_truth.get("hand_eye", {})
        rows.append([arm, _fmt(held.get("median"), 3), _fmt(paper.HANDEYE_HELDOUT_MM.get(arm)),
                     _ratio(held.get("median"), paper.HANDEYE_HELDOUT_MM.get(arm)),
                     _fmt(he.get("translation_mm"), 3), _fmt(he.get("rotation_deg"), 3),
                     _fmt(arm_truth.get("max_identifiable_joint_offset_error_deg"), 3)])
    b2b = truth.get("base_to_base", {})
    title = (f"Calibration: held-out 3-D corner error (k-fold); twin: errors against truth\n"
             f"(base-to-base error {_fmt(b2b.get('translation_mm'), 3)} mm / {_fmt(b2b.get('rotation_deg'), 3)} deg)")
    return _table(title, ["arm", "held-out med. mm", "paper mm", "ratio", "hand-eye mm", "hand-eye deg",
                          "joint-zero deg"], rows)


def _ratio(ours: Any, theirs: Any) -> str:
    """``ours / theirs`` (the paper's) with a mark when it is outside the issue-12 band of +-25 %."""
    if ours is None or not theirs:
        return "--"
    r = float(ours) / float(theirs)
    return f"{r:.2f}{'' if 0.75 <= r <= 1.25 else ' !'}"


def heldout_table(results: dict[str, Any]) -> str:
    """The paper's held-out table: per object, all objects, and the paper's row."""
    held = results.get("heldout") or {}
    header = ["object", "kf", "points", "median", "RMSE", "p90", "<=5mm %", "<=10mm %"]

    def row(name: str, keyframes: Any, stats: dict[str, Any]) -> list[str]:
        return [name, str(keyframes), f"{stats.get('count', 0):,}", _fmt(stats.get("median_mm")),
                _fmt(stats.get("rmse_mm")), _fmt(stats.get("p90_mm")), _fmt(stats.get("within_5mm_pct")),
                _fmt(stats.get("within_10mm_pct"))]

    rows = [row(o.get("object") or "-", o.get("keyframes", 0), o.get("aggregate", {}))
            for o in held.get("objects", [])]
    agg = held.get("aggregate", {})
    rows.append(row("all (darp, twin)", agg.get("keyframes", 0), agg))
    p = paper.HELDOUT
    rows.append(["paper (DARP, real)", str(p["keyframes"]), f"{p['points']:,}",
                 *(_fmt(p[key]) for key in paper.HELDOUT_FIGURES)])
    ours = [agg.get("median_mm"), agg.get("rmse_mm"), agg.get("p90_mm"), agg.get("within_5mm_pct"),
            agg.get("within_10mm_pct")]
    theirs = [p[key] for key in paper.HELDOUT_FIGURES]
    rows.append(["darp / paper", "", "", *(_ratio(a, b) for a, b in zip(ours, theirs, strict=True))])
    return _table("Held-out RGB-D evaluation, mm (point-to-mesh, kf keyframes kept out of fusion)",
                  header, rows)


def truth_table(results: dict[str, Any]) -> str:
    """Ground truth, which the paper could not measure: accuracy, completeness and F-score."""
    truth = results.get("truth") or {}
    objects = truth.get("objects") or {}
    if not objects:
        return ""
    header = ["object", "acc. median", "acc. p90", "complete 2mm %", "5mm %", "F-score 2mm %", "5mm %"]

    def row(name: str, t: dict[str, Any]) -> list[str]:
        acc = (t.get("cloud") or t).get("accuracy", {})
        comp = (t.get("cloud") or t).get("completeness", {})
        fs = (t.get("cloud") or t).get("fscore_pct", {})
        return [name, _fmt(acc.get("median_mm"), 3), _fmt(acc.get("p90_mm"), 3),
                _fmt(comp.get("within_2mm_pct")), _fmt(comp.get("within_5mm_pct")),
                _fmt(fs.get("2mm")), _fmt(fs.get("5mm"))]

    rows = [row(name, t) for name, t in objects.items()]
    if truth.get("aggregate"):
        rows.append(row("all", truth["aggregate"]))
    note = ("\n(truth and calibration define the world alike: midway between the bases,\n"
            " x from base to base, z up; the report splits off one rigid world offset)")
    return _table("Against ground truth, mm (fused cloud vs the true object mesh; twin only)", header, rows) + note
