"""``darp hardware check [--rig RIG.yaml] [--json]``: pre-flight check of the real rig; reads, never moves.

Prints a table of checks (ok / warning / FAIL with the reason), then one ``darp: error:`` line per
failure on stderr. Exit codes: 0 when nothing required failed, 2 otherwise (a bad rig file, a missing
camera or stream profile, an unreachable arm, a joint outside its limits). The logic is
:mod:`darp.hardware.check`; see docs/hardware.md.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from darp.cli._app import app, error
from darp.cli._options import RigFile

hardware_app = typer.Typer(help="The real rig: pre-flight checks (nothing moves).", no_args_is_help=True)
app.add_typer(hardware_app, name="hardware")

STYLE = {"ok": "green", "warning": "yellow", "FAIL": "bold red"}


def _print_table(report: Any) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(soft_wrap=False)
    console.print(f"[bold]darp hardware check[/bold]  {report.rig_path}")
    if report.cameras:
        cams = Table(title="RealSense devices", title_justify="left")
        for column in ("name", "serial", "firmware", "USB"):
            cams.add_column(column)
        for c in report.cameras:
            usb = f"[yellow]{c.usb}[/yellow]" if c.on_usb2 else c.usb
            cams.add_row(c.name, c.serial, c.firmware, usb)
        console.print(cams)
    table = Table(title="Checks", title_justify="left")
    table.add_column("check")
    table.add_column("verdict")
    table.add_column("detail", overflow="fold")
    for check in report.checks:
        table.add_row(check.name, f"[{STYLE[check.verdict]}]{check.verdict}[/]", check.detail)
    console.print(table)
    failed = len(report.failures)
    warnings = sum(c.verdict == "warning" for c in report.checks)
    console.print(f"{'FAIL' if failed else 'ok'}: {len(report.checks)} checks, {failed} failed, {warnings} warning(s)")


@hardware_app.command("check")
def check(
    rig_file: RigFile = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON instead of tables.")] = False,
    timeout_s: Annotated[float, typer.Option("--timeout-s", min=0.0, help="Seconds each arm's controller may take "
                                             "to answer.")] = 3.0,
    park_tolerance_rad: Annotated[float, typer.Option("--park-tolerance-rad", min=0.0, help="Radians from the park "
                                                      "pose still 'at park'.")] = 0.05,
) -> None:
    """Check cameras, streams and arms of the real rig without moving anything; exit 2 if something required fails."""
    from darp.hardware.check import check_rig
    from darp.kinematics.rig import default_rig_path

    report = check_rig(rig_file if rig_file is not None else default_rig_path(), arm_timeout_s=timeout_s,
                       park_tol_rad=park_tolerance_rad)
    if as_json:
        typer.echo(json.dumps(report.to_dict(), indent=2))
    else:
        _print_table(report)
    for failure in report.failures:
        error(f"{failure.name}: {failure.detail}")
    if report.failures:
        raise typer.Exit(code=2)
