"""A job for the processing runner's tests: its interface and nothing else, without a survey."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class FakeJob:
    """The runner's job interface and nothing else: settings are a dict of groups."""

    out: Path
    settings: dict[str, Any] = field(default_factory=lambda: {"a": 1, "b": 1, "c": 1})
    inputs: str = "v1"
    parts: tuple[str, ...] = ("left", "right")
    fail: str | None = None  # the stage that raises
    ran: list[str] = field(default_factory=list)
    markers: dict[str, str | None] = field(default_factory=dict)  # UNFINISHED.txt as each stage saw it
    closed: int = 0

    @property
    def name(self) -> str:
        return "fake"

    def identity(self) -> dict[str, Any]:
        return {"inputs": self.inputs}

    def settings_fingerprint(self, groups: Sequence[str]) -> str:
        return json.dumps({g: self.settings[g] for g in groups}, sort_keys=True)

    def report(self, stage: str, done: float, total: float | None) -> None:
        pass

    def close(self) -> None:
        self.closed += 1
