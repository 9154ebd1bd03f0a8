"""CPU accounting of a process tree (studies/batch.py): this process, Ray's processes, workers, forkservers.

A process that exits is counted through its parent's children times once its parent reaps it (a
forkserver reaps its survey processes, the raylet its workers), so a snapshot of the live tree holds the
CPU of the whole tree, dead processes included, as long as their parents live.
"""

from __future__ import annotations

import os
import resource
import threading
import time
from pathlib import Path
from typing import Any

# A process's reaped children are counted under this role (a forkserver's children are the survey processes).
CHILDREN_OF = {"forkservers": "survey processes (forked)", "raylet": "ray workers", "ray workers": "forkservers",
               "driver (this process)": "driver's children"}

Snapshot = dict[tuple[int, float], tuple[str, float, float]]


def role(name: str, cmdline: list[str], root: bool) -> str:
    """What a process of the tree is: the driver, one of Ray's own processes, a worker, a forkserver."""
    text = " ".join(cmdline)
    if root:
        return "driver (this process)"
    if "multiprocessing.forkserver" in text:
        return "forkservers"
    for key, label in (("gcs_server", "gcs_server"), ("raylet", "raylet"), ("dashboard/dashboard.py", "dashboard"),
                       ("autoscaler/_private/monitor.py", "autoscaler monitor"), ("log_monitor.py", "log_monitor"),
                       ("DashboardAgent", "dashboard agent"), ("RuntimeEnvAgent", "runtime env agent")):
        if key in name or key in text:
            return label
    if name.startswith("ray::") or "default_worker.py" in text:
        return "ray workers"
    if "multiprocessing" in text or "darp-" in name:
        return "survey processes (forked)"
    return "other: " + name


class CpuTree:
    """Snapshots of the CPU seconds of this process and all its descendants, and their difference by role."""

    def __init__(self) -> None:
        import psutil

        self.psutil: Any = psutil
        self.root = psutil.Process()

    def snapshot(self) -> Snapshot:
        """(pid, start time) -> (role, own CPU-s, CPU-s of its reaped children)."""
        seen: dict[int, tuple[tuple[int, float], str, float, float, int]] = {}
        for proc in [self.root, *self.root.children(recursive=True)]:
            try:
                with proc.oneshot():
                    t = proc.cpu_times()
                    seen[proc.pid] = ((proc.pid, proc.create_time()),
                                      role(proc.name(), proc.cmdline(), proc.pid == self.root.pid),
                                      t.user + t.system, t.children_user + t.children_system, proc.ppid())
            except self.psutil.Error:  # it exited meanwhile: its parent's children times hold it
                continue
        out: Snapshot = {}
        for key, name, own, children, ppid in seen.values():
            if ppid in seen and seen[ppid][1] == "forkservers":
                # forked from a forkserver (its command line is the same; empty once it has exited, unreaped)
                name = "survey processes (forked)"
            out[key] = (name, own, children)
        return out


def delta(before: Snapshot, after: Snapshot) -> dict[str, float]:
    """CPU-s by role between two snapshots. A process's reaped children count under ``CHILDREN_OF`` its role.
    A process gone by ``after`` was reaped by a live parent whose children times now hold its whole life:
    what it had used by ``before`` is taken off again."""
    by_role: dict[str, float] = {}

    def add(name: str, value: float) -> None:
        by_role[name] = by_role.get(name, 0.0) + value

    for key, (name, own, children) in after.items():
        own0, children0 = before.get(key, (name, 0.0, 0.0))[1:]
        add(name, own - own0)
        add(CHILDREN_OF.get(name, name + "'s children"), children - children0)
    for key, (name, own0, children0) in before.items():
        if key not in after:
            add(name, -own0 - children0)  # the parent's (a live role's children) share holds its whole life
    return {k: round(v, 2) for k, v in sorted(by_role.items(), key=lambda kv: -kv[1]) if abs(v) >= 0.005}


def thread_cpu() -> dict[int, float]:
    """CPU seconds of each thread of this process (Linux: /proc/self/task)."""
    import psutil

    return {t.id: t.user_time + t.system_time for t in psutil.Process().threads()}


def timed_process_one(*call: Any) -> dict[str, Any]:
    """``darp.batch.tasks.process_one(*call)`` with what it took in its process: wall; CPU of the process
    before the call (the fork's and the start's share) and during it, of the calling thread and of the
    other threads alive at its end (OpenCV's, Open3D's, BLAS's pools); its process and parent (the worker's
    forkserver: which worker ran it). A module's function, so a task pickles it by reference: the child
    imports this light module, not Ray's cloudpickle (``import ray``: 0.5 CPU-s per child, measured)."""
    from darp.batch.tasks import process_one

    main = threading.get_native_id()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    before, t0, w0 = thread_cpu(), time.perf_counter(), time.time()
    outcome = process_one(*call)
    after, r1 = thread_cpu(), resource.getrusage(resource.RUSAGE_SELF)
    used = {tid: cpu - before.get(tid, 0.0) for tid, cpu in after.items()}
    return {"name": Path(call[0]).name, "status": outcome.status, "start": w0, "wall_s": time.perf_counter() - t0,
            "process_cpu_before_s": r0.ru_utime + r0.ru_stime,
            "process_cpu_s": r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime,
            "main_thread_cpu_s": used.get(main, 0.0),
            "other_threads_cpu_s": sum(v for k, v in used.items() if k != main),
            "threads": len(after), "pid": os.getpid(), "ppid": os.getppid()}


RAY_OWN = ("gcs_server", "raylet", "dashboard", "autoscaler monitor", "log_monitor", "dashboard agent",
           "runtime env agent")

__all__ = ["CHILDREN_OF", "RAY_OWN", "CpuTree", "delta", "role", "thread_cpu", "timed_process_one"]
