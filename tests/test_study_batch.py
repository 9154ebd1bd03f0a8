"""studies/cputree.py: the CPU accounting of studies/batch.py (roles, reaped children, exited processes)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import pytest

from helpers.script_modules import load_study


@pytest.fixture(scope="module")
def cputree() -> ModuleType:
    return load_study("cputree")


def test_roles_of_rays_processes(cputree: ModuleType) -> None:
    role = cputree.role
    assert role("python", ["python", "bench.py"], True) == "driver (this process)"
    assert role("raylet", ["/x/ray/core/src/ray/raylet/raylet", "--flag"], False) == "raylet"
    assert role("gcs_server", ["/x/gcs_server"], False) == "gcs_server"
    assert role("ray::DashboardAgent", ["ray::DashboardAgent"], False) == "dashboard agent"
    assert role("ray::IDLE", ["ray::IDLE"], False) == "ray workers"
    assert role("python", ["python", "-c", "from multiprocessing.forkserver import main; main(3, 4)"],
                False) == "forkservers"
    assert role("python", ["python", "/x/ray/_private/log_monitor.py"], False) == "log_monitor"


def test_delta_counts_reaped_children_and_takes_off_what_an_exited_process_had(cputree: ModuleType) -> None:
    before = {(1, 0.0): ("forkservers", 2.0, 10.0), (2, 0.0): ("ray workers", 1.0, 0.0),
              (3, 0.0): ("survey processes (forked)", 0.5, 0.0)}
    # pid 3 exited and was reaped by the forkserver (its 4.5 s, 0.5 of them before, in its children times)
    after = {(1, 0.0): ("forkservers", 2.1, 14.5), (2, 0.0): ("ray workers", 1.3, 0.0),
             (4, 0.0): ("raylet", 0.2, 0.0)}
    d = cputree.delta(before, after)
    assert d["survey processes (forked)"] == pytest.approx(4.0)
    assert d["forkservers"] == pytest.approx(0.1)
    assert d["ray workers"] == pytest.approx(0.3)
    assert d["raylet"] == pytest.approx(0.2)


def test_a_real_child_is_counted_alive_and_after_it_exits(cputree: ModuleType) -> None:
    tree = cputree.CpuTree()
    s0 = tree.snapshot()
    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass\ntime.sleep(5)"
    child = subprocess.Popen([sys.executable, "-c", burn])
    try:
        deadline = time.time() + 30
        while time.time() < deadline:
            alive = cputree.delta(s0, tree.snapshot())
            if alive.get("other: python", 0.0) >= 0.3:
                break
            time.sleep(0.2)
        assert alive.get("other: python", 0.0) >= 0.3  # a live descendant, its own CPU
    finally:
        child.kill()
        child.wait()
    after = cputree.delta(s0, tree.snapshot())
    assert after.get("driver's children", 0.0) >= 0.3  # reaped: in this process's children times


def test_process_io_hashes_outputs_without_their_timings(tmp_path: Path) -> None:
    """studies/process_io.py's byte-identity check: timings are ignored, anything else is not."""
    import json

    process_io = load_study("process_io")
    runs = []
    for k, seconds in enumerate((1.5, 9.25)):
        folder = tmp_path / f"run{k}"
        (folder / "keyframes").mkdir(parents=True)
        (folder / "keyframes" / "a.npz").write_bytes(b"\x00\x01pixels")
        (folder / "results.json").write_text(json.dumps({"stages": {"poses": seconds, "mesh": seconds / 2},
                                                         "metrics": {"accuracy_mm": 1.25}}))
        (folder / "stages.json").write_text(json.dumps({"stages": {"poses": {"seconds": seconds, "summary": {}}}}))
        runs.append(folder)
    first, second = (process_io.output_hashes(folder) for folder in runs)
    assert set(first) == {"keyframes/a.npz", "results.json", "stages.json"} and first == second
    (runs[1] / "results.json").write_text(json.dumps({"stages": {"poses": 1.5, "mesh": 0.75},
                                                      "metrics": {"accuracy_mm": 1.26}}))
    (runs[1] / "keyframes" / "a.npz").write_bytes(b"\x00\x02pixels")
    changed = process_io.output_hashes(runs[1])
    assert {k for k in first if first[k] != changed[k]} == {"results.json", "keyframes/a.npz"}
