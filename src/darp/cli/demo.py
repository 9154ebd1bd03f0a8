"""``darp demo``: the whole DARP system end to end on the digital twin.

Calibrate the rig from simulated ChArUco captures, survey paper objects autonomously with that
calibration, process the surveys (poses, keyframes, fusion, meshes, held-out and ground-truth
evaluation) and write the report; print the results next to the paper's numbers. Each step is one of
darp's own commands, so the demo is also a script of how to use them. Finished steps are skipped when
the demo is run again on the same folder.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, run
from darp.cli._options import Profile, SettingsFile, TwinObject, out_option, twin_settings
from darp.errors import DarpError

DEFAULT_OBJECTS = (TwinObject.mug, TwinObject.ketchup, TwinObject.dumbbell)


def _step(title: str) -> None:
    typer.secho(f"\n== {title}", bold=True)


def _call(args: list[Any]) -> None:
    """Run a darp command; stop the demo with its error if it fails."""
    argv = [str(a) for a in args]
    code = run(argv)
    if code != 0:
        raise DarpError(f"step failed (exit {code}): darp {' '.join(argv)}")


@app.command("demo")
def demo_command(
    out: Annotated[Path, out_option("Folder for everything the demo makes.", show_default=True)] = Path("demo_out"),
    objects: Annotated[list[TwinObject] | None, typer.Option(
        "--object", help="Twin object to survey; repeat per object (default: mug, ketchup, dumbbell).",
        show_default=False)] = None,
    seed: Annotated[int, typer.Option("--seed", min=0,
                                      help="Seed of the twin (true rig errors, placements, noise).")] = 0,
    fps: Annotated[int, typer.Option("--fps", min=1, help="Camera frame rate of the demo surveys: 6, 15 or 30 "
                                     "(the real rig records 30).")] = 6,
    captures: Annotated[int, typer.Option("--captures", min=1, max=10000, help="Calibration captures per arm.")] = 20,
    profile: Annotated[Profile, typer.Option(
        "--profile", help="Twin error profile: paper (the default) has the real rig's uncalibrated errors and "
        "reproduces its error levels; realistic has only errors a calibration absorbs.")] = Profile.paper,
    settings_file: SettingsFile = None,
) -> None:
    """Run the whole system on the digital twin: calibrate, survey, process, report (6-9 minutes on 2 idle cores).

    Default profile paper: the real rig's error levels. --profile realistic: only errors calibration absorbs.
    """
    from darp.twin.placement import seeded_placements  # numpy and the kinematics load only when the demo runs

    started = time.monotonic()
    twin_args: list[Any] = ["--profile", profile.value]
    label = profile.value
    if settings_file is not None:
        settings = twin_settings(profile, seed, settings_file)  # a bad file stops here, named
        seed, label = settings.seed, f"{settings_file}, profile {settings.profile}"
        twin_args = ["--settings", settings_file]
    names = list(dict.fromkeys(o.value for o in (objects or DEFAULT_OBJECTS)))
    out.mkdir(parents=True, exist_ok=True)
    calib_dir = out / "calibration"
    captures_dir = calib_dir / "captures"
    calibration = calib_dir / "calibration.json"
    surveys_dir = out / "surveys"
    processed = out / "processed"

    _step(f"1/4 calibration: {captures} ChArUco captures per arm on the twin ({label}, seed {seed})")
    if not (captures_dir / "captures.json").exists():
        _call(["calib", "capture", "--twin", "--seed", seed, *twin_args, "--captures", captures,
               "--out", captures_dir, "--overwrite"])
    if not calibration.exists():
        _call(["calib", "solve", captures_dir, "--out", calibration, "--report", calib_dir / "report",
               "--truth", captures_dir / "truth" / "calibration.json"])
    else:
        _done_before(calibration)

    _step(f"2/4 autonomous surveys of {', '.join(names)} at {fps} fps (same twin rig, seed {seed})")
    surveys = []
    for name, (x_m, y_m, yaw_deg) in zip(names, seeded_placements(seed, len(names)), strict=True):
        folder = surveys_dir / name
        if not folder.exists():
            # The same seed as the calibration: the same true rig (its errors), another placement.
            _call(["collect", name, "--twin", "--object", name, "--seed", seed, *twin_args,
                   "--fps", fps, "--calibration", calibration, "--out", surveys_dir,
                   "--placement", f"{x_m:.4f},{y_m:.4f},{yaw_deg:.1f}",
                   "--viewpoints", "orbit"])  # the paper's fixed orbit: the demo reproduces the paper
        else:
            _done_before(folder)
        surveys.append(folder)

    _step("3/4 processing: poses, keyframes, fusion, meshes, held-out and ground-truth evaluation")
    _call(["process", *surveys, "--calibration", calibration, "--out", processed, "--resume"])

    _step("4/4 report")
    _call(["report", processed])

    _print_summary(calib_dir, processed)
    typer.secho(f"\ndemo finished in {time.monotonic() - started:.0f} s; report: {processed / 'report.html'}",
                bold=True)


def _done_before(path: Path) -> None:
    """Say that a step is skipped because an earlier run finished it."""
    typer.echo(f"{path}: done by an earlier run, kept (delete it to redo that step)")


def _load(path: Path) -> dict[str, Any]:
    try:
        data: dict[str, Any] = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DarpError(f"cannot read demo results: {err}", path) from err
    return data


def _print_summary(calib_dir: Path, processed: Path) -> None:
    """Print the calibration and reconstruction numbers next to the paper's."""
    from darp.cli._demo_tables import calibration_table, heldout_table, truth_table

    typer.echo("")
    for table in (
        calibration_table(calib_dir),
        heldout_table(_load(processed / "results.json")),
        truth_table(_load(processed / "results.json")),
    ):
        if table:
            typer.echo(table)
            typer.echo("")
