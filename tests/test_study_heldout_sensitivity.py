"""studies/heldout_sensitivity.py on the session's processed tiny twin survey: the baseline reproduces the
pipeline's own held-out distances; injected errors are seeded, change what they should, and bad input is named."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from helpers.script_modules import load_study


@pytest.fixture(scope="module")
def sensitivity() -> ModuleType:
    return load_study("heldout_sensitivity")


def _recorded_mm(processed: Path) -> np.ndarray:
    with np.load(processed / "evaluation" / "heldout_distances.npz") as data:
        return np.sort(np.concatenate([data[k] for k in data.files]).astype(np.float64) * 1000.0)


def test_baseline_reproduces_the_pipelines_heldout_distances(sensitivity: ModuleType, processed_path: Path) -> None:
    from darp.processing.settings import ProcessSettings

    again = np.sort(sensitivity.reevaluate(processed_path, sensitivity.Case("baseline"), ProcessSettings()))
    recorded = _recorded_mm(processed_path)
    assert again.size == recorded.size > 1000
    np.testing.assert_allclose(again, recorded, atol=1e-3)  # float32 distances, in mm


def test_injected_errors_are_seeded_and_move_the_figures(sensitivity: ModuleType, processed_path: Path) -> None:
    from darp.processing.settings import ProcessSettings

    settings = ProcessSettings()
    base = sensitivity.figures(sensitivity.reevaluate(processed_path, sensitivity.Case("baseline"), settings))
    noisy_case = sensitivity.Case.parse("noisy=pixel_px:0.15")
    noisy = sensitivity.reevaluate(processed_path, noisy_case, settings)
    np.testing.assert_array_equal(noisy, sensitivity.reevaluate(processed_path, noisy_case, settings))
    assert sensitivity.figures(noisy)["median_mm"] > 1.1 * base["median_mm"]  # held-out points carry the noise
    moved = sensitivity.figures(sensitivity.reevaluate(
        processed_path, sensitivity.Case.parse("moved=pose_mm:3,pose_deg:0.3"), settings))
    assert moved["median_mm"] != pytest.approx(base["median_mm"], rel=1e-3)


def test_view_error_is_shared_by_a_views_keyframes_and_has_its_size(sensitivity: ModuleType) -> None:
    case = sensitivity.Case("c", pose_mm=2.0, pose_deg=0.2)
    a, b = sensitivity.view_error(case, "mug", "arm110", 3), sensitivity.view_error(case, "mug", "arm110", 3)
    np.testing.assert_array_equal(a, b)
    lengths = [np.linalg.norm(sensitivity.view_error(case, "mug", "arm111", v)[:3, 3]) for v in range(400)]
    assert np.sqrt(np.mean(np.square(lengths))) == pytest.approx(2e-3, rel=0.1)


def test_main_prints_pools_and_writes_json(sensitivity: ModuleType, processed_path: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.json"
    assert sensitivity.main([str(processed_path), "--case", "field=field_px:0.2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| baseline |" in text and "| field |" in text
    rows = json.loads(out.read_text())["rows"]
    assert [r["case"]["name"] for r in rows] == ["baseline", "field"]
    assert rows[0]["points"] == _recorded_mm(processed_path).size and 0 <= rows[1]["in_band"] <= 5


@pytest.mark.parametrize(("spec", "message"), [
    ("nothing", "expected NAME=key:value"),
    ("x=size:2", "unknown key 'size'"),
    ("x=pose_mm:two", "pose_mm needs a number"),
    ("x=pixel_px:-1", "pixel_px must be >= 0"),
])
def test_bad_cases_are_named(sensitivity: ModuleType, spec: str, message: str) -> None:
    with pytest.raises(SystemExit, match=message):
        sensitivity.Case.parse(spec)


def test_a_folder_that_is_not_a_processed_survey_is_named(sensitivity: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match=f"{tmp_path}: not a processed survey"):
        sensitivity.main([str(tmp_path)])
