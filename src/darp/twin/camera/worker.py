"""Render and record one twin camera in a subprocess, so that both cameras use both CPU cores.

Rendering, the depth and IR models and bag compression take about 40-50 ms of CPU per 640x480 frame
set, so one process records two 30 fps cameras at a fraction of real time. A :class:`CameraWorker` owns
one camera's :class:`~darp.twin.camera.sensor.TwinCamera` (same model, spec, settings and seed as the
in-process one) and its :class:`~darp.formats.realsense.bag.writer.BagWriter`. The simulation stays in the
main process; per frame tick it sends the joint positions of the whole scene, the camera's true pose,
the timestamps and the IMU samples since the previous tick (a few hundred bytes), and the worker
renders and writes. Requests are pipelined (at most ``max_pending`` frames in flight); the worker
handles them in order with the same noise stream as in-process rendering, so the files are
byte-identical either way.

The worker is started with the ``spawn`` method: a fresh interpreter, no inherited OpenGL state. It
reports its CPU time per frame, per capture stage and per recording, and its memory high-water mark.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import resource
import signal
import time
import traceback
from typing import Any

import numpy as np

from darp.errors import RecordingError, TwinError, interrupts_deferred

READY_TIMEOUT_S = 120.0
REPLY_TIMEOUT_S = 120.0  # a worker silent for this long (alive, but stuck) is given up on
_POLL_S = 0.5  # how often a waiting parent checks that its worker is still alive


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _limit_threads(threads: int) -> None:
    """Threads of llvmpipe's rasteriser and of OpenCV in this worker (before any GL context exists).

    The workers themselves are the parallelism; with about one worker per core, threads inside a worker
    can only spin or wait. On the twin's 2-core machine, run alone, the IR pair costs 8.7 ms of CPU
    single-threaded against 11.7 ms with OpenCV's two threads, the depth model 4.8 against 6.7 ms, a
    render 6.7-7.0 against 7.5-8.1 ms with llvmpipe's two threads (``LP_NUM_THREADS=0`` rasterises in
    the calling thread); in a two-worker recording the difference was within the run-to-run noise.
    An ``LP_NUM_THREADS`` already in the environment is kept.
    """
    import cv2

    os.environ.setdefault("LP_NUM_THREADS", "0" if threads <= 1 else str(threads))
    cv2.setNumThreads(0 if threads <= 1 else threads)


def _worker_main(conn: Any, model: Any, spec: Any, cam_settings: Any, seed: int, dropouts: dict[int, float],
                 threads: int) -> None:
    """Subprocess loop: build the camera, then serve open / frame / close requests in order."""
    try:
        _limit_threads(threads)
        os.environ.setdefault("MUJOCO_GL", "egl")
        from darp.formats.realsense.bag.writer import BagWriter
        from darp.twin.camera.render import mujoco
        from darp.twin.camera.sensor import TwinCamera

        data = mujoco.MjData(model)
        camera = TwinCamera(model, spec, cam_settings, seed=seed, dropout_geoms=dropouts)
        conn.send(("ready",))
    except BaseException as err:  # reported to the parent, which raises
        with contextlib.suppress(OSError):  # the parent may be gone already
            conn.send(("error", f"{type(err).__name__}: {err}", traceback.format_exc()))
        return
    writer = None
    faults_at_open, cpu_at_open = 0, 0.0
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the parent is gone (killed or interrupted): drop the bag, end quietly
            if writer is not None:
                writer.abort()
            return
        kind = message[0]
        try:
            if kind == "open":
                writer = BagWriter(*message[1], **message[2])
                faults_at_open = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
                cpu_at_open = time.process_time()
            elif kind == "frame":
                _, n, stamp_ms, qpos, T_world_cam, motion, keys, motion_px = message
                if writer is None:
                    raise TwinError("a frame came before the recording was opened")
                cpu0, t0 = time.process_time(), time.perf_counter()
                for key, values, stamp, index in motion:
                    writer.write_motion(key, values, stamp, index)
                cpu1, t1 = time.process_time(), time.perf_counter()
                data.qpos[:] = qpos
                mujoco.mj_kinematics(model, data)
                frames = camera.capture(data, T_world_cam, timestamp_s=stamp_ms / 1e3, motion_px=motion_px)
                cpu2, t2 = time.process_time(), time.perf_counter()
                for key in keys:
                    writer.write_image(key, frames[key], stamp_ms, n)
                cpu3, t3 = time.process_time(), time.perf_counter()
                conn.send(("ok", n, t2 - t1, (t1 - t0) + (t3 - t2), cpu3 - cpu0, (cpu1 - cpu0) + (cpu3 - cpu2)))
            elif kind in ("close", "abort"):
                if writer is not None:
                    writer.close() if kind == "close" else writer.abort()
                writer = None
                usage = resource.getrusage(resource.RUSAGE_SELF)
                conn.send(("closed", usage.ru_maxrss / 1024.0, dict(camera.stage_cpu_s),
                           usage.ru_minflt - faults_at_open, time.process_time() - cpu_at_open))
            elif kind == "quit":
                camera.close()
                conn.send(("bye",))
                return
        except BaseException as err:
            if writer is not None:
                writer.abort()
                writer = None
            try:
                conn.send(("error", f"{type(err).__name__}: {err}", traceback.format_exc()))
            except OSError:  # the parent is gone
                return


class CameraWorker:
    """One camera rendered and recorded in a subprocess (see the module docstring)."""

    def __init__(self, model: Any, spec: Any, cam_settings: Any, seed: int, dropouts: dict[int, float], *,
                 max_pending: int = 4, threads: int | None = None) -> None:
        """``threads``: rendering and OpenCV threads inside the worker (default: the available cores
        shared by two workers; 1 on a 2-core machine)."""
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        threads = max(1, available_cores() // 2) if threads is None else max(1, int(threads))
        self._proc = ctx.Process(target=_worker_main,
                                 args=(child, model, spec, cam_settings, seed, dropouts, threads),
                                 daemon=True, name=f"darp-camera-{spec.serial}")
        # The worker ignores SIGINT from its first instruction (inherited through exec): Ctrl-C reaches the
        # whole process group, and the parent alone handles it (and stops the worker).
        # SIGTERM/SIGHUP meanwhile are held until the start is complete (an interrupted start leaves the child
        # a truncated pickle, which it reports with a traceback); the caller's cleanup then stops the worker.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            with interrupts_deferred():
                self._proc.start()
        except KeyboardInterrupt:  # held during the start, raised now: nobody will stop this worker but us
            if self._proc.pid is not None:
                self._proc.kill()
                self._proc.join(5.0)
            raise
        finally:
            signal.signal(signal.SIGINT, previous)
        child.close()
        self.max_pending = max(1, int(max_pending))
        self.pending = 0
        # capture/write: wall seconds; cpu: the worker's CPU seconds per frame (all threads), write_cpu: of writing
        self.timings_s = {"capture": 0.0, "write": 0.0, "cpu": 0.0, "write_cpu": 0.0}
        self.peak_rss_mb = 0.0  # the worker's resident-set high-water mark, after a recording
        self.stage_cpu_s: dict[str, float] = {}  # the camera's CPU seconds per capture stage (cumulative)
        self.minor_faults = 0  # the worker's page faults during its last recording
        self.recording_cpu_s = 0.0  # the worker's CPU seconds from opening to closing its last recording
        self._broken = False  # interrupted mid-conversation: the pipe may hold half a message; only kill is safe
        try:
            self._guarded(self._expect, "ready", READY_TIMEOUT_S)
        except BaseException:
            self._broken = True
            self.shutdown()
            raise

    def _guarded(self, call: Any, *args: Any) -> Any:
        """Run one exchange with the worker; an interrupt (Ctrl-C, SIGTERM) in the middle of it leaves the
        pipe in an unknown state, so the worker is marked broken and will be killed, not talked to."""
        if self._broken:
            raise TwinError(f"camera worker {self._proc.name} was interrupted")
        try:
            return call(*args)
        except KeyboardInterrupt:
            self._broken = True
            raise

    def _expect(self, kind: str, timeout_s: float | None = None) -> tuple[Any, ...]:
        """The next reply, which must be ``kind``; a dead worker, or one silent for ``timeout_s``
        (default REPLY_TIMEOUT_S), is an error instead of a wait for ever."""
        limit = REPLY_TIMEOUT_S if timeout_s is None else timeout_s
        waited = 0.0
        while not self._conn.poll(_POLL_S):
            waited += _POLL_S
            if not self._proc.is_alive() and not self._conn.poll(0):
                raise TwinError(f"camera worker {self._proc.name} exited (code {self._proc.exitcode})")
            if waited >= limit:
                raise TwinError(f"camera worker {self._proc.name} did not answer within {limit:.0f} s")
        try:
            reply: tuple[Any, ...] = self._conn.recv()
        except (EOFError, OSError):
            raise TwinError(f"camera worker {self._proc.name} exited (code {self._proc.exitcode})") from None
        if reply[0] == "error":
            raise RecordingError(f"camera worker failed: {reply[1]}")
        if reply[0] != kind:
            raise TwinError(f"camera worker answered {reply[0]!r}, expected {kind!r}")
        return reply

    def _collect(self) -> None:
        self.pending -= 1  # answered (or failed): either way no longer in flight
        reply = self._expect("ok")
        self.timings_s["capture"] += reply[2]
        self.timings_s["write"] += reply[3]
        self.timings_s["cpu"] += reply[4]
        self.timings_s["write_cpu"] += reply[5]

    def open(self, *args: Any, **kwargs: Any) -> None:
        """Open the bag in the worker (arguments of :class:`BagWriter`)."""
        self._guarded(self._conn.send, ("open", args, kwargs))

    def frame(self, n: int, stamp_ms: float, qpos: np.ndarray, T_world_cam: np.ndarray,
              motion: list[tuple[str, np.ndarray, float, int]], keys: tuple[str, ...],
              motion_px: np.ndarray | None = None) -> None:
        """Queue one frame tick: IMU samples first, then the rendered images (``motion_px``: see
        :meth:`darp.twin.camera.sensor.TwinCamera.capture`)."""
        self._guarded(self._frame, n, stamp_ms, qpos, T_world_cam, motion, keys, motion_px)

    def _frame(self, n: int, stamp_ms: float, qpos: np.ndarray, T_world_cam: np.ndarray,
               motion: list[tuple[str, np.ndarray, float, int]], keys: tuple[str, ...],
               motion_px: np.ndarray | None) -> None:
        while self.pending >= self.max_pending:
            self._collect()
        self._conn.send(("frame", n, stamp_ms, np.asarray(qpos, dtype=float), np.asarray(T_world_cam, dtype=float),
                         motion, keys, motion_px))
        self.pending += 1

    def close_recording(self, abort: bool = False) -> None:
        """Wait for every queued frame, then finish (or abort) the bag. A worker interrupted mid-exchange
        is left alone here (the caller removes the unfinished files; :meth:`shutdown` kills it)."""
        if self._broken:
            if abort:
                return
            raise TwinError(f"camera worker {self._proc.name} was interrupted")
        self._guarded(self._close_recording, abort)

    def _close_recording(self, abort: bool) -> None:
        first_error: BaseException | None = None
        while self.pending:
            try:
                self._collect()
            except RecordingError as err:  # the worker's own error reply: it is still serving
                first_error = first_error or err
            except TwinError:  # dead or stuck: nothing more will come
                self.pending = 0
                raise
        self._conn.send(("abort" if abort or first_error else "close",))
        reply = self._expect("closed", READY_TIMEOUT_S)
        _, self.peak_rss_mb, self.stage_cpu_s, self.minor_faults, self.recording_cpu_s = reply
        if first_error is not None and not abort:
            raise first_error

    def shutdown(self, timeout_s: float = 10.0) -> None:
        """Stop the subprocess (idempotent); one that does not quit within ``timeout_s`` is terminated."""
        if self._broken and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=timeout_s)
        if self._proc.is_alive():
            try:
                self._conn.send(("quit",))
                if self._conn.poll(timeout_s):
                    self._conn.recv()
            except (OSError, EOFError):
                pass
            self._proc.join(timeout=timeout_s)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout=5.0)
        self._conn.close()


__all__ = ["CameraWorker"]
