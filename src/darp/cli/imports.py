"""``darp import``: an RGB-D sequence from any camera and arm -> an imported survey that ``darp process`` takes.

    darp import SEQ -o OUT --intrinsics K.txt [--depth-scale-m 0.001]
                (--trajectory FILE|DIR --trajectory-format tum|log|pose-txt|nerfstudio
                 | --flange-poses poses.csv|DIR -c handeye-calibration.json [--unit mm] [--quaternion wxyz])
                [--arm NAME] [--every N] [--envelope manip_envelope.json]
    darp process OUT -o RESULTS [--settings S.yaml]

See docs/any-arm.md.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from darp.cli._app import app
from darp.cli._options import calibration_option, input_argument, out_option


class TrajectoryFormat(StrEnum):
    """World-from-camera trajectory formats (darp.formats.trajectories.FORMATS)."""

    tum = "tum"
    log = "log"
    pose_txt = "pose-txt"
    nerfstudio = "nerfstudio"


class Unit(StrEnum):
    """Translation unit of flange poses."""

    m = "m"
    mm = "mm"


class QuaternionOrder(StrEnum):
    """Quaternion component order of a pose CSV."""

    xyzw = "xyzw"
    wxyz = "wxyz"


@app.command("import")
def import_command(
    sequence: Annotated[Path, input_argument("Folder of colour and 16-bit depth images (names or sub-folders "
                                             "with 'color'/'rgb' and 'depth'; frames matched by their number).")],
    out: Annotated[Path, out_option("Imported survey folder to write (keyframes/, import.json).")],
    intrinsics: Annotated[Path | None, typer.Option("--intrinsics", help="Depth/colour intrinsics (registered "
                                                    "streams): 3x3 .txt/.npy, .npz or .json; a nerfstudio "
                                                    "transforms.json gives its own; a RealSense .bag/.db3 its "
                                                    "colour stream's.", exists=True,
                                                    dir_okay=False, show_default=False)] = None,
    depth_scale_m: Annotated[float, typer.Option("--depth-scale-m", help="Metres per depth unit (0.001: mm).")
                             ] = 0.001,
    trajectory: Annotated[Path | None, typer.Option("--trajectory", help="World-from-camera poses (a file, or "
                                                    "the folder of per-frame pose.txt).", exists=True,
                                                    show_default=False)] = None,
    trajectory_format: Annotated[TrajectoryFormat, typer.Option("--trajectory-format", help="Format of "
                                                                "--trajectory.")] = TrajectoryFormat.pose_txt,
    flange_poses: Annotated[Path | None, typer.Option("--flange-poses", help="Base-from-flange poses per frame: "
                                                      "id,x,y,z,q1..q4 CSV or a folder of 4x4 .txt/.npy.",
                                                      exists=True, show_default=False)] = None,
    calibration: Annotated[Path | None, calibration_option("Hand-eye calibration (darp calib handeye) for "
                                                           "--flange-poses.")] = None,
    unit: Annotated[Unit, typer.Option("--unit", help="Translation unit of --flange-poses.")] = Unit.m,
    quaternion: Annotated[QuaternionOrder, typer.Option("--quaternion", help="Quaternion order of a flange "
                                                        "pose CSV.")] = QuaternionOrder.xyzw,
    arm: Annotated[str, typer.Option("--arm", help="Name of the arm (the calibration's arm with -c).")] = "",
    every: Annotated[int, typer.Option("--every", min=1, help="Keep every N-th frame.")] = 1,
    envelope: Annotated[Path | None, typer.Option("--envelope", help="manip_envelope.json (object cylinder in the "
                                                  "poses' world frame) to crop fusion and evaluation to.",
                                                  exists=True, dir_okay=False, show_default=False)] = None,
) -> None:
    """Import an RGB-D sequence with poses as a survey that darp process fuses, meshes and evaluates."""
    from darp.calibration.anyarm import PoseConventions, load_intrinsics
    from darp.formats.calibration import read_calibration
    from darp.formats.trajectories import read_nerfstudio, read_trajectory
    from darp.processing.imported import ImportSpec, import_sequence

    if (trajectory is None) == (flange_poses is None):
        raise typer.BadParameter("give exactly one of --trajectory and --flange-poses", param_hint="'--trajectory'")
    K = None
    dist = np.zeros(5)
    model = "Brown Conrady"
    if intrinsics is not None:
        cam = load_intrinsics(intrinsics)
        K, dist, model = cam.K, cam.dist, cam.model
    if trajectory is not None:
        if trajectory_format is TrajectoryFormat.nerfstudio:
            poses, intr = read_nerfstudio(trajectory)
            if K is None and {"fl_x", "cx", "cy"} <= set(intr):
                K = np.array([[intr["fl_x"], 0, intr["cx"]], [0, intr.get("fl_y", intr["fl_x"]), intr["cy"]],
                              [0, 0, 1]])
        else:
            poses = read_trajectory(trajectory, trajectory_format.value)
        source = str(trajectory)
        name = arm or "arm"
    else:
        assert flange_poses is not None
        if calibration is None:
            raise typer.BadParameter("--flange-poses needs the hand-eye: -c/--calibration", param_hint="'-c'")
        cal = read_calibration(calibration)
        name = arm or next(iter(cal.arms))
        if name not in cal.arms:
            raise typer.BadParameter(f"arm {name!r} is not in {calibration} (has {', '.join(cal.arms)})",
                                     param_hint="'--arm'")
        conv = PoseConventions(unit.value, quaternion.value)
        if flange_poses.is_dir():
            from darp.calibration.anyarm import check_rigid, read_matrix_file
            from darp.formats.trajectories import frame_key

            raw = {}
            for f in sorted(flange_poses.iterdir()):
                if f.suffix in (".txt", ".npy"):
                    T = read_matrix_file(f)
                    T[:3, 3] *= conv.scale
                    raw[frame_key(f.name)] = check_rigid(T, f)
        else:
            from darp.calibration.anyarm import read_pose_csv

            raw = read_pose_csv(flange_poses, conv)
        from darp.calibration.diagnose import check_translation_unit

        check_translation_unit(np.array(list(raw.values())), unit.value, flange_poses)
        a = cal.arms[name]
        poses = {k: a.T_world_base @ F @ a.T_wrist_cam for k, F in raw.items()}
        source = str(flange_poses)
    if K is None:
        raise typer.BadParameter("no intrinsics: give --intrinsics", param_hint="'--intrinsics'")
    record = import_sequence(ImportSpec(sequence, out, K, dist, depth_scale_m, poses, source, name, every,
                                         distortion_model=model, envelope=envelope))
    typer.echo(f"wrote {out} ({record['frames']} frames, {record['heldout']} held out; median depth "
               f"{record['median_depth_m']:.2f} m; neighbouring frames agree to "
               f"{record['pose_check']['neighbour_median_mm']:.1f} mm median)")
