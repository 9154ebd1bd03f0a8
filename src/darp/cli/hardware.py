"""``darp hardware check [--rig RIG.yaml] [--json] [--twin-cameras]``: pre-flight check of the real rig; reads,
never moves. ``darp hardware vendor-sim [--rig RIG.yaml]``: Unitree's controller with simulated motors for every
arm of the rig (docs/hardware.md, "Vendor in the loop").

Prints a table of checks (ok / warning / FAIL with the reason), then one ``darp: error:`` line naming the first
failure and the others. Exit codes: 0 when nothing required failed, 2 otherwise (a bad rig file, a missing
camera or stream profile, an unreachable arm, a joint outside its limits). The logic is
:mod:`darp.hardware.check`; see docs/hardware.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, error
from darp.cli._options import RigFile

hardware_app = typer.Typer(help="The real rig: pre-flight checks (nothing moves); Unitree's controller with "
                           "simulated motors.", no_args_is_help=True)
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
    twin_cameras: Annotated[bool, typer.Option("--twin-cameras", help="The cameras will be the twin's: no "
                                               "RealSense is looked for.")] = False,
) -> None:
    """Check cameras, streams and arms of the real rig without moving anything; exit 2 if something required fails."""
    from darp.hardware.check import check_rig
    from darp.kinematics.rig import default_rig_path

    report = check_rig(rig_file if rig_file is not None else default_rig_path(), arm_timeout_s=timeout_s,
                       park_tol_rad=park_tolerance_rad, twin_cameras=twin_cameras)
    if as_json:
        typer.echo(json.dumps(report.to_dict(), indent=2))
    else:
        _print_table(report)
    if report.failures:  # one line: the first failure, and how many more the table (or JSON) lists
        first, more = report.failures[0], report.failures[1:]
        also = f" (and {len(more)} more failed check(s): {', '.join(f.name for f in more)})" if more else ""
        error(f"{first.name}: {first.detail}{also}")
        raise typer.Exit(code=2)


@hardware_app.command("vendor-sim")
def vendor_sim(
    rig_file: RigFile = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Folder that receives each controller's config/ "
                                             "and log (default: a temporary folder).", show_default=False)] = None,
    duration_s: Annotated[float, typer.Option("--duration-s", min=0.0, help="Stop after this many seconds "
                                              "(0: run until Ctrl-C).")] = 0.0,
) -> None:
    """Run Unitree's controller with simulated motors for every arm of the rig, on its ports, at its park pose."""
    import time

    from darp.hardware.settings import load_hardware_settings
    from darp.hardware.vendor_sim import SimController
    from darp.kinematics.rig import default_rig_path, load_rig

    path = rig_file if rig_file is not None else default_rig_path()
    rig = load_rig(path)
    settings = load_hardware_settings(path, rig.arm_ids)
    controllers: list[SimController] = []
    try:
        for arm_id in rig.arm_ids:
            link = settings.arms[arm_id]
            if link.controller_ip != "127.0.0.1":
                error(f"{arm_id}: controller_ip {link.controller_ip}: a simulated controller runs on 127.0.0.1")
                raise typer.Exit(code=2)
            folder = None if out is None else out / arm_id
            sim = SimController(arm_id, link.controller_port, link.sdk_port, q0_rad=rig.arm(arm_id).park_q_rad,
                                run_dir=folder)
            controllers.append(sim.start())
            typer.echo(f"{arm_id}: z1_ctrl_sim pid {sim.pid} on SDK ports {link.controller_port}/{link.sdk_port} "
                       f"(log {sim.log_path})")
        typer.echo("controllers running; Ctrl-C stops them")
        # a controller that ends (killed: the "controller killed" case) is reported once; the other arms'
        # controllers keep running, as the real rig's separate z1_ctrl processes would
        deadline = time.monotonic() + duration_s if duration_s > 0 else None
        ended: set[str] = set()
        while len(ended) < len(controllers) and (deadline is None or time.monotonic() < deadline):
            for c in controllers:
                if c.name not in ended and not c.running:
                    ended.add(c.name)
                    error(f"{c.name}: z1_ctrl_sim ended (log {c.log_path})")
            time.sleep(0.2)
        if ended:
            raise typer.Exit(code=2)
    except KeyboardInterrupt:
        typer.echo("stopping")
    finally:
        for c in controllers:
            c.stop()
