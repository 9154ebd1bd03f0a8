"""The episode folder: partial -> accepted | rejected | left partial; events; never silently overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from darp.acquisition.episode import Episode, check_name, read_events
from darp.errors import AcquisitionError
from helpers.acquisition_fakes import FakeClock


def test_accept_renames_and_keeps_the_events(tmp_path: Path) -> None:
    clock = FakeClock(100.0)
    ep = Episode(tmp_path, "mug", clock=clock)
    assert ep.path == tmp_path / "mug.partial" and ep.path.is_dir()
    (ep.path / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n")
    clock.sleep(2.5)
    ep.events("decision", value=1.5, where=[1, 2])
    final = ep.accept("all checks passed", extra={"timings": {"planning_s": 0.2}})
    assert final == tmp_path / "mug" and ep.status == "accepted"
    assert not (tmp_path / "mug.partial").exists()
    assert (final / "arm_poses.csv").is_file()
    events = read_events(final)
    assert [e["kind"] for e in events] == ["episode_start", "decision", "episode_accepted"]
    assert events[1]["rig_time_s"] == pytest.approx(102.5) and events[1]["where"] == [1, 2]
    outcome = json.loads((final / "outcome.json").read_text())
    assert outcome["status"] == "accepted" and outcome["timings"]["planning_s"] == 0.2


def test_reject_marks_the_folder_with_the_reason_and_report(tmp_path: Path) -> None:
    ep = Episode(tmp_path, "cup")
    report = {"passed": False, "checks": [{"name": "dropped.arm110", "passed": False, "detail": "40 of 400 dropped"},
                                          {"name": "files", "passed": True, "detail": "ok"}]}
    folder = ep.reject("verification", "verification failed", report)
    assert folder == tmp_path / "cup.rejected"
    text = (folder / "REJECTED.txt").read_text()
    assert text.splitlines()[0] == "rejected: verification"
    assert "failed check dropped.arm110: 40 of 400 dropped" in text and "files" not in text
    assert json.loads((folder / "verification.json").read_text()) == report


def test_partial_is_marked_and_stays(tmp_path: Path) -> None:
    ep = Episode(tmp_path, "clock")
    folder = ep.mark_partial("interrupted", "KeyboardInterrupt")
    assert folder == tmp_path / "clock.partial"
    assert (folder / "PARTIAL.txt").read_text().startswith("partial: interrupted\nKeyboardInterrupt")
    assert json.loads((folder / "outcome.json").read_text())["status"] == "partial"
    ep.events("after_close")  # ignored once closed, never raises
    assert read_events(folder)[-1]["kind"] == "episode_partial"


@pytest.mark.parametrize("existing", ["mug", "mug.partial", "mug.rejected"])
def test_existing_episode_needs_overwrite(tmp_path: Path, existing: str) -> None:
    (tmp_path / existing).mkdir()
    (tmp_path / existing / "keep.txt").write_text("old")
    with pytest.raises(AcquisitionError, match="already exists.*--overwrite"):
        Episode(tmp_path, "mug")
    assert (tmp_path / existing / "keep.txt").read_text() == "old"


def test_overwrite_replaces_only_when_the_new_episode_ends(tmp_path: Path) -> None:
    (tmp_path / "mug").mkdir()
    (tmp_path / "mug" / "old.txt").write_text("old")
    with pytest.raises(AcquisitionError, match="not a survey folder darp wrote"):  # not darp's: never deleted
        Episode(tmp_path, "mug", overwrite=True)
    (tmp_path / "mug" / "events.jsonl").write_text("")  # an earlier episode's folder
    (tmp_path / "mug.partial").mkdir()  # a stale partial goes at once
    ep = Episode(tmp_path, "mug", overwrite=True)
    assert (tmp_path / "mug" / "old.txt").is_file()  # the accepted survey survives a re-run until it ends
    assert not list((tmp_path / "mug.partial").glob("old.txt"))
    ep.reject("no_object", "nothing found")
    assert not (tmp_path / "mug").exists() and (tmp_path / "mug.rejected").is_dir()


@pytest.mark.parametrize("name", ["", ".hidden", "a/b", "..", "x.partial", "x.rejected"])
def test_bad_names_are_refused(name: str) -> None:
    with pytest.raises(AcquisitionError, match="survey name"):
        check_name(name)


def test_read_events_drops_a_cut_short_last_line(tmp_path: Path) -> None:
    path = tmp_path / "events.jsonl"
    path.write_text('{"kind": "a"}\n{"kind": "b"}\n{"kind": "c", "va')
    assert [e["kind"] for e in read_events(path)] == ["a", "b"]
    path.write_text('{"kind": "a"}\nnot json\n{"kind": "c"}\n')
    with pytest.raises(AcquisitionError, match="line 2"):
        read_events(path)
