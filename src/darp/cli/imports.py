"""``darp import``: an RGB-D sequence from any camera and arm -> an imported survey that ``darp process`` takes.

    darp import NERFSTUDIO|TUM|OPEN3D_FOLDER -o OUT     (poses, pairing and, where given, intrinsics from the folder)
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
from darp.formats.limits import DEPTH_SCALE_MAX_M
from darp.formats.trajectories import TUM_MAX_DT_S


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
    out: Annotated[Path, out_option("Imported survey folder to write (keyframes/, import.json).", folder=True)],
    intrinsics: Annotated[Path | None, typer.Option("--intrinsics", help="Depth/colour intrinsics (registered "
                                                    "streams): 3x3 .txt/.npy, .npz or .json; a nerfstudio "
                                                    "transforms.json gives its own; a RealSense .bag/.db3 its "
                                                    "colour stream's.", exists=True,
                                                    dir_okay=False, show_default=False)] = None,
    depth_scale_m: Annotated[float | None, typer.Option("--depth-scale-m", min=0.0, max=DEPTH_SCALE_MAX_M,
                                                        help="Metres per depth unit (0.001: mm); "
                                                        "default: the folder format's (TUM 1/5000, nerfstudio's "
                                                        "depth_unit_scale_factor), else 0.001.",
                                                        show_default=False)] = None,
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
    max_time_difference_s: Annotated[float, typer.Option("--max-time-difference-s", min=0.0, help="TUM folders: "
                                                         "the most a depth frame's stamp may differ from its colour "
                                                         "image's and its pose's.")] = TUM_MAX_DT_S,
) -> None:
    """Import an RGB-D sequence with poses as a survey that darp process fuses, meshes and evaluates."""
    if depth_scale_m == 0.0:  # 0 is not "the default": a depth image at 0 m per unit has no depth
        raise typer.BadParameter("must be > 0 metres per depth unit, got 0", param_hint="'--depth-scale-m'")
    from darp.formats.calibration import read_calibration
    from darp.formats.intrinsics import load_intrinsics
    from darp.formats.poses import PoseConventions, read_pose_csv, read_pose_folder
    from darp.formats.trajectories import (
        detect_posed_folder,
        read_nerfstudio_folder,
        read_open3d_folder,
        read_trajectory,
        read_tum_folder,
    )
    from darp.processing.imported import ImportSpec, import_sequence

    posed = None
    if trajectory is None and flange_poses is None:
        detected = detect_posed_folder(sequence)
        if detected is None:
            subs = [d.name for d in sorted(sequence.iterdir()) if d.is_dir() and detect_posed_folder(d)] if (
                sequence.is_dir()) else []
            hint = f"; its sub-folders {', '.join(subs)} are: import each" if subs else ""
            raise typer.BadParameter("give exactly one of --trajectory and --flange-poses (SEQUENCE is not a "
                                     f"nerfstudio, TUM RGB-D or Open3D folder whose poses darp finds itself{hint})",
                                     param_hint="'--trajectory'")
        kind = detected
    elif trajectory is not None and flange_poses is not None:
        raise typer.BadParameter("give exactly one of --trajectory and --flange-poses", param_hint="'--trajectory'")
    else:
        kind = trajectory_format.value
    K = None
    dist = np.zeros(5)
    model = "Brown Conrady"
    if intrinsics is not None:
        cam = load_intrinsics(intrinsics)
        K, dist, model = cam.K, cam.dist, cam.model
    if flange_poses is None:
        if kind == "nerfstudio":
            posed = read_nerfstudio_folder(trajectory or sequence)
        elif kind == "tum" and (sequence / "depth.txt").is_file():
            posed = read_tum_folder(sequence, trajectory, max_time_difference_s)
        elif kind == "log" and (sequence / "depth").is_dir():
            posed = read_open3d_folder(sequence, trajectory)
        if posed is not None:
            poses, source = posed.poses, posed.source
        else:  # a trajectory file or folder with a generic image folder (find_frames)
            traj = trajectory if trajectory is not None else sequence / "trajectory.log"
            poses, source = read_trajectory(traj, kind), str(traj)
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
            from darp.formats.trajectories import frame_key

            raw = read_pose_folder(flange_poses, conv, key=lambda f: frame_key(f.name))
        else:
            raw = read_pose_csv(flange_poses, conv)
        from darp.calibration.diagnose import check_translation_unit

        check_translation_unit(np.array(list(raw.values())), unit.value, flange_poses)
        a = cal.arms[name]
        poses = {k: a.T_world_base @ F @ a.T_wrist_cam for k, F in raw.items()}
        source = str(flange_poses)
    by_key: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if K is None and posed is not None and posed.intrinsics:
        by_key = posed.intrinsics
        K, dist = by_key[min(by_key, key=lambda k: int(k) if k.isdigit() else 0)]
    if K is None:
        raise typer.BadParameter("no intrinsics: give --intrinsics", param_hint="'--intrinsics'")
    scale = depth_scale_m or (posed.depth_scale_m if posed is not None else None) or 0.001
    spec = ImportSpec(sequence, out, K, dist, scale, poses, source, name, every, distortion_model=model,
                      envelope=envelope, intrinsics_by_key=by_key)
    if posed is not None:
        spec.colour_files, spec.depth_files, spec.stamps = posed.colour, posed.depth, posed.stamps
    from darp.formats.io_output import unfinished_folder

    with unfinished_folder(out, "darp import"):
        record = import_sequence(spec)
    typer.echo(f"wrote {out} ({record['frames']} frames, {record['heldout']} held out; median depth "
               f"{record['median_depth_m']:.2f} m; neighbouring frames agree to "
               f"{record['pose_check']['neighbour_median_mm']:.1f} mm median)")
