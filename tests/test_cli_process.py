"""``darp keyframes``, ``darp process`` and ``darp report`` from the command line: outputs on a tiny twin
survey, and one-line errors with exit code 2 for bad input."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from darp.cli._app import run


def one_error_line(capsys, must_contain: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("darp: error:") and must_contain in err[0], err


def test_missing_survey_folder(tmp_path: Path, capsys) -> None:
    assert run(["process", str(tmp_path / "nope"), "--out", str(tmp_path / "out"), "-c", str(tmp_path / "c.json")]) == 2
    one_error_line(capsys, "does not exist")


def test_folder_without_surveys(tmp_path: Path, capsys) -> None:
    (tmp_path / "empty").mkdir()
    assert run(["process", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2  # named before -c is asked for
    one_error_line(capsys, "not a survey folder")
    assert run(["keyframes", str(tmp_path / "empty"), "--out", str(tmp_path / "kf"), "--truth-poses"]) == 2
    one_error_line(capsys, "empty")


def test_a_bad_calibration_file_is_one_line_for_a_batch(tmp_path: Path, capsys) -> None:
    """The calibration is one file for every survey: unreadable, it is one line before any survey starts (was: one
    'open failed' line per survey, a count line and a table of FAILED rows)."""
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n")
    (tmp_path / "cal.json").write_text("{}")
    assert run(["process", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "o"),
                "-c", str(tmp_path / "cal.json")]) == 2
    one_error_line(capsys, "cal.json")
    assert not (tmp_path / "o").exists()


def test_report_without_results(tmp_path: Path, capsys) -> None:
    assert run(["report", str(tmp_path)]) == 2
    one_error_line(capsys, "no processed survey")


@pytest.mark.slow
def test_bad_settings_and_calibration(survey_path: Path, tmp_path: Path, capsys) -> None:
    settings = tmp_path / "settings.yaml"
    settings.write_text("fusion: {voxel_size_mm: 2}\n")
    assert run(["process", str(survey_path), "--out", str(tmp_path / "o"), "--truth-poses",
                "--settings", str(settings)]) == 2
    one_error_line(capsys, "voxel_size_mm")
    settings.write_text("keyframes: {per_view: 0}\n")
    assert run(["keyframes", str(survey_path), "--out", str(tmp_path / "o"), "--truth-poses",
                "--settings", str(settings)]) == 2
    one_error_line(capsys, "per_view")
    assert run(["process", str(survey_path), "--out", str(tmp_path / "o")]) == 2
    one_error_line(capsys, "'--calibration': required")
    bad = tmp_path / "cal.json"
    bad.write_text("{}")
    assert run(["process", str(survey_path), "--out", str(tmp_path / "o"), "-c", str(bad)]) == 2
    one_error_line(capsys, "cal.json")
    real = tmp_path / "real"  # a survey without truth/: --truth-poses cannot work
    shutil.copytree(survey_path, real, ignore=shutil.ignore_patterns("truth"))
    assert run(["process", str(real), "--out", str(tmp_path / "o"), "--truth-poses",
                "-c", str(survey_path / "truth" / "calibration.json")]) == 2
    one_error_line(capsys, "truth")


@pytest.mark.slow
def test_keyframes_process_and_report(survey_path: Path, tmp_path: Path, capsys) -> None:
    calibration = str(survey_path / "truth" / "calibration.json")
    kf = tmp_path / "kf"
    assert run(["keyframes", str(survey_path), "-c", calibration, "--out", str(kf)]) == 0
    index = json.loads((kf / "keyframes.json").read_text())
    assert index["schema"] == "darp-keyframes/1" and index["keyframes"]
    assert all((kf / entry["file"]).is_file() for entry in index["keyframes"])

    out = tmp_path / "out"
    assert run(["process", str(survey_path), "-c", calibration, "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    per = json.loads((out / "cube" / "results.json").read_text())
    summary = json.loads((out / "results.json").read_text())
    assert per["schema"] == "darp-results/1" and summary["schema"] == "darp-results-summary/1"
    assert summary["surveys"][0]["name"] == "cube" and summary["heldout"]["aggregate"]["count"] > 0
    for name in ("arm110.ply", "arm111.ply", "fused.ply", "mesh.ply", "poses/summary.json"):
        assert (out / "cube" / name).is_file(), name
    assert run(["process", str(survey_path), "-c", calibration, "--out", str(out), "--resume"]) == 0

    assert run(["report", str(out)]) == 0
    md = (out / "report.md").read_text()
    html = (out / "report.html").read_text()
    for heading in ("Release composition", "Held-out RGB-D evaluation", "Per-object results", "Cross-arm consistency",
                    "Ground truth (digital twin)", "Representative multimodal observations", "Figures"):
        assert f"## {heading}" in md and heading in html, heading
    assert "paper (DARP, real rig)" in md and "1,563,466" in md and "2.13" in md
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(images) == 4  # observations, cross-arm, partial/fused, held-out histogram
    assert all((out / image).is_file() for image in images)
    assert html.count("data:image/png;base64,") == len(images)


@pytest.mark.slow
def test_a_survey_without_truth_is_processed_without_truth_metrics(survey_path: Path, tmp_path: Path) -> None:
    real = tmp_path / "mug"
    shutil.copytree(survey_path, real, ignore=shutil.ignore_patterns("truth"))
    out = tmp_path / "out"
    assert run(["process", str(real), "-c", str(survey_path / "truth" / "calibration.json"), "--out", str(out)]) == 0
    per = json.loads((out / "mug" / "results.json").read_text())
    assert per["truth"] is None and per["heldout"]["aggregate"]["count"] > 0
    assert run(["report", str(out)]) == 0
    assert "Ground truth" not in (out / "report.md").read_text()


@pytest.mark.slow
def test_keyframes_and_process_read_a_cut_recording_with_one_warning(survey_path: Path, tmp_path: Path, capsys) -> None:
    """arm110's bag cut inside a chunk at about 90 %: both commands warn once, naming it, and use what is left."""
    from darp.formats.realsense.bag.reader import BagRecording
    from helpers.damaged_recordings import cut_copy, salvage_warning

    copy = tmp_path / "cube"
    copy.mkdir()
    for entry in survey_path.iterdir():  # the rest of the survey as is (links: the bags are large)
        (copy / entry.name).symlink_to(entry)
    name = "cam348522076490.bag"
    with BagRecording(survey_path / name) as whole:
        chunks = whole._index.chunks
        victim = chunks[len(chunks) * 9 // 10]
        depth_chunks = whole._data["depth"]["chunk"]
    recovered = int((depth_chunks < chunks.index(victim)).sum())
    (copy / name).unlink()
    cut_copy(survey_path / name, copy / name, victim.data_start + victim.data_len // 2)
    calibration = str(survey_path / "truth" / "calibration.json")

    kf = tmp_path / "kf"
    assert run(["keyframes", str(copy), "-c", calibration, "--out", str(kf)]) == 0
    salvage_warning(capsys.readouterr().err, copy / name, "no index", f"truncated at byte {victim.pos}: ",
                    f"recovered {recovered} depth")
    assert json.loads((kf / "keyframes.json").read_text())["keyframes"]

    out = tmp_path / "out"
    assert run(["process", str(copy), "-c", calibration, "--out", str(out)]) == 0
    salvage_warning(capsys.readouterr().err, copy / name, "no index", f"truncated at byte {victim.pos}: ")
    poses = json.loads((out / "cube" / "poses" / "summary.json").read_text())
    assert poses["arms"]["arm110"]["frames"] == recovered
    assert json.loads((out / "cube" / "results.json").read_text())["heldout"]["aggregate"]["count"] > 0
