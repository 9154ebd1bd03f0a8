"""``darp recording``: inspect and export RealSense recordings (filled in by the formats work)."""

from __future__ import annotations

import typer

from darp.cli._app import app

recording_app = typer.Typer(help="Inspect and export RealSense recordings (.bag, .db3).", no_args_is_help=True)
app.add_typer(recording_app, name="recording")
