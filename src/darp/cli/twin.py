"""``darp twin``: record simulated surveys with the digital twin and list its objects.

    darp twin record --waypoints FILE --object NAME|PATH [--scale S] [--placement x,y,yaw_deg]
                     [--seed N] [--profile ideal|realistic] [--fps 30] [--resolution 640x480]
                     [--settings FILE] [--rig FILE] [--out DIR] [--overwrite]
    darp twin waypoints --object NAME|PATH [--placement ...] --out FILE   (an orbit to start from)
    darp twin objects

Waypoints format and every setting: docs/twin.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, fail

twin_app = typer.Typer(help="The digital twin: record simulated surveys with ground truth.", no_args_is_help=True)
app.add_typer(twin_app, name="twin")

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


def _load_object(spec: str, scale: float) -> Any:
    from darp.twin.objects.model import load_mesh_object, make_object

    path = Path(spec)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        return load_mesh_object(path, scale=scale)
    return make_object(spec, scale=scale)


def _parse_placement(text: str) -> tuple[float, float, float]:
    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        x, y, yaw = (float(p) for p in parts)
    except ValueError:
        raise fail(f"--placement expects x,y,yaw_deg (metres, metres, degrees), got {text!r}") from None
    return x, y, yaw


def _placement(text: str | None, obj: Any, rig: Any, seed: int) -> Any:
    import numpy as np

    from darp.twin.objects.model import ObjectPlacement, RectRegion, random_placement

    z = rig.table.height_m
    if text is not None:
        x, y, yaw_deg = _parse_placement(text)
        return ObjectPlacement(x, y, float(np.deg2rad(yaw_deg)), z)
    ws = rig.workspace
    region = RectRegion(ws.x_range_m[0], ws.x_range_m[1], ws.y_range_m[0], ws.y_range_m[1], z)
    rng = np.random.default_rng([seed, 0x9A1])
    return random_placement(rng, region, clearance_m=min(obj.radius_m, 0.5 * (ws.x_range_m[1] - ws.x_range_m[0]) - 1e-3))


def _parse_resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise fail(f"--resolution expects WIDTHxHEIGHT, e.g. 640x480, got {text!r}") from None
    return w, h


@twin_app.command("record")
def record_command(
    waypoints: Annotated[Path, typer.Option("--waypoints", "-w", help="Waypoints file (YAML or CSV).",
                                            show_default=False)],
    obj_name: Annotated[str, typer.Option("--object", "-o", help="Object name (see `darp twin objects`) or mesh file.",
                                          show_default=False)],
    scale: Annotated[float, typer.Option(help="Scale of the object (0.001 for a mesh in millimetres).")] = 1.0,
    placement: Annotated[str | None, typer.Option(help="x,y,yaw_deg on the table (default: random, seeded).",
                                                  show_default=False)] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of every random draw (default 0).", show_default=False)] = None,
    profile: Annotated[str, typer.Option(help="Error profile: ideal or realistic.")] = "realistic",
    fps: Annotated[int | None, typer.Option(help="Camera frame rate (default 30).", show_default=False)] = None,
    resolution: Annotated[str | None, typer.Option(help="Image size WIDTHxHEIGHT (default 640x480).",
                                                   show_default=False)] = None,
    settings_file: Annotated[Path | None, typer.Option("--settings", help="Twin settings YAML (replaces --profile).",
                                                       show_default=False)] = None,
    rig_file: Annotated[Path | None, typer.Option("--rig", help="Rig YAML (default: the packaged rig).",
                                                  show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(help="Survey folder to create (default: ./<object>).",
                                             show_default=False)] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing survey folder.")] = False,
    workers: Annotated[bool, typer.Option(help="Render each camera in its own process (same files, faster).")] = True,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Record a twin survey: arms through the waypoints, both cameras, joint log, envelope and truth/."""
    import dataclasses

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from darp.kinematics.rig import load_rig
    from darp.twin.record import record_survey
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import load_waypoints

    rig = load_rig(rig_file)
    settings = TwinSettings.load(settings_file) if settings_file else TwinSettings.from_profile(profile, seed=seed or 0)
    if seed is not None:
        settings = dataclasses.replace(settings, seed=seed)
    if fps is not None:
        settings = settings.with_camera(fps=fps)
    if resolution is not None:
        w, h = _parse_resolution(resolution)
        settings = settings.with_camera(width=w, height=h)
    plan = load_waypoints(waypoints, arm_ids=rig.arm_ids)
    obj = _load_object(obj_name, scale)
    place = _placement(placement, obj, rig, settings.seed)
    folder = out if out is not None else Path(obj.name)
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                  TextColumn("{task.completed:.1f}/{task.total:.1f} s simulated"), TimeElapsedColumn(),
                  disable=quiet, transient=False) as bar:
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
    obj_name: Annotated[str, typer.Option("--object", "-o", help="Object name or mesh file.", show_default=False)],
    out: Annotated[Path, typer.Option(help="Waypoints YAML file to write.", show_default=False)],
    placement: Annotated[str, typer.Option(help="x,y,yaw_deg of the object on the table.")] = "0,0,0",
    scale: Annotated[float, typer.Option(help="Scale of the object.")] = 1.0,
    distance: Annotated[float, typer.Option(help="Camera-to-centre distance, metres.")] = 0.35,
    elevation: Annotated[float, typer.Option(help="Camera elevation above the horizontal, degrees.")] = 45.0,
    azimuths: Annotated[str, typer.Option(help="Azimuths around the arm's side of the object, degrees.")] = "-40,-20,0,20,40",
    dwell: Annotated[float, typer.Option(help="Pause at each view, seconds.")] = 0.5,
    rig_file: Annotated[Path | None, typer.Option("--rig", help="Rig YAML.", show_default=False)] = None,
) -> None:
    """Write an orbit of look-at views per arm (nominal rig) as a waypoints file for `darp twin record`."""
    from darp.kinematics.rig import load_rig
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints, save_waypoints

    rig = load_rig(rig_file)
    obj = _load_object(obj_name, scale)
    x, y, _ = _parse_placement(placement)
    try:
        az = [float(a) for a in azimuths.replace(",", " ").split()]
    except ValueError:
        raise fail(f"--azimuths expects degrees separated by commas, got {azimuths!r}") from None
    centre = [x, y, rig.table.height_m + 0.5 * obj.height_m]
    plan = WaypointPlan({a: tuple(orbit_waypoints(rig, a, centre, distance, azimuths_deg=az, elevation_deg=elevation,
                                                  dwell_s=dwell)) for a in rig.arm_ids}, rig.arm_ids)
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
