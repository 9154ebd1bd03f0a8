"""studies/completeness.py's seeds, rows and per-object summary, on processed results it finds (no darp
run: a survey whose results.json is already in --out is read, not redone)."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from helpers.script_modules import load_study


@pytest.fixture(scope="module")
def completeness() -> ModuleType:
    return load_study("completeness")


def _results(out: Path, name: str, seeable: float, co: tuple[float, float], co_seeable: float) -> None:
    folder = out / "processed" / name
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({
        "clouds": {"fused": 1234},
        "heldout": {"aggregate": {"median_mm": 0.4}},
        "cross_arm": {"directions": [{"co_observed_pct": co[0]}, {"co_observed_pct": co[1]}]},
        "truth": {"cloud": {"accuracy": {"median_mm": 0.1}},
                  "seeable": {"completeness_pct": {"5mm": seeable}, "co_seeable_pct": co_seeable}}}))


def test_rows_and_summary_say_where_co_observation_is_bounded_by_geometry(
        completeness: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # picture_frame is the sixth paper object: seeds 500, 501 at --seed 0 whatever else is listed
    _results(tmp_path, "picture_frame_s500", 99.9, (4.4, 2.9), 0.0)  # faces towards the arms: nothing co-seeable
    _results(tmp_path, "picture_frame_s501", 94.0, (12.0, 15.0), 6.0)
    out_json = tmp_path / "c.json"
    assert completeness.main(["--objects", "picture_frame", "--placements", "2", "--out", str(tmp_path),
                              "--json", str(out_json)]) == 0
    text = capsys.readouterr().out
    assert "| picture_frame_s500 | picture_frame | 1,234 | 99.9 % | 0.100 | 0.400 | 4.4 / 2.9 % | 0.0 % |" in text
    assert ("picture_frame: seeable @5 mm min 94.0 / median 97.0 % over 2 placements (>= 95 %: 1); co-observed, "
            "lower arm, min 2.9 % (>= 10 %: 1; below 10 % where both arms can see < 10 % of the seeable surface: 1)"
            in text)
    assert "2 of 2 surveys processed; 0 failed" in text
    rows = json.loads(out_json.read_text())["rows"]
    assert [r["seed"] for r in rows] == [500, 501] and rows[1]["co_seeable_pct"] == 6.0


def test_first_placement_extends_a_campaign_without_redoing_its_start(
        completeness: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # placement 0 (seed 600, the mug is the seventh object) is absent: starting at 1 must not collect it
    _results(tmp_path, "mug_s601", 98.0, (30.0, 25.0), 20.0)
    assert completeness.main(["--objects", "mug", "--placements", "2", "--first-placement", "1",
                              "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "mug_s600" not in text and "| mug_s601 | mug |" in text
    assert "1 of 1 surveys processed; 0 failed" in text
    assert not (tmp_path / "surveys").exists()  # nothing was collected


def _clouds(out: Path, name: str, arm110: np.ndarray, arm111: np.ndarray) -> None:
    import open3d as o3d

    for arm, points in (("arm110", arm110), ("arm111", arm111)):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        assert o3d.io.write_point_cloud(str(out / "processed" / name / f"{arm}.ply"), cloud)


def test_runs_side_by_side_merge_and_the_gallery_draws_each_objects_least_complete_survey(
        completeness: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # two workers' runs: the mug in one, the cup in the other; the gallery must read the clouds they left
    rng = np.random.default_rng(1)
    shared = rng.uniform(-0.03, 0.03, (300, 3))  # seen by both arms
    for name, seeable in (("mug_s600", 99.5), ("mug_s601", 97.1), ("cup_s900", 99.0)):
        _results(tmp_path, name, seeable, (40.0, 35.0), 20.0)
        _clouds(tmp_path, name, np.vstack([shared, shared[:50] + [0.2, 0, 0]]), shared + 1e-4)
    assert completeness.main(["--objects", "mug", "--placements", "2", "--out", str(tmp_path),
                              "--json", str(tmp_path / "a.json")]) == 0
    assert completeness.main(["--objects", "cup", "--placements", "1", "--out", str(tmp_path),
                              "--json", str(tmp_path / "b.json")]) == 0
    capsys.readouterr()
    png = tmp_path / "gallery.png"
    assert completeness.main(["--from-json", str(tmp_path / "b.json"), str(tmp_path / "a.json"),
                              "--gallery", str(png)]) == 0
    text = capsys.readouterr().out
    assert text.index("| mug_s600 |") < text.index("| mug_s601 |") < text.index("| cup_s900 |")  # by seed
    assert "3 of 3 surveys processed; 0 failed" in text and f"gallery: {png}" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not list(tmp_path.glob("*.partial.png"))
    rows = completeness.merged_rows([tmp_path / "a.json", tmp_path / "b.json"])
    assert {o: r["survey"] for o, r in completeness.least_complete(rows).items()} == {"mug": "mug_s601",
                                                                                       "cup": "cup_s900"}


def test_from_json_names_a_file_that_is_not_a_campaign_run(completeness: ModuleType, tmp_path: Path) -> None:
    bad = tmp_path / "notes.json"
    bad.write_text('{"rows": []}')
    with pytest.raises(SystemExit, match="notes.json: not a --json file of this study"):
        completeness.main(["--from-json", str(bad)])
