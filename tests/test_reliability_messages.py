"""Issue 32, messages: what darp prints under faults says the right thing once - the failing stage on a full disk,
nothing from libpng or matplotlib, no progress bar in a pipe or log, a report table that survives ``|`` in a name,
one line from ``hardware check``, and a closed stdout that neither cuts a command short nor exits 1 silently."""

from __future__ import annotations

import errno
import logging
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from darp.cli._app import run
from darp.errors import FormatError
from helpers.runner_job import FakeJob


def test_a_full_disk_in_a_stage_names_that_stage(tmp_path: Path) -> None:
    from darp.processing.runner import Stage, StageFailure, process_survey

    def fusion(job: FakeJob) -> dict[str, Any]:
        raise OSError(errno.ENOSPC, "No space left on device", str(job.out / "fused.ply"))

    stages = (Stage("poses", lambda job: {}, ()), Stage("fusion", fusion, ("fused.ply",)))
    with pytest.raises(StageFailure) as caught:
        process_survey(FakeJob(tmp_path), stages)
    assert caught.value.stage == "fusion"
    assert caught.value.reason == f"{tmp_path / 'fused.ply'}: no space left on device"


def test_a_damaged_png_prints_nothing_of_libpng(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    import cv2

    from darp.formats.io_input import decode_image

    path = tmp_path / "a.png"
    assert cv2.imwrite(str(path), np.arange(64 * 64, dtype=np.uint16).reshape(64, 64))
    path.write_bytes(path.read_bytes()[:200])
    assert decode_image(path, cv2.IMREAD_UNCHANGED) is None
    out, err = capfd.readouterr()
    assert err == "" and out == ""


def test_matplotlib_notes_are_silenced_by_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["twin", "objects"]) == 0
    assert logging.getLogger("matplotlib").getEffectiveLevel() >= logging.ERROR


def test_no_progress_bar_outside_a_terminal() -> None:
    from darp.cli._options import progress_bar

    assert progress_bar(quiet=False).disable  # pytest's stderr is not a terminal
    cli = Path(__file__).parents[1] / "src" / "darp" / "cli"
    for path in cli.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        for match in re.finditer(r"\bProgress\(", text):
            call = text[match.start():match.start() + 400]
            assert path.name == "_options.py" or "is_terminal" in call, f"{path.name}: a Progress drawn anywhere"


def test_a_pipe_in_a_survey_name_keeps_the_report_table_whole() -> None:
    from darp.processing.report import Block, _md_table_to_html, to_markdown

    table = Block("table", headers=("survey", "median mm"), rows=(("a|b", "1.0"), ("c", "2.0")))
    text = to_markdown([table])
    rows = [line for line in text.splitlines() if line.startswith("|")]
    assert all(len(re.split(r"(?<!\\)\|", r)) == 4 for r in rows), rows
    html = _md_table_to_html(text)
    assert "<td>a|b</td>" in html and html.count("<tr>") == 3


def test_a_closed_stdout_is_quiet_and_does_not_cut_the_command_short(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    out = tmp_path / "w.yaml"
    closed = subprocess.run(["bash", "-c", f'"{sys.executable}" -m darp twin waypoints --object cube -o "{out}" >&-'],
                            capture_output=True, text=True, env=env, timeout=120)
    assert closed.returncode == 0 and closed.stderr == "" and out.is_file()
    proc = subprocess.Popen([sys.executable, "-m", "darp", "rig", "show"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before darp writes: a broken pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0 and err == ""


def test_an_image_that_is_a_pipe_or_damaged_is_refused_or_undecodable(tmp_path: Path) -> None:
    from darp.formats.io_input import decode_image

    fifo = tmp_path / "f.png"
    os.mkfifo(fifo)
    with pytest.raises(FormatError, match="named pipe"):
        decode_image(fifo, 0)
    path = tmp_path / "x.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 10)
    assert decode_image(path, 0) is None


def test_a_signal_while_exiting_after_a_complete_run_is_one_line() -> None:
    import signal

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    code = ("import atexit, sys, time\n"
            "atexit.register(lambda: (print('exiting', flush=True), time.sleep(30)))  # a slow library exit hook\n"
            "from darp.cli import main\nsys.argv = ['darp', 'rig', 'show']\nmain()\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)
    assert proc.stdout is not None and proc.stderr is not None
    for line in proc.stdout:
        if line.strip() == "exiting":
            break
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=20) == 143
    err = proc.stderr.read()
    assert err.strip().splitlines() == [err.strip()] and "stopped by SIGTERM while exiting" in err, err
