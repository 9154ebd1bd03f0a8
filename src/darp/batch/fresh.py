"""A function call in a fresh process forked from a forkserver that has already imported darp's heavy modules.

A Ray worker that runs surveys one after another would keep the native state of the last one (the twin's
renderer, Open3D); a fresh worker per survey (``max_calls=1``) pays the import of darp's processing stack
(numpy, OpenCV, Open3D with dash/plotly: 2-3 s on a free core) every time. Here the worker is reused and
each call runs in a child forked from a :mod:`multiprocessing` forkserver instead: the forkserver is
started once per worker (by fork + exec, so none of the Ray worker's threads come along), imports
:data:`PRELOAD` once, and forks a child per call. Nothing native beyond importing (no EGL context, no
Open3D geometry, no MuJoCo model) exists in the forkserver, so every call starts from the same clean,
already-imported state; MuJoCo and the renderer are imported in the child, after the fork.

The child inherits the worker's environment (``MUJOCO_GL``, ``OPENBLAS_CORETYPE``, ``PYTHONPATH`` ...), is
killed if the forkserver goes away (the worker died or was cancelled), and sends back its result or
its exception. A child that dies without an answer (a crash in native code, a signal, ``os._exit``)
raises :class:`ChildCrashed`, which names the exit code or signal; the Ray executor retries a task on
it like a dead worker (``retry_exceptions``).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import pickle
import signal
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from darp.errors import DarpError

# Imported once per worker by its forkserver: darp's processing stack (Open3D, OpenCV, scipy, the stages).
# What a survey's processing imports lazily (figures, the bag reader, truth, trimesh, matplotlib, scipy's
# ndimage and optimize, PIL, lz4): imported once here, each fresh child starts warm. Measured on a
# 640x480 survey: the first survey in a process took 7.6 s with only the first two, 5.6 s with all (the
# second 5.5 s). Nothing here creates a thread or a native context (MuJoCo stays out: the child imports it).
PRELOAD: tuple[str, ...] = (
    "darp.batch.tasks", "darp.batch.generate", "darp.evaluation.figures", "darp.formats.realsense.bag.reader",
    "darp.formats.truth", "trimesh", "matplotlib.pyplot", "scipy.ndimage", "scipy.optimize", "PIL.Image", "lz4.block",
)
PR_SET_PDEATHSIG = 1


class ChildCrashed(DarpError):
    """The fresh process of a task died without returning (exit code or signal in the message)."""


_context: Any = None


def forkserver_context(preload: Sequence[str] = PRELOAD) -> Any:
    """This process's forkserver context (its preload set on first use; the forkserver starts lazily)."""
    global _context
    if _context is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(list(preload))
        _context = ctx
    return _context


def exit_reason(exitcode: int | None) -> str:
    """``exit code 3`` or ``killed by signal SIGSEGV`` for a child's ``exitcode``."""
    if exitcode is None:
        return "no exit code"
    if exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _die_with_parent() -> None:
    """Ask Linux to kill this child when its parent (the forkserver) exits (best effort)."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux
        pass


def _child(conn: Any, payload: bytes, threads: int | None = None) -> None:
    _die_with_parent()
    try:
        if threads is not None:
            from darp.batch.threads import limit_threads

            limit_threads(threads)
        fn, args = pickle.loads(payload)
        answer: tuple[str, Any] = ("ok", fn(*args))
    except BaseException as err:  # everything goes back to the caller
        answer = ("error", err)
    try:
        data = pickle.dumps(answer)
    except Exception as err:  # an unpicklable result or exception
        value = answer[1]
        data = pickle.dumps(("error", DarpError(f"{type(value).__name__}: {value}" if answer[0] == "error"
                                                else f"result not picklable: {err}")))
    conn.send_bytes(data)
    conn.close()


@contextlib.contextmanager
def _without_main() -> Iterator[None]:
    """Start a child without re-running this process's ``__main__`` in it: multiprocessing would import the
    main script again (``__mp_main__``; in a Ray worker, Ray's ``default_worker.py`` and all of Ray) in
    every child, while ``fn`` travels by reference to its module or by value (cloudpickle) anyway."""
    from multiprocessing import spawn

    original = spawn.get_preparation_data

    def preparation(name: str) -> dict[str, Any]:
        data = dict(original(name))
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    spawn.get_preparation_data = preparation
    try:
        yield
    finally:
        spawn.get_preparation_data = original


def _dumps(fn: Callable[..., Any], args: tuple[Any, ...]) -> bytes:
    """By reference for a module's function; by value (Ray's cloudpickle) for closures and ``__main__``'s
    functions, which the child (that does not run ``__main__``) could not look up."""
    if getattr(fn, "__module__", None) != "__main__":
        try:
            return pickle.dumps((fn, args))
        except (pickle.PicklingError, AttributeError, TypeError):
            pass
    from ray import cloudpickle

    return bytes(cloudpickle.dumps((fn, args)))  # type: ignore[no-untyped-call]


def dumps_call(fn: Callable[..., Any], args: tuple[Any, ...]) -> bytes:
    """``(fn, args)`` pickled for :func:`call_pickled_in_fresh_process`: a module's function by reference
    (the child imports it, preloaded), a closure or ``__main__``'s function by value."""
    return _dumps(fn, args)


