"""pytest fixtures that install the fakes into ``sys.modules`` and fail a test that broke an SDK contract.

Import them into a test module: ``from fakes.fixtures import fake_z1, fake_rs  # noqa: F401``.
"""

from __future__ import annotations

import sys

import pytest


@pytest.fixture
def fake_z1(monkeypatch):
    """The fake ``unitree_arm_interface`` (stock binding, no controller yet); checks for violations after."""
    from fakes import fake_unitree_arm_interface as fake

    fake.reset()
    monkeypatch.setitem(sys.modules, "unitree_arm_interface", fake)
    yield fake
    violations = list(fake.WORLD.violations)
    fake.reset()
    assert not violations, f"the code under test broke the Z1 SDK contract: {violations}"


@pytest.fixture
def fake_rs(monkeypatch):
    """The fake ``pyrealsense2`` (version 2.59 semantics, no cameras yet); checks for violations after."""
    from fakes import fake_pyrealsense2 as fake

    fake.reset()
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake)
    yield fake
    violations = list(fake.WORLD.violations)
    fake.reset()
    assert not violations, f"the code under test broke the RealSense contract: {violations}"
