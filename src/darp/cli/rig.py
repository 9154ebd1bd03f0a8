"""``darp rig``: show a rig file and draw the rig at given joint configurations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from darp.cli._app import app

rig_app = typer.Typer(help="The dual-arm rig: print and plot its geometry.", no_args_is_help=True)
app.add_typer(rig_app, name="rig")


def parse_joints(text: str, option: str) -> np.ndarray:
    """Six comma- (or space-) separated joint angles in radians; a KinematicsError names the option."""
    from darp.errors import KinematicsError

    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        q = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise KinematicsError(f"{option}: expected 6 numbers (radians), got {text!r}") from None
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise KinematicsError(f"{option}: expected 6 finite numbers (radians), got {len(parts)} in {text!r}")
    return q


@rig_app.command("show")
def show(
    rig_file: Path | None = typer.Argument(None, help="Rig YAML file (default: the packaged rig)."),
    as_yaml: bool = typer.Option(False, "--yaml", help="Print the rig as YAML instead of tables."),
) -> None:
    """Print a rig: arms, bases, camera mounts, park poses, table, workspace and margins."""
    from rich.console import Console
    from rich.table import Table

    from darp.kinematics.rig import load_rig
    from darp.kinematics.rig_yaml import xyz_rpy_from_pose

    rig = load_rig(rig_file)
    if as_yaml:
        typer.echo(rig.to_yaml(), nl=False)
        return
    console = Console()
    console.print(f"[bold]rig {rig.name}[/bold]  ({rig.source})")
    console.print(f"wrist frame: {rig.wrist_frame};  world: origin on the table between the bases, x from "
                  f"{rig.arm_ids[0]} towards {rig.arm_ids[1]}, z up")
    console.print(f"base separation {rig.base_separation_m:.4f} m, relative yaw {rig.relative_yaw_deg:.2f} deg")

    def fmt(values: np.ndarray, digits: int = 4) -> str:
        return "(" + ", ".join(f"{v:+.{digits}f}" for v in values) + ")"

    table = Table(title="arms", show_lines=True)
    for column in ("arm", "side", "camera", "base xyz (m) / rpy (deg)", "T_flange_cam xyz (m) / rpy (deg)",
                   "park q (rad)", "camera at park (m)"):
        table.add_column(column)
    for arm_id, arm in rig.arms.items():
        base_xyz, base_rpy = xyz_rpy_from_pose(arm.T_world_base)
        cam_xyz, cam_rpy = xyz_rpy_from_pose(arm.T_flange_cam)
        park_cam = rig.T_world_cam(arm_id, arm.park_q_rad)
        table.add_row(
            arm_id, arm.side, arm.camera_serial,
            f"{fmt(base_xyz)}\n{fmt(np.degrees(base_rpy), 2)}",
            f"{fmt(cam_xyz)}\n{fmt(np.degrees(cam_rpy), 2)}",
            fmt(arm.park_q_rad, 3),
            f"{fmt(park_cam[:3, 3], 3)}\nlooking {fmt(park_cam[:3, 2], 2)}",
        )
    console.print(table)
    t, w, m, body = rig.table, rig.workspace, rig.margins, rig.camera_body
    console.print(f"table: top at z = {t.height_m:.3f} m, x {t.x_range_m} m, y {t.y_range_m} m")
    console.print(f"workspace: x {w.x_range_m}, y {w.y_range_m}, z {w.z_range_m} m")
    console.print(f"camera body: {fmt(body.size_m * 1000, 1)} mm, centre {fmt(body.center_cam_m * 1000, 1)} mm "
                  "in the optical frame")
    console.print(f"margins: table {m.table_clearance_m * 1000:.0f} mm, arm-arm {m.arm_arm_margin_m * 1000:.0f} mm, "
                  f"joint limits {m.joint_limit_margin_rad:.3f} rad")


@rig_app.command("plot")
def plot(
    out: Path = typer.Option(..., "--out", "-o", help="Image to write (.png, .svg or .pdf)."),
    rig_file: Path | None = typer.Option(None, "--rig", help="Rig YAML file (default: the packaged rig)."),
    config: str = typer.Option(
        "park", "--config", help="Configuration for both arms: park, or a Z1 named one (forward, stow, ...)."),
    q110: str | None = typer.Option(None, "--q110", help="arm110 joints, 6 radians: '0,0.6,-1.2,1.2,0,0'."),
    q111: str | None = typer.Option(None, "--q111", help="arm111 joints, 6 radians."),
    calibration: Path | None = typer.Option(
        None, "--calibration", "-c", help="Draw with calibrated bases, mounts and joint offsets."),
) -> None:
    """Draw both arms (links, collision capsules), cameras (frustums) and the table: two views."""
    from darp.errors import KinematicsError
    from darp.formats.calibration import read_calibration
    from darp.kinematics import z1
    from darp.kinematics.rig import load_rig
    from darp.reconstruction.rig_figures import plot_rig

    rig = load_rig(rig_file)
    cal = read_calibration(calibration) if calibration is not None else None
    if config != "park" and config not in z1.NAMED_CONFIGS:
        names = ", ".join(["park", *z1.NAMED_CONFIGS])
        raise KinematicsError(f"--config: unknown configuration {config!r} (choose from {names})")
    given = {"arm110": q110, "arm111": q111}
    q_by_arm = {}
    for arm_id, arm in rig.arms.items():
        text = given.get(arm_id)
        if text is not None:
            q = parse_joints(text, f"--q{arm_id.removeprefix('arm')}")
        else:
            q = arm.park_q_rad if config == "park" else z1.NAMED_CONFIGS[config]
        if not z1.within_limits(q):  # still drawn: seeing where an infeasible pose goes is the point
            typer.echo(f"darp: warning: {arm_id}: joints {np.round(q, 4).tolist()} are outside the Z1 limits",
                       err=True)
        q_by_arm[arm_id] = np.asarray(q, dtype=np.float64)
    path = plot_rig(rig, q_by_arm, out, calibration=cal)
    typer.echo(f"wrote {path}")