def call_in_fresh_process(fn: Callable[..., Any], args: tuple[Any, ...] = (), *, what: str = "task",
                          threads: int | None = None) -> Any:
    """``fn(*args)`` in a fresh child of this process's forkserver: its result, or its exception raised
    here; :class:`ChildCrashed` naming ``what`` and the exit code/signal if the child died. ``threads``:
    every library's thread pool in the child sized to it (:func:`darp.batch.threads.limit_threads`)."""
    return loads_answer(call_pickled_in_fresh_process(_dumps(fn, args), what=what, threads=threads))


def loads_answer(data: bytes) -> Any:
    """The result a child sent back (:func:`call_pickled_in_fresh_process`), or its exception raised."""
    status, value = pickle.loads(data)
    if status == "error":
        raise value
    return value


def call_pickled_in_fresh_process(payload: bytes, *, what: str = "task", threads: int | None = None) -> bytes:
    """A call pickled by :func:`dumps_call` in a fresh child: the child's answer, still pickled
    (:func:`loads_answer` gives its result or raises its exception). This process unpickles neither the
    call nor its result, so it never imports their modules: a Ray worker stays light, only its
    forkserver and the children import darp's processing stack. :class:`ChildCrashed` if the child died."""
    ctx = forkserver_context()
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_child, args=(send, payload, threads), name=f"darp-{what}")
    with _without_main():
        child.start()
    send.close()
    data: bytes | None
    try:
        data = receive.recv_bytes()
    except EOFError:
        data = None
    finally:
        receive.close()
    if data is None:
        child.join()
        raise ChildCrashed(f"{what}: its process (pid {child.pid}) died: {exit_reason(child.exitcode)}")
    # The answer is here: the child's exit (freeing its memory: 0.09-0.12 s after a tiny survey at load 16,
    # measured) need not hold up the next task. Its forkserver reaps it; multiprocessing forgets it when
    # the next child starts (or at active_children()).
    return data


def run_pickled(payload: bytes, what: str, threads: int | None = None) -> bytes:
    """What one Ray task runs (``isolation="fork"``): a call pickled by the driver (:func:`dumps_call`), in
    a fresh forked process, its libraries' thread pools sized to ``threads``; the child's answer goes back
    still pickled (the driver calls :func:`loads_answer`). The worker only passes bytes on: Ray would
    otherwise unpickle ``fn`` and the result in the worker, which then imports darp's processing stack
    itself (measured: 2.2 CPU-s per worker, on its first task, inside the batch)."""
    return call_pickled_in_fresh_process(payload, what=what, threads=threads)


def run_with_threads(threads: int, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in this process with every library's thread pool sized to ``threads`` (what a task
    runs with ``isolation="worker"``: a fresh Ray worker per task). Ray has unpickled ``fn`` by then, so
    the libraries its module imports (darp's tasks: OpenCV, Open3D) are sized; Open3D imported later
    inside ``fn`` keeps its default (it reads no environment variable)."""
    from darp.batch.threads import limit_threads

    limit_threads(threads)
    return fn(*args)


def idle(sleep_s: float = 0.0) -> int:
    """A task that only waits ``sleep_s``: its parent's process id (in a fresh process: the forkserver, so
    one per worker). Used to start the workers' forkservers before a batch and to time the fixed cost."""
    import os
    import time

    time.sleep(sleep_s)
    return os.getppid()


__all__ = ["PRELOAD", "ChildCrashed", "call_in_fresh_process", "call_pickled_in_fresh_process", "dumps_call",
           "exit_reason", "forkserver_context", "idle", "loads_answer", "run_pickled",
           "run_with_threads"]
