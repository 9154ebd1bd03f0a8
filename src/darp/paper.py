"""The DARP paper's published figures on its real rig: the one place darp's reports and benchmarks read them.

The paper (Sec. IV) reports a held-out geometric hand-eye error per arm and a held-out point-to-mesh table
over its whole release. darp prints its own results next to these; nothing computes with them.
"""

from __future__ import annotations

from typing import Final

HANDEYE_HELDOUT_MM: Final[dict[str, float]] = {"arm110": 3.58, "arm111": 3.93}
"""Held-out geometric hand-eye error per arm (calibration section), in millimetres."""

HELDOUT: Final[dict[str, float | int]] = {
    "keyframes": 224, "points": 1_563_466, "median_mm": 2.13, "rmse_mm": 4.04, "p90_mm": 6.38,
    "within_5mm_pct": 83.82, "within_10mm_pct": 96.56,
}
"""Held-out point-to-mesh figures over the release (Sec. IV-C): counts, distances in mm, shares in %."""

HELDOUT_FIGURES: Final[tuple[str, ...]] = ("median_mm", "rmse_mm", "p90_mm", "within_5mm_pct", "within_10mm_pct")
"""The five held-out figures a twin run is compared on (the counts depend on the release's size)."""

__all__ = ["HANDEYE_HELDOUT_MM", "HELDOUT", "HELDOUT_FIGURES"]
