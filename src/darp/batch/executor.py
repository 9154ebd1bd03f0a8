"""Run one function over many surveys: a plain loop, or Ray Core tasks (one per survey).

Ray tasks request ``num_cpus`` and ``memory``, are retried ``max_retries`` times when their worker
or their process dies (a crash, a signal, the node lost; a ``DarpError`` is the input's fault and is not
retried), and each runs in a fresh process (the twin's native renderer and Open3D keep process-wide
state): by default (``isolation="fork"``) a child forked from a forkserver that the reused worker
started once with darp's heavy modules imported (:mod:`darp.batch.fresh`), so a task does not pay
the 2-3 s import; ``isolation="worker"`` is a fresh Ray worker per task (``max_calls=1``) instead.
``failure(args, error)``, when given, turns a task that still crashes after its retries into a result
(a failed survey) instead of an error of the batch. Every output darp writes is atomic, so a retried
task never sees or leaves a half-written file. ``ray`` starts a local Ray instance on this machine;
``ray:ADDRESS`` joins a running cluster (``ray:auto`` the one this node belongs to).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from darp.errors import ConfigError, DarpError

ProgressFn = Callable[[int, int], None]  # (tasks done, tasks in all)
DEFAULT_MEMORY_BYTES = 2 * 1024**3  # a survey's processing peaks near 1 GiB at 640x480 (docs/scaling.md)
# Environment the workers need on a cluster (a local Ray inherits this process's environment anyway).
WORKER_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "OPENBLAS_CORETYPE", "PYTHONPATH")
# Ray runs its workers at nice 15 by default: on a shared machine they then get a fraction of what the same
# work gets in the loop (measured: +58 % at load 14 with 0.05 s of fixed cost per task). A local Ray started
# by darp keeps nice 0 unless this variable is set.
WORKER_NICENESS = "RAY_worker_niceness"


@dataclass(frozen=True)
class Executor:
    """Where a batch runs: ``local`` (a plain loop in this process) or ``ray`` (address None: local Ray)."""

    kind: str = "local"
    address: str | None = None

    def __str__(self) -> str:
        return self.kind if self.address is None else f"{self.kind}:{self.address}"


def parse_executor(value: str | Executor) -> Executor:
    """``local``, ``ray`` or ``ray:ADDRESS`` (e.g. ``ray:auto``, ``ray:10.0.0.5:6379``)."""
    if isinstance(value, Executor):
        return value
    kind, _, address = value.partition(":")
    if kind not in ("local", "ray") or (kind == "local" and address):
        raise ConfigError(f"executor {value!r}: expected local, ray or ray:ADDRESS")
    if address and address != "auto" and _host_port(address) is None:
        raise ConfigError(f"executor {value!r}: expected ray:auto, ray:HOST:PORT or ray:ray://HOST:PORT")
    return Executor(kind, address or None)


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of ``HOST:PORT`` or ``ray://HOST:PORT``, or None when it is not of that form."""
    rest = address.removeprefix("ray://")
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        return None
    return host.strip("[]"), int(port)


PROBE_TIMEOUT_S = 5.0  # a Ray head that does not accept a TCP connection in this long is not there


def probe_ray_address(address: str) -> None:
    """Fail in seconds, not minutes, when nothing listens at a Ray address (``ray.init`` retries a dead address
    for a long time inside native code, where not even SIGTERM reaches darp)."""
    import socket

    where = _host_port(address)
    if where is None:
        return
    try:
        with socket.create_connection(where, timeout=PROBE_TIMEOUT_S):
            pass
    except OSError as err:
        reason = "timed out" if isinstance(err, TimeoutError) else (err.strerror or str(err)).lower()
        raise DarpError(f"no Ray cluster reachable at {address} ({reason}); start one there with 'ray start --head' "
                        "or use --executor local") from None


def ray_init_options(address: str | None = None, num_cpus: int | None = None) -> dict[str, Any]:
    """``ray.init`` options of the Ray darp starts (``address`` None) or joins: lean.

    No dashboard (its head process still starts, without its modules), no metrics export nor usage
    statistics (``_system_config`` and ``RAY_USAGE_STATS_ENABLED=0`` unless the user set it), no worker
    logs streamed to the driver (a task's errors come back with its result), and for a local Ray its
    workers at this process's priority (``RAY_worker_niceness=0`` unless set). Measured: Ray's own
    processes then use 0.07 of a core while tasks run (docs/scaling.md, CPU accounting)."""
    options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR"}
    if address is None:  # a local Ray: the system config is the head's to set
        os.environ.setdefault(WORKER_NICENESS, "0")
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        options["_system_config"] = {"enable_metrics_collection": False}
        if num_cpus is not None:
            options["num_cpus"] = num_cpus
    return options


ISOLATIONS = ("fork", "worker")
FailureFn = Callable[[tuple[Any, ...], BaseException], Any]  # (a crashed task's args, its error) -> its result


