"""The command line under faults (issue 15): outputs that would land on their inputs, read-only and full file
systems, and signals at fixed moments of a run (start-up, worker start, recording). Each case asserts the exit
code, one ``darp:`` line on stderr (no traceback), inputs unchanged and nothing unfinished under a final name."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from darp.cli._app import run

FIXTURE_BAG = Path(__file__).parent / "fixtures" / "recordings" / "rs257_uncompressed.bag"


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("darp: error:") and all(w in err for w in words), err
    return err


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_calib_solve_refuses_an_output_inside_the_captures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    caps = tmp_path / "caps"
    caps.mkdir()
    (caps / "captures.json").write_text('{"schema": "x"}')
    before = _snapshot(caps)
    assert run(["calib", "solve", str(caps), "-o", str(caps / "captures.json"), "-q"]) == 2
    _one_error_line(capsys, "--out", "refusing to write over an input")
    assert _snapshot(caps) == before


def test_calib_check_refuses_to_replace_the_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    caps, cal = tmp_path / "caps", tmp_path / "cal.json"
    caps.mkdir()
    cal.write_text("{}")
    assert run(["calib", "check", str(caps), "-c", str(cal), "-o", str(cal)]) == 2
    _one_error_line(capsys, "is the input")
    assert cal.read_text() == "{}"


@pytest.mark.parametrize("command", ["process", "keyframes"])
def test_processing_refuses_an_output_over_the_raw_survey(command: str, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    survey = tmp_path / "s"
    survey.mkdir()
    (survey / "arm_poses.csv").write_text("time_s,arm,q1,q2,q3,q4,q5,q6\n")
    out = tmp_path if command == "process" else survey / "kf"  # process writes <out>/<survey>/
    assert run([command, str(survey), "-o", str(out), "--truth-poses"]) == 2
    _one_error_line(capsys, "refusing to write over an input")
    assert sorted(p.name for p in survey.iterdir()) == ["arm_poses.csv"]


def test_twin_overwrite_deletes_only_what_darp_wrote(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    waypoints = tmp_path / "w.yaml"
    waypoints.write_text("arms:\n  arm110:\n    - [0.0, 1.2, -1.0, 0.2, 0.0, 0.0]\n")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("precious")
    assert run(["twin", "record", "-w", str(waypoints), "--object", "cube", "-o", str(mine), "--overwrite",
                "--no-workers", "-q"]) == 2
    _one_error_line(capsys, "refusing to delete it")
    assert (mine / "thesis.tex").read_text() == "precious"
    assert run(["twin", "record", "-w", str(waypoints), "--object", "cube", "-o", str(tmp_path), "--overwrite",
                "--no-workers", "-q"]) == 2  # the output would hold the waypoints file
    _one_error_line(capsys, "holds the input")


@pytest.mark.parametrize("code, words", [(errno.EROFS, "read-only file system"),
                                         (errno.ENOSPC, "no space left on device")])
def test_a_write_error_is_one_line_naming_the_output(code: int, words: str, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    def refuse(*args: object, **kwargs: object) -> tuple[int, str]:
        raise OSError(code, os.strerror(code), str(tmp_path / ".out.yaml.x.partial"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    out = tmp_path / "out.yaml"
    assert run(["twin", "waypoints", "--object", "cube", "--azimuth-deg", "0", "-o", str(out)]) == 2
    assert _one_error_line(capsys, words) == f"darp: error: {out}: {words}"
    assert list(tmp_path.iterdir()) == []


def test_export_on_a_full_disk_midway_leaves_no_temporary_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    real_replace, calls = os.replace, []

    def full_after_three(src: str, dst: str) -> None:  # the disk fills after three frames
        calls.append(dst)
        if len(calls) > 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", full_after_three)
    out = tmp_path / "e"
    before = FIXTURE_BAG.read_bytes()
    assert run(["recording", "export", str(FIXTURE_BAG), "-o", str(out)]) == 2
    _one_error_line(capsys, "no space left on device")
    assert not [p for p in out.iterdir() if p.name.endswith(".partial")]
    assert FIXTURE_BAG.read_bytes() == before


def _userns_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k none /mnt"],
                           capture_output=True, check=False)
    return probe.returncode == 0


@pytest.mark.skipif(not _userns_tmpfs(), reason="needs user namespaces to mount a tiny tmpfs")
@pytest.mark.parametrize("mode", ["full", "ro"])
def test_export_to_a_real_full_or_read_only_tmpfs(mode: str, tmp_path: Path) -> None:
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    prepare = ("dd if=/dev/zero of=$M/fill bs=4k count=100 2>/dev/null; " if mode == "full"
               else "mount -o remount,ro $M; ")
    script = (f"M={mnt}; mount -t tmpfs -o size=400k none $M && {prepare}"
              f'"{sys.executable}" -m darp recording export {FIXTURE_BAG} -o $M/e; echo "rc=$?"; ls -A $M $M/e 2>&1')
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}, check=False)
    assert "rc=2" in done.stdout, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("darp: error:"), done.stderr
    assert (mode == "full") == ("no space left on device" in lines[0]) and ".partial" not in done.stdout


def _tiny_recording(tmp_path: Path) -> tuple[list[str], Path]:
    waypoints = tmp_path / "w.yaml"
    waypoints.write_text("arms:\n  arm110:\n    - {q_rad: [0.1, 1.2, -1.0, 0.2, 0.0, 0.0], dwell_s: 0.2}\n")
    out = tmp_path / "s"
    return [sys.executable, "-m", "darp", "twin", "record", "-w", str(waypoints), "--object", "cube",
            "--placement", "0,0,0", "--fps", "6", "--resolution", "424x240", "-o", str(out), "-q"], out


@pytest.mark.slow
@pytest.mark.parametrize("sig,delay", [(signal.SIGINT, 1.1), (signal.SIGTERM, 2.3), (signal.SIGHUP, 3.6),
                                       (signal.SIGINT, 0.6)],
                         ids=["SIGINT", "SIGTERM", "SIGHUP", "SIGINT-during-imports"])
def test_a_signal_at_a_fixed_moment_ends_twin_record_cleanly(sig: signal.Signals, delay: float,
                                                             tmp_path: Path) -> None:
    """Moments spread over the first ~4 s (start-up, worker start, recording; fixed, so that a failure reruns
    the same way); the last case aims at the imports, where an interrupt inside a native extension's own
    Python evaluation once ended the run by SIGINT."""
    command, out = _tiny_recording(tmp_path)
    child = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, start_new_session=True,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "MUJOCO_GL": "egl"})
    time.sleep(delay)
    sent = time.monotonic()
    if sig == signal.SIGINT:  # Ctrl-C: the whole process group (camera workers too)
        os.killpg(child.pid, sig)
    else:
        child.send_signal(sig)
    try:
        _, err = child.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(child.pid, signal.SIGKILL)
        pytest.fail(f"{sig.name} at {delay:.2f} s: still running 30 s later")
    took = time.monotonic() - sent
    finished = child.returncode == 0
    assert finished or child.returncode == 128 + sig, (delay, child.returncode, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1, (delay, err)
    assert took < 10.0, (delay, took)
    assert not out.with_name("s.partial").exists(), (delay, err)
    if finished or out.exists():  # a signal after the final rename (a fast host) finds the recording complete
        assert (out / ".darp-written").is_file() and not (out / "PARTIAL.txt").exists(), (delay, err)


@pytest.mark.slow
def test_a_killed_recording_stays_marked_partial(tmp_path: Path) -> None:
    command, out = _tiny_recording(tmp_path)
    child = subprocess.Popen(command, stderr=subprocess.DEVNULL, start_new_session=True,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "MUJOCO_GL": "egl"})
    partial = out.with_name("s.partial")
    deadline = time.monotonic() + 60
    while not partial.exists() and time.monotonic() < deadline and child.poll() is None:
        time.sleep(0.05)
    time.sleep(1.5)  # past set-up: worker start or recording (fixed, so that a failure reruns the same way)
    os.killpg(child.pid, signal.SIGKILL)
    child.wait()
    assert not out.exists()
    assert (partial / "PARTIAL.txt").is_file()  # the first file written, never removed


def test_an_interrupt_is_held_until_a_deferred_block_ends() -> None:
    """A child process's start is not cut in half: the interrupt comes at the block's end, once."""
    from darp.errors import Interrupted, interrupts_deferred, raise_interrupted

    steps = []
    with pytest.raises(Interrupted) as caught, interrupts_deferred():
        raise_interrupted(signal.SIGTERM)
        steps.append("after the signal")
        with interrupts_deferred():  # nested: still held
            raise_interrupted(signal.SIGHUP)
            steps.append("nested")
        steps.append("outer end")
    assert steps == ["after the signal", "nested", "outer end"]
    assert caught.value.signum == signal.SIGTERM  # the first signal wins
    with pytest.raises(Interrupted):  # outside a block: at once
        raise_interrupted(signal.SIGTERM)
    with interrupts_deferred():  # nothing pending: nothing raised
        pass
