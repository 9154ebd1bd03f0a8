"""``darp twin``: record simulated surveys with the digital twin and list its objects.

    darp twin record -w FILE --object NAME|PATH [--scale S] [--placement x,y,yaw_deg]
                     [--seed N] [--profile ideal|realistic|paper | --settings FILE] [--fps 30] [--resolution 640x480]
                     [--settings FILE] [--rig RIG.yaml] [-o DIR] [--overwrite]
    darp twin waypoints --object NAME|PATH [--placement ...] [--distance-m 0.35] [--elevation-deg 45]
                        [--azimuth-deg -40 --azimuth-deg 0 ...] [--dwell-s 0.5] -o FILE   (an orbit to start from)
    darp twin objects

Waypoints format and every setting: docs/twin.md.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app
from darp.cli._options import (
    Placement,
    Profile,
    ProfileOption,
    Quiet,
    Resolution,
    RigFile,
    SettingsFile,
    out_option,
    parse_placement,
    parse_resolution,
    progress_bar,
    refuse_output_over_inputs,
)
from darp.formats.limits import DWELL_MAX_S

twin_app = typer.Typer(help="The digital twin: record simulated surveys with ground truth.", no_args_is_help=True)
app.add_typer(twin_app, name="twin")

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
PLACEMENT_HELP = "x,y,yaw_deg of the object on the table, in metres, metres and degrees"


def load_object(spec: str, scale: float) -> Any:
    """A built-in twin object by name, or a mesh file (``darp twin objects`` lists the names), of a size an
    envelope can hold (1 mm to 5 m across and high after ``--scale``)."""
    from darp.formats.limits import ENVELOPE_SIZE_MAX_M

    if not (math.isfinite(scale) and 1e-4 <= scale <= 1e3):  # mm-to-m is 1e-3; nothing real needs 1e4
        raise typer.BadParameter(f"expected a scale from 0.0001 to 1000, got {scale:g}", param_hint="'--scale'")
    obj = _load_object(spec, scale)
    size = max(obj.radius_m, obj.height_m)
    if not (math.isfinite(size) and 1e-3 <= size <= ENVELOPE_SIZE_MAX_M):
        raise typer.BadParameter(f"{spec} at scale {scale:g} is {size:.3g} m in radius or height: not within 1 mm "
                                 f"to {ENVELOPE_SIZE_MAX_M:g} m (is the scale right?)", param_hint="'--scale'")
    return obj


def _load_object(spec: str, scale: float) -> Any:
    from darp.cli._outputs import add_input
    from darp.twin.objects.model import OBJECT_NAMES, load_mesh_object, make_object

    path = Path(spec)
    if spec in OBJECT_NAMES:  # a built-in name is the built-in object, even with a file of that name here
        if path.exists():
            typer.echo(f"darp: warning: --object {spec}: using the built-in object (a file {spec!r} is in the "
                       f"working folder: give ./{spec} to use it)", err=True)
        return make_object(spec, scale=scale)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists() or "/" in spec:
        add_input(path)  # the mesh is an input: -o may not be it
        return load_mesh_object(path, scale=scale)
    return make_object(spec, scale=scale)


def place_object(placement: Placement | None, obj: Any, rig: Any, seed: int) -> Any:
    """The object's placement on the table: the given one, or a random one in the workspace (seeded)."""
    import numpy as np

    from darp.twin.objects.model import ObjectPlacement, RectRegion, random_placement

    z = rig.table.height_m
    if placement is not None:
        return ObjectPlacement(placement.x_m, placement.y_m, float(np.deg2rad(placement.yaw_deg)), z)
    ws = rig.workspace
    region = RectRegion(ws.x_range_m[0], ws.x_range_m[1], ws.y_range_m[0], ws.y_range_m[1], z)
    clearance = min(obj.radius_m, 0.5 * (ws.x_range_m[1] - ws.x_range_m[0]) - 1e-3)
    return random_placement(np.random.default_rng([seed, 0x9A1]), region, clearance_m=clearance)


