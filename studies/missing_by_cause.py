#!/usr/bin/env python3
"""Where the seeable surface goes: one markdown row per processed twin survey, from its results.json.

For each processed survey folder (or folder of them) given, prints seeable completeness at 5 mm, the
points of the seeable surface lost at each step (``truth.seeable.missing_by_cause``: share of the
missing samples x the missing share; see docs/processing.md section 8), the fused cloud's accuracy
against the true mesh, the held-out figures and the cross-arm co-observed share. Surveys without
``truth.seeable`` (no recorded feasible poses, or not a twin survey) are skipped with a note.

    python studies/missing_by_cause.py processed/ [processed-variant/ ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

SHORT = {"not_in_view": "not in view", "grazing_or_range": "grazing", "no_depth": "no depth",
         "depth_filter": "depth filter", "crop": "crop", "support": "support", "outlier_removal": "SOR",
         "surface_fit": "fit"}


def row(results: dict[str, Any], label: str) -> str | None:
    """One markdown row, or None when the survey has no seeable section."""
    truth = results.get("truth") or {}
    seeable = truth.get("seeable") or {}
    if not seeable.get("completeness_pct"):
        return None
    c5 = float(seeable["completeness_pct"]["5mm"])
    missing = 100.0 - c5
    shares = (seeable.get("missing_by_cause") or {}).get("share_pct") or {}
    causes = ", ".join(f"{SHORT.get(k, k)} {missing * float(v) / 100.0:.1f}" for k, v in shares.items()
                       if missing * float(v) / 100.0 >= 0.1) or "-"
    acc = truth["cloud"]["accuracy"]
    held = results["heldout"]["aggregate"]
    co = " / ".join(f"{d['co_observed_pct']:.1f}" for d in (results.get("cross_arm") or {}).get("directions", []))
    return (f"| {results.get('object') or results.get('survey')} | {label} | {results['clouds']['fused']:,} | "
            f"{c5:.1f} % | {causes} | {acc['median_mm']:.3f} / {acc['p90_mm']:.3f} | {held['median_mm']:.3f} / "
            f"{held['rmse_mm']:.2f} / {held['within_10mm_pct']:.2f} % | {co or '-'} % |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="processed survey folders, or folders holding them")
    args = parser.parse_args()
    print("| object | processed | fused points | seeable @5 mm | lost, points of seeable | accuracy median / p90, mm "
          "| held-out median / RMSE, mm / within 10 mm | co-observed |")
    print("|---|---|---|---|---|---|---|---|")
    for folder in args.folders:
        paths = [folder / "results.json"] if (folder / "stages.json").is_file() else sorted(
            p for p in folder.glob("*/results.json"))
        for path in paths:
            line = row(json.loads(path.read_text(encoding="utf-8")), str(path.parent.parent.name))
            print(line if line is not None else f"<!-- {path.parent}: no truth.seeable -->")


if __name__ == "__main__":
    main()
