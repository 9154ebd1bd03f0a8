"""``darp import``: an RGB-D sequence from any camera and arm -> an imported survey that ``darp process`` takes.

    darp import NERFSTUDIO|TUM|OPEN3D_FOLDER -o OUT     (poses, pairing and, where given, intrinsics from the folder)
    darp import SEQ -o OUT --intrinsics K.txt|K.json|camera_info.yaml [--depth-scale-m 0.001]
                (--trajectory FILE|DIR --trajectory-format tum|log|pose-txt|nerfstudio|table
                 | --flange-poses TABLE|DIR (-c calibration.json | --hand-eye FILE) [--unit mm] [--quaternion wxyz])
                [--id-column NAME] [--order FILE] [--pair-shift N] [--force]
                [--heldout EVERY,OFFSET | --heldout-list FILE] [--arm NAME] [--every N] [--envelope FILE]
    darp process OUT -o RESULTS [--settings S.yaml]

Frames pair with poses by :mod:`darp.formats.pairing`'s rule; the pairing is printed and checked against the
likely mistakes (poses shifted by one, inverted poses or hand-eye, the other quaternion order): one that fits
much better is an error (``--force`` keeps the data as given, with a warning). See docs/any-arm.md.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from darp.cli._app import app
from darp.cli._options import calibration_option, input_argument, out_option
from darp.cli.calib import Force, IdColumn, OrderFile, PairShift
from darp.formats.limits import DEPTH_SCALE_MAX_M
from darp.formats.trajectories import TUM_MAX_DT_S

CHECK_PAIRS = 6  # neighbouring frame pairs the pairing check back-projects per reading
NAME_PAIRS = 24  # neighbouring frame pairs scanned to name frames that disagree


class TrajectoryFormat(StrEnum):
    """World-from-camera trajectory formats (darp.formats.trajectories.FORMATS, and pose tables)."""

    tum = "tum"
    log = "log"
    pose_txt = "pose-txt"
    nerfstudio = "nerfstudio"
    table = "table"


class Unit(StrEnum):
    """Translation unit of flange poses."""

    m = "m"
    mm = "mm"


class QuaternionOrder(StrEnum):
    """Quaternion component order of a pose CSV."""

    xyzw = "xyzw"
    wxyz = "wxyz"


@dataclass(frozen=True)
class HeldoutEvery:
    """``--heldout EVERY,OFFSET``: frame i (in import order) is held out when ``i % EVERY == OFFSET``."""

    every: int
    offset: int


def parse_heldout(value: str | HeldoutEvery) -> HeldoutEvery:
    """``EVERY,OFFSET`` (``EVERY`` >= 2, 0 <= ``OFFSET`` < ``EVERY``)."""
    if isinstance(value, HeldoutEvery):
        return value
    try:
        every, offset = (int(v) for v in str(value).split(","))
    except ValueError:
        raise typer.BadParameter(f"expected EVERY,OFFSET (e.g. 5,2), got {value!r}") from None
    if every < 2 or not 0 <= offset < every:
        raise typer.BadParameter(f"needs EVERY >= 2 and 0 <= OFFSET < EVERY, got {value!r}")
    return HeldoutEvery(every, offset)


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
    flange_poses: Annotated[Path | None, typer.Option("--flange-poses", help="Base-from-flange poses per frame: a "
                                                      "table (.csv/.txt/.npz/.json) or a folder of 4x4 files.",
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
    hand_eye: Annotated[Path | None, typer.Option("--hand-eye", help="Known hand-eye (flange-from-camera) for "
                                                  "--flange-poses instead of -c: easy_handeye/MoveIt YAML or "
                                                  "launch, a Transform, a bare 4x4 .txt/.npy/.json.", exists=True,
                                                  dir_okay=False, show_default=False)] = None,
    hand_eye_unit: Annotated[Unit | None, typer.Option("--hand-eye-unit", help="Translation unit of a bare 4x4 "
                                                       "--hand-eye (default: --unit).", show_default=False)] = None,
    rotation: Annotated[str, typer.Option("--rotation", help="What 3 rotation values after x y z mean in a pose "
                                          "table: rotvec (UR style) or euler-<axes>-<deg|rad> (e.g. "
                                          "euler-xyz-deg; SciPy's axes: lower case extrinsic).")] = "",
    id_column: IdColumn = None,
    order: OrderFile = None,
    pair_shift: PairShift = 0,
    force: Force = False,
    heldout: Annotated[HeldoutEvery | None, typer.Option("--heldout", parser=parse_heldout, metavar="EVERY,OFFSET",
                                                         help="Held-out split: frame i (import order) is held out "
                                                         "when i % EVERY == OFFSET (default 5,2).",
                                                         show_default=False)] = None,
    heldout_list: Annotated[Path | None, typer.Option("--heldout-list", help="Held-out frames: one image name or "
                                                      "frame id per line (instead of --heldout).", exists=True,
                                                      dir_okay=False, show_default=False)] = None,
) -> None:
    """Import an RGB-D sequence with poses as a survey that darp process fuses, meshes and evaluates."""
    if depth_scale_m == 0.0:  # 0 is not "the default": a depth image at 0 m per unit has no depth
        raise typer.BadParameter("must be > 0 metres per depth unit, got 0", param_hint="'--depth-scale-m'")
    from darp.formats.intrinsics import load_intrinsics
    from darp.formats.trajectories import (
        detect_posed_folder,
        read_nerfstudio_folder,
        read_open3d_folder,
        read_tum_folder,
    )
    from darp.processing.imported import ImportSpec, import_sequence

    if heldout is not None and heldout_list is not None:
        raise typer.BadParameter("give --heldout or --heldout-list, not both", param_hint="'--heldout'")
    if flange_poses is not None and (calibration is None) == (hand_eye is None):
        raise typer.BadParameter("--flange-poses needs the hand-eye: exactly one of -c/--calibration and --hand-eye",
                                 param_hint="'--hand-eye'")
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
        carried = sequence / "manip_envelope.json"
        if envelope is None and carried.is_file():  # a darp export carries its survey's object envelope
            envelope = carried
            typer.echo(f"using the object envelope beside the sequence: {carried} (--envelope to give another)")
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
    if flange_poses is None and kind == "nerfstudio":
        posed = read_nerfstudio_folder(trajectory or sequence)
    elif flange_poses is None and kind == "tum" and (sequence / "depth.txt").is_file():
        posed = read_tum_folder(sequence, trajectory, max_time_difference_s)
    elif flange_poses is None and kind == "log" and (sequence / "depth").is_dir():
        posed = read_open3d_folder(sequence, trajectory)
    by_key: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if K is None and posed is not None and posed.intrinsics:
        by_key = posed.intrinsics
        K, dist = by_key[min(by_key, key=lambda k: int(k) if k.isdigit() else 0)]
    if K is None:
        raise typer.BadParameter("no intrinsics: give --intrinsics", param_hint="'--intrinsics'")
    scale = depth_scale_m or (posed.depth_scale_m if posed is not None else None) or 0.001
    lines: list[str] = []
    if posed is not None:
        poses, source, name = posed.poses, posed.source, arm or "arm"
        colour_files, depth_files, stamps = posed.colour, posed.depth, posed.stamps
    else:
        from darp.formats.poses import PoseConventions

        conv = PoseConventions(unit.value, quaternion.value, rotation)
        readings, source, name = _readings(trajectory, kind, flange_poses, calibration, hand_eye,
                                           hand_eye_unit or unit, conv, arm, id_column)
        colour_files, depth_files, poses, lines = _pair_and_check(sequence, readings, source, K, scale, order,
                                                                  pair_shift, force)
        stamps = {}
    held_keys = None
    if heldout_list is not None:
        from darp.formats.pairing import frame_id, read_order_file

        ids = {frame_id(n) for n in read_order_file(heldout_list)}
        rename = {frame_id(p.name): k for k, p in depth_files.items()}
        held_keys = frozenset(rename.get(i, i) for i in ids)
    spec = ImportSpec(sequence, out, K, dist, scale, _exact(poses), source, name, every, distortion_model=model,
                      envelope=envelope, intrinsics_by_key=by_key, heldout_keys=held_keys)
    if heldout is not None:
        spec.heldout_every, spec.heldout_offset = heldout.every, heldout.offset
    spec.colour_files, spec.depth_files, spec.stamps = colour_files, depth_files, stamps
    for line in lines:
        typer.echo(line)
    from darp.formats.io_output import unfinished_folder

    with unfinished_folder(out, "darp import"):
        record = import_sequence(spec)
    typer.echo(f"wrote {out} ({record['frames']} frames, {record['heldout']} held out; median depth "
               f"{record['median_depth_m']:.2f} m; neighbouring frames agree to "
               f"{record['pose_check']['neighbour_median_mm']:.1f} mm median)")


@dataclass
class Readings:
    """The poses as given (world-from-camera by pose id, names in table order) and the likely misreadings."""

    poses: dict[str, np.ndarray]
    names: dict[str, str]
    has_ids: bool
    alternatives: dict[str, dict[str, np.ndarray]]


def _readings(trajectory: Path | None, kind: str, flange_poses: Path | None, calibration: Path | None,
              hand_eye: Path | None, hand_eye_unit: Unit, conv: Any, arm: str, id_column: str | None
              ) -> tuple[Readings, str, str]:
    """World-from-camera poses from a trajectory or flange poses + hand-eye, with their likely misreadings."""
    from darp.formats.pose_tables import read_pose_table, swapped_quaternion_table
    from darp.formats.poses import PoseConventions
    from darp.formats.trajectories import read_trajectory
    from darp.kinematics.transforms import invert_transform

    unit = conv.unit
    if flange_poses is None:
        assert trajectory is not None
        if kind in ("pose-txt", "table"):
            table = read_pose_table(trajectory, PoseConventions("m", conv.quaternion, conv.rotation), id_column)
            given, names, has_ids = table.poses, table.names, table.has_ids
            swapped = swapped_quaternion_table(table, id_column)
        else:
            given = read_trajectory(trajectory, kind)
            names, has_ids, swapped = {k: k for k in given}, True, None
        alts = {"inverted poses": {k: invert_transform(T) for k, T in given.items()}}
        if swapped is not None:
            alts["quaternion order"] = swapped.poses
        return Readings(given, names, has_ids, alts), str(trajectory), arm or "arm"
    from darp.calibration.diagnose import check_translation_unit
    from darp.formats.hand_eye import T_BODY_OPTICAL, read_hand_eye

    table = read_pose_table(flange_poses, conv, id_column)
    check_translation_unit(np.array(list(table.poses.values())), unit, flange_poses)
    if hand_eye is not None:
        he = read_hand_eye(hand_eye, hand_eye_unit.value, arm)
        T_wb, X, name = np.eye(4), he.T_wrist_cam, arm or "arm"
        for note in he.notes:
            warnings.warn(note, _warning_class(), stacklevel=2)
    else:
        from darp.formats.calibration import read_calibration

        cal = read_calibration(calibration)  # type: ignore[arg-type]
        name = arm or next(iter(cal.arms))
        if name not in cal.arms:
            raise typer.BadParameter(f"arm {name!r} is not in {calibration} (has {', '.join(cal.arms)})",
                                     param_hint="'--arm'")
        T_wb, X = cal.arms[name].T_world_base, cal.arms[name].T_wrist_cam
        he = None

    def world(poses: dict[str, np.ndarray], Xc: np.ndarray, invert: bool = False) -> dict[str, np.ndarray]:
        return {k: T_wb @ (invert_transform(F) if invert else F) @ Xc for k, F in poses.items()}

    alts = {"inverted hand-eye": world(table.poses, invert_transform(X)),
            "inverted poses": world(table.poses, X, invert=True)}
    swapped = swapped_quaternion_table(table, id_column)
    if swapped is not None:
        alts["quaternion order"] = world(swapped.poses, X)
    if he is not None and not he.optical:
        alts["ROS body camera frame"] = world(table.poses, X @ T_BODY_OPTICAL)
    return Readings(world(table.poses, X), table.names, table.has_ids, alts), str(flange_poses), name


def _warning_class() -> type[Warning]:
    from darp.processing.imported import ImportWarning

    return ImportWarning


def _exact(poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Poses with rotations made exactly orthonormal (products of poses that each passed the rigidity rule may
    add up past it; processing checks the same rule), translations untouched."""
    from darp.geometry.transforms import orthonormalize

    out = {}
    for k, T in poses.items():
        M = np.array(T, np.float64)
        M[:3, :3] = orthonormalize(M[:3, :3])
        M[3] = [0.0, 0.0, 0.0, 1.0]
        out[k] = M
    return out


