"""``darp twin generate``: N randomised twin surveys from one seed.

Survey ``i`` draws everything from ``numpy.random.default_rng([seed, i])``, so the batch is the same
whatever runs it (a loop, local Ray, a cluster) and survey ``i`` does not depend on N:

- the object: one of the choices (paper objects by name, user meshes by path), with a texture seed;
- its placement in the rig's workspace and its yaw (uniform);
- its materials: each part's colour jittered, and ``dark`` / ``specular`` flags switched on at random
  (they change the twin's IR return and dropouts);
- the error draws: the twin settings' seed (joint-zero biases, hand-eye and base errors, noise; it
  also seeds the table's texture);
- the lighting (:class:`darp.twin.settings.LightingSettings`): ambient, key and fill levels from dim to
  bright and the key light's direction turned about the vertical, from a generator of its own
  (``[seed, i, 1]``) so that the draws above are the same as before lighting was drawn;
- the survey: per arm a few orbit views at a random distance, elevation and azimuth spread.

Each survey is recorded by :func:`darp.twin.record.record_survey`, which builds it in
``<name>.partial/`` and renames it when complete: a retried task starts over, a finished survey is
skipped. ``generate.json`` lists every survey's draws.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
MANIFEST = "generate.json"


@dataclass(frozen=True)
class SurveySpec:
    """The draws of one generated survey (JSON-able)."""

    name: str
    object: str  # a twin object name or a mesh path
    texture_seed: int
    x_m: float
    y_m: float
    yaw_rad: float
    colour_jitter: tuple[float, float, float]
    dark: bool
    specular: bool
    twin_seed: int
    distance_m: float
    elevation_deg: float
    azimuths_deg: tuple[float, ...]
    profile: str = "realistic"
    fps: int = 6
    width: int = 424
    height: int = 240
    dwell_s: float = 0.6
    lighting: tuple[float, float, float, float] = (0.35, 0.45, 0.25, 0.0)  # ambient, key, fill, key yaw (deg)


def plan_surveys(n: int, seed: int, objects: Sequence[str], *, profile: str = "realistic", fps: int = 6,
                 width: int = 424, height: int = 240, views: int = 3) -> list[SurveySpec]:
    """The draws of ``n`` surveys from ``seed`` (see the module docstring)."""
    from darp.kinematics.rig import load_rig

    rig = load_rig()
    ws = rig.workspace
    specs = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        obj = str(objects[int(rng.integers(len(objects)))])
        margin = 0.06
        x = float(rng.uniform(ws.x_range_m[0] + margin, ws.x_range_m[1] - margin))
        y = float(rng.uniform(ws.y_range_m[0] + margin, ws.y_range_m[1] - margin))
        spread = float(rng.uniform(15.0, 35.0))
        azimuths = tuple(float(a) for a in np.linspace(-spread, spread, views)) if views > 1 else (0.0,)
        stem = Path(obj).stem if Path(obj).suffix.lower() in MESH_SUFFIXES else obj
        specs.append(SurveySpec(
            name=f"{i:06d}_{stem}", object=obj, texture_seed=int(rng.integers(2**31)), x_m=round(x, 4),
            y_m=round(y, 4), yaw_rad=round(float(rng.uniform(-np.pi, np.pi)), 4),
            colour_jitter=tuple(round(float(v), 3) for v in rng.uniform(0.7, 1.3, 3)),  # type: ignore[arg-type]
            dark=bool(rng.random() < 0.2), specular=bool(rng.random() < 0.2), twin_seed=int(rng.integers(2**31)),
            distance_m=round(float(rng.uniform(0.30, 0.38)), 3), elevation_deg=round(float(rng.uniform(30, 50)), 1),
            azimuths_deg=azimuths, profile=profile, fps=fps, width=width, height=height,
            lighting=_lighting(np.random.default_rng([seed, i, 1]))))
    return specs


def _lighting(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A dim to bright studio lighting (ambient, key, fill, key yaw in degrees), from its own generator so
    that the other draws stay as they were."""
    ambient, key, fill = (round(float(v), 3) for v in rng.uniform((0.15, 0.2, 0.05), (0.5, 0.7, 0.4)))
    return ambient, key, fill, round(float(rng.uniform(-180.0, 180.0)), 1)


def _object(spec: SurveySpec) -> Any:
    from darp.twin.objects.model import load_mesh_object, make_object

    path = Path(spec.object)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        obj = load_mesh_object(path)
    else:
        obj = make_object(spec.object, seed=spec.texture_seed)
    parts = []
    for part in obj.parts:
        r, g, b, a = part.rgba
        r, g, b = (float(np.clip(c * j, 0.0, 1.0)) for c, j in zip((r, g, b), spec.colour_jitter, strict=True))
        parts.append(dataclasses.replace(part, rgba=(r, g, b, a), dark=part.dark or spec.dark,
                                         specular=part.specular or spec.specular))
    obj.parts = parts
    return obj


def record_generated(spec: SurveySpec, out_dir: str) -> dict[str, Any]:
    """Record one generated survey into ``out_dir/<name>`` (skipped if it is already complete)."""
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement
    from darp.twin.record import record_survey
    from darp.twin.settings import LightingSettings, TwinSettings
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints

    folder = Path(out_dir) / spec.name
    if (folder / "truth" / "object.json").is_file():
        return {"name": spec.name, "skipped": True}
    rig = load_rig()
    obj = _object(spec)
    placement = ObjectPlacement(spec.x_m, spec.y_m, spec.yaw_rad, rig.table.height_m)
    centre = (spec.x_m, spec.y_m, rig.table.height_m + 0.5 * obj.height_m)
    plan = WaypointPlan({arm: tuple(orbit_waypoints(rig, arm, centre, spec.distance_m, azimuths_deg=spec.azimuths_deg,
                                                    elevation_deg=spec.elevation_deg, dwell_s=spec.dwell_s))
                         for arm in rig.arm_ids}, rig.arm_ids)
    ambient, key, fill, key_yaw = spec.lighting
    settings = dataclasses.replace(
        TwinSettings.from_profile(spec.profile, seed=spec.twin_seed).with_camera(
            fps=spec.fps, width=spec.width, height=spec.height),
        lighting=LightingSettings(ambient=ambient, key=key, fill=fill, key_yaw_deg=key_yaw))
    result = record_survey(folder, plan, obj, placement, settings=settings, rig=rig)
    return {"name": spec.name, "skipped": False, "duration_s": result.duration_s, "frames": result.frames}


def generate_batch(n: int, seed: int, objects: Sequence[str], out: str | Path, executor: Any, *,
                   progress: Any = None, **spec_options: Any) -> list[dict[str, Any]]:
    """Plan ``n`` surveys, write ``generate.json`` and record them on ``executor`` (one task each)."""
    from darp.batch.executor import run_tasks
    from darp.formats.atomic import write_json_atomic

    out = Path(out)
    specs = plan_surveys(n, seed, objects, **spec_options)
    write_json_atomic(out / MANIFEST, {"seed": seed, "n": n, "objects": list(objects),
                                       "surveys": [dataclasses.asdict(s) for s in specs]})
    costs = [s.width * s.height * s.fps * len(s.azimuths_deg) for s in specs]  # frames x pixels, roughly
    return run_tasks(record_generated, [(s, str(out)) for s in specs], executor, progress=progress, costs=costs)


__all__ = ["MANIFEST", "SurveySpec", "generate_batch", "plan_surveys", "record_generated"]
