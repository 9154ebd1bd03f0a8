"""The arms' display colours, one home for the viewer, the figures and the reports: arm110 red, arm111 blue (as in
the paper's figures). An arm of another rig gets one of :data:`OTHER_COLOURS` by its index."""

from __future__ import annotations

ARM_COLOURS = {"arm110": "#d62728", "arm111": "#1f5fd6"}  # red, blue
OTHER_COLOURS = ("#2ca02c", "#ff7f0e", "#9467bd")  # green, orange, purple


def arm_colour(arm: str, index: int = 0) -> str:
    """The arm's colour as ``#rrggbb`` (matplotlib, HTML); ``index`` picks one for an arm darp does not name."""
    return ARM_COLOURS.get(arm, OTHER_COLOURS[index % len(OTHER_COLOURS)])


def arm_rgb(arm: str, index: int = 0) -> tuple[int, int, int]:
    """The same colour as 8-bit ``(r, g, b)`` (rerun, point clouds)."""
    code = arm_colour(arm, index)
    return int(code[1:3], 16), int(code[3:5], 16), int(code[5:7], 16)


__all__ = ["ARM_COLOURS", "OTHER_COLOURS", "arm_colour", "arm_rgb"]
