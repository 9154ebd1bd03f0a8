"""Fixtures shared by several test modules. Helpers (doubles, synthetic data, oracles) are in ``helpers/``,
importable as ``helpers.<module>`` because pytest puts this folder on ``sys.path`` for this conftest."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from darp.kinematics.rig import Rig, load_rig


@pytest.fixture
def fake_z1(monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    """The fake ``unitree_arm_interface`` (stock binding, no controller yet); checks for violations after."""
    from helpers.fakes import fake_unitree_arm_interface as fake

    fake.reset()
    monkeypatch.setitem(sys.modules, "unitree_arm_interface", fake)
    yield fake
    violations = list(fake.WORLD.violations)
    fake.reset()
    assert not violations, f"the code under test broke the Z1 SDK contract: {violations}"


@pytest.fixture
def fake_rs(monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    """The fake ``pyrealsense2`` (version 2.59 semantics, no cameras yet); checks for violations after."""
    from helpers.fakes import fake_pyrealsense2 as fake

    fake.reset()
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake)
    yield fake
    violations = list(fake.WORLD.violations)
    fake.reset()
    assert not violations, f"the code under test broke the RealSense contract: {violations}"


@pytest.fixture(scope="module")
def rig() -> Rig:
    """The packaged (nominal) rig, loaded once per module."""
    return load_rig()


@pytest.fixture(scope="session")
def survey_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The processing tests' tiny twin survey of a cube (:func:`helpers.twin_surveys.record_tiny_survey`),
    recorded once per session; tests read it and write elsewhere."""
    from helpers.twin_surveys import record_tiny_survey

    return record_tiny_survey(tmp_path_factory.mktemp("twin") / "cube")


@pytest.fixture(scope="session")
def processed_path(survey_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny twin survey processed once per session with its true poses (``<out>/cube/``): what the
    export, dataset and viewer tests read."""
    from darp.cli._app import run

    out = tmp_path_factory.mktemp("processed")
    assert run(["process", str(survey_path), "--truth-poses", "--out", str(out)]) == 0
    return out / survey_path.name


# Vendor in the loop: Unitree's controller (simulated motors) and SDK binding, built once per venv (helpers/vendor.py).
from helpers.vendor import controllers, vendor_build, vendor_sdk  # noqa: E402

__all__ = ["controllers", "vendor_build", "vendor_sdk"]
