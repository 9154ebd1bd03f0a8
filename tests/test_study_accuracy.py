"""studies/accuracy.py's argument, mode and table logic (no darp run: cheap)."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest

from helpers.script_modules import load_study


@pytest.fixture(scope="module")
def accuracy() -> ModuleType:
    return load_study("accuracy")


def test_modes_parse_in_a_fixed_order_and_reject_unknown(accuracy: ModuleType) -> None:
    assert accuracy.parse_modes("refine, paper,all,refine") == ["paper", "refine", "all"]
    with pytest.raises(SystemExit, match="unknown mode"):
        accuracy.parse_modes("paper,magic")
    assert [accuracy.corrections_spec(m) for m in accuracy.MODES] == list(accuracy.MODES)


def test_the_kinematic_model_is_asked_only_when_needed_and_offered(accuracy: ModuleType) -> None:
    assert accuracy.model_supported("Usage: darp calib solve [OPTIONS] CAPTURES\n  --model [paper|kinematic]")
    assert not accuracy.model_supported("Usage: darp calib solve [OPTIONS] CAPTURES\n  --out PATH")
    assert accuracy.mode_model("kinematics", True) == accuracy.KINEMATIC_MODEL
    assert accuracy.mode_model("all", True) == accuracy.KINEMATIC_MODEL
    assert accuracy.mode_model("kinematics", False) is None
    assert accuracy.mode_model("refine", True) is None and accuracy.mode_model("paper", True) is None


def _write_results(folder: Path, name: str, median: float, corrections: dict) -> None:
    (folder / name).mkdir(parents=True)
    (folder / name / "results.json").write_text(json.dumps({
        "heldout": {"aggregate": {"median_mm": median}}, "corrections": corrections,
        "truth": {"cloud": {"accuracy": {"median_mm": 1.5}},
                  "pose_error": {"arm110": {"translation_median_mm": 4.0}, "arm111": {"translation_median_mm": 2.0}}},
        "stages": {"keyframes": 10.0, "fusion": 2.0}}))


def test_summary_marks_a_switch_that_does_nothing(accuracy: ModuleType, tmp_path: Path) -> None:
    pooled = {"heldout": {"aggregate": {"median_mm": 1.4, "rmse_mm": 6.6, "p90_mm": 6.3, "within_5mm_pct": 85.0,
                                        "within_10mm_pct": 94.1, "count": 1000}},
              "truth": {"aggregate": {"accuracy": {"median_mm": 2.2}, "completeness": {"within_5mm_pct": 77.0}}}}
    rows = []
    for mode, corrections, median in (("paper", {"mode": "paper", "applied": []}, 1.4),
                                      ("depth", {"mode": "depth", "applied": ["depth"]}, 1.4),
                                      ("time", {"mode": "time", "applied": ["time"],  # estimated, refused
                                                "time": {"applied_s": [], "warning": "no time offset"}}, 1.4),
                                      ("refine", {"mode": "refine", "applied": ["refine"],
                                                  "refine": {"seconds": 3.0, "counts": {"accepted": 5}}}, 1.2)):
        folder = tmp_path / mode
        _write_results(folder, "mug", median, corrections)
        data = json.loads(json.dumps(pooled))
        data["heldout"]["aggregate"]["median_mm"] = median
        (folder / "results.json").write_text(json.dumps(data))
        rows.append({"seed": 0, "mode": mode, "model": None, "handeye_heldout_mm": {"arm110": 3.4, "arm111": 3.0},
                     "process_s": 60.0, **accuracy.summarise_processed(folder, ["mug"])})
    assert rows[0]["heldout_median_mm"] == 1.4 and rows[0]["truth_completeness_5mm_pct"] == 77.0
    assert rows[0]["pose_error_median_mm"] == 3.0
    assert rows[3]["records"] == ["refine"] and rows[3]["stage_seconds"]["refine"] == 3.0
    accuracy.mark_effects(rows)
    assert [r["effect"] for r in rows] == ["baseline", "no effect (switch does nothing on this branch)",
                                           "ran, nothing applied", "applied"]
    lines = accuracy.table_lines(rows)
    assert lines[0] == accuracy.HEADER and len(lines) == 1 + 4 + 2
    assert lines[2][2] == "no effect" and lines[3][2] == "ran, nothing applied" and lines[4][4] == "1.20"
    assert all(len(line) == len(accuracy.HEADER) for line in lines)


def test_combinations_and_the_gauge_aligned_accuracy(accuracy: ModuleType, tmp_path: Path) -> None:
    """``a+b`` modes run ``--corrections a,b`` (the kinematic model when they include kinematics); the table
    reports the raw and the gauge-aligned truth accuracy (mean of the surveys' medians)."""
    assert accuracy.parse_modes("kinematics+depth+table,paper,all") == ["paper", "all", "kinematics+depth+table"]
    assert accuracy.corrections_spec("kinematics+depth") == "kinematics,depth"
    assert accuracy.mode_model("kinematics+depth", True) == accuracy.KINEMATIC_MODEL
    assert accuracy.mode_model("depth+table", True) is None
    with pytest.raises(SystemExit, match="unknown mode"):
        accuracy.parse_modes("depth+magic")
    for name, aligned in (("mug", 1.2), ("ketchup", 0.8)):
        _write_results(tmp_path, name, 0.6, {"mode": "depth+table", "applied": ["depth", "table"],
                                             "table": {"keyframes": 10, "fitted": 10}})
        data = json.loads((tmp_path / name / "results.json").read_text())
        data["truth"]["world_gauge"] = {"translation_mm": 2.0, "rotation_deg": 0.2,
                                        "accuracy_aligned": {"median_mm": aligned}}
        (tmp_path / name / "results.json").write_text(json.dumps(data))
    row = accuracy.summarise_processed(tmp_path, ["mug", "ketchup"])
    assert row["truth_aligned_median_mm"] == pytest.approx(1.0)
    assert row["surveys"]["mug"]["gauge_translation_mm"] == 2.0 and row["records"] == ["table"]
    row.update(seed=0, mode="depth+table", model=None)
    rows = [{"seed": 0, "mode": "paper", "model": None, "heldout_median_mm": 1.4}, row]
    accuracy.mark_effects(rows)
    assert rows[1]["effect"] == "applied (nothing recorded for depth)"
    assert accuracy.table_lines(rows)[2][accuracy.HEADER.index("truth aligned mm")] == "1.000"
