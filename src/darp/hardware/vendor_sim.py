"""Unitree's own controller with simulated motors: find darp's vendor build and run ``z1_ctrl_sim`` processes.

``scripts/build_z1_vendor.sh`` builds, into ``<venv>/z1_vendor/``, the vendor's ``z1_ctrl`` with darp's
simulated motors (``bin/z1_ctrl_sim``, native/z1_sim) and the SDK's Python binding with darp's port patch
(``python/unitree_arm_interface*.so``, put on the venv's path by a ``.pth`` file). :class:`SimController`
starts one controller the way the vendor runs ``z1_ctrl`` (from a ``build/`` folder beside ``config/``), on
the SDK port pair of one arm, and waits until it answers; see docs/hardware.md, "Vendor in the loop".
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

import numpy as np

from darp.errors import HardwareError

BUILD_HINT = "build it with: bash scripts/build_z1_vendor.sh (make test does it)"
READY_LINE = "[darp-sim] ready"


@dataclass(frozen=True)
class VendorBuild:
    """Where the vendor build lies: the controller program, the binding's folder, the vendor config."""

    root: Path
    controller: Path
    binding_dir: Path
    config_dir: Path


def find_vendor_build(prefix: str | Path | None = None) -> VendorBuild:
    """The vendor build under ``prefix`` (default: this Python's venv, or ``$DARP_Z1_VENDOR_BUILD``)."""
    env = os.environ.get("DARP_Z1_VENDOR_BUILD")
    root = Path(env) if env and prefix is None else Path(prefix if prefix is not None else sys.prefix) / "z1_vendor"
    build = VendorBuild(root, root / "bin" / "z1_ctrl_sim", root / "python", root / "config")
    if not build.controller.is_file() or not (build.config_dir / "config.xml").is_file():
        raise HardwareError(f"no vendor build of z1_ctrl_sim in {root}: {BUILD_HINT}")
    return build


