"""``JointLogger``: a background thread that writes every arm's joint state to ``arm_poses.csv`` at ~33 Hz.

Each tick reads every arm's :meth:`~darp.backend.ArmBackend.read_state` and appends one row
per arm with the state's own host-clock time (``time.time()`` seconds, the clock RealSense global
timestamps use), through :class:`~darp.formats.arm_poses.ArmPoseWriter` (validated, flushed every few
rows, fsynced on close). Ticks follow an absolute schedule, so the mean rate does not drift when a read
is slow; a tick that is more than a whole period late is skipped rather than bunched. A sample already
logged (same time as the arm's previous row: the arm's driver has not produced a new one) is not
repeated. An error in the thread (an arm fault, a full disk) stops logging and is raised by
:meth:`JointLogger.stop`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Self

from darp.backend import ArmBackend
from darp.errors import DarpError, HardwareError
from darp.formats.arm_poses import ArmPoseWriter

log = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 33.0


class JointLogger:
    """Log ``arms`` (by arm id) to ``path`` at ``rate_hz`` from a daemon thread; start(), then stop()."""

    def __init__(self, arms: Mapping[str, ArmBackend], path: str | Path, *, rate_hz: float = DEFAULT_RATE_HZ,
                 flush_every: int = 8, overwrite: bool = False) -> None:
        if not arms:
            raise HardwareError("the joint logger needs at least one arm")
        if not 0 < rate_hz <= 500:
            raise HardwareError(f"joint log rate must be in (0, 500] Hz, got {rate_hz}")
        self.arms = dict(arms)
        self.path = Path(path)
        self.rate_hz = float(rate_hz)
        self._flush_every = flush_every
        self._overwrite = overwrite
        self._writer: ArmPoseWriter | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._last_time: dict[str, float] = {}
        self.ticks = 0
        self.skipped_ticks = 0
        self.repeated_samples = 0

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def rows_written(self) -> int:
        return self._writer.rows_written if self._writer is not None else 0

    def start(self) -> None:
        """Create the file (header row) and log a first row per arm now, then every period."""
        if self._thread is not None:
            raise HardwareError("the joint logger is already running", self.path)
        self._writer = ArmPoseWriter(self.path, known_arms=tuple(self.arms), flush_every=self._flush_every,
                                     overwrite=self._overwrite)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="darp-joint-log", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                self._tick()
                next_t += period
                delay = next_t - time.monotonic()
                if delay < -period:  # more than a period late: drop the missed ticks
                    missed = int(-delay // period)
                    self.skipped_ticks += missed
                    next_t += missed * period
                    delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
        except BaseException as err:  # any failure stops the log; stop() raises it
            self._error = err
            log.info("joint log stopped: %s", err)  # stop() raises it

    def _tick(self) -> None:
        assert self._writer is not None
        for arm_id, arm in self.arms.items():
            state = arm.read_state()
            if self._last_time.get(arm_id) == state.time_s:
                self.repeated_samples += 1
                continue
            self._writer.write(state.time_s, arm_id, state.q_rad)
            self._last_time[arm_id] = state.time_s
        self.ticks += 1

    def stop(self) -> None:
        """Stop the thread and close the file; raises the thread's error, if it had one (idempotent)."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._thread = None
        if self._writer is not None:
            self._writer.close()
        error, self._error = self._error, None
        if error is not None:
            if isinstance(error, DarpError):
                raise HardwareError(f"the joint log stopped early: {error.message}", self.path) from error
            raise HardwareError(f"the joint log stopped early: {type(error).__name__}: {error}", self.path) from error

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = ["DEFAULT_RATE_HZ", "JointLogger"]
