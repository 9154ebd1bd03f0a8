"""``darp rig``: show a rig file and draw the rig at given joint configurations."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from darp.cli._app import app
from darp.cli._options import ArmConfig, Joints, RigFile, calibration_option, out_option, parse_joints

rig_app = typer.Typer(help="The dual-arm rig: print and plot its geometry.", no_args_is_help=True)
app.add_typer(rig_app, name="rig")


def _joints_option(arm: str) -> Any:
    return typer.Option(f"--q{arm.removeprefix('arm')}-rad", parser=parse_joints, metavar="Q1,..,Q6",
                        help=f"{arm} joints, 6 radians: '0,0.6,-1.2,1.2,0,0' (replaces --config for this arm).",
                        show_default=False)


@rig_app.command("show")
def show(
    rig_file: RigFile = None,
    as_yaml: Annotated[bool, typer.Option("--yaml", help="Print the rig as YAML instead of tables.")] = False,
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
    for column in ("arm", "side", "camera", "base xyz (m) / rpy (deg)", "T_wrist_cam xyz (m) / rpy (deg)",
                   "park q (rad)", "camera at park (m)"):
        table.add_column(column)
    for arm_id, arm in rig.arms.items():
        base_xyz, base_rpy = xyz_rpy_from_pose(arm.T_world_base)
        cam_xyz, cam_rpy = xyz_rpy_from_pose(arm.T_wrist_cam)
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
    out: Annotated[Path, out_option("Image to write (.png, .svg or .pdf).")],
    rig_file: RigFile = None,
    config: Annotated[ArmConfig, typer.Option("--config", help="Configuration for both arms: park, or a Z1 named "
                                              "one.")] = ArmConfig.park,
    q110: Annotated[Joints | None, _joints_option("arm110")] = None,
    q111: Annotated[Joints | None, _joints_option("arm111")] = None,
    calibration: Annotated[Path | None, calibration_option("Draw with calibrated bases, mounts and joint "
                                                           "offsets.")] = None,
) -> None:
    """Draw both arms (links, collision capsules), cameras (frustums) and the table: two views."""
    from darp.formats.calibration import read_calibration
    from darp.kinematics import z1
    from darp.kinematics.rig import load_rig
    from darp.reconstruction.rig_figures import plot_rig

    rig = load_rig(rig_file)
    cal = read_calibration(calibration) if calibration is not None else None
    given = {"arm110": q110, "arm111": q111}
    q_by_arm = {}
    for arm_id, arm in rig.arms.items():
        joints = given.get(arm_id)
        if joints is not None:
            q = np.array(joints.rad, dtype=np.float64)
        else:
            q = arm.park_q_rad if config is ArmConfig.park else z1.NAMED_CONFIGS[config.value]
        if not z1.within_limits(q):  # still drawn: seeing where an infeasible pose goes is the point
            typer.echo(f"darp: warning: {arm_id}: joints {np.round(q, 4).tolist()} are outside the Z1 limits",
                       err=True)
        q_by_arm[arm_id] = np.asarray(q, dtype=np.float64)
    path = plot_rig(rig, q_by_arm, out, calibration=cal)
    typer.echo(f"wrote {path}")