def port_free(port: int, host: str = "127.0.0.1") -> bool:
    """True when a UDP socket can bind ``host:port`` now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((host, int(port)))
        except OSError:
            return False
    return True


def request_fsm_state(sdk_port: int, state: int, *, duration_s: float = 0.06, host: str = "127.0.0.1") -> None:
    """Act as another SDK client for a moment: ask the controller on ``sdk_port`` for FSM ``state`` (its C++
    value, :data:`darp.hardware.z1_binding.FSM_NAMES`) every 2 ms for ``duration_s`` (fault injection: the
    controller follows the latest request it reads, at 250 Hz). The datagram is the SDK's ``SendCmd``
    (arm_common.h, packed: head 0xFE 0xFF, int32 state, bool track, 140-byte value union)."""
    message = bytes([0xFE, 0xFF]) + struct.pack("<iB", int(state), 0) + bytes(140)
    deadline = time.monotonic() + duration_s
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        while time.monotonic() < deadline:
            sock.sendto(message, (host, int(sdk_port)))
            time.sleep(0.002)


class SimController:
    """One ``z1_ctrl_sim``: the vendor controller (FSM, trajectories, safety) driving simulated motors.

    ``sdk_port``: where it listens for the SDK (the arm's ``controller_port``); ``client_port``: where it
    sends (the arm's ``sdk_port``); ``q0_rad``: the joints at power-on; ``plant``: ``(host, port)`` of an
    external plant (see native/z1_sim/README.md) instead of the built-in motor model; ``joint_ranges``:
    narrower hard stops by joint number (1..6), e.g. a cable or fixture the arm runs into; ``nice``: the
    process's nice level (root only). Its output goes to ``<run_dir>/controller.log``. Use as a context
    manager, or :meth:`start` and :meth:`stop`.
    """

    def __init__(self, name: str, sdk_port: int, client_port: int, *,
                 q0_rad: Sequence[float] | np.ndarray | None = None, run_dir: str | Path | None = None,
                 plant: tuple[str, int] | None = None,
                 build: VendorBuild | None = None, verbose: bool = False, lag_floor_s: float | None = None,
                 nice: int = -10, joint_ranges: dict[int, tuple[float, float]] | None = None) -> None:
        self.name = name
        self.sdk_port = int(sdk_port)
        self.client_port = int(client_port)
        self.q0_rad = None if q0_rad is None else np.asarray(q0_rad, dtype=np.float64).reshape(6)
        self.plant = plant
        self.verbose = verbose
        self.lag_floor_s = lag_floor_s
        self.nice = int(nice)
        self.joint_ranges = dict(joint_ranges or {})
        self.build = build
        self._own_dir = run_dir is None
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.process: subprocess.Popen[bytes] | None = None
        self._log_handle: object | None = None

    @property
    def log_path(self) -> Path:
        if self.run_dir is None:
            raise HardwareError(f"{self.name}: the controller was never started")
        return self.run_dir / "controller.log"

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def command(self) -> list[str]:
        """The command line that starts this controller."""
        build = self.build or find_vendor_build()
        # The vendor's z1_ctrl raises itself to SCHED_FIFO for the real arm; this one only asks for a higher
        # nice level (root only: elsewhere nice says so in the log and the controller runs at the normal one),
        # so that rendering or a busy host does not starve its 250/500 Hz loops (it drops the arm to PASSIVE
        # after about 2 s without an exchange). It needs about 2 % of a core.
        cmd = ["nice", "-n", str(self.nice)] if self.nice and shutil.which("nice") else []
        cmd += [str(build.controller), "--sdk-port", str(self.sdk_port), "--client-port", str(self.client_port)]
        if self.q0_rad is not None:
            cmd += ["--q0", ",".join(f"{v:.9f}" for v in self.q0_rad)]
        if self.plant is not None:
            cmd += ["--plant", f"{self.plant[0]}:{self.plant[1]}"]
        for joint, (lo, hi) in sorted(self.joint_ranges.items()):
            cmd += ["--joint-range", f"{joint}:{lo:.9f}:{hi:.9f}"]
        if self.lag_floor_s is not None:
            cmd += ["--lag-floor-s", f"{self.lag_floor_s:g}"]
        if self.verbose:
            cmd.append("--verbose")
        cmd.append("--exit-with-parent")  # no controller outlives the darp process that started it
        return cmd

    def start(self, timeout_s: float = 10.0) -> Self:
        """Start the process and wait until the controller's SDK link is up; a HardwareError otherwise."""
        if self.running:
            return self
        build = self.build = self.build or find_vendor_build()
        if not port_free(self.sdk_port):
            raise HardwareError(f"{self.name}: cannot start z1_ctrl_sim: UDP port {self.sdk_port} (its SDK port) "
                                f"is taken by another process (another controller still running?)")
        if self.run_dir is None:
            self.run_dir = Path(tempfile.mkdtemp(prefix=f"z1ctrl-{self.name}-"))
        config = self.run_dir / "config"
        if not config.is_dir():
            shutil.copytree(build.config_dir, config)
            for item in config.iterdir():  # the controller saves states and teach files here
                item.chmod(0o644)
        (self.run_dir / "build").mkdir(parents=True, exist_ok=True)
        log = open(self.log_path, "ab")  # noqa: SIM115 (kept open for the child's lifetime)
        self._log_handle = log
        self.process = subprocess.Popen(self.command(), cwd=self.run_dir / "build", stdout=log,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while READY_LINE not in self.log_text():
            if self.process.poll() is not None:
                tail = " | ".join(self.log_text().strip().splitlines()[-3:])
                self._close_log()
                raise HardwareError(f"{self.name}: z1_ctrl_sim exited with code {self.process.returncode}: {tail}")
            if time.monotonic() > deadline:
                self.stop()
                raise HardwareError(f"{self.name}: z1_ctrl_sim did not start within {timeout_s:g} s "
                                    f"(log: {self.log_path})")
            time.sleep(0.05)
        return self

    def log_text(self) -> str:
        """Everything the controller printed so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def toggle_motor_link(self) -> None:
        """Simulate a motor link loss (the motors stop answering), or restore it (SIGUSR1)."""
        self._signal(signal.SIGUSR1)

    def kill(self) -> None:
        """Kill the controller at once (SIGKILL), as a crash would."""
        self._signal(signal.SIGKILL)
        if self.process is not None:
            self.process.wait(timeout=5.0)
        self._close_log()

    def stop(self, timeout_s: float = 3.0) -> None:
        """End the controller (SIGINT, then SIGKILL after ``timeout_s``); idempotent."""
        proc = self.process
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5.0)
        self._close_log()

    def remove_run_dir(self) -> None:
        """Delete the run folder when this object created it (after :meth:`stop`)."""
        if self._own_dir and self.run_dir is not None and not self.running:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    def _signal(self, sig: signal.Signals) -> None:
        if not self.running:
            raise HardwareError(f"{self.name}: z1_ctrl_sim is not running")
        assert self.process is not None
        os.kill(self.process.pid, sig)

    def _close_log(self) -> None:
        handle, self._log_handle = self._log_handle, None
        if handle is not None:
            handle.close()  # type: ignore[attr-defined]

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
        self.remove_run_dir()


__all__ = ["BUILD_HINT", "SimController", "VendorBuild", "find_vendor_build", "port_free", "request_fsm_state"]