def run_tasks(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]], executor: Executor, *,
              num_cpus: float = 1.0, memory_bytes: int = DEFAULT_MEMORY_BYTES, max_retries: int = 2,
              progress: ProgressFn | None = None, ray_init: dict[str, Any] | None = None,
              isolation: str = "fork", failure: FailureFn | None = None, threads: int | None = None,
              costs: Sequence[float] | None = None) -> list[Any]:
    """``[fn(*args) for args in calls]`` on the executor, results in the order of ``calls``.

    The first task error is raised after every task has finished (its DarpError as is); with
    ``failure``, a task whose process crashed on every try gives ``failure(args, error)`` instead.
    On Ray, each task's libraries (BLAS, OpenMP, OpenCV, Open3D) use ``threads`` threads (default: the
    task's ``num_cpus``, at least 1; :mod:`darp.batch.threads`), and tasks are submitted in decreasing
    ``costs`` (e.g. the survey's bytes; default: the order of ``calls``) so that the largest start first
    and the workers finish together. The local loop keeps the order and this process's threads.
    """
    if isolation not in ISOLATIONS:
        raise ConfigError(f"isolation {isolation!r}: expected one of {', '.join(ISOLATIONS)}")
    if costs is not None and len(costs) != len(calls):
        raise ConfigError(f"costs: {len(costs)} for {len(calls)} tasks")
    if executor.kind == "local":
        results = []
        for k, args in enumerate(calls):
            results.append(fn(*args))
            if progress is not None:
                progress(k + 1, len(calls))
        return results
    return _run_ray(fn, calls, executor.address, num_cpus=num_cpus, memory_bytes=memory_bytes,
                    max_retries=max_retries, progress=progress, ray_init=ray_init or {}, isolation=isolation,
                    failure=failure, threads=max(1, int(num_cpus)) if threads is None else max(1, int(threads)),
                    order=submission_order(len(calls), costs))


def submission_order(n: int, costs: Sequence[float] | None) -> list[int]:
    """Task indices in the order they are submitted: the largest cost first (ties: call order)."""
    if costs is None:
        return list(range(n))
    return sorted(range(n), key=lambda k: (-float(costs[k]), k))


def _run_ray(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]], address: str | None, *, num_cpus: float,
             memory_bytes: int, max_retries: int, progress: ProgressFn | None,
             ray_init: dict[str, Any], isolation: str, failure: FailureFn | None, threads: int,
             order: Sequence[int]) -> list[Any]:
    try:
        import ray
    except ImportError:
        raise DarpError("--executor ray needs Ray (pip install ray, or make setup)") from None
    started_here = not ray.is_initialized()
    if started_here:
        options: dict[str, Any] = {**ray_init_options(address), **ray_init}
        if address is not None:
            options["runtime_env"] = {"env_vars": {k: os.environ[k] for k in WORKER_ENV if k in os.environ}}
            probe_ray_address(address)
        ray.init(address=address, **options)
    try:
        from darp.batch.fresh import ChildCrashed, dumps_call, loads_answer, run_pickled, run_with_threads

        if isolation == "fork":  # reused workers, a forked process per task, the call pickled here
            remote = ray.remote(num_cpus=num_cpus, memory=memory_bytes, max_retries=max_retries,
                                retry_exceptions=[ChildCrashed])(run_pickled)  # type: ignore[call-overload]
            what = getattr(fn, "__name__", "task")
            submitted = {k: remote.remote(dumps_call(fn, tuple(calls[k])), what, threads) for k in order}
        else:  # a fresh worker per task
            remote = ray.remote(num_cpus=num_cpus, memory=memory_bytes, max_retries=max_retries, max_calls=1,
                                retry_exceptions=False)(run_with_threads)
            submitted = {k: remote.remote(threads, fn, *calls[k]) for k in order}
        refs = [submitted[k] for k in range(len(calls))]
        index = {ref: k for k, ref in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        errors: list[tuple[int, BaseException]] = []
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                k = index[ref]
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    cause = err.cause if isinstance(getattr(err, "cause", None), BaseException) else err
                    crashed = isinstance(cause, ChildCrashed)
                except ray.exceptions.RayError as err:  # the worker died max_retries + 1 times
                    cause, crashed = DarpError(f"task {k} failed on Ray: {_first_line(err)}"), True
                else:
                    if isolation != "fork":
                        results[k] = value
                        continue
                    try:  # the child's answer, pickled: its result, or the exception fn raised there
                        results[k] = loads_answer(value)
                        continue
                    except BaseException as err:  # fn's own error in the child, as Ray raised it before
                        cause, crashed = err, False
                if failure is not None and crashed:
                    results[k] = failure(calls[k], cause)
                else:
                    errors.append((k, cause))
            if progress is not None:
                progress(len(refs) - len(pending), len(refs))
        if errors:
            raise sorted(errors, key=lambda e: e[0])[0][1]
        return results
    finally:
        if started_here:
            ray.shutdown()


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


__all__ = ["DEFAULT_MEMORY_BYTES", "ISOLATIONS", "Executor", "parse_executor", "ray_init_options", "run_tasks",
           "submission_order"]
