"""Where the real data sets are: ``../shared/realdata`` beside the repository (read in place, never
copied into git), or the folder named by ``DARP_REALDATA`` for a checkout that lives elsewhere."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[2]


def realdata(name: str) -> Path:
    """The real data set ``name`` (it may be absent: see :func:`needs`)."""
    root = os.environ.get("DARP_REALDATA") or REPOSITORY.parent / "shared" / "realdata"
    return Path(root) / name


def needs(path: Path) -> pytest.MarkDecorator:
    """Skip a test, with the reason, where the real data set is not present."""
    return pytest.mark.skipif(not path.is_dir(), reason=f"real data set {path} not present (set DARP_REALDATA)")
