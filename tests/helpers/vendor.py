"""Vendor-in-the-loop fixtures: Unitree's controller (simulated motors) and SDK binding, built once per venv.

``vendor_sdk`` runs ``scripts/build_z1_vendor.sh`` for this Python (cached under the venv: seconds when up to
date) and returns the real ``unitree_arm_interface``. The tests skip only when the vendor's sources are not
beside the repository (the script's exit code 3); a failing build fails them. Ports are drawn per test from
a range no stock program uses, so parallel test workers do not collide.
"""

from __future__ import annotations

import importlib
import random
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from darp.hardware.vendor_sim import SimController, VendorBuild, find_vendor_build

REPO = Path(__file__).resolve().parents[2]
PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])  # the packaged rig's park pose (both arms)


def build_vendor() -> VendorBuild:
    """Build (or find up to date) the vendor software for this Python; skip when its sources are absent."""
    proc = subprocess.run(["bash", str(REPO / "scripts" / "build_z1_vendor.sh"), sys.executable, "--quiet"],
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode == 3:
        pytest.skip(f"the vendor sources are not here: {proc.stderr.strip()}")
    assert proc.returncode == 0, f"scripts/build_z1_vendor.sh failed: {proc.stderr.strip()}"
    return find_vendor_build()


@pytest.fixture(scope="session")
def vendor_build() -> VendorBuild:
    return build_vendor()


@pytest.fixture(scope="session")
def vendor_sdk(vendor_build: VendorBuild) -> ModuleType:
    """The real binding (the .pth written by the build is read at start-up only: the path is added here)."""
    if str(vendor_build.binding_dir) not in sys.path:
        sys.path.insert(0, str(vendor_build.binding_dir))
    module = importlib.import_module("unitree_arm_interface")
    assert getattr(module, "DARP_PORTS", 0) == 1, f"not darp's patched binding: {module.__file__}"
    return module


def free_ports(n: int) -> list[int]:
    """``n`` consecutive UDP ports, free now, from 20000-59999."""
    rng = random.Random()
    for _ in range(200):
        base = rng.randrange(20000, 60000 - n, 2)
        ports = list(range(base, base + n))
        ok = True
        for port in ports:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                try:
                    sock.bind(("0.0.0.0", port))
                except OSError:
                    ok = False
                    break
        if ok:
            return ports
    raise RuntimeError("no free UDP ports")


@pytest.fixture
def controllers(vendor_build: VendorBuild, tmp_path: Path) -> Iterator[list[SimController]]:
    """Two vendor controllers with simulated motors at the park pose, on fresh port pairs (arm110, arm111)."""
    ports = free_ports(4)
    sims = [SimController(arm_id, ports[2 * k], ports[2 * k + 1], q0_rad=PARK, run_dir=tmp_path / arm_id,
                          build=vendor_build) for k, arm_id in enumerate(("arm110", "arm111"))]
    try:
        for sim in sims:
            sim.start()
        yield sims
    finally:
        for sim in sims:
            sim.stop()


def rig_yaml(tmp_path: Path, sims: list[SimController], *, speed: float = 1.2, accel: float = 5.0) -> Path:
    """The packaged rig with a ``hardware:`` section pointing at ``sims``' ports."""
    from darp.kinematics.rig import default_rig_path

    text = default_rig_path().read_text()
    arms = "\n".join(f"    {s.name}: {{controller_port: {s.sdk_port}, sdk_port: {s.client_port}}}" for s in sims)
    path = tmp_path / "rig.yaml"
    path.write_text(f"{text}\nhardware:\n  arms:\n{arms}\n  motion: {{max_speed_rad_s: {speed}, "
                    f"max_accel_rad_s2: {accel}}}\n")
    return path
