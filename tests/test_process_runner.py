"""The stage runner (darp.processing.runner) with tiny fake stages and no survey: success, failure cleaning,
resume, missing outputs, the UNFINISHED.txt lifecycle, staged outputs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from darp.errors import DarpError, ProcessingError, ReconstructionError
from darp.processing.runner import (
    STAGES_FILE,
    UNFINISHED_FILE,
    Stage,
    StageFailure,
    process_survey,
    read_stage_state,
    staged_outputs,
    unfinished_reason,
)
from helpers.runner_job import FakeJob


def _step(name: str, files: Any) -> Stage[FakeJob]:
    """A stage writing ``files(job)`` (or the tuple) with staged outputs, recording that it ran."""

    def run(job: FakeJob) -> dict[str, Any]:
        job.ran.append(name)
        job.markers[name] = unfinished_reason(job.out)
        names = list(files(job) if callable(files) else files)
        with staged_outputs(job.out, names) as paths:
            for path in paths.values():
                path.write_text(f"{name} {job.settings}")
            if job.fail == name:
                raise ReconstructionError(f"{name} cannot go on", job.out / "input.txt")
        return {"wrote": names}

    return Stage(name, run, files, (name,))


def _parts(job: FakeJob) -> tuple[str, ...]:
    """Outputs that depend on the job (as fusion's one cloud per arm)."""
    return (*(f"{p}.ply" for p in job.parts), "b.txt")


STAGES = (_step("a", ("a.txt",)), _step("b", _parts), _step("c", ("c/c.json",)))
ALL_FILES = ("a.txt", "left.ply", "right.ply", "b.txt", "c/c.json")


def _exists(job: FakeJob) -> list[str]:
    return [f for f in ALL_FILES if (job.out / f).is_file()]


def test_success_runs_every_stage_records_it_and_leaves_no_marker(tmp_path: Path) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    job = FakeJob(tmp_path / "out")
    report = process_survey(job, STAGES)
    assert job.ran == ["a", "b", "c"] and list(report) == ["a", "b", "c"]
    assert all(not r["skipped"] and r["seconds"] >= 0 for r in report.values())
    assert report["b"]["summary"] == {"wrote": ["left.ply", "right.ply", "b.txt"]}
    assert _exists(job) == list(ALL_FILES)
    assert not (job.out / UNFINISHED_FILE).exists() and unfinished_reason(job.out) is None
    state = read_stage_state(job.out)
    assert state["survey"] == "fake" and list(state["stages"]) == ["a", "b", "c"] and "failed" not in state
    assert len({s["fingerprint"] for s in state["stages"].values()}) == 3
    assert job.closed == 1
    assert not [p for p in job.out.rglob("*") if p.name.endswith(".partial")]


def test_failure_removes_the_failed_and_later_stages_outputs_and_marks_the_folder(tmp_path: Path) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    process_survey(FakeJob(tmp_path / "out"), STAGES)  # a complete earlier run
    job = FakeJob(tmp_path / "out", fail="b")
    with pytest.raises(StageFailure) as caught:
        process_survey(job, STAGES)
    err = caught.value
    assert isinstance(err, ProcessingError) and isinstance(err, DarpError)
    assert (err.survey, err.stage) == ("fake", "b") and "b cannot go on" in err.reason
    assert str(err).startswith("survey fake: b failed: ") and "\n" not in str(err)
    assert job.ran == ["a", "b"] and job.closed == 1
    # every declared output of b (computed from the job: both parts) and of the later stage c is gone
    assert _exists(job) == ["a.txt"]
    assert not [p for p in job.out.rglob("*") if p.name.endswith(".partial")]
    assert unfinished_reason(job.out) is not None and unfinished_reason(job.out).startswith("failed: b: ")
    state = json.loads((job.out / STAGES_FILE).read_text())
    assert state["failed"]["stage"] == "b" and list(state["stages"]) == ["a"]


def test_a_library_error_inside_a_stage_fails_that_stage_on_one_line(tmp_path: Path) -> None:
    def broken(job: FakeJob) -> dict[str, Any]:
        raise ValueError("bad value\nsecond line")

    job = FakeJob(tmp_path / "out")
    with pytest.raises(StageFailure) as caught:
        process_survey(job, (Stage("broken", broken, ("x.txt",)),))
    assert caught.value.reason == "ValueError: bad value"


def test_resume_skips_unchanged_stages_and_reruns_from_a_changed_setting(tmp_path: Path) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    process_survey(FakeJob(tmp_path / "out"), STAGES)
    again = FakeJob(tmp_path / "out")
    report = process_survey(again, STAGES, resume=True)
    assert again.ran == [] and all(r["skipped"] for r in report.values())
    assert report["b"]["summary"] == {"wrote": ["left.ply", "right.ply", "b.txt"]}  # the recorded summary
    assert not (again.out / UNFINISHED_FILE).exists()

    changed = FakeJob(tmp_path / "out", settings={"a": 1, "b": 2, "c": 1})  # b's settings group changed
    report = process_survey(changed, STAGES, resume=True)
    assert changed.ran == ["b", "c"] and report["a"]["skipped"] and not report["c"]["skipped"]

    without = FakeJob(tmp_path / "out", settings={"a": 1, "b": 2, "c": 1})
    process_survey(without, STAGES)  # no resume: everything runs
    assert without.ran == ["a", "b", "c"]

    other_inputs = FakeJob(tmp_path / "out", settings={"a": 1, "b": 2, "c": 1}, inputs="v2")
    process_survey(other_inputs, STAGES, resume=True)  # the job's identity is in every fingerprint
    assert other_inputs.ran == ["a", "b", "c"]


@pytest.mark.parametrize("missing", ["left.ply", "b.txt"])
def test_a_missing_output_forces_its_stage_and_the_later_ones_to_rerun(tmp_path: Path, missing: str) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    process_survey(FakeJob(tmp_path / "out"), STAGES)
    (tmp_path / "out" / missing).unlink()
    job = FakeJob(tmp_path / "out")
    process_survey(job, STAGES, resume=True)
    assert job.ran == ["b", "c"] and _exists(job) == list(ALL_FILES)


def test_an_unreadable_or_misshapen_stages_file_skips_nothing(tmp_path: Path) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    process_survey(FakeJob(tmp_path / "out"), STAGES)
    for text in ('{"stages": [1, 2]}', "[1, 2]", "{not json", '{"stages": {"a": 1, "b": [], "c": null}}'):
        (tmp_path / "out" / STAGES_FILE).write_text(text)
        job = FakeJob(tmp_path / "out")
        process_survey(job, STAGES, resume=True)
        assert job.ran == ["a", "b", "c"], text


def test_the_unfinished_marker_lifecycle(tmp_path: Path) -> None:
    (tmp_path / "out" / "c").mkdir(parents=True)
    job = FakeJob(tmp_path / "out")
    process_survey(job, STAGES)
    assert job.markers == {"a": "running: a", "b": "running: b", "c": "running: c"}  # each stage marked
    assert unfinished_reason(job.out) is None

    def interrupted(job: FakeJob) -> dict[str, Any]:
        with staged_outputs(job.out, ["b.txt"]) as paths:
            paths["b.txt"].write_text("half")
            raise KeyboardInterrupt

    stages = (STAGES[0], Stage("b", interrupted, _parts, ("b",)), STAGES[2])
    with pytest.raises(KeyboardInterrupt):
        process_survey(FakeJob(tmp_path / "out", settings={"a": 1, "b": 3, "c": 1}), stages, resume=True)
    assert unfinished_reason(job.out) == "running: b"  # as a SIGKILL would leave it
    assert "not results" in (job.out / UNFINISHED_FILE).read_text()
    assert (job.out / "b.txt").read_text() != "half"  # the earlier run's file; the interrupted one never landed
    assert not [p for p in job.out.rglob("*") if p.name.endswith(".partial")]

    failing = FakeJob(tmp_path / "out", fail="c")
    with pytest.raises(StageFailure):
        process_survey(failing, STAGES)
    assert unfinished_reason(job.out) == f"failed: c: {job.out / 'input.txt'}: c cannot go on"

    done = FakeJob(tmp_path / "out")
    process_survey(done, STAGES, resume=True)  # a completed resume removes the marker
    assert done.ran == ["c"] and unfinished_reason(job.out) is None


def test_unfinished_reason_of_an_empty_marker_and_of_none(tmp_path: Path) -> None:
    assert unfinished_reason(tmp_path) is None
    (tmp_path / UNFINISHED_FILE).write_text("")
    assert unfinished_reason(tmp_path) == "unfinished"


def test_staged_outputs_land_together_under_unique_temporary_names(tmp_path: Path) -> None:
    with staged_outputs(tmp_path, ["x.ply", "y.ply"]) as first, staged_outputs(tmp_path, ["x.ply"]) as second:
        assert first["x.ply"] != second["x.ply"]  # two writers of one output never share a temporary file
        assert all(p.name.endswith(".partial") and p.parent == tmp_path for p in first.values())
        first["x.ply"].write_text("x")
        first["y.ply"].write_text("y")
        second["x.ply"].write_text("other x")
        assert not (tmp_path / "x.ply").exists()  # nothing final until the block ends
    assert (tmp_path / "x.ply").read_text() in ("x", "other x") and (tmp_path / "y.ply").read_text() == "y"
    with pytest.raises(OSError), staged_outputs(tmp_path, ["z.ply", "y.ply"]) as paths:
        paths["z.ply"].write_text("z")
        raise OSError("disk full")
    assert not (tmp_path / "z.ply").exists() and (tmp_path / "y.ply").read_text() == "y"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.ply", "y.ply"]
