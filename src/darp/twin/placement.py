"""Checks on a twin placement before anything is built or moved.

A placement is refused (:class:`~darp.errors.TwinError`, the command line's exit 2) unless, in this
order:

1. **finite**: x, y, yaw and the table height are finite numbers;
2. **on the table**: the object's footprint (a disc of its radius about the placement) lies on the
   table top of the rig file;
3. **clear of both robots**: the object's envelope (a vertical cylinder of its radius and height
   standing on the table) keeps at least ``clear_m`` from every link, the base included, and the
   camera of each arm at its park configuration;
4. **inside the reachable workspace**: the centre lies in the rig file's placement workspace (the
   region the surveys' viewpoints are planned for) and the object is no taller than its height range.

The envelope is conservative (the true mesh lies inside it), so a refused placement may be one whose
mesh would just clear an arm; the message says by how much.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from darp.errors import TwinError
from darp.kinematics.collision import envelope_primitive, min_distance

PLACEMENT_CLEARANCE_M = 0.02  # the object envelope keeps this far from either parked arm


def _where(placement: Any) -> str:
    return (f"placement x={placement.x_m:g} m, y={placement.y_m:g} m, "
            f"yaw={math.degrees(placement.yaw_rad):g} deg")


def validate_placement(rig: Any, radius_m: float, height_m: float, placement: Any, *,
                       clear_m: float = PLACEMENT_CLEARANCE_M) -> None:
    """Raise :class:`TwinError` naming the problem when ``placement`` (an ``ObjectPlacement``) of an
    object of ``radius_m`` and ``height_m`` is not finite, not on the table, touches a parked arm or
    lies outside the rig's placement workspace (see the module docstring)."""
    values = {"x": placement.x_m, "y": placement.y_m, "yaw": placement.yaw_rad, "table z": placement.table_z_m}
    bad = [f"{k}={v}" for k, v in values.items() if not math.isfinite(float(v))]
    if bad:
        raise TwinError(f"placement must be finite numbers, got {', '.join(bad)}")
    x, y, r = float(placement.x_m), float(placement.y_m), float(radius_m)
    t = rig.table
    if not (t.x_range_m[0] <= x - r and x + r <= t.x_range_m[1] and t.y_range_m[0] <= y - r
            and y + r <= t.y_range_m[1]):
        raise TwinError(f"{_where(placement)}: the object (radius {r * 1000:.0f} mm) is not on the table "
                        f"(x {t.x_range_m[0]:g}..{t.x_range_m[1]:g} m, y {t.y_range_m[0]:g}..{t.y_range_m[1]:g} m)")
    envelope = envelope_primitive(np.array([x, y, t.height_m]), r, float(height_m), table_height_z=t.height_m)
    for arm_id in rig.arm_ids:
        prims = rig.arm_primitives(arm_id, np.asarray(rig.arms[arm_id].park_q_rad, dtype=float))
        d = min_distance(prims, [envelope])
        if d.distance_m < clear_m:
            # rounded down to 0.1 mm: a refusal never reads as if the object kept the clearance
            where = "inside" if d.distance_m < 0 else f"{math.floor(d.distance_m * 1e4) / 10:.1f} mm from"
            raise TwinError(f"{_where(placement)}: the object is {where} {arm_id}'s {d.name_a} "
                            f"(it must keep {clear_m * 1000:.0f} mm from both robots)")
    ws = rig.workspace
    if not (ws.x_range_m[0] <= x <= ws.x_range_m[1] and ws.y_range_m[0] <= y <= ws.y_range_m[1]):
        raise TwinError(f"{_where(placement)}: the centre is outside the reachable workspace "
                        f"(x {ws.x_range_m[0]:g}..{ws.x_range_m[1]:g} m, y {ws.y_range_m[0]:g}..{ws.y_range_m[1]:g} m "
                        "in the rig file)")
    if float(height_m) > ws.z_range_m[1]:
        raise TwinError(f"{_where(placement)}: the object is {height_m * 1000:.0f} mm tall, taller than the "
                        f"workspace's {ws.z_range_m[1] * 1000:.0f} mm")


def seeded_placements(seed: int, count: int) -> list[tuple[float, float, float]]:
    """``count`` object placements ``(x_m, y_m, yaw_deg)`` near the middle of the shared workspace, any yaw,
    drawn from ``seed`` (``darp demo``'s placements; the studies reuse them to survey what the demo surveys).
    Not validated: :func:`validate_placement` refuses a bad one when the twin is built."""
    rng = np.random.default_rng([seed, 7])
    return [(float(rng.uniform(-0.08, 0.08)), float(rng.uniform(-0.12, 0.12)), float(rng.uniform(0.0, 360.0)))
            for _ in range(count)]


__all__ = ["PLACEMENT_CLEARANCE_M", "seeded_placements", "validate_placement"]
