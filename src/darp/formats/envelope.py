"""``manip_envelope.json``: the object envelope and the robot configuration used for a survey.

Schema 1 (every key optional; a value may also be ``null``)::

    schema_version  1 (absent in the real DARP release's files: read as a legacy file, see below)
    object          object name
    center_m        [x, y, z] object centre in the world frame, metres
    radius_m        envelope radius (> 0), metres
    height_m        envelope height (> 0), metres
    standoff_m      nominal camera-to-centre distance (> 0), metres
    park_q_rad      {arm: [6 joint angles]}: where each arm parks while the other moves
    view_q_rad      {arm: [[6 joint angles], ...]}: the planned (accepted) view configurations
    localisation    free object: the localisation / cross-arm confirmation record

Any other top-level key is kept in :attr:`Envelope.extra` and written back unchanged. Files without
``schema_version`` may spell the geometry without unit suffixes (``center``/``centre``, ``radius``,
``height``, ``standoff``, ``object_name``/``name``); those values are taken to be metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from darp.errors import FormatError
from darp.formats.arm_poses import DEFAULT_ARMS
from darp.formats.limits import ENVELOPE_SIZE_MAX_M, JOINT_ABS_MAX_RAD, POSITION_ABS_MAX_M
from darp.formats.schema import (
    as_array,
    as_dict,
    as_int,
    as_optional_float,
    as_str,
    load_json_object,
    to_jsonable,
    write_json_checked,
)

SCHEMA_VERSION = 1
ENVELOPE_FILE = "manip_envelope.json"

# Spellings accepted in legacy (schema-less) files, by schema-1 key.
LEGACY_ALIASES: dict[str, tuple[str, ...]] = {
    "object": ("object_name", "name"),
    "center_m": ("center", "centre", "object_center"),
    "radius_m": ("radius",),
    "height_m": ("height",),
    "standoff_m": ("standoff",),
}
KNOWN_KEYS = (
    "schema_version", "object", "center_m", "radius_m", "height_m", "standoff_m",
    "park_q_rad", "view_q_rad", "localisation",
)


@dataclass
class Envelope:
    """The survey's object envelope (any geometric value may be unknown) and robot configuration."""

    object_name: str | None = None
    center_m: tuple[float, float, float] | None = None  # world frame
    radius_m: float | None = None
    height_m: float | None = None
    standoff_m: float | None = None
    park_q_rad: dict[str, tuple[float, ...]] = field(default_factory=dict)
    view_q_rad: dict[str, list[tuple[float, ...]]] = field(default_factory=dict)
    localisation: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    schema_version: int | None = SCHEMA_VERSION  # None: a legacy file without the key

    @property
    def has_geometry(self) -> bool:
        """True when centre, radius and height are all known."""
        return None not in (self.center_m, self.radius_m, self.height_m)


def _check_ranges(env: Envelope, path: str | Path | None, known_arms: tuple[str, ...] | None) -> None:
    """Refuse values outside the plausible ranges (docs/reliability.md) and arms the rig does not have."""
    if env.center_m is not None and max(abs(v) for v in env.center_m) > POSITION_ABS_MAX_M:
        raise FormatError(f"center_m: {list(env.center_m)} is more than {POSITION_ABS_MAX_M:g} m from the "
                          "world origin", path)
    for key in ("radius_m", "height_m", "standoff_m"):
        value = getattr(env, key)
        if value is not None and value > ENVELOPE_SIZE_MAX_M:
            raise FormatError(f"{key}: {value!r} m is larger than {ENVELOPE_SIZE_MAX_M:g} m", path)
    for key, per_arm in (("park_q_rad", {a: [q] for a, q in env.park_q_rad.items()}), ("view_q_rad", env.view_q_rad)):
        for arm, qs in per_arm.items():
            if known_arms is not None and arm not in known_arms:
                raise FormatError(f"{key}.{arm}: unknown arm (expected one of: {', '.join(known_arms)})", path)
            for k, q in enumerate(qs):
                worst = max(abs(v) for v in q)
                if worst > JOINT_ABS_MAX_RAD:
                    where = f"{key}.{arm}" + (f"[{k}]" if key == "view_q_rad" else "")
                    raise FormatError(f"{where}: a joint angle of {worst!r} rad is outside +-"
                                      f"{JOINT_ABS_MAX_RAD:.4f}", path)


