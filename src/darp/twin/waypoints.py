"""Scripted joint waypoints for ``darp twin record``: the file format and an orbit helper.

YAML form (``schema`` optional; angles in SDK radians unless the key says degrees)::

    schema: darp-twin-waypoints/1
    speed_rad_s: 0.6          # default joint speed of every move (optional)
    dwell_s: 0.5              # default pause after reaching each waypoint (optional)
    order: [arm110, arm111]   # which arm goes first (optional; default: as listed under arms)
    arms:
      arm110:
        - [0.0, 1.2, -1.0, 0.2, 0.0, 0.0]                 # six joint angles, rad
        - {q_deg: [10, 70, -60, 15, 0, 0], dwell_s: 1.0}  # degrees, own dwell
        - {named: forward, speed_rad_s: 0.3}              # a named Z1 configuration
      arm111:
        - {q_rad: [0.0, 1.2, -1.0, 0.2, 0.0, 0.0]}

CSV form: a header ``arm,q1,q2,q3,q4,q5,q6`` plus optional ``dwell_s`` and ``speed_rad_s`` columns,
one waypoint per row in radians; arms run in the order of their first row.

Each arm visits its waypoints in order and returns to its park configuration before the next arm
starts (the recorder's job); the other arm stays parked.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from darp.errors import ConfigError
from darp.formats.atomic import write_text_atomic
from darp.formats.io_input import LIMITS
from darp.formats.limits import DWELL_MAX_S
from darp.formats.schema import refuse_unknown_keys
from darp.formats.text import load_yaml, read_utf8_text
from darp.kinematics import z1

SCHEMA = "darp-twin-waypoints/1"
DEFAULT_DWELL_S = 0.5
MAX_SPEED_RAD_S = 3.1416  # the Z1's joint velocity limit (pi rad/s)


@dataclass(frozen=True, eq=False)
class Waypoint:
    """One joint target (SDK angles), the pause after reaching it and an optional speed."""

    q_rad: np.ndarray
    dwell_s: float = DEFAULT_DWELL_S
    speed_rad_s: float | None = None


@dataclass(frozen=True)
class WaypointPlan:
    """Waypoints per arm and the order in which the arms move."""

    arms: dict[str, tuple[Waypoint, ...]]
    order: tuple[str, ...]

    def __post_init__(self) -> None:
        if sorted(self.order) != sorted(self.arms):
            raise ConfigError(f"order {list(self.order)} must list each arm of the plan once ({', '.join(self.arms)})")

    @property
    def n_waypoints(self) -> int:
        return sum(len(w) for w in self.arms.values())


def _check_q(q: Any, where: str, degrees: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: expected six numbers, got {q!r}") from None
    if arr.shape != (6,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{where}: expected six finite numbers, got {q!r}")
    if degrees:
        arr = np.deg2rad(arr)
    lower, upper = z1.joint_limits("urdf")
    bad = np.nonzero((arr < lower) | (arr > upper))[0]
    if bad.size:
        j = int(bad[0])
        raise ConfigError(f"{where}: joint{j + 1} = {arr[j]:.4f} rad is outside the Z1 limits "
                          f"[{lower[j]:.4f}, {upper[j]:.4f}]")
    return arr


def _positive(value: Any, where: str, allow_zero: bool) -> float:
    """A dwell (``allow_zero``; at most DWELL_MAX_S) or a joint speed (> 0; at most the Z1's limit)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) \
            or value < 0 or (value == 0 and not allow_zero):
        raise ConfigError(f"{where}: expected a number {'>=' if allow_zero else '>'} 0, got {value!r}")
    high = DWELL_MAX_S if allow_zero else MAX_SPEED_RAD_S
    if value > high:
        raise ConfigError(f"{where}: {value!r} is more than {high:g} {'s' if allow_zero else 'rad/s'}")
    return float(value)


def _waypoint(entry: Any, where: str, dwell: float, speed: float | None) -> Waypoint:
    if isinstance(entry, list):
        return Waypoint(_check_q(entry, where), dwell, speed)
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: expected a list of six angles or a mapping, got {type(entry).__name__}")
    keys = [k for k in ("q_rad", "q_deg", "named") if k in entry]
    if len(keys) != 1:
        raise ConfigError(f"{where}: give exactly one of q_rad, q_deg, named")
    refuse_unknown_keys(entry, ("q_rad", "q_deg", "named", "dwell_s", "speed_rad_s"), where, error=ConfigError)
    if keys[0] == "named":
        name = entry["named"]
        if name not in z1.NAMED_CONFIGS:
            raise ConfigError(f"{where}: unknown named configuration {name!r} "
                              f"(known: {', '.join(z1.NAMED_CONFIGS)})")
        q = _check_q(z1.NAMED_CONFIGS[name], where)
    else:
        q = _check_q(entry[keys[0]], f"{where}.{keys[0]}", degrees=keys[0] == "q_deg")
    d = _positive(entry["dwell_s"], f"{where}.dwell_s", True) if "dwell_s" in entry else dwell
    s = _positive(entry["speed_rad_s"], f"{where}.speed_rad_s", False) if "speed_rad_s" in entry else speed
    return Waypoint(q, d, s)


def plan_from_dict(data: dict[str, Any]) -> WaypointPlan:
    """Validate parsed YAML (errors name the entry, e.g. ``arms.arm110[2]``)."""
    schema = data.get("schema", SCHEMA)
    if schema != SCHEMA:
        raise ConfigError(f"schema: expected {SCHEMA!r}, got {schema!r}")
    refuse_unknown_keys(data, ("schema", "speed_rad_s", "dwell_s", "order", "arms"), error=ConfigError)
    dwell = _positive(data["dwell_s"], "dwell_s", True) if "dwell_s" in data else DEFAULT_DWELL_S
    speed = _positive(data["speed_rad_s"], "speed_rad_s", False) if "speed_rad_s" in data else None
    arms_data = data.get("arms")
    if not isinstance(arms_data, dict) or not arms_data:
        raise ConfigError("arms: expected a mapping of arm id to a list of waypoints")
    arms: dict[str, tuple[Waypoint, ...]] = {}
    for arm_id, entries in arms_data.items():
        if not isinstance(entries, list) or not entries:
            raise ConfigError(f"arms.{arm_id}: expected a non-empty list of waypoints")
        arms[str(arm_id)] = tuple(_waypoint(e, f"arms.{arm_id}[{k}]", dwell, speed) for k, e in enumerate(entries))
    order = data.get("order", list(arms))
    if not isinstance(order, list):
        raise ConfigError("order: expected a list of arm ids")
    return WaypointPlan(arms, tuple(str(a) for a in order))


def _plan_from_csv(text: str) -> WaypointPlan:
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    required = ["arm", "q1", "q2", "q3", "q4", "q5", "q6"]
    missing = [c for c in required if c not in header]
    if missing:
        raise ConfigError(f"line 1: missing column(s) {', '.join(missing)}")
    extra = sorted(set(header) - set(required) - {"dwell_s", "speed_rad_s"})
    if extra:
        raise ConfigError(f"line 1: unknown column(s) {', '.join(extra)}")
    arms: dict[str, list[Waypoint]] = {}
    for line, row in enumerate(reader, start=2):
        row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
        try:
            q = [float(row[f"q{k}"]) for k in range(1, 7)]
            dwell = float(row["dwell_s"]) if row.get("dwell_s") else DEFAULT_DWELL_S
            speed = float(row["speed_rad_s"]) if row.get("speed_rad_s") else None
        except ValueError:
            raise ConfigError(f"line {line}: not a number in {row}") from None
        arm = row.get("arm", "")
        if not arm:
            raise ConfigError(f"line {line}: empty arm id")
        d = _positive(dwell, f"line {line}: dwell_s", True)
        s = None if speed is None else _positive(speed, f"line {line}: speed_rad_s", False)
        arms.setdefault(arm, []).append(Waypoint(_check_q(q, f"line {line}"), d, s))
    if not arms:
        raise ConfigError("no waypoint rows after the header")
    return WaypointPlan({a: tuple(w) for a, w in arms.items()}, tuple(arms))


def load_waypoints(path: str | Path, arm_ids: Sequence[str] | None = None) -> WaypointPlan:
    """Read a YAML (``.yaml``/``.yml``) or CSV (``.csv``) waypoints file; errors name the file."""
    path = Path(path)
    text = read_utf8_text(path, "a waypoints file", ConfigError, limit=LIMITS["yaml"])
    try:
        if path.suffix.lower() == ".csv":
            plan = _plan_from_csv(text)
        else:
            try:
                data = load_yaml(text)
            except yaml.YAMLError as err:
                raise ConfigError(f"invalid YAML: {str(err).splitlines()[0]}") from None
            except RecursionError:
                raise ConfigError("nested too deeply") from None
            if not isinstance(data, dict):
                raise ConfigError("top level must be a mapping (schema, dwell_s, speed_rad_s, order, arms)")
            plan = plan_from_dict(data)
        if arm_ids is not None:
            unknown = [a for a in plan.arms if a not in arm_ids]
            if unknown:
                raise ConfigError(f"unknown arm(s) {', '.join(unknown)} (rig arms: {', '.join(arm_ids)})")
    except ConfigError as err:
        if err.path is not None:
            raise
        raise ConfigError(err.message, path) from None
    return plan


def plan_to_dict(plan: WaypointPlan) -> dict[str, Any]:
    arms = {arm: [{"q_rad": [round(float(v), 9) for v in w.q_rad], "dwell_s": w.dwell_s,
                   **({"speed_rad_s": w.speed_rad_s} if w.speed_rad_s is not None else {})} for w in wps]
            for arm, wps in plan.arms.items()}
    return {"schema": SCHEMA, "order": list(plan.order), "arms": arms}


def save_waypoints(path: str | Path, plan: WaypointPlan) -> None:
    """Write ``plan`` as waypoints YAML (atomically)."""
    write_text_atomic(path, yaml.safe_dump(plan_to_dict(plan), sort_keys=False, default_flow_style=None))


def orbit_waypoints(rig: Any, arm_id: str, center_world: Sequence[float], distance_m: float, *,
                    azimuths_deg: Sequence[float] = (-30.0, 0.0, 30.0), elevation_deg: float = 45.0,
                    dwell_s: float = DEFAULT_DWELL_S) -> list[Waypoint]:
    """Views of ``center_world`` at ``distance_m`` from ``arm_id``'s side of the object (nominal rig).

    Azimuth 0 looks from the arm's base towards the object; the camera sits ``elevation_deg`` above
    the horizontal. Views without an IK solution are skipped (a ConfigError if none is left).
    """
    from darp.kinematics.ik import solve_look_at

    arm = rig.arm(arm_id)
    T_base_world = np.linalg.inv(arm.T_world_base)
    center_base = (T_base_world @ np.append(np.asarray(center_world, dtype=float), 1.0))[:3]
    heading = np.arctan2(center_base[1], center_base[0])
    q_prev: np.ndarray | None = None
    out: list[Waypoint] = []
    elev = np.deg2rad(elevation_deg)
    for az in np.deg2rad(np.asarray(azimuths_deg, dtype=float)):
        a = heading + np.pi + az  # camera on the base's side of the object
        view_from = np.array([np.cos(a) * np.cos(elev), np.sin(a) * np.cos(elev), np.sin(elev)])
        result = solve_look_at(center_base, distance_m, T_frame_cam=arm.T_wrist_cam, view_dir_base=-view_from,
                               q_init=q_prev, up_hint=np.array([0.0, 0.0, 1.0]), limits="sdk")
        if result.success:
            out.append(Waypoint(np.asarray(result.q, dtype=float), dwell_s))
            q_prev = np.asarray(result.q, dtype=float)
    if not out:
        raise ConfigError(f"no reachable view of {list(center_world)} at {distance_m} m for {arm_id}")
    return out


__all__ = ["SCHEMA", "Waypoint", "WaypointPlan", "load_waypoints", "orbit_waypoints", "plan_from_dict",
           "plan_to_dict", "save_waypoints"]
