"""``darp collect``: one autonomous object survey, on the digital twin or on the real rig.

    darp collect NAME --twin [--object mug|PATH|none] [--scale S] [--placement x,y,yaw_deg] [--seed N]
                      [--profile ideal|realistic|paper | --settings FILE] [--fps 30] [--resolution 640x480]
                      [-c FILE | --truth-calibration] [--viewpoints coverage|orbit] [--rig RIG.yaml] [-o DIR]
                      [--overwrite] [--quiet]
    darp collect NAME --hardware [--rig RIG.yaml] -c FILE [--viewpoints coverage|orbit] [-o DIR] [--overwrite]
                      [--quiet]

The survey folder is ``<out>/NAME`` when accepted, ``<out>/NAME.rejected`` when rejected (REJECTED.txt
says why) and ``<out>/NAME.partial`` after an interruption (PARTIAL.txt). Exit codes: 0 accepted,
1 rejected, 2 bad input or an error, 130 interrupted. See docs/acquisition.md.
"""

from __future__ import annotations

from enum import StrEnum
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
    calibration_option,
    out_option,
    parse_placement,
    parse_resolution,
    progress_bar,
    twin_settings,
)
from darp.cli.twin import PLACEMENT_HELP


class Viewpoints(StrEnum):
    """How each arm's views are planned (darp.acquisition.survey)."""

    coverage = "coverage"
    orbit = "orbit"


PHASES = {"localise": "localising", "confirm": "confirming", "plan": "planning", "record": "recording",
          "verify": "verifying", "done": "done"}


def _run_with_progress(quiet: bool, title: str, run: Any) -> Any:
    """Call ``run(progress)`` under a rich progress bar showing the survey's phase."""
    from rich.progress import BarColumn, TextColumn, TimeElapsedColumn

    with progress_bar(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.fields[note]}"),
                      TimeElapsedColumn(), quiet=quiet, transient=False) as bar:
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
    hardware: Annotated[bool, typer.Option("--hardware", help="Run on the real rig (--rig, with its hardware: "
                                           "section).")] = False,
    rig_file: RigFile = None,
    twin_cameras: Annotated[bool, typer.Option("--twin-cameras", help="With --hardware: the twin's cameras and "
                                               "scene following the arms' reported joints instead of RealSense "
                                               "(--object, --placement, --seed, --profile, --fps, --resolution "
                                               "apply; its truth is written).")] = False,
    obj_name: Annotated[str, typer.Option("--object", help="Twin: object name, mesh file, or 'none' (an empty "
                                          "table).")] = "mug",
    scale: Annotated[float, typer.Option("--scale", help="Twin: object scale (0.001 for a mesh in "
                                         "millimetres).")] = 1.0,
    placement: Annotated[Placement | None, typer.Option(
        "--placement", parser=parse_placement, metavar="X,Y,YAW_DEG",
        help=f"Twin: {PLACEMENT_HELP} (default: random, seeded).", show_default=False)] = None,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Twin: seed of every random draw.")] = 0,
    profile: ProfileOption = Profile.realistic,
    settings_file: SettingsFile = None,
    fps: Annotated[int, typer.Option("--fps", min=1, help="Twin: camera frame rate.")] = 30,
    resolution: Annotated[Resolution, typer.Option("--resolution", parser=parse_resolution, metavar="WIDTHxHEIGHT",
                                                   help="Twin: image size.")] = Resolution(640, 480),
    calibration: Annotated[Path | None, calibration_option(
        "Calibration for live decisions (required with --hardware; default on the twin: the rig's nominal "
        "values).")] = None,
    truth_calibration: Annotated[bool, typer.Option("--truth-calibration", help="Twin: decide with the twin's true "
                                                    "calibration instead of --calibration.")] = False,
    viewpoints: Annotated[Viewpoints, typer.Option(
        "--viewpoints", help="coverage: plan both arms' views for coverage of the envelope's surface (the sides "
        "between the arms and the top included) with a co-observed band, and add next best views from the "
        "recorded depth; orbit: the paper's fixed orbit per arm (what darp demo uses to reproduce the paper).",
        show_default=True)] = Viewpoints.coverage,
    out: Annotated[Path, out_option("Folder that receives the survey folder.", show_default=True)] = Path("."),
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing NAME (and "
                                            "NAME.partial/.rejected).")] = False,
    quiet: Quiet = False,
) -> None:
    """Survey one object autonomously: localise, confirm, plan, record both cameras, verify."""
    if twin == hardware:
        raise typer.BadParameter("choose exactly one", param_hint="'--twin' / '--hardware'")
    if truth_calibration and (hardware or calibration is not None):
        raise typer.BadParameter("the twin's true calibration is for --twin without --calibration",
                                 param_hint="'--truth-calibration'")
    if hardware and calibration is None:
        raise typer.BadParameter("required with --hardware (the rig's current calibration epoch)",
                                 param_hint="'--calibration'")
    from darp.acquisition.episode import check_name

    check_name(name)
    if hardware:
        assert calibration is not None
        twin_scene = None
        if twin_cameras:
            twin_scene = {"settings": twin_settings(profile, seed, settings_file).with_camera(
                fps=fps, width=resolution.width, height=resolution.height), "object": obj_name, "scale": scale,
                "placement": placement}
        _collect_hardware(name, rig_file, calibration, out, overwrite, quiet, viewpoints, twin_scene)
    else:
        settings = twin_settings(profile, seed, settings_file)
        _collect_twin(name, obj_name, scale, placement, settings, fps, resolution, calibration,
                      truth_calibration, rig_file, out, overwrite, quiet, viewpoints)


