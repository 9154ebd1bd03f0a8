"""When a survey's result should not be trusted: the signals that can see a bad result, beside the held-out figures.

The held-out median measures how well views agree with each other. A calibration or kinematic error that moves
every view of an arm the same way passes it (at twice the ``paper`` profile's errors a mug kept a 2 mm held-out
median with keyframe poses 10-14 mm off the truth), and a nearly empty reconstruction is scored against the scrap
of surface it has. Other signals see those cases; each is reported, and the survey is **flagged** when one is
outside its stated bound or disagrees with the held-out figure:

- ``heldout_median_mm``: flagged above ``max_heldout_median_mm`` (twice the paper's).
- ``cross_arm_mm``: the two arms' clouds in their co-observed region (point-to-plane median, the larger of
  the two directions). Views of one arm agree but the arms do not: the calibration moved one arm's views.
  Flagged above ``max_cross_arm_mm``, or above ``cross_arm_factor`` x the held-out median (at least
  ``cross_arm_floor_mm``); two arms with no co-observed surface are flagged too (nothing to compare).
- ``handeye_heldout_p90_mm``: the calibration's own held-out corner error (``darp calib solve``), when it
  states one. Flagged above ``max_handeye_p90_mm``.
- ``arm_p90_mm``: each arm's held-out p90. Flagged above ``max_arm_p90_mm``: one arm's frames disagree
  with the surface (the pooled figures can hide one arm's tail).
- ``coverage_pct``: on twin surveys the share of the seeable true surface within 5 mm of the fused cloud
  (``truth.seeable``), else the share of the envelope's top and side that the fused voxels cover. Flagged
  below ``min_seeable_pct`` (twin) or ``min_envelope_pct``.
- ``truth_vs_heldout`` (twin surveys): the fused cloud's median distance to the truth over the held-out median.
  Flagged above ``max_truth_mm``, or above ``truth_factor`` x the held-out median (at least ``truth_floor_mm``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from darp import paper


@dataclass(frozen=True)
class TrustBounds:
    """The stated bounds of the trust flags (module doc)."""

    max_heldout_median_mm: float = 2.0 * float(paper.HELDOUT["median_mm"])  # twice the paper's held-out median
    max_cross_arm_mm: float = float(paper.HELDOUT["p90_mm"])  # co-observed surface apart by more than the paper's p90
    cross_arm_factor: float = 3.0  # ... or by more than this x the held-out median (and at least cross_arm_floor_mm)
    cross_arm_floor_mm: float = 2.0
    # the calibration's held-out corner p90: 3x the paper's worse per-arm median. A calibration at the real rig's
    # level has a p90 about 2x its median (the paper-profile demo: medians 4.07 / 4.96 mm, p90 8.22 mm), so only
    # a calibration clearly worse than the paper's is flagged
    max_handeye_p90_mm: float = 3.0 * max(paper.HANDEYE_HELDOUT_MM.values())
    max_arm_p90_mm: float = 20.0  # one arm's held-out p90, about 3x the paper's pooled p90
    min_seeable_pct: float = 50.0  # twin: share of the seeable true surface within 5 mm of the fused cloud
    min_envelope_pct: float = 10.0  # the share of the envelope's top and side the fused voxels could cover
    max_truth_mm: float = 5.0  # twin: the fused cloud's median distance to the truth ...
    truth_factor: float = 3.0  # ... or this x the held-out median (and at least truth_floor_mm)
    truth_floor_mm: float = 2.0


def _num(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(float(value)) else None


def trust_signals(results: dict[str, Any], *, handeye_p90_mm: float | None = None,
                  envelope_pct: float | None = None, bounds: TrustBounds | None = None) -> dict[str, Any]:
    """``{"signals": {...}, "flags": [one line each], "bounds": {...}}`` of one survey's ``results.json`` document."""
    b = bounds or TrustBounds()
    held = (results.get("heldout") or {})
    median = _num((held.get("aggregate") or {}).get("median_mm"))
    signals: dict[str, Any] = {"heldout_median_mm": median}
    flags: list[str] = []
    if median is not None and median > b.max_heldout_median_mm:
        flags.append(f"held-out median {median:.2f} mm, above {b.max_heldout_median_mm:g} mm (twice the paper's)")
    cross = results.get("cross_arm") or {}
    planes = [_num(((d or {}).get("point_to_plane") or {}).get("median_mm")) for d in cross.get("directions") or []]
    planes_known = [p for p in planes if p is not None]
    cross_mm = max(planes_known) if planes_known else None
    signals["cross_arm_mm"] = cross_mm
    n_arms = len((results.get("keyframes") or {}).get("arms") or {})
    if cross_mm is not None:
        relative = max(b.cross_arm_floor_mm, b.cross_arm_factor * (median or 0.0))
        if cross_mm > b.max_cross_arm_mm or cross_mm > relative:
            flags.append(f"the arms disagree: their co-observed surface lies {cross_mm:.2f} mm apart (point-to-plane "
                         f"median; bounds {b.max_cross_arm_mm:g} mm and {relative:.2f} mm from the held-out median "
                         f"{median or float('nan'):.2f} mm): calibration or kinematics move one arm's views")
    elif cross and n_arms >= 2:
        flags.append("the arms' clouds share no co-observed surface: their agreement cannot be checked")
    signals["handeye_heldout_p90_mm"] = handeye_p90_mm
    if handeye_p90_mm is not None and handeye_p90_mm > b.max_handeye_p90_mm:
        flags.append(f"the calibration's own held-out corner error is {handeye_p90_mm:.2f} mm (p90), above "
                     f"{b.max_handeye_p90_mm:g} mm: poses cannot be better than that")
    arms = {arm: _num((row or {}).get("p90_mm")) for arm, row in (held.get("arms") or {}).items()}
    known = {a: v for a, v in arms.items() if v is not None}
    signals["arm_p90_mm"] = arms
    for arm, p90 in sorted(known.items()):
        if p90 > b.max_arm_p90_mm:
            flags.append(f"{arm}'s held-out p90 is {p90:.2f} mm, above {b.max_arm_p90_mm:g} mm: that arm's frames "
                         "disagree with the surface")
    truth = results.get("truth") or {}
    seeable = (truth.get("seeable") or {}) if isinstance(truth, dict) else {}
    completeness = seeable.get("completeness_pct") if isinstance(seeable, dict) else None
    seeable_pct = _num(completeness.get("5mm")) if isinstance(completeness, dict) else None
    if seeable_pct is not None:
        signals["coverage_pct"] = {"seeable_within_5mm": seeable_pct}
        if seeable_pct < b.min_seeable_pct:
            flags.append(f"the fused cloud covers {seeable_pct:.1f} % of the surface its poses could see (within "
                         f"5 mm), below {b.min_seeable_pct:g} %: the held-out figures measure a fraction of the object")
    elif envelope_pct is not None:
        signals["coverage_pct"] = {"envelope": envelope_pct}
        if envelope_pct < b.min_envelope_pct:
            flags.append(f"the fused cloud covers about {envelope_pct:.1f} % of the envelope's top and side, below "
                         f"{b.min_envelope_pct:g} %: the held-out figures measure a fraction of the object")
    accuracy = _num((((truth.get("cloud") or {}) if isinstance(truth, dict) else {}).get("accuracy") or {})
                    .get("median_mm"))
    if accuracy is not None:
        signals["truth_accuracy_mm"] = accuracy
        relative = max(b.truth_floor_mm, b.truth_factor * (median or 0.0))
        if accuracy > b.max_truth_mm or accuracy > relative:
            flags.append(f"the fused cloud is {accuracy:.2f} mm from the true surface (median), "
                         f"{accuracy / max(median or 1e-9, 1e-9):.1f}x the held-out median: whole views moved "
                         "together, which the held-out figure cannot see")
    return {"signals": signals, "flags": flags, "bounds": asdict(b)}


def envelope_coverage_pct(points: int, envelope: dict[str, Any], voxel_m: float) -> float | None:
    """The share (%) of the envelope's top and side that ``points`` voxels of ``voxel_m`` could cover at most."""
    radius, height = _num(envelope.get("radius_m")), _num(envelope.get("height_m"))
    if radius is None or height is None or radius <= 0 or height <= 0:
        return None
    return 100.0 * points * voxel_m * voxel_m / (math.pi * radius * radius + 2.0 * math.pi * radius * height)


__all__ = ["TrustBounds", "envelope_coverage_pct", "trust_signals"]
