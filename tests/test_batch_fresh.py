"""darp.batch.fresh: a call in a fresh process forked from a forkserver that preloaded darp (no Ray needed)."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

os.environ.setdefault("DARP_FRESH_TEST", "inherited")  # before this process's forkserver starts

from darp.batch.executor import submission_order
from darp.batch.fresh import ChildCrashed, call_in_fresh_process, exit_reason
from darp.errors import DarpError, TwinError


def _where(names: tuple[str, ...]) -> dict[str, object]:
    return {"pid": os.getpid(), "ppid": os.getppid(), "env": {n: os.environ.get(n) for n in names},
            "open3d": "open3d" in sys.modules, "mujoco": "mujoco" in sys.modules,
            "main_file": getattr(sys.modules["__main__"], "__file__", None)}


def _grow(marker: str) -> int:
    sys.modules.setdefault("darp_fresh_marker", sys)  # process state a fresh process must not see
    return len(marker)


def _has_marker() -> bool:
    return "darp_fresh_marker" in sys.modules


def _raise_darp(path: str) -> None:
    raise TwinError("the survey is broken", Path(path))


def _exit(code: int) -> None:
    os._exit(code)


def _segfault() -> None:
    os.kill(os.getpid(), signal.SIGSEGV)


def test_each_call_is_a_fresh_child_of_one_preloaded_forkserver() -> None:
    names = ("DARP_FRESH_TEST", "MUJOCO_GL", "OPENBLAS_CORETYPE")
    first, second = (call_in_fresh_process(_where, (names,)) for _ in range(2))
    assert first["pid"] != second["pid"] != os.getpid()
    assert first["ppid"] == second["ppid"] != os.getpid()  # the same forkserver forked both
    assert first["env"] == {n: os.environ.get(n) for n in names}  # the environment is inherited
    assert first["env"]["DARP_FRESH_TEST"] == "inherited"
    assert first["open3d"] and not first["mujoco"]  # processing preloaded; nothing of the twin's renderer
    assert first["main_file"] is None  # this process's __main__ (pytest here, Ray's worker script) is not re-run
    assert call_in_fresh_process(_grow, ("abc",)) == 3
    assert not call_in_fresh_process(_has_marker)  # the previous call's state died with its process


def _pools() -> dict[str, object]:
    import cv2
    import open3d

    return {"opencv": cv2.getNumThreads(), "open3d": open3d.utility.get_max_threads(),
            "omp": os.environ.get("OMP_NUM_THREADS"), "opencv_env": os.environ.get("OPENCV_FOR_THREADS_NUM")}


def test_a_task_runs_with_its_thread_budget_in_every_library() -> None:
    """threads=1 (a num_cpus=1 Ray task) reaches OpenCV and Open3D, which OMP_NUM_THREADS alone does not."""
    one = call_in_fresh_process(_pools, threads=1)
    assert one == {"opencv": 1, "open3d": 1, "omp": "1", "opencv_env": "1"}
    two = call_in_fresh_process(_pools, threads=2)
    assert (two["opencv"], two["open3d"], two["omp"]) == (2, 2, "2")
    untouched = call_in_fresh_process(_pools)  # no budget: the forkserver's own configuration
    assert untouched["omp"] == os.environ.get("OMP_NUM_THREADS")


def test_submission_order_puts_the_largest_first() -> None:
    assert submission_order(4, [5.0, 9.0, 1.0, 9.0]) == [1, 3, 0, 2]
    assert submission_order(3, None) == [0, 1, 2]


def test_errors_come_back_and_crashes_are_named() -> None:
    with pytest.raises(TwinError, match="the survey is broken") as info:
        call_in_fresh_process(_raise_darp, ("s0",))
    assert info.value.path == Path("s0")
    with pytest.raises(ChildCrashed, match=r"_exit: its process \(pid \d+\) died: exit code 3"):
        call_in_fresh_process(_exit, (3,), what="_exit")
    with pytest.raises(ChildCrashed, match="killed by signal SIGSEGV"):
        call_in_fresh_process(_segfault)
    assert issubclass(ChildCrashed, DarpError)
    assert exit_reason(-9) == "killed by signal SIGKILL" and exit_reason(None) == "no exit code"
