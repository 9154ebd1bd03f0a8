"""Issue 16 item 2: the camera-to-joint-log time offset estimated from a survey's own depth."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from darp.reconstruction.time_align import TimeAlignSettings, TimeOffsetEstimate, _from_costs, _parabola_min, accept


def test_the_parabola_finds_an_interior_minimum_and_refuses_an_edge() -> None:
    grid = np.arange(-0.03, 0.0401, 0.0025)
    assert _parabola_min(grid, (grid - 0.0061) ** 2) == pytest.approx(0.0061, abs=1e-6)
    assert _parabola_min(grid, grid) is None  # minimum on the grid's edge
    assert _parabola_min(grid, -((grid - 0.01) ** 2)) is None  # a maximum is no estimate


def test_the_bootstrap_std_reflects_how_well_the_frames_agree() -> None:
    grid = np.arange(-0.03, 0.0401, 0.0025)
    rng = np.random.default_rng(0)
    s = TimeAlignSettings(bootstrap=100)

    def frames(spread_s: float) -> np.ndarray:
        centres = 0.005 + rng.normal(0.0, spread_s, 40)
        return np.array([(grid - c) ** 2 + 1e-4 for c in centres])

    tight = _from_costs(TimeOffsetEstimate("a", None), grid, frames(0.002), s)
    loose = _from_costs(TimeOffsetEstimate("a", None), grid, frames(0.04), s)
    assert tight.offset_s == pytest.approx(0.005, abs=0.0015) and tight.std_s is not None
    assert loose.std_s is not None and loose.std_s > 3 * tight.std_s
    assert accept(tight, s) and not accept(loose, s)


@pytest.mark.slow
def test_a_known_offset_is_recovered_from_a_small_twin_survey(survey_path: Path, tmp_path: Path) -> None:
    """The tiny survey's camera stamps have no latency; moving its joint log 15 ms earlier makes the log
    sampled at the stamps lag by 15 ms, which the estimator must find within its std (and a few ms)."""
    from darp.formats.calibration import read_calibration
    from darp.formats.survey import open_survey
    from darp.processing.job import SurveyJob
    from darp.processing.settings import CorrectionSettings, ProcessSettings

    shifted = tmp_path / survey_path.name
    shutil.copytree(survey_path, shifted)
    log = shifted / "arm_poses.csv"
    lines = log.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        t, rest = line.split(",", 1)
        out.append(f"{float(t) - 0.015:.6f},{rest}")
    log.write_text("\n".join(out) + "\n")
    cal_path = shifted / "truth" / "calibration.json"
    job = SurveyJob(survey=open_survey(shifted), out=tmp_path / "out", calibration=read_calibration(cal_path),
                    calibration_path=cal_path, settings=ProcessSettings(corrections=CorrectionSettings(time=True)))
    try:
        record = job.time_alignment_record()
    finally:
        job.close()
    for arm, entry in record["arms"].items():
        assert entry["source"] == "survey"
        est, std = entry["offset_s"], entry["std_s"]
        assert est is not None and std is not None, entry
        assert abs(est - 0.015) < max(3 * std, 0.004), (arm, est, std)
    assert record["applied_s"], record


def test_cameras_that_disagree_are_not_pooled() -> None:
    from darp.reconstruction.time_align import pooled_offset

    grid = np.arange(-0.03, 0.0401, 0.0025)
    rng = np.random.default_rng(1)
    s = TimeAlignSettings(bootstrap=100)

    def camera(arm: str, centre_s: float) -> TimeOffsetEstimate:
        costs = np.array([(grid - centre_s - rng.normal(0.0, 0.004)) ** 2 for _ in range(30)])
        est = _from_costs(TimeOffsetEstimate(arm, None, n_moving=30, grid_s=grid.tolist()), grid, costs, s)
        est.frame_costs = costs
        return est

    agree = pooled_offset([camera("a", 0.005), camera("b", 0.006)], s)
    assert agree.offset_s == pytest.approx(0.0055, abs=0.002) and accept(agree, s)
    split = pooled_offset([camera("a", 0.0), camera("b", 0.015)], s)
    assert split.offset_s is None and "disagree" in split.reason and not accept(split, s)
