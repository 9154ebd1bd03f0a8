"""darp.batch: the executor spec, the batch's draws, and one task per survey on a local Ray."""

from __future__ import annotations

import json
import os
import shutil
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from darp.batch.executor import Executor, parse_executor, run_tasks
from darp.batch.generate import plan_surveys
from darp.batch.tasks import crashed_outcome
from darp.cli._app import run
from darp.errors import ConfigError, DarpError, TwinError


def test_executor_spec() -> None:
    assert parse_executor("ray") == Executor("ray", None)
    assert parse_executor("ray:10.0.0.5:6379") == Executor("ray", "10.0.0.5:6379")
    assert parse_executor("local") == Executor()
    with pytest.raises(ConfigError, match="expected local, ray"):
        parse_executor("dask")


def test_bad_executor_is_one_error_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["process", str(tmp_path), "--truth-poses", "--out", str(tmp_path / "o"), "--executor", "spark"]) == 2
    assert capsys.readouterr().err.startswith("darp: error: Invalid value for '--executor'")


def test_the_draws_depend_on_the_seed_and_the_index_only(tmp_path: Path) -> None:
    import trimesh

    mesh = tmp_path / "my_part.ply"
    trimesh.creation.box(extents=(0.05, 0.04, 0.03)).export(mesh)
    objects = ["cube", "mug", str(mesh)]
    a, b = plan_surveys(6, 7, objects), plan_surveys(9, 7, objects)
    assert a == b[:6]  # survey i does not depend on N
    assert plan_surveys(6, 8, objects) != a
    assert len({s.name for s in b}) == 9 and {s.object for s in b} == set(objects)
    assert len({(s.x_m, s.y_m, s.yaw_rad, s.twin_seed) for s in b}) == 9
    assert any(s.dark for s in b) or any(s.specular for s in b) or len({s.colour_jitter for s in b}) == 9
    assert len({s.lighting for s in b}) == 9 and all(0.15 <= s.lighting[0] <= 0.5 for s in b)


@pytest.fixture(scope="module")
def local_ray() -> Iterator[Any]:
    ray = pytest.importorskip("ray")
    os.environ["DARP_RAY_TEST_ENV"] = "inherited"  # the workers, their forkservers and the children see it
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()
    os.environ.pop("DARP_RAY_TEST_ENV", None)


@pytest.mark.slow
def test_ray_tasks_keep_order_retry_a_dead_worker_and_raise_darp_errors(local_ray: Any, tmp_path: Path) -> None:
    def square(x: int) -> tuple[int, int, int, str | None, str | None]:
        return x * x, os.getpid(), os.getppid(), os.environ.get("DARP_RAY_TEST_ENV"), os.environ.get("MUJOCO_GL")

    out = run_tasks(square, [(k,) for k in range(4)], Executor("ray"))
    assert [v for v, *_ in out] == [0, 1, 4, 9]
    assert len({pid for _, pid, *_ in out}) == 4  # a fresh process per task ...
    assert len({ppid for _, _, ppid, *_ in out}) <= 2  # ... forked by the forkserver of one of the 2 reused workers
    assert {(env, gl) for *_, env, gl in out} == {("inherited", os.environ.get("MUJOCO_GL"))}

    import cv2
    import open3d

    def pools() -> tuple[int, int, str | None]:  # imports OpenCV and Open3D with it, as darp's tasks do
        return cv2.getNumThreads(), open3d.utility.get_max_threads(), os.environ.get("OPENCV_FOR_THREADS_NUM")

    # a num_cpus=1 task: one thread in OpenCV and Open3D too (Ray's OMP_NUM_THREADS reaches neither)
    assert run_tasks(pools, [()], Executor("ray")) == [(1, 1, "1")]
    assert run_tasks(pools, [()], Executor("ray"), isolation="worker") == [(1, 1, "1")]
    assert run_tasks(pools, [()], Executor("ray"), threads=2) == [(2, 2, "2")]
    marker = tmp_path / "died-once"

    def dies_once(path: str) -> str:
        if not os.path.exists(path):
            open(path, "w").close()
            os._exit(1)  # the worker crashes: Ray retries the task on a new one
        return "ok"

    seen: list[tuple[int, int]] = []
    assert run_tasks(dies_once, [(str(marker),)], Executor("ray"), max_retries=1,
                     progress=lambda d, n: seen.append((d, n))) == ["ok"]
    assert seen == [(1, 1)]

    def bad_input(k: int) -> None:
        raise TwinError(f"survey {k} is broken", Path(f"s{k}"))

    with pytest.raises(DarpError, match="survey 0 is broken"):
        run_tasks(bad_input, [(0,), (1,)], Executor("ray"))

    tries = tmp_path / "tries.txt"

    def segfault(folder: str, out: str) -> None:
        with open(tries, "a") as f:
            f.write("try\n")
        os.kill(os.getpid(), signal.SIGSEGV)  # native code crashing in the survey's process

    outcomes = run_tasks(segfault, [("surveys/s0", "out/s0")], Executor("ray"), max_retries=1, failure=crashed_outcome)
    assert tries.read_text().count("try") == 2  # retried once on the crash
    assert outcomes[0].status == "failed" and outcomes[0].stage == "worker" and outcomes[0].name == "s0"
    assert "killed by signal SIGSEGV" in outcomes[0].message
    assert run_tasks(square, [(3,)], Executor("ray"))[0][0] == 9  # the worker survived its child's crash


@pytest.mark.slow
def test_twin_generate_and_process_on_ray(local_ray: Any, tmp_path: Path) -> None:
    """Two tiny twin surveys made and processed on a local Ray (one task each), end to end."""
    gen, processed = tmp_path / "gen", tmp_path / "processed"
    assert run(["twin", "generate", "-n", "2", "--seed", "3", "--object", "cube", "--views", "1", "--fps", "6",
                "--out", str(gen), "--executor", "ray"]) == 0
    manifest = json.loads((gen / "generate.json").read_text())
    names = [s["name"] for s in manifest["surveys"]]
    assert sorted(p.name for p in gen.iterdir() if p.is_dir()) == names
    assert not list(gen.glob("*.partial"))
    # a rerun finds the surveys complete and records nothing again (what a retried task relies on)
    stamp = (gen / names[0] / "arm_poses.csv").stat().st_mtime_ns
    assert run(["twin", "generate", "-n", "2", "--seed", "3", "--object", "cube", "--views", "1",
                "--out", str(gen)]) == 0
    assert (gen / names[0] / "arm_poses.csv").stat().st_mtime_ns == stamp
    # a broken survey beside them fails alone on Ray: named in the summary, the others processed, exit 2
    broken = gen / "zz_broken"
    shutil.copytree(gen / names[0], broken)
    (broken / "arm_poses.csv").write_text("not,a,joint,log\n", encoding="utf-8")
    assert run(["process", str(gen), "--truth-poses", "--out", str(processed), "--executor", "ray"]) == 2
    summary = json.loads((processed / "results.json").read_text())
    assert [f["name"] for f in summary["failed"]] == ["zz_broken"]
    assert all((processed / n / "results.json").is_file() for n in names)
    assert not (processed / "zz_broken" / "results.json").exists()
    objects = [json.loads((gen / n / "truth" / "object.json").read_text()) for n in names]
    assert not np.allclose(objects[0]["T_world_object"], objects[1]["T_world_object"])