def _pair_and_check(sequence: Path, readings: Readings, source: str, K: np.ndarray, scale: float,
                    order: Path | None, shift: int, force: bool
                    ) -> tuple[dict[str, Path], dict[str, Path], dict[str, np.ndarray], list[str]]:
    """Pair the folder's frames with the poses, apply ``shift``, check the pairing; (colour, depth, poses by frame
    key, lines to print). Frame keys are numbers (the ids' own, or their natural order)."""
    from darp.formats.pairing import describe_pairs, natural_key, pair_names, read_order_file, rgbd_frames, shift_poses

    colour, depth = rgbd_frames(sequence)
    names = [str(p.relative_to(sequence)) for p in depth.values()]
    pose_names = [readings.names[k] for k in readings.poses]
    pairing, omap, pmap = pair_names(names, pose_names, source, order=read_order_file(order) if order else None,
                                     poses_have_ids=readings.has_ids)
    by_name = {readings.names[k]: k for k in readings.poses}
    fid = {str(p.relative_to(sequence)): k for k, p in depth.items()}
    ids = {fid[n]: omap[n] for n in names if n in omap}  # depth id -> pairing id
    pose_of = {pmap[n]: by_name[n] for n in pose_names if n in pmap}  # pairing id -> pose id
    keys = sorted(ids.values(), key=natural_key)  # every frame, paired or not (a shift moves poses along them)
    numeric = all(k.isdigit() for k in keys)
    new = {k: (k if numeric else str(i)) for i, k in enumerate(keys)}
    frames = [new[k] for k in keys]
    if pairing.no_pose and not shift:
        warnings.warn(f"{source}: no pose for {len(pairing.no_pose)} of {len(names)} depth images (e.g. "
                      f"{pairing.no_pose[0]}); those frames are skipped (missing frames?)", _warning_class(),
                      stacklevel=2)
    if pairing.no_observation:
        warnings.warn(f"{source}: {len(pairing.no_observation)} pose(s) without a depth image (e.g. "
                      f"{pairing.no_observation[0]}): missing frames?", _warning_class(), stacklevel=2)

    def posed(reading: dict[str, np.ndarray], s: int = 0) -> dict[str, np.ndarray]:
        p = {new[k]: reading[pose_of[k]] for k in keys if pose_of.get(k) in reading}
        return shift_poses(p, frames, s) if s else p

    given = posed(readings.poses, shift)
    depth_out = {new[ids[d]]: p for d, p in depth.items() if d in ids and new[ids[d]] in given}
    colour_out = {new[ids[d]]: colour[d] for d in ids if d in colour and new[ids[d]] in given}
    lines = [describe_pairs(pairing)]
    if shift:
        lines.append(f"poses shifted by {shift} (--pair-shift): frame i takes the pose of frame i{shift:+d}")
    lines += _check(sequence, depth_out, given, readings, posed, shift, K, scale, source, force)
    return colour_out, depth_out, given, lines


