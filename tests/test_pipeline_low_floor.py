"""An empty fusion says when the crop's floor, raised by the calibration's stated error, cut the object away."""

from __future__ import annotations

from darp.processing.diagnostics import low_floor_hint
from darp.reconstruction.crop import EnvelopeCrop


def test_a_floor_above_half_the_object_is_named() -> None:
    # the 4x sweep's dumbbell: 43 mm kept above the table for a 37 mm object
    hint = low_floor_hint(EnvelopeCrop((0.0, 0.0, 0.02), 0.05, 0.037, 0.0, 0.01, 0.043))
    assert hint.startswith("; the crop keeps only points 43 mm above the table")
    assert "116 % of the object's 37 mm height" in hint and "--corrections table" in hint
    assert "\n" not in hint


def test_a_low_floor_adds_nothing() -> None:
    assert low_floor_hint(EnvelopeCrop((0.0, 0.0, 0.04), 0.05, 0.08, 0.0, 0.01, 0.012)) == ""