@twin_app.command("record")
def record_command(
    waypoints: Annotated[Path, typer.Option("--waypoints", "-w", help="Waypoints file (YAML or CSV).", exists=True,
                                            dir_okay=False, show_default=False)],
    obj_name: Annotated[str, typer.Option("--object", help="Object name (see `darp twin objects`) or mesh file.",
                                          show_default=False)],
    scale: Annotated[float, typer.Option("--scale", help="Scale of the object (0.001 for a mesh in "
                                         "millimetres).")] = 1.0,
    placement: Annotated[Placement | None, typer.Option(
        "--placement", parser=parse_placement, metavar="X,Y,YAW_DEG",
        help=f"{PLACEMENT_HELP} (default: random, seeded).", show_default=False)] = None,
    seed: Annotated[int | None, typer.Option("--seed", min=0, help="Seed of every random draw (default 0).",
                                             show_default=False)] = None,
    profile: ProfileOption = Profile.realistic,
    fps: Annotated[int | None, typer.Option("--fps", help="Camera frame rate (default 30).",
                                            show_default=False)] = None,
    resolution: Annotated[Resolution | None, typer.Option(
        "--resolution", parser=parse_resolution, metavar="WIDTHxHEIGHT", help="Image size (default 640x480).",
        show_default=False)] = None,
    settings_file: SettingsFile = None,
    rig_file: RigFile = None,
    out: Annotated[Path | None, out_option("Survey folder to create (default: ./<object>).")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing survey folder.")] = False,
    workers: Annotated[bool, typer.Option("--workers/--no-workers", help="Render each camera in its own process "
                                          "(same files, faster).")] = True,
    quiet: Quiet = False,
) -> None:
    """Record a twin survey: arms through the waypoints, both cameras, joint log, envelope and truth/."""
    import dataclasses

    from rich.progress import BarColumn, TextColumn, TimeElapsedColumn

    from darp.kinematics.rig import load_rig
    from darp.twin.record import record_survey
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import load_waypoints

    rig = load_rig(rig_file)
    settings = (TwinSettings.load(settings_file) if settings_file
                else TwinSettings.from_profile(profile.value, seed=seed or 0))
    if seed is not None:
        settings = dataclasses.replace(settings, seed=seed)
    if fps is not None:
        settings = settings.with_camera(fps=fps)
    if resolution is not None:
        settings = settings.with_camera(width=resolution.width, height=resolution.height)
    plan = load_waypoints(waypoints, arm_ids=rig.arm_ids)
    obj = load_object(obj_name, scale)
    place = place_object(placement, obj, rig, settings.seed)
    folder = out if out is not None else Path(obj.name)
    sources = [p for p in (waypoints, settings_file, rig_file, Path(obj_name)) if p is not None and p.exists()]
    refuse_output_over_inputs(folder, sources, "--out", folder_output=True)
    with progress_bar(TextColumn("[bold]{task.description}"), BarColumn(),
                      TextColumn("{task.completed:.1f}/{task.total:.1f} s simulated"), TimeElapsedColumn(),
                      quiet=quiet, transient=False) as bar:
        task = bar.add_task(f"twin {obj.name}", total=1.0)

        def progress(done_s: float, total_s: float) -> None:
            bar.update(task, completed=min(done_s, total_s), total=total_s)

        result = record_survey(folder, plan, obj, place, settings=settings, rig=rig, scale=scale,
                               overwrite=overwrite, progress=progress, camera_workers=workers)
    frames = ", ".join(f"{a}: {n}" for a, n in result.frames.items())
    typer.echo(f"wrote {result.folder} ({result.duration_s:.1f} s simulated; depth frames {frames}; "
               f"log rows {sum(result.log_rows.values())})")
    if result.contact_events:
        first = result.contact_events[0]
        typer.echo(f"darp: warning: {len(result.contact_events)} contact checks found a collision, first at "
                   f"t={first.time_s:.3f} s: {first.contact.arm_geom} against {first.contact.other_geom} "
                   f"(see {result.folder / 'truth' / 'contacts.json'})", err=True)


@twin_app.command("waypoints")
def waypoints_command(
    obj_name: Annotated[str, typer.Option("--object", help="Object name or mesh file.", show_default=False)],
    out: Annotated[Path, out_option("Waypoints YAML file to write.")],
    placement: Annotated[Placement, typer.Option("--placement", parser=parse_placement, metavar="X,Y,YAW_DEG",
                                                 help=f"{PLACEMENT_HELP}.")] = Placement(0.0, 0.0, 0.0),
    scale: Annotated[float, typer.Option("--scale", help="Scale of the object.")] = 1.0,
    distance_m: Annotated[float, typer.Option("--distance-m", min=0.0, help="Camera-to-centre distance, "
                                              "metres.")] = 0.35,
    elevation_deg: Annotated[float, typer.Option("--elevation-deg", help="Camera elevation above the horizontal, "
                                                 "degrees.")] = 45.0,
    azimuth_deg: Annotated[list[float] | None, typer.Option(
        "--azimuth-deg", help="Azimuth of one view around the arm's side of the object, degrees; repeat per view "
        "(default: -40, -20, 0, 20, 40).", show_default=False)] = None,
    dwell_s: Annotated[float, typer.Option("--dwell-s", min=0.0, max=DWELL_MAX_S,
                                           help="Pause at each view, seconds.")] = 0.5,
    rig_file: RigFile = None,
) -> None:
    """Write an orbit of look-at views per arm (nominal rig) as a waypoints file for `darp twin record`."""
    from darp.kinematics.rig import load_rig
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints, save_waypoints

    rig = load_rig(rig_file)
    obj = load_object(obj_name, scale)
    az = list(azimuth_deg) if azimuth_deg else [-40.0, -20.0, 0.0, 20.0, 40.0]
    centre = [placement.x_m, placement.y_m, rig.table.height_m + 0.5 * obj.height_m]
    plan = WaypointPlan({a: tuple(orbit_waypoints(rig, a, centre, distance_m, azimuths_deg=az,
                                                  elevation_deg=elevation_deg, dwell_s=dwell_s))
                         for a in rig.arm_ids}, rig.arm_ids)
    save_waypoints(out, plan)
    typer.echo(f"wrote {out} ({plan.n_waypoints} waypoints)")


@twin_app.command("objects")
def objects_command() -> None:
    """List the twin's built-in objects with their envelopes (and the paper's)."""
    from darp.twin.objects.model import OBJECT_NAMES, make_object

    typer.echo(f"{'object':<14} {'radius_cm':>9} {'height_cm':>9} {'paper_r_cm':>10} {'paper_h_cm':>10} parts")
    for name in OBJECT_NAMES:
        obj = make_object(name)
        pr = f"{obj.paper_radius_m * 100:.2f}" if obj.paper_radius_m else "-"
        ph = f"{obj.paper_height_m * 100:.2f}" if obj.paper_height_m else "-"
        parts = ", ".join(p.name for p in obj.parts)
        typer.echo(f"{name:<14} {obj.radius_m * 100:>9.2f} {obj.height_m * 100:>9.2f} {pr:>10} {ph:>10} {parts}")
