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
    connect: Annotated[str | None, typer.Option("--connect", metavar="URL", help="Send to a rerun viewer already "
                                                "running (e.g. on another machine): rerun+http://HOST:PORT/proxy, "
                                                "HOST:PORT or a local port; default: open a new viewer.",
                                                show_default=False)] = None,
) -> None:
    """Show both arms moving, camera frustums, RGB/depth/IR, clouds, mesh and held-out errors in rerun."""
    import time

    from darp.errors import ConfigError
    from darp.view import view, viewer_url

    if connect is not None:
        if save is not None:
            raise typer.BadParameter("give --save or --connect, not both", param_hint="'--connect'")
        try:
            connect = viewer_url(connect)
        except ConfigError as err:
            raise typer.BadParameter(err.message, param_hint="'--connect'") from None
    started = time.monotonic()
    stats = view(path, save, calibration_path=calibration, every_s=every_s, connect=connect)
    what = (f"{stats.arm_states} arm states, {stats.images} camera frames, {stats.clouds} clouds, "
            f"{stats.mesh_triangles} mesh triangles, {stats.heldout_points} held-out points")
    where = f"wrote {save}" if save else f"sent to {connect}" if connect else "sent to rerun"
    typer.echo(f"{where}: {what} ({time.monotonic() - started:.1f} s)")
