"""``darp poses``: camera trajectories of a survey from the joint log and a calibration (eq. 1)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from darp.cli._app import app
from darp.cli._options import ImageStream, RigFile, calibration_option, input_argument, out_option
from darp.kinematics.camera_poses import DEFAULT_MAX_GAP_S


def warn(message: str) -> None:
    """One unwrapped warning line on stderr."""
    typer.echo(f"darp: warning: {message}", err=True)


@app.command("poses")
def poses(
    survey: Annotated[Path, input_argument("Survey folder (cam<serial>.bag x2, arm_poses.csv, ...).")],
    out: Annotated[Path, out_option("Output folder (created; files replaced atomically).", folder=True)],
    calibration: Annotated[Path | None, calibration_option(
        "Calibration JSON of the rig epoch (default: the rig's nominal values).")] = None,
    rig_file: RigFile = None,
    stream: Annotated[ImageStream, typer.Option("--stream", help="Stream whose frames get poses.")] = (
        ImageStream.depth),
    max_gap_s: Annotated[float, typer.Option("--max-gap-s", min=1e-6, help="Longest joint-log gap interpolated "
                                             "across, seconds.")] = DEFAULT_MAX_GAP_S,
    clock_offset_s: Annotated[float, typer.Option("--clock-offset-s", help="Camera clock minus host clock, seconds: "
                                                  "camera time = host time + offset.")] = 0.0,
    figure: Annotated[bool, typer.Option("--figure/--no-figure", help="Write trajectories.png.")] = True,
) -> None:
    """Camera pose at every frame of both cameras: TUM files, .npz arrays, summary.json, a figure.

    Frames outside the joint log, or inside a log gap longer than --max-gap-s, get no pose.
    """
    from rich.console import Console
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from darp.formats.calibration import read_calibration
    from darp.formats.io_output import unfinished_folder
    from darp.formats.survey import open_survey
    from darp.kinematics.rig import load_rig
    from darp.reconstruction.poses import FIGURE_FILE, recover_survey_poses, write_survey_poses

    err = Console(stderr=True)
    rig = load_rig(rig_file)
    cal = read_calibration(calibration) if calibration is not None else rig.nominal_calibration()
    serial_to_arm = {arm.serial: arm_id for arm_id, arm in cal.arms.items()}
    opened = open_survey(survey, serial_to_arm=serial_to_arm, mapping_source=calibration)
    if opened.partial is not None:  # PARTIAL.txt: the survey did not finish; its poses are partial too
        warn(f"{survey}: unfinished survey ({opened.partial}): the poses cover what was recorded")
    if calibration is None:
        warn(f"no --calibration given: using the nominal transforms of rig {rig.name!r} and zero joint "
             "offsets; poses can be centimetres off")

    columns = (SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=True, disable=not err.is_terminal) as progress:
        task = progress.add_task("reading the joint log", total=len(opened.arms) + 1 + int(figure))

        def on_arm(arm: str) -> None:
            progress.update(task, description=f"{arm}: frame index of cam{opened.serials[arm]} and eq. 1")
            progress.advance(task)

        result = recover_survey_poses(
            opened, cal, calibration_path=calibration, stream=stream.value, max_gap_s=max_gap_s,
            clock_offset_s=clock_offset_s, wrist_frame=rig.wrist_frame, on_arm=on_arm,
        )
        progress.update(task, description="writing trajectories")
        with unfinished_folder(out, "darp poses"):  # UNFINISHED.txt until every file is there
            write_survey_poses(result, out)
            progress.advance(task)
            if figure:
                from darp.reconstruction.rig_figures import plot_trajectories

                progress.update(task, description="drawing the figure")
                plot_trajectories(result, out / FIGURE_FILE, rig=rig)
                progress.advance(task)

    for warning in result.warnings:
        warn(warning)
    table = Table(title=f"{opened.name}: camera poses ({stream} frames)")
    for column in ("arm", "camera", "frames", "posed", "before log", "after log", "in gap"):
        table.add_column(column, justify="right")
    for arm, traj in result.trajectories.items():
        c = traj.poses.counts()
        table.add_row(arm, traj.serial, str(c["frames"]), str(c["posed"]), str(c["before_log"]),
                      str(c["after_log"]), str(c["in_gap"]))
    Console().print(table)
    typer.echo(f"wrote {out}")
