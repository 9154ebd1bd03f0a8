"""``darp collect``: one autonomous object survey, on the digital twin or on the real rig.

    darp collect NAME --twin [--object mug|PATH] [--scale S] [--placement x,y,yaw_deg] [--seed N]
                      [--profile ideal|realistic] [--fps 30] [--resolution 640x480]
                      [--calibration FILE|truth] [--rig FILE] [--out DIR] [--overwrite] [--quiet]
    darp collect NAME --hardware rig.yaml --calibration FILE [--out DIR] [--overwrite] [--quiet]

The survey folder is ``<out>/NAME`` when accepted, ``<out>/NAME.rejected`` when rejected (REJECTED.txt
says why) and ``<out>/NAME.partial`` after an interruption (PARTIAL.txt). Exit codes: 0 accepted,
1 rejected, 2 bad input or an error, 130 interrupted. See docs/acquisition.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, fail

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
PHASES = {"localise": "localising", "confirm": "confirming", "plan": "planning", "record": "recording",
          "verify": "verifying", "done": "done"}


def _object(spec: str, scale: float) -> Any:
    from darp.twin.objects.model import load_mesh_object, make_object

    path = Path(spec)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        return load_mesh_object(path, scale=scale)
    return make_object(spec, scale=scale)


def _placement(text: str | None, obj: Any, rig: Any, seed: int) -> Any:
    import numpy as np

    from darp.twin.objects.model import ObjectPlacement, RectRegion, random_placement

    z = rig.table.height_m
    if text is not None:
        parts = [p for p in text.replace(",", " ").split() if p]
        try:
            x, y, yaw_deg = (float(p) for p in parts)
        except ValueError:
            raise fail(f"--placement expects x,y,yaw_deg (metres, metres, degrees), got {text!r}") from None
        return ObjectPlacement(x, y, float(np.deg2rad(yaw_deg)), z)
    ws = rig.workspace
    region = RectRegion(ws.x_range_m[0], ws.x_range_m[1], ws.y_range_m[0], ws.y_range_m[1], z)
    clearance = min(obj.radius_m, 0.5 * (ws.x_range_m[1] - ws.x_range_m[0]) - 1e-3)
    return random_placement(np.random.default_rng([seed, 0x9A1]), region, clearance_m=clearance)


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise fail(f"--resolution expects WIDTHxHEIGHT, e.g. 640x480, got {text!r}") from None
    return w, h


def _run_with_progress(quiet: bool, title: str, run: Any) -> Any:
    """Call ``run(progress)`` under a rich progress bar showing the survey's phase."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.fields[note]}"),
                  TimeElapsedColumn(), disable=quiet, transient=False) as bar:
        task = bar.add_task(title, total=1.0, note="")

        def progress(phase: str, fraction: float, message: str) -> None:
            bar.update(task, description=f"{title}: {PHASES.get(phase, phase)}", completed=fraction, note=message)

        return run(progress)


def _report(outcome: Any) -> None:
    """Print the outcome; a rejected survey exits with code 1."""
    env = outcome.envelope
    if outcome.status == "accepted":
        views = ", ".join(f"{a} {len(p.views)}" for a, p in outcome.plans.items())
        c = env.center_m
        typer.echo(f"accepted: {outcome.folder} (views {views}; centre ({c[0]:.3f}, {c[1]:.3f}) m, radius "
                   f"{env.radius_m * 100:.1f} cm, height {env.height_m * 100:.1f} cm, standoff "
                   f"{env.standoff_m * 100:.1f} cm)")
        return
    typer.echo(f"darp: survey rejected ({outcome.reason}): {outcome.message}", err=True)
    typer.echo(f"kept in {outcome.folder}", err=True)
    raise typer.Exit(code=1)


