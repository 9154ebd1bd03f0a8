"""``darp demo`` rerun: steps an earlier run finished are skipped, and it says so (was: bare step headings)."""

from __future__ import annotations

from pathlib import Path

from darp.cli._app import run


def test_a_rerun_names_each_step_it_skips(tmp_path: Path, capsys) -> None:
    out = tmp_path / "demo"
    (out / "calibration" / "captures").mkdir(parents=True)
    (out / "calibration" / "captures" / "captures.json").write_text("{}")
    (out / "calibration" / "calibration.json").write_text("{}")
    for name in ("mug", "cup"):
        (out / "surveys" / name).mkdir(parents=True)
    assert run(["demo", "-o", str(out), "--object", "mug", "--object", "cup"]) == 2
    captured = capsys.readouterr()
    said = [line for line in captured.out.splitlines() if "done by an earlier run" in line]
    kept = [out / "calibration" / "calibration.json", out / "surveys" / "mug", out / "surveys" / "cup"]
    assert said == [f"{p}: done by an earlier run, kept (delete it to redo that step)" for p in kept]
    assert "darp: error:" in captured.err  # the fake surveys stop processing
