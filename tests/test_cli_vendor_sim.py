"""``darp hardware vendor-sim``: one controller ending does not take the other arms' controllers with it."""

from __future__ import annotations

from pathlib import Path

import pytest

import darp.hardware.vendor_sim as vendor_sim
from darp.cli._app import run


class FakeSim:
    """Stands in for :class:`SimController`: arm111's controller ends after a few polls, arm110's never does."""

    instances: list[FakeSim] = []

    def __init__(self, name: str, sdk_port: int, client_port: int, *, q0_rad: object = None,
                 run_dir: Path | None = None) -> None:
        self.name, self.polls, self.stopped = name, 0, False
        FakeSim.instances.append(self)

    def start(self) -> FakeSim:
        return self

    @property
    def pid(self) -> int:
        return 1000 + len(FakeSim.instances)

    @property
    def log_path(self) -> Path:
        return Path(f"/nowhere/{self.name}.log")

    @property
    def running(self) -> bool:
        self.polls += 1
        if self.stopped:
            return False
        if self.name == "arm111":
            return self.polls < 3
        return True

    def stop(self) -> None:
        self.stopped = True


def test_one_controller_ending_leaves_the_other_running(monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    FakeSim.instances = []
    monkeypatch.setattr(vendor_sim, "SimController", FakeSim)
    monkeypatch.setattr("time.sleep", lambda s: None)
    rc = run(["hardware", "vendor-sim", "--duration-s", "0.5"])
    err = capsys.readouterr().err
    arm110, arm111 = FakeSim.instances
    # arm111's end is one error line naming it; arm110's controller kept running (polled well after arm111
    # ended) until the duration was up
    assert err.count("darp: error:") == 1 and "arm111: z1_ctrl_sim ended" in err
    assert arm110.polls > arm111.polls + 5
    assert arm110.stopped and arm111.stopped
    assert rc == 2
