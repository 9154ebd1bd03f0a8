"""Simulated host clock: ``sleep`` advances time and runs the scheduled events in time order.

Time is kept as integer nanoseconds since the simulation start, so that event order and timestamps
are exact and deterministic (no floating-point drift over a long survey); :meth:`SimClock.now`
returns host-clock seconds (``start_time_s`` plus elapsed time).

Events are *processes*: a callback that is called at its due time and returns the time of its next
call (or None to stop). Processes due at the same nanosecond run in the order they were added. The
twin registers the joint logger (~33 Hz with jitter), each camera's frame tick (30 fps), the IMU and
the collision monitor as processes; arm motion needs no integration step because a move is an
analytic function of time (:mod:`darp.twin.arm_sim`).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass

from darp.backend import Clock
from darp.errors import TwinError

NS_PER_S = 1_000_000_000

ProcessFn = Callable[[int], "int | None"]
"""Called with the current time (ns since start); returns the next due time in ns, or None to stop."""


def s_to_ns(t_s: float) -> int:
    """Seconds to integer nanoseconds (rounded)."""
    return round(t_s * NS_PER_S)


@dataclass
class _Process:
    name: str
    fn: ProcessFn
    active: bool = True


class SimClock(Clock):
    """Deterministic simulated clock with an event queue."""

    def __init__(self, start_time_s: float = 1_700_000_000.0) -> None:
        self.start_time_s = float(start_time_s)
        self._now_ns = 0
        self._queue: list[tuple[int, int, int]] = []  # (due ns, insertion order, process id)
        self._processes: dict[int, _Process] = {}
        self._ids = itertools.count()
        self._order = itertools.count()
        self._running = False

    # -- time -----------------------------------------------------------------------------------
    @property
    def elapsed_ns(self) -> int:
        """Nanoseconds since the simulation start."""
        return self._now_ns

    def now(self) -> float:
        """Host-clock seconds."""
        return self.start_time_s + self._now_ns / NS_PER_S

    def host_time_s(self, elapsed_ns: int) -> float:
        """Host-clock seconds of a simulation instant."""
        return self.start_time_s + elapsed_ns / NS_PER_S

    def sleep(self, duration_s: float) -> None:
        """Advance by ``duration_s``, running every event due up to and including the end time."""
        if not duration_s >= 0:
            raise TwinError(f"cannot sleep for {duration_s} s")
        self.advance_to(self._now_ns + s_to_ns(duration_s))

    def advance_to(self, target_ns: int) -> None:
        """Run due events in order until ``target_ns`` (ns since start), then set the time there."""
        if self._running:
            raise TwinError("SimClock.sleep called from inside a scheduled event")
        self._running = True
        try:
            while self._queue and self._queue[0][0] <= target_ns:
                due, _, pid = heapq.heappop(self._queue)
                process = self._processes.get(pid)
                if process is None or not process.active:
                    continue
                self._now_ns = max(self._now_ns, due)
                nxt = process.fn(self._now_ns)
                if nxt is None:
                    process.active = False
                    del self._processes[pid]
                    continue
                if nxt <= due:
                    raise TwinError(f"process {process.name!r} scheduled itself at {nxt} ns, not after {due} ns")
                heapq.heappush(self._queue, (int(nxt), next(self._order), pid))
            self._now_ns = max(self._now_ns, target_ns)
        finally:
            self._running = False

    # -- processes --------------------------------------------------------------------------------
    def add_process(self, name: str, fn: ProcessFn, first_due_ns: int | None = None) -> int:
        """Schedule ``fn`` first at ``first_due_ns`` (default: now); returns a handle for :meth:`remove`."""
        due = self._now_ns if first_due_ns is None else int(first_due_ns)
        if due < self._now_ns:
            raise TwinError(f"process {name!r} cannot start in the past ({due} < {self._now_ns} ns)")
        pid = next(self._ids)
        self._processes[pid] = _Process(name, fn)
        heapq.heappush(self._queue, (due, next(self._order), pid))
        return pid

    def remove(self, handle: int) -> None:
        """Stop a process (idempotent)."""
        process = self._processes.pop(handle, None)
        if process is not None:
            process.active = False


__all__ = ["NS_PER_S", "ProcessFn", "SimClock", "s_to_ns"]