def _check(sequence: Path, depth: dict[str, Path], given: dict[str, np.ndarray], readings: Readings, posed: Any,
           shift: int, K: np.ndarray, scale: float, source: str, force: bool) -> list[str]:
    """The pairing check (docs/any-arm.md): neighbouring frames' back-projections as given and under each likely
    mistake; raise (or with ``force`` warn) when a mistake fits much better; name frames that disagree."""
    import cv2

    from darp.formats.io_input import decode_image
    from darp.formats.pairing import judge_alternatives, natural_key, neighbour_agreement

    order = sorted(given, key=natural_key)
    if len(order) < 3:
        return []
    cache: dict[str, np.ndarray] = {}

    def img(k: str) -> np.ndarray:
        if k not in cache:
            d = decode_image(depth[k], cv2.IMREAD_UNCHANGED, "a depth image")
            cache[k] = d if d is not None and d.ndim == 2 else np.zeros((2, 2), np.uint16)
        return cache[k]

    def score(poses: dict[str, np.ndarray], starts: list[int]) -> list[float]:
        ks = [k for i in starts for k in (order[i], order[i + 1])]
        return neighbour_agreement([img(k) for k in ks], K, scale, [poses.get(k) for k in ks])

    def spread(n: int) -> list[int]:
        return sorted({int(round(v)) for v in np.linspace(0, len(order) - 2, min(n, len(order) - 1))})

    starts = spread(CHECK_PAIRS)
    readings_now = {"as given": given, "shift+1": posed(readings.poses, shift + 1),
                    "shift-1": posed(readings.poses, shift - 1)}
    readings_now.update({k: posed(v, shift) for k, v in readings.alternatives.items()})
    scores = {k: float(np.nanmedian(v)) if np.any(np.isfinite(v := score(p, starts))) else float("nan")
              for k, p in readings_now.items()}
    kept = judge_alternatives(scores, source, "neighbouring frames' back-projections", force=force)
    lines = ["pairing check: neighbouring frames agree to " + ", ".join(f"{v:.1f} mm {k}" for k, v in scores.items())
             + " (median)"]
    if kept:
        warnings.warn(kept, _warning_class(), stacklevel=2)
    wide = spread(NAME_PAIRS)
    per = score(given, wide)
    med = float(np.nanmedian(per)) if np.any(np.isfinite(per)) else float("nan")
    bad = [(order[i], order[i + 1], v) for i, v in zip(wide, per, strict=True) if v > max(5 * med, 20.0)]
    if bad:
        text = ", ".join(f"{depth[a].name} / {depth[b].name} ({v:.0f} mm)" for a, b, v in bad[:5])
        warnings.warn(f"{source}: {len(bad)} neighbouring frame pair(s) disagree far more than the median "
                      f"{med:.1f} mm: {text}; check those frames' poses and pairing", _warning_class(), stacklevel=2)
    return lines