def _settings(viewpoints: Viewpoints) -> Any:
    from darp.acquisition.survey import SurveySettings

    return SurveySettings(viewpoint_strategy=viewpoints.value)


def _collect_hardware(name: str, rig_file: Path | None, calibration: Path, out: Path, overwrite: bool,
                      quiet: bool, viewpoints: Viewpoints = Viewpoints.coverage,
                      twin_scene: dict[str, Any] | None = None) -> None:
    """A survey on the rig's arms with its RealSense cameras, or (``twin_scene``) with twin cameras and a twin
    object that follow the arms (the twin's truth is written into the survey, as on the twin)."""
    from darp.acquisition.survey import run_survey
    from darp.cli._hardware_rig import open_hardware
    from darp.formats.calibration import read_calibration

    cal = read_calibration(calibration)
    before_finalise, object_name, scene, scale = None, None, {}, 1.0
    if twin_scene is not None:
        scale = twin_scene["scale"]
        from darp.cli.twin import load_object, place_object
        from darp.kinematics.rig import load_rig
        from darp.twin.record import write_twin_truth

        empty = twin_scene["object"].strip().lower() == "none"
        obj = None if empty else load_object(twin_scene["object"], scale)
        place = None if obj is None else place_object(twin_scene["placement"], obj, load_rig(rig_file),
                                                      twin_scene["settings"].seed)
        scene = {"obj": obj, "placement": place}
        object_name = None if obj is None else obj.name
    rig_backend, mirror = open_hardware(rig_file, twin_settings=None if twin_scene is None else twin_scene["settings"],
                                        **scene)
    if mirror is not None:
        def before_finalise(folder: Path) -> None:
            write_twin_truth(folder, mirror, scene["obj"], scene["placement"], scale)
    with rig_backend:
        outcome = _run_with_progress(quiet, name, lambda progress: run_survey(
            rig_backend, rig_backend.rig, out, name, calibration=cal, overwrite=overwrite, progress=progress,
            object_name=object_name, before_finalise=before_finalise, settings=_settings(viewpoints)))
    _report(outcome)


def _collect_twin(name: str, obj_name: str, scale: float, placement: Placement | None, settings: Any,
                  fps: int, resolution: Resolution, calibration: Path | None, truth_calibration: bool,
                  rig_file: Path | None, out: Path, overwrite: bool, quiet: bool,
                  viewpoints: Viewpoints = Viewpoints.coverage) -> None:
    """Decisions use ``calibration``, the twin's true one (``truth_calibration``) or else the rig's nominal."""
    from darp.acquisition.survey import run_survey
    from darp.cli.twin import load_object, place_object
    from darp.formats.calibration import read_calibration
    from darp.kinematics.rig import load_rig
    from darp.twin.record import write_twin_truth
    from darp.twin.rig_backend import TwinRig

    rig = load_rig(rig_file)
    settings = settings.with_camera(fps=fps, width=resolution.width, height=resolution.height)
    seed = settings.seed
    empty = obj_name.strip().lower() == "none"  # an empty table: the survey must end cleanly
    obj = None if empty else load_object(obj_name, scale)
    place = None if obj is None else place_object(placement, obj, rig, seed)
    cal = read_calibration(calibration) if calibration is not None else None
    twin_rig = TwinRig(settings, rig=rig, obj=obj, placement=place)
    with twin_rig:
        if truth_calibration:
            cal = twin_rig.true_rig.calibration(settings)

        def write_truth(folder: Path) -> None:
            write_twin_truth(folder, twin_rig, obj, place, scale)

        outcome = _run_with_progress(quiet, name, lambda progress: run_survey(
            twin_rig, rig, out, name, calibration=cal, overwrite=overwrite, progress=progress,
            object_name=None if obj is None else obj.name, before_finalise=write_truth,
            settings=_settings(viewpoints)))
        contacts = list(twin_rig.contact_events)
    if contacts:
        first = contacts[0]
        typer.echo(f"darp: warning: the twin saw {len(contacts)} contact(s) during motion, first at "
                   f"t={first.time_s:.3f} s: {first.contact.arm_geom} against {first.contact.other_geom}", err=True)
    _report(outcome)


__all__ = ["collect_command"]
