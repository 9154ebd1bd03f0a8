"""``darp view SURVEY|PROCESSED_DIR [--save FILE.rrd]``: the survey in rerun (entities: docs/ecosystem.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from darp.cli._app import app
from darp.cli._options import calibration_option, input_argument


@app.command("view")
def view_command(
    path: Annotated[Path, input_argument("A survey folder, or a processed survey (a folder of darp process's "
                                         "output).")],
    save: Annotated[Path | None, typer.Option("--save", help="Write the recording to this .rrd file and open "
                                              "no window.", show_default=False)] = None,
    calibration: Annotated[Path | None, calibration_option("Calibration for the arms' base poses and eq. 1 "
                                                           "(default: the twin's truth, else the nominal rig).")
                           ] = None,
    every_s: Annotated[float, typer.Option("--every-s", min=0.0, help="A raw survey: seconds between the "
                                           "frames shown.")] = 0.5,
) -> None:
    """Show both arms moving, camera frustums, RGB/depth/IR, clouds, mesh and held-out errors in rerun."""
    import time

    from darp.view import view

    started = time.monotonic()
    stats = view(path, save, calibration_path=calibration, every_s=every_s)
    what = (f"{stats.arm_states} arm states, {stats.images} camera frames, {stats.clouds} clouds, "
            f"{stats.mesh_triangles} mesh triangles, {stats.heldout_points} held-out points")
    typer.echo(f"{'wrote ' + str(save) if save else 'sent to rerun'}: {what} ({time.monotonic() - started:.1f} s)")