@app.command("collect")
def collect_command(
    name: Annotated[str, typer.Argument(help="Survey name: the folder created under --out.", show_default=False)],
    twin: Annotated[bool, typer.Option("--twin", help="Run on the digital twin.")] = False,
    hardware: Annotated[Path | None, typer.Option("--hardware", help="Run on the real rig described by this rig "
                                                  "YAML (with its hardware: section).", show_default=False)] = None,
    obj_name: Annotated[str, typer.Option("--object", "-o", help="Twin: object name, mesh file, or 'none' (an "
                                          "empty table).")] = "mug",
    scale: Annotated[float, typer.Option(help="Twin: object scale (0.001 for a mesh in millimetres).")] = 1.0,
    placement: Annotated[str | None, typer.Option(help="Twin: x,y,yaw_deg on the table (default: random, seeded).",
                                                  show_default=False)] = None,
    seed: Annotated[int, typer.Option(help="Twin: seed of every random draw.")] = 0,
    profile: Annotated[str, typer.Option(help="Twin: error profile, ideal or realistic.")] = "realistic",
    fps: Annotated[int, typer.Option(help="Twin: camera frame rate.")] = 30,
    resolution: Annotated[str, typer.Option(help="Twin: image size WIDTHxHEIGHT.")] = "640x480",
    calibration: Annotated[str | None, typer.Option(help="Calibration file for live decisions; on the twin also "
                                                    "'truth' (its true calibration). Default on the twin: the rig's "
                                                    "nominal values.", show_default=False)] = None,
    rig_file: Annotated[Path | None, typer.Option("--rig", help="Twin: rig YAML (default: the packaged rig).",
                                                  show_default=False)] = None,
    out: Annotated[Path, typer.Option(help="Folder that receives the survey folder.")] = Path("."),
    overwrite: Annotated[bool, typer.Option(help="Replace an existing NAME (and NAME.partial/.rejected).")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Survey one object autonomously: localise, confirm, plan, record both cameras, verify."""
    if twin == (hardware is not None):
        raise fail("choose exactly one of --twin and --hardware RIG.yaml")
    from darp.acquisition.episode import check_name

    check_name(name)
    if hardware is not None:
        _collect_hardware(name, hardware, calibration, out, overwrite, quiet)
    else:
        _collect_twin(name, obj_name, scale, placement, seed, profile, fps, resolution, calibration, rig_file, out,
                      overwrite, quiet)


def _read_calibration(spec: str) -> Any:
    from darp.formats.calibration import read_calibration

    return read_calibration(Path(spec))


def _collect_hardware(name: str, rig_yaml: Path, calibration: str | None, out: Path, overwrite: bool,
                      quiet: bool) -> None:
    if calibration is None or calibration == "truth":
        raise fail("--hardware needs --calibration FILE (the rig's current calibration epoch)")
    cal = _read_calibration(calibration)
    from darp.acquisition.survey import run_survey
    from darp.hardware.rig import HardwareRig

    with HardwareRig.open(rig_yaml) as rig_backend:
        outcome = _run_with_progress(quiet, name, lambda progress: run_survey(
            rig_backend, rig_backend.rig, out, name, calibration=cal, overwrite=overwrite, progress=progress))
    _report(outcome)


def _collect_twin(name: str, obj_name: str, scale: float, placement: str | None, seed: int, profile: str, fps: int,
                  resolution: str, calibration: str | None, rig_file: Path | None, out: Path, overwrite: bool,
                  quiet: bool) -> None:
    from darp.acquisition.survey import run_survey
    from darp.formats.atomic import write_json_atomic
    from darp.formats.truth import TRUTH_DIR
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import to_world
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings
    from darp.twin.truth import write_truth

    rig = load_rig(rig_file)
    w, h = _resolution(resolution)
    settings = TwinSettings.from_profile(profile, seed=seed).with_camera(fps=fps, width=w, height=h)
    empty = obj_name.strip().lower() == "none"  # an empty table: the survey must end cleanly
    obj = None if empty else _object(obj_name, scale)
    place = None if obj is None else _placement(placement, obj, rig, seed)
    cal = None if calibration in (None, "truth") else _read_calibration(calibration)
    with TwinRig(settings, rig=rig, obj=obj, placement=place) as twin_rig:
        if calibration == "truth":
            cal = twin_rig.true_rig.calibration(settings)

        def write_twin_truth(folder: Path) -> None:
            if obj is None or place is None:
                write_truth(folder, true_rig=twin_rig.true_rig, settings=settings,
                            camera_poses={a: c.truth for a, c in twin_rig.cameras.items()})
                return
            info = {"name": obj.name, "source": obj.source, "scale": scale,
                    "T_world_object": place.T_world_object.tolist(),
                    "placement": {"x_m": place.x_m, "y_m": place.y_m, "yaw_rad": place.yaw_rad,
                                  "table_z_m": place.table_z_m},
                    "center_m": [place.x_m, place.y_m, place.table_z_m + 0.5 * obj.height_m],
                    "radius_m": obj.radius_m, "height_m": obj.height_m}
            write_truth(folder, true_rig=twin_rig.true_rig, settings=settings,
                        camera_poses={a: c.truth for a, c in twin_rig.cameras.items()}, object_info=info,
                        object_mesh_world=to_world(obj, place))
            write_json_atomic(folder / TRUTH_DIR / "contacts.json", [
                {"time_s": e.time_s, "arm": e.contact.arm_id, "arm_geom": e.contact.arm_geom,
                 "other": e.contact.other, "other_geom": e.contact.other_geom, "distance_m": e.contact.distance_m}
                for e in twin_rig.contact_events])

        outcome = _run_with_progress(quiet, name, lambda progress: run_survey(
            twin_rig, rig, out, name, calibration=cal, overwrite=overwrite, progress=progress,
            object_name=None if obj is None else obj.name, before_finalise=write_twin_truth))
        contacts = list(twin_rig.contact_events)
    if contacts:
        first = contacts[0]
        typer.echo(f"darp: warning: the twin saw {len(contacts)} contact(s) during motion, first at "
                   f"t={first.time_s:.3f} s: {first.contact.arm_geom} against {first.contact.other_geom}", err=True)
    _report(outcome)


__all__ = ["collect_command"]
