"""benchmarks/run.py and benchmarks/results.py: verdicts, the one results table, and the runner's child
processes (a benchmark's rows come back as JSON, a failing benchmark becomes an error row, the run goes on)."""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path
from types import ModuleType

import pytest

from helpers.script_modules import BENCHMARKS, load_benchmark


@pytest.fixture(scope="module")
def results() -> ModuleType:
    return load_benchmark("results")


@pytest.fixture(scope="module")
def run() -> ModuleType:
    return load_benchmark("run")


def test_verdicts_follow_the_target_on_the_ratio_or_on_darps_value(results: ModuleType) -> None:
    faster = results.Target("ratio", ">=", 5.0, "issue 3")
    at_most = results.Target("darp", "<=", 2.0)
    assert results.row("k", "fk", "configurations/s", 600.0, 100.0, "Pinocchio", faster).verdict == "met"
    r = results.row("k", "fk", "configurations/s", 400.0, 100.0, "Pinocchio", faster)
    assert r.ratio == pytest.approx(4.0) and r.verdict == "not met"
    assert results.row("k", "ik", "ms", 1.5, target=at_most).verdict == "met"
    assert results.row("k", "ik", "ms", 2.5, target=at_most).verdict == "not met"
    assert results.row("k", "ik", "ms", 2.5).verdict == "no target"
    # a target on the ratio with no peer measured (libigl not installed): not measured, never met
    missing = results.row("f", "p2m", "M points/s", 1.2, None, "libigl", results.Target("ratio", ">=", 1.0))
    assert missing.ratio is None and missing.verdict == "not measured"
    nan = results.row("f", "p2m", "M points/s", math.nan, 1.0, "libigl", at_most)
    assert nan.darp is None and nan.verdict == "not measured"
    assert results.Row("x", "run", "", None, error="exit 1: boom").verdict == "error"
    assert faster.text("configurations/s") == "ratio >= 5x (issue 3)" and at_most.text("ms") == "darp <= 2 ms"


def test_a_row_survives_its_json_record(results: ModuleType) -> None:
    r = results.row("bag_read", "lz4 bag", "frames/s", 900.0, 400.0, "pyrealsense2", results.Target("ratio", ">=", 2.0),
                    note="load 1.2")
    record = json.loads(json.dumps(r.record()))
    assert record["ratio"] == pytest.approx(2.25) and record["verdict"] == "met"
    assert results.Row.from_record(record) == r


def test_the_table_names_the_machine_and_every_row(results: ModuleType, tmp_path: Path) -> None:
    five = results.Target("ratio", ">=", 5)
    rows = [results.row("kinematics", "FK", "configurations/s", 6e6, 1e6, "Pinocchio", five),
            results.Row("fusion", "run", "", None, error="exit 1: ImportError")]
    info = results.machine()
    assert info["cores"] >= 1 and info["python"] and info["cpu"] and "numpy" in info["libraries"]
    md, js = results.write(tmp_path / "out", rows, info, {"kinematics": {"seconds": 3.0, "rows": 1}})
    text = md.read_text()
    assert info["cpu"] in text
    assert "| kinematics | FK | configurations/s | 6,000,000 | 1,000,000 (Pinocchio) | 6.00x |" in text
    assert "| fusion | run [exit 1: ImportError] |" in text and "1 met, 1 error" in text
    data = json.loads(js.read_text())
    assert data["machine"] == json.loads(json.dumps(info))
    assert [r["verdict"] for r in data["rows"]] == ["met", "error"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["results.json", "results.md"]  # no temp left


def test_every_benchmark_script_is_run_and_returns_rows(run: ModuleType) -> None:
    scripts = {p.stem for p in BENCHMARKS.glob("*.py")} - {"run", "results"}
    assert scripts == set(run.BENCHMARKS)
    for name in scripts:
        tree = ast.parse((BENCHMARKS / f"{name}.py").read_text())
        functions = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert "rows" in functions, f"benchmarks/{name}.py has no rows() for the runner"
        rows = functions["rows"].args
        assert len(rows.args) == len(rows.defaults), f"benchmarks/{name}.py: rows() must run with its defaults"


def test_the_runner_collects_rows_and_goes_on_after_a_failure(run: ModuleType, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "fake.py").write_text(
        "from results import Target, row\n\n\n"
        "def rows():\n    print('the fake report')\n"
        "    return [row('fake', 'case', 's', 2.0, 4.0, 'a peer', Target('ratio', '<=', 1.0))]\n")
    (tmp_path / "broken.py").write_text("def rows():\n    raise RuntimeError('no device here')\n")
    monkeypatch.setattr(run, "HERE", tmp_path)
    monkeypatch.setattr(run, "BENCHMARKS", {"fake": "a peer", "broken": "another"})
    out = tmp_path / "out"
    assert run.main(["--out", str(out)]) == 1  # a benchmark failed
    data = json.loads((out / "results.json").read_text())
    fake, broken = data["rows"]
    assert (fake["case"], fake["ratio"], fake["verdict"]) == ("case", 0.5, "met")
    assert broken["verdict"] == "error" and "RuntimeError: no device here" in broken["error"]
    assert "the fake report" in (out / "logs" / "fake.log").read_text()
    assert set(data["benchmarks"]) == {"fake", "broken"}
    printed = capsys.readouterr().out
    assert "| fake | case | s | 2 | 4 (a peer) | 0.50x | ratio <= 1x | met |" in printed
    with pytest.raises(SystemExit):
        run.main(["--only", "nothing", "--out", str(out)])