def envelope_from_dict(payload: dict[str, Any], path: str | Path | None = None,
                       known_arms: tuple[str, ...] | None = DEFAULT_ARMS) -> Envelope:
    """Validate a parsed JSON object and build the :class:`Envelope` (``known_arms=None``: any arm id)."""
    payload = dict(payload)
    version: int | None = None
    if "schema_version" in payload:
        version = as_int(payload.pop("schema_version"), "schema_version", path, minimum=1)
        if version > SCHEMA_VERSION:
            raise FormatError(
                f"schema_version {version} is newer than this darp understands ({SCHEMA_VERSION})", path
            )
    else:
        for key, aliases in LEGACY_ALIASES.items():
            for alias in aliases:
                if alias in payload and key not in payload:
                    payload[key] = payload.pop(alias)

    name = payload.pop("object", None)
    center = payload.pop("center_m", None)
    env = Envelope(
        object_name=None if name is None else as_str(name, "object", path),
        center_m=None if center is None else tuple(as_array(center, "center_m", path, (3,)).tolist()),
        radius_m=as_optional_float(payload.pop("radius_m", None), "radius_m", path, positive=True),
        height_m=as_optional_float(payload.pop("height_m", None), "height_m", path, positive=True),
        standoff_m=as_optional_float(payload.pop("standoff_m", None), "standoff_m", path, positive=True),
        schema_version=version,
    )
    park = payload.pop("park_q_rad", None)
    for arm, q in (as_dict(park, "park_q_rad", path) if park is not None else {}).items():
        env.park_q_rad[arm] = tuple(as_array(q, f"park_q_rad.{arm}", path, (6,)).tolist())
    views = payload.pop("view_q_rad", None)
    for arm, qs in (as_dict(views, "view_q_rad", path) if views is not None else {}).items():
        if not isinstance(qs, list):
            raise FormatError(f"view_q_rad.{arm}: expected a list of joint vectors", path)
        array = as_array(qs, f"view_q_rad.{arm}", path, (len(qs), 6)) if qs else None
        env.view_q_rad[arm] = [] if array is None else [tuple(row) for row in array.tolist()]
    record = payload.pop("localisation", None)
    env.localisation = None if record is None else as_dict(record, "localisation", path)
    env.extra = payload  # whatever is left: kept, never interpreted
    _check_ranges(env, path, known_arms)
    return env


def envelope_to_dict(env: Envelope) -> dict[str, Any]:
    """The JSON object for ``env`` (schema 1); ``None`` values are written as ``null``."""
    clash = sorted(set(env.extra) & (set(KNOWN_KEYS) | {a for al in LEGACY_ALIASES.values() for a in al}))
    if clash:
        raise FormatError(f"extra keys clash with schema keys: {', '.join(clash)}")
    payload: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "object": env.object_name,
        "center_m": None if env.center_m is None else list(env.center_m),
        "radius_m": env.radius_m,
        "height_m": env.height_m,
        "standoff_m": env.standoff_m,
    }
    if env.park_q_rad:
        payload["park_q_rad"] = {arm: list(q) for arm, q in env.park_q_rad.items()}
    if env.view_q_rad:
        payload["view_q_rad"] = {arm: [list(q) for q in qs] for arm, qs in env.view_q_rad.items()}
    if env.localisation is not None:
        payload["localisation"] = env.localisation
    payload.update(env.extra)
    return payload


def read_envelope(path: str | Path, known_arms: tuple[str, ...] | None = DEFAULT_ARMS) -> Envelope:
    """Read and validate ``manip_envelope.json`` (``known_arms=None``: any arm id)."""
    return envelope_from_dict(load_json_object(path), Path(path), known_arms)


def write_envelope(path: str | Path, env: Envelope) -> None:
    """Validate ``env`` with the reader's rules and write it atomically (schema 1)."""
    try:
        payload = to_jsonable(envelope_to_dict(env))
    except FormatError as err:
        raise FormatError(err.message, path) from None
    envelope_from_dict(payload, path, None)  # refuse to write what the reader would refuse
    write_json_checked(path, payload)
