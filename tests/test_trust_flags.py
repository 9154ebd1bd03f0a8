"""Trust flags (issue 28 item 5): the signals beside the held-out figures and the flags they raise, on results
documents and on twin surveys recorded at 1x, 2x and 4x the ``paper`` profile's errors."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest

from darp.evaluation.trust import TrustBounds, envelope_coverage_pct, trust_signals


def clean() -> dict[str, Any]:
    """A plausible two-arm results document (the paper's level of agreement)."""
    stats = {"median_mm": 0.2, "p90_mm": 0.5}
    return {"keyframes": {"arms": {"arm110": {}, "arm111": {}}},
            "heldout": {"aggregate": {"median_mm": 2.0, "p90_mm": 6.0},
                        "arms": {"arm110": {"p90_mm": 6.5}, "arm111": {"p90_mm": 5.5}}},
            "cross_arm": {"directions": [{"point_to_plane": stats}, {"point_to_plane": {"median_mm": 0.3}}]},
            "truth": None}


def test_a_clean_document_raises_no_flag() -> None:
    t = trust_signals(clean(), handeye_p90_mm=3.9, envelope_pct=40.0)
    assert t["flags"] == [] and t["signals"]["cross_arm_mm"] == 0.3 and t["signals"]["heldout_median_mm"] == 2.0
    assert t["bounds"] == json.loads(json.dumps(TrustBounds().__dict__))


@pytest.mark.parametrize(("change", "words"), [
    (lambda r: r["cross_arm"]["directions"][0]["point_to_plane"].update(median_mm=6.5), "arms disagree"),
    (lambda r: r["cross_arm"]["directions"][0]["point_to_plane"].update(median_mm=6.2), "arms disagree"),  # > 3x
    (lambda r: r.update(cross_arm={"directions": [{"point_to_plane": {}}, {"point_to_plane": {}}]}), "no co-observed"),
    (lambda r: r["heldout"]["arms"]["arm111"].update(p90_mm=27.0), "arm111's held-out p90"),
    (lambda r: r["heldout"]["aggregate"].update(median_mm=5.0), "held-out median 5.00"),
    (lambda r: r.update(truth={"cloud": {"accuracy": {"median_mm": 6.5}}}), "from the true surface"),
    (lambda r: r.update(truth={"cloud": {"accuracy": {"median_mm": 4.5}},
                               "seeable": {"completeness_pct": {"5mm": 25.7}}}), "surface its poses could see"),
])
def test_each_signal_flags_when_out_of_bounds(change: Any, words: str) -> None:
    r = copy.deepcopy(clean())
    change(r)
    flags = trust_signals(r, handeye_p90_mm=3.9, envelope_pct=40.0)["flags"]
    assert any(words in f for f in flags), flags


def test_calibration_and_coverage_bounds() -> None:
    assert "calibration's own held-out" in trust_signals(clean(), handeye_p90_mm=12.5)["flags"][0]
    # a calibration at the real rig's level (the paper-profile demo, seed 0: p90 8.22 mm) is not flagged
    assert trust_signals(clean(), handeye_p90_mm=8.22, envelope_pct=40.0)["flags"] == []
    assert "envelope's top and side" in trust_signals(clean(), envelope_pct=4.4)["flags"][0]
    # 1,000 voxels of 2 mm (40 cm^2) over an envelope of radius 5 cm and height 10 cm (78.5 + 314.2 cm^2)
    assert envelope_coverage_pct(1000, {"radius_m": 0.05, "height_m": 0.1}, 0.002) == pytest.approx(
        100 * 40.0 / (3.14159 * 25 + 2 * 3.14159 * 50), rel=1e-3)
    assert envelope_coverage_pct(10, {"radius_m": None}, 0.002) is None


@pytest.mark.slow
def test_twin_surveys_at_2x_and_4x_the_paper_errors_are_flagged_and_1x_is_not(tmp_path: Path) -> None:
    """Tiny mug surveys (424x240, three views per arm, seed 3) at 1x, 2x and 4x the ``paper`` profile's errors,
    processed with the twin's true calibration; the 1x survey is then exported, imported and compared with
    Open3D's TSDF by benchmarks/real_fusion.py."""
    from darp.cli._app import run
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import make_object
    from darp.twin.record import record_survey
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints
    from helpers.script_modules import load_benchmark
    from helpers.twin_surveys import TINY_PLACEMENT

    obj, rig = make_object("mug"), load_rig()
    centre = (TINY_PLACEMENT.x_m, TINY_PLACEMENT.y_m, 0.5 * obj.height_m)
    plan = WaypointPlan({arm: tuple(orbit_waypoints(rig, arm, centre, 0.33, azimuths_deg=(-25.0, 0.0, 25.0),
                                                    elevation_deg=40.0, dwell_s=0.8))
                         for arm in ("arm110", "arm111")}, ("arm110", "arm111"))
    flags = {}
    for scale in (1, 2, 4):
        survey = tmp_path / f"mug-x{scale}"
        settings = TwinSettings.from_profile("paper", seed=3).scaled(scale).with_camera(fps=6, width=424, height=240)
        record_survey(survey, plan, obj, TINY_PLACEMENT, settings=settings)
        assert run(["process", str(survey), "-o", str(tmp_path / "out"), "-c",
                    str(survey / "truth" / "calibration.json")]) == 0
        r = json.loads((tmp_path / "out" / survey.name / "results.json").read_text())
        flags[scale] = r["trust"]["flags"]
        print(scale, json.dumps(r["trust"]["signals"]))
    assert flags[1] == [], flags[1]
    assert len(flags[2]) >= 2 and len(flags[4]) >= 2, flags
    from darp.processing.results import write_summary

    write_summary(tmp_path / "out", [tmp_path / "out" / f"mug-x{scale}" for scale in (1, 2, 4)])
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    assert {s["name"]: bool(s.get("trust_flags")) for s in summary["surveys"]} == {
        "mug-x1": False, "mug-x2": True, "mug-x4": True}
    assert run(["report", str(tmp_path / "out")]) == 0
    assert "not trusted" in (tmp_path / "out" / "report.md").read_text()
    # the paper-profile survey through export and import: the measured surface against Open3D's TSDF
    assert run(["export", "open3d", str(tmp_path / "out" / "mug-x1"), "-o", str(tmp_path / "o3d")]) == 0
    left = sorted(p for p in (tmp_path / "o3d").iterdir() if p.is_dir())[0]
    assert run(["import", str(left), "-o", str(tmp_path / "imp")]) == 0
    bench = load_benchmark("real_fusion")
    m = bench.measure(tmp_path / "imp", tmp_path / "bench", stride=2, peers=("vbg2",))
    assert m["surface"] == "measured" and m["darp"]["points"] == m["vbg2"]["points"] > 1000
    assert m["darp"]["median_mm"] < 10 and m["vbg2"]["median_mm"] < 10
