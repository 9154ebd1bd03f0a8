"""Issue 32, outputs: one guard for every command (darp.cli._outputs) refuses an output that is, lies inside or (a
folder output) holds an input, and locks each output so that a second run on it is refused in one line; folders
built by several writes carry UNFINISHED.txt until they are whole; --resume checks every file a stage wrote."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path
from typing import Any

import pytest

from darp.cli._app import run
from darp.formats.atomic import UNFINISHED_FILE
from darp.formats.io_output import OutputBusy, lock_path, output_lock, unfinished_folder
from helpers.runner_job import FakeJob

FIXTURE_BAG = Path(__file__).parent / "fixtures" / "recordings" / "rs257_uncompressed.bag"
RIG = Path(__file__).parents[1] / "src" / "darp" / "data" / "rig_default.yaml"


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    lines = [line for line in err.splitlines() if not line.startswith("darp: warning:")]
    assert "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith("darp: error:") and all(w in lines[0] for w in words), err
    return lines[0]


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _survey(tmp_path: Path) -> Path:
    s = tmp_path / "s"
    s.mkdir()
    (s / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n")
    return s


def _cases(tmp_path: Path) -> dict[str, tuple[list[str], str]]:
    rig = tmp_path / "rig.yaml"
    shutil.copy(RIG, rig)
    (tmp_path / "mesh.ply").write_text("ply\n")
    (tmp_path / "r.pdf").write_text("%PDF")
    s = _survey(tmp_path)
    g = tmp_path / "g"
    g.mkdir(exist_ok=True)
    bag_dir = tmp_path / "rec"
    bag_dir.mkdir()
    shutil.copy(FIXTURE_BAG, bag_dir / "cam1.bag")
    return {
        "calib handeye -o inside": (["calib", "handeye", str(g), "-o", str(g / "handeye.yaml")], "is inside"),
        "calib handeye --report inside": (["calib", "handeye", str(g), "-o", str(tmp_path / "c.json"),
                                           "--report", str(g / "report")], "is inside"),
        "twin waypoints --rig": (["twin", "waypoints", "--object", "cube", "--rig", str(rig), "-o", str(rig)], "is"),
        "twin waypoints --object": (["twin", "waypoints", "--object", str(tmp_path / "mesh.ply"),
                                     "-o", str(tmp_path / "mesh.ply")], "is"),
        "rig plot": (["rig", "plot", "--rig", str(tmp_path / "r.pdf"), "-o", str(tmp_path / "r.pdf")], "is"),
        "poses into the survey": (["poses", str(s), "-o", str(s / "poses")], "is inside"),
        "export into its input": (["export", "tum", str(s), "-o", str(s / "tum")], "is inside"),
        "import into its input": (["import", str(g), "-o", str(g / "imported")], "is inside"),
        "recording export into the recording's folder": (["recording", "export", str(bag_dir / "cam1.bag"),
                                                          "-o", str(bag_dir)], "holds"),
    }


CASES = ["calib handeye -o inside", "calib handeye --report inside", "twin waypoints --rig", "twin waypoints --object",
         "rig plot", "poses into the survey", "export into its input", "import into its input",
         "recording export into the recording's folder"]


@pytest.mark.parametrize("case", CASES)
def test_an_output_over_an_input_is_refused_and_the_input_is_untouched(case: str, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    argv, words = _cases(tmp_path)[case]
    before = _snapshot(tmp_path)
    assert run(argv) == 2
    _one_error_line(capsys, "refusing to write over an input", words)
    assert _snapshot(tmp_path) == before


def test_a_file_named_like_a_built_in_object_does_not_shadow_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cube").write_text("not a mesh")
    assert run(["twin", "waypoints", "--object", "cube", "-o", "w.yaml"]) == 0
    err = capsys.readouterr().err
    assert "using the built-in object" in err and len(err.strip().splitlines()) == 1
    assert run(["twin", "waypoints", "--object", "./cube", "-o", "w2.yaml"]) == 2  # the file, when asked for
    _one_error_line(capsys, "cube")


def test_a_second_run_on_a_locked_output_is_refused_in_one_line(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "w.yaml"
    with output_lock(out):
        assert lock_path(out).is_file()
        assert run(["twin", "waypoints", "--object", "cube", "-o", str(out)]) == 2
        _one_error_line(capsys, str(out), "another darp run is writing it")
        assert not out.exists()
    assert not lock_path(out).exists()  # released and removed
    assert run(["twin", "waypoints", "--object", "cube", "-o", str(out)]) == 0
    assert out.is_file() and not lock_path(out).exists()


def test_the_lock_is_exclusive_between_holders(tmp_path: Path) -> None:
    with output_lock(tmp_path / "x"), pytest.raises(OutputBusy), output_lock(tmp_path / "x"):
        pass
    with output_lock(tmp_path / "x"), output_lock(tmp_path / "y"):  # other outputs are free
        pass


def test_an_unfinished_folder_keeps_its_marker_until_it_is_whole(tmp_path: Path) -> None:
    with unfinished_folder(tmp_path / "ok", "test") as folder:
        assert (folder / UNFINISHED_FILE).is_file()
        (folder / "a.txt").write_text("a")
    assert sorted(p.name for p in (tmp_path / "ok").iterdir()) == ["a.txt"]
    with pytest.raises(OSError), unfinished_folder(tmp_path / "half", "test") as folder:
        (folder / "a.txt").write_text("a")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert (tmp_path / "half" / UNFINISHED_FILE).is_file()


def test_a_marker_that_cannot_be_written_leaves_no_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import darp.formats.io_output as io_output

    def full(*args: Any, **kwargs: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io_output, "write_text_atomic", full)
    with pytest.raises(OSError), unfinished_folder(tmp_path / "new", "test"):
        pass
    assert not (tmp_path / "new").exists()


def test_capture_writer_refuses_a_folder_that_is_not_a_capture_folder(tmp_path: Path) -> None:
    from darp.calibration.board import DEFAULT_BOARD
    from darp.calibration.captures import CaptureWriter
    from darp.errors import CalibrationError

    survey = _survey(tmp_path)
    (survey / "truth").mkdir()
    (survey / "truth" / "settings.yaml").write_text("seed: 1\n")
    before = _snapshot(survey)
    with pytest.raises(CalibrationError, match="holds no captures"):
        CaptureWriter(survey, DEFAULT_BOARD, overwrite=True)
    assert _snapshot(survey) == before


def test_twin_record_never_deletes_a_partial_folder_it_did_not_create(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["twin", "waypoints", "--object", "cube", "-o", str(tmp_path / "w.yaml")]) == 0
    partial = tmp_path / "obj.partial"
    partial.mkdir()
    (partial / "PARTIAL.txt").write_text("partial\n")
    (partial / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert run(["twin", "record", "--object", "cube", "-w", str(tmp_path / "w.yaml"), "-o", str(tmp_path / "obj"),
                "-q", "--no-workers"]) == 2
    _one_error_line(capsys, "unfinished recording", "--overwrite")
    assert (partial / "notes.txt").read_text() == "mine"


def _stages() -> tuple[Any, ...]:
    from darp.processing.runner import Stage

    def kf(job: FakeJob) -> dict[str, Any]:
        job.ran.append("kf")
        (job.out / "kf").mkdir(exist_ok=True)
        for name in ("index.json", "a.npz", "b.npz"):
            (job.out / "kf" / name).write_text(name)
        return {}

    def mesh(job: FakeJob) -> dict[str, Any]:
        job.ran.append("mesh")
        (job.out / "mesh.ply").write_text("m")
        return {}

    return (Stage("kf", kf, ("kf/index.json",)), Stage("mesh", mesh, ("mesh.ply",)))


def test_resume_reruns_a_stage_whose_written_file_was_deleted(tmp_path: Path) -> None:
    from darp.processing.runner import process_survey

    process_survey(FakeJob(tmp_path), _stages())
    job = FakeJob(tmp_path)
    process_survey(job, _stages(), resume=True)
    assert job.ran == []  # all there: nothing reruns
    (tmp_path / "kf" / "b.npz").unlink()  # a keyframe file, not a declared output
    job = FakeJob(tmp_path)
    process_survey(job, _stages(), resume=True)
    assert job.ran == ["kf", "mesh"] and (tmp_path / "kf" / "b.npz").is_file()


def test_resume_with_a_misshapen_stages_file_says_so_and_reruns(tmp_path: Path) -> None:
    from darp.errors import DarpWarning
    from darp.processing.runner import STAGES_FILE, process_survey

    process_survey(FakeJob(tmp_path), _stages())
    (tmp_path / STAGES_FILE).write_text('{"stages": [1, 2]}')
    job = FakeJob(tmp_path)
    with pytest.warns(DarpWarning, match="'stages' must map each stage name"):
        process_survey(job, _stages(), resume=True)
    assert job.ran == ["kf", "mesh"]


def test_a_run_holding_an_output_in_another_process_refuses_this_one(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    import os
    import subprocess
    import sys

    out = tmp_path / "w.yaml"
    code = ("import sys, time\nfrom darp.formats.io_output import output_lock\n"
            f"with output_lock({str(out)!r}):\n    print('held', flush=True)\n    time.sleep(30)\n")
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")})
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert run(["twin", "waypoints", "--object", "cube", "-o", str(out)]) == 2
        _one_error_line(capsys, f"pid {holder.pid}", "another darp run is writing it")
    finally:
        holder.kill()
        holder.wait()
    assert run(["twin", "waypoints", "--object", "cube", "-o", str(out)]) == 0  # the kernel freed the lock


def test_an_output_in_folders_not_made_yet_is_locked_too(tmp_path: Path) -> None:
    out = tmp_path / "a" / "b" / "out.json"
    with output_lock(out) as held:
        assert held is not None and held.parent == out.parent
        with pytest.raises(OutputBusy), output_lock(out):
            pass
    assert not (tmp_path / "a").exists()  # the folders made for the lock alone are gone again
