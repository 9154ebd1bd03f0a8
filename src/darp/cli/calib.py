"""``darp calib``: ChArUco calibration of the rig (board, plan, capture, solve, check).

    darp calib board -o board.pdf [--squares-x 10 --squares-y 7 --square-mm 30 --marker-mm 22
                     --dictionary DICT_5X5_100 --paper auto]
    darp calib plan -o plan.json [--rig RIG.yaml] [--captures 30] [--seed 0] [--board-yaw-deg 0] [--candidates 300]
    darp calib capture (--twin [--seed N] [--profile realistic|paper | --settings FILE] [--captures 30]
                        | --hardware) [--rig RIG.yaml]
                       -o DIR [--plan plan.json] [--stream color|ir1] [--overwrite]
    darp calib solve CAPTURES -o calibration.json [--report DIR] [--folds 5] [--truth FILE] [--epoch NAME]
    darp calib check CAPTURES -c calibration.json [--board-unmoved] [-o result.json] [--json]
    darp calib handeye CAPTURES -o calibration.json [--intrinsics FILE] [--eye-to-hand] [--report DIR] [--folds 5]
    darp calib export CAPTURES -o GENERIC_DIR     (a twin/Z1 capture folder as a generic any-arm folder)

``check`` exits 0 when the calibration still holds and 1 when it is stale. See docs/calibration.md;
``handeye`` and ``export`` (any arm, any camera) are in docs/any-arm.md.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from darp.cli._app import app
from darp.cli._options import (
    CalibModel,
    CaptureStream,
    Dictionary,
    Paper,
    Profile,
    ProfileOption,
    Quiet,
    RigFile,
    SettingsFile,
    calibration_option,
    input_argument,
    out_option,
    progress_bar,
    refuse_output_over_inputs,
    twin_settings,
)

calib_app = typer.Typer(help="Calibrate the rig with a ChArUco board: hand-eye, bases, joint-zero offsets.",
                        no_args_is_help=True)
app.add_typer(calib_app, name="calib")

SquaresX = Annotated[int, typer.Option("--squares-x", help="Squares along the board's x.")]
SquaresY = Annotated[int, typer.Option("--squares-y", help="Squares along the board's y.")]
SquareMm = Annotated[float, typer.Option("--square-mm", help="Square side, millimetres.")]
MarkerMm = Annotated[float, typer.Option("--marker-mm", help="ArUco marker side, millimetres.")]
DictionaryOption = Annotated[Dictionary, typer.Option("--dictionary", help="OpenCV ArUco dictionary.")]
Captures = Annotated[int, typer.Option("--captures", min=1, max=10000, help="Captures per arm (when planning).")]
def _folds(value: int) -> int:
    if value != 0 and value < 2:  # one fold holds everything out; a negative count is no count
        raise typer.BadParameter(f"expected 0 (no held-out evaluation) or at least 2 folds, got {value}")
    return value


Folds = Annotated[int, typer.Option("--folds", callback=_folds, help="k of the k-fold held-out evaluation "
                                    "(0: none, else at least 2).")]
Seed = Annotated[int, typer.Option("--seed", min=0, help="Seed of the random candidates (and, on the twin, of its "
                                   "true rig errors).")]


def _board(squares_x: int, squares_y: int, square_mm: float, marker_mm: float, dictionary: Dictionary) -> Any:
    from darp.calibration.board import make_board_spec

    return make_board_spec(squares_x, squares_y, square_mm / 1e3, marker_mm / 1e3, dictionary.value)


def _progress(quiet: bool) -> Any:
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    return progress_bar(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TimeElapsedColumn(), quiet=quiet, transient=True)


@calib_app.command("board")
def board_command(
    out: Annotated[Path, out_option("PDF to write.")],
    squares_x: SquaresX = 10, squares_y: SquaresY = 7, square_mm: SquareMm = 30.0, marker_mm: MarkerMm = 22.0,
    dictionary: DictionaryOption = Dictionary.DICT_5X5_100,
    paper: Annotated[Paper, typer.Option("--paper", help="Paper size (auto: the smallest that fits).")] = Paper.auto,
) -> None:
    """Write a printable board at true scale (print at 100 %, check the 100 mm ruler)."""
    from darp.calibration.board import spec_text, write_board_pdf

    board = _board(squares_x, squares_y, square_mm, marker_mm, dictionary)
    layout = write_board_pdf(board, out, paper=paper.value)
    typer.echo(f"wrote {out} ({layout['paper']}, {layout['page_mm'][0]:.0f} x {layout['page_mm'][1]:.0f} mm): "
               f"{spec_text(board)}")


@calib_app.command("plan")
def plan_command(
    out: Annotated[Path, out_option("Plan JSON to write.")],
    rig_file: RigFile = None,
    captures: Captures = 30,
    seed: Seed = 0,
    board_yaw_deg: Annotated[float, typer.Option("--board-yaw-deg", help="Board yaw on the table (centred on the "
                                                 "workspace), degrees.")] = 0.0,
    candidates: Annotated[int, typer.Option("--candidates", help="Random candidate poses tried per arm.")] = 300,
    squares_x: SquaresX = 10, squares_y: SquaresY = 7, square_mm: SquareMm = 30.0, marker_mm: MarkerMm = 22.0,
    dictionary: DictionaryOption = Dictionary.DICT_5X5_100,
    extend: Annotated[Path | None, typer.Option("--extend", help="Capture folder already taken: plan --captures "
                                                "extra poses per arm where --model is poorly determined (greedy "
                                                "D-optimal; the board is where those captures saw it).",
                                                exists=True, file_okay=False, show_default=False)] = None,
    model: Annotated[CalibModel, typer.Option("--model", help="Arm model the extra poses should determine "
                                              "(with --extend).")] = CalibModel.kinematic_compliance,
) -> None:
    """Plan diverse, feasible, collision-free capture poses for both arms (nominal rig)."""
    import numpy as np

    from darp.calibration.plan import PlanSettings, default_board_pose, plan_captures
    from darp.kinematics.rig import load_rig

    rig = load_rig(rig_file)
    if extend is not None:
        from darp.calibration.captures import read_captures
        from darp.calibration.plan_model import extend_plan

        refuse_output_over_inputs(out, [extend], "--out")
        extra, info = extend_plan(read_captures(extend), rig, captures, model=model.value,
                                  n_candidates=max(candidates, 2 * captures), seed=seed)
        extra.save(out)
        typer.echo(f"wrote {out}: {info['chosen']} extra poses for {info['model']} (from {info['candidates']} "
                   f"feasible candidates, {info['captures']} captures taken)")
        return
    board = _board(squares_x, squares_y, square_mm, marker_mm, dictionary)
    plan = plan_captures(rig, board, default_board_pose(rig, board, np.radians(board_yaw_deg)),
                         settings=PlanSettings(n_per_arm=captures, n_candidates=max(candidates, captures)), seed=seed)
    plan.save(out)
    counts = ", ".join(f"{a}: {len(p)} ({sum(x.via_park for x in p)} via park)" for a, p in plan.poses.items())
    typer.echo(f"wrote {out}: {counts}")


@calib_app.command("capture")
def capture_command(
    out: Annotated[Path, out_option("Capture folder to create.", folder=True)],
    twin: Annotated[bool, typer.Option("--twin", help="Capture on the digital twin.")] = False,
    hardware: Annotated[bool, typer.Option("--hardware", help="Capture on the real rig (--rig, with its "
                                           "hardware: section).")] = False,
    rig_file: RigFile = None,
    twin_cameras: Annotated[bool, typer.Option("--twin-cameras", help="With --hardware: the twin's cameras and "
                                               "board following the arms' reported joints instead of RealSense "
                                               "(--seed/--profile/--settings choose the twin; its truth is "
                                               "written).")] = False,
    plan_file: Annotated[Path | None, typer.Option("--plan", help="Plan from `darp calib plan` (default: plan now).",
                                                   exists=True, dir_okay=False, show_default=False)] = None,
    seed: Seed = 0,
    profile: ProfileOption = Profile.realistic,
    settings_file: SettingsFile = None,
    captures: Captures = 30,
    stream: Annotated[CaptureStream, typer.Option("--stream", help="Image stream the board is detected in.")] = (
        CaptureStream.color),
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace captures already in --out.")] = False,
    quiet: Quiet = False,
) -> None:
    """Take calibration captures (one arm moving at a time) on the twin or the real rig."""
    if twin == hardware:
        raise typer.BadParameter("choose exactly one", param_hint="'--twin' / '--hardware'")
    from darp.calibration.captures import check_capture_output
    from darp.calibration.plan import CapturePlan

    check_capture_output(out, overwrite)  # before any work: a survey or a user's folder is refused at once
    plan = CapturePlan.load(plan_file) if plan_file is not None else None
    total = sum(len(p) for p in plan.poses.values()) if plan is not None else 2 * captures
    from darp.formats.io_output import unfinished_folder

    with unfinished_folder(out, "darp calib capture"), _progress(quiet) as bar:
        task = bar.add_task("capturing", total=total)

        def tick(arm: str, k: int) -> None:
            bar.update(task, advance=1, description=f"capturing {arm}")

        if twin:
            from darp.kinematics.rig import load_rig
            from darp.twin.calib_capture import capture_twin

            settings = twin_settings(profile, seed, settings_file)
            caps = capture_twin(out, seed=settings.seed, profile=settings.profile, settings=settings,
                                n_per_arm=captures, plan=plan,
                                stream=stream.value, rig=load_rig(rig_file) if rig_file is not None else None,
                                overwrite=overwrite, on_capture=tick)
        else:
            mirror = twin_settings(profile, seed, settings_file) if twin_cameras else None
            caps = _capture_hardware(rig_file, out, plan, captures, seed, stream.value, overwrite, tick, mirror)
    counts = ", ".join(f"{a}: {len(caps.for_arm(a))}" for a in caps.arms)
    typer.echo(f"wrote {out} ({counts})")


def _capture_hardware(rig_file: Path | None, out: Path, plan: Any, n: int, seed: int, stream: str,
                      overwrite: bool, tick: Any, twin: Any = None) -> Any:
    """Captures on the real rig through the hardware backend; ``twin``: the settings of twin cameras (and a
    twin board) that follow the arms, whose truth is written to ``out/truth`` (docs/hardware.md)."""
    from darp.calibration.board import DEFAULT_BOARD
    from darp.calibration.capture_run import CaptureRunSettings, run_capture_plan
    from darp.calibration.captures import CaptureWriter
    from darp.calibration.plan import PlanSettings, default_board_pose, plan_captures
    from darp.cli._hardware_rig import open_hardware, twin_board_pose, write_capture_truth
    from darp.kinematics.rig import load_rig

    rig = load_rig(rig_file)
    if plan is None:
        board_pose = default_board_pose(rig, DEFAULT_BOARD) if twin is None else twin_board_pose(rig, DEFAULT_BOARD)
        plan = plan_captures(rig, DEFAULT_BOARD, board_pose, settings=PlanSettings(n_per_arm=n), seed=seed)
    scene = {} if twin is None else {"board": plan.board, "T_world_board": plan.T_world_board}
    backend, mirror = open_hardware(rig_file, twin_settings=twin, **scene)
    with backend:  # connect first: a rig that fails to connect leaves no capture folder
        source = f"hardware:{rig.name}" + ("" if twin is None else f"+twin:{twin.profile}:seed{twin.seed}")
        writer = CaptureWriter(out, plan.board, source=source, overwrite=overwrite)
        run_capture_plan(backend, plan, writer, park_q={a: rig.arm(a).park_q_rad for a in rig.arm_ids},
                         settings=CaptureRunSettings(stream=stream), on_capture=tick)
        if mirror is not None:
            write_capture_truth(out, mirror, plan.T_world_board)
    return writer.close()


@calib_app.command("solve")
def solve_command(
    captures: Annotated[Path, input_argument("Capture folder.")],
    out: Annotated[Path, out_option("Calibration JSON to write.")],
    report: Annotated[Path | None, typer.Option(
        "--report", help="Report folder to write (figures, summary.md).", file_okay=False,
                                                show_default=False)] = None,
    folds: Folds = 5,
    truth: Annotated[Path | None, typer.Option("--truth", help="True calibration to compare with (default: the "
                                               "captures' truth/calibration.json when present).", exists=True,
                                               dir_okay=False, show_default=False)] = None,
    epoch: Annotated[str | None, typer.Option("--epoch", help="Epoch label (default calib-<date>).",
                                              show_default=False)] = None,
    compare: Annotated[bool, typer.Option("--compare/--no-compare", help="Also solve with OpenCV alone, for the "
                                          "comparison table.")] = True,
    model: Annotated[CalibModel, typer.Option("--model", help="Arm model: paper (joint zeros), kinematic (+ joint "
                                              "origins and axis tilts), kinematic+compliance (+ gravity sag of "
                                              "joints 2-4), kinematic+compliance+backlash (+ backlash, from the "
                                              "captures' move directions); the paper model is solved beside a "
                                              "richer one.")]
    = CalibModel.paper,
    quiet: Quiet = False,
) -> None:
    """Calibrate from captures: hand-eye per arm, bases in one world frame, joint-zero offsets."""
    from darp.calibration.captures import read_captures
    from darp.calibration.solve import SolveSettings, solve_captures
    from darp.formats.calibration import read_calibration, write_calibration

    refuse_output_over_inputs(out, [captures, *([truth] if truth else [])], "--out")
    if report is not None:
        refuse_output_over_inputs(report, [captures, *([truth] if truth else [])], "--report", folder_output=True)
    caps = read_captures(captures)
    truth_path = truth if truth is not None else caps.truth_calibration_path()
    truth_cal = read_calibration(truth_path) if truth_path is not None else None
    with _progress(quiet) as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        outcome = solve_captures(caps, SolveSettings(folds=folds, compare=compare, epoch=epoch, model=model.value),
                                 truth=truth_cal, progress=progress)
    write_calibration(out, outcome.calibration)
    if report is not None:
        from darp.calibration.report import write_report

        write_report(outcome, report)
    cal = outcome.calibration
    typer.echo(f"wrote {out} (epoch {cal.epoch}; {cal.report['n_used']}/{cal.report['n_captures']} captures used)")
    for arm, a in cal.arms.items():
        held = a.residuals.get("heldout", {}).get("corner_3d_mm")
        held_text = f", held-out 3-D corner error median {held['median']:.3f} mm" if held else ""
        typer.echo(f"  {arm}: fit {a.residuals['fit_reprojection_px']['median']:.3f} px{held_text}")
        if a.kinematics is not None:
            k = a.kinematics
            rich = (k.get("heldout") or {}).get("corner_3d_mm")
            rich_text = f", held-out median {rich['median']:.3f} mm" if rich else ""
            typer.echo(f"    model {k['model']}: {len(k['estimated'])} kinematic parameters estimated, fit "
                       f"{k['fit_reprojection_px']['median']:.3f} px{rich_text} (used by --corrections kinematics)")
    for name, label in (("darp", "against truth"), ("darp_model", f"against truth ({model.value} model)")):
        if outcome.truth is not None and name in outcome.truth:
            t = outcome.truth[name]
            he = max(v["hand_eye"]["translation_mm"] for v in t["arms"].values())
            b2b = t["base_to_base"]
            typer.echo(f"  {label}: hand-eye <= {he:.3f} mm, base-to-base {b2b['translation_mm']:.3f} mm"
                       f" / {b2b['rotation_deg']:.4f} deg")


@calib_app.command("check")
def check_command(
    captures: Annotated[Path, input_argument("Folder of a few new captures.")],
    calibration: Annotated[Path, calibration_option("Calibration JSON to check.")],
    board_unmoved: Annotated[bool, typer.Option("--board-unmoved", help="The board is where it was at "
                                                "calibration (stricter).")] = False,
    out: Annotated[Path | None, out_option("Write the result to this JSON file.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON instead of the summary.")] = False,
) -> None:
    """Tell whether a calibration still holds (exit 0) or is stale (exit 1) from a few new captures."""
    import json

    from darp.calibration.captures import read_captures
    from darp.calibration.check import CheckSettings, check_calibration
    from darp.formats.calibration import read_calibration
    from darp.formats.schema import to_jsonable, write_json_checked

    if out is not None:
        refuse_output_over_inputs(out, [calibration, captures], "--out")
    result = check_calibration(read_calibration(calibration), read_captures(captures),
                               CheckSettings(board_unmoved=board_unmoved), cal_path=calibration)
    if out is not None:
        write_json_checked(out, result.to_dict())
    if as_json:
        typer.echo(json.dumps(to_jsonable(result.to_dict()), indent=2))
    else:
        _print_check(result)
    if not result.ok:
        raise typer.Exit(code=1)


def _print_check(result: Any) -> None:
    for arm, r in result.arms.items():
        state = "ok" if r.ok else "STALE"
        typer.echo(f"{arm}: {state}: {r.n_captures} captures, median 3-D corner error "
                   f"{r.corner_3d_mm['median']:.3f} mm (limit {r.limit_mm:.3f}), reprojection "
                   f"{r.reprojection_px['median']:.3f} px (limit {r.limit_px:.3f})"
                   + ("" if r.ok else f": {'; '.join(r.reasons)}"))
    if result.board_disagreement is not None:
        d = result.board_disagreement
        typer.echo(f"board seen by the two arms differs by {d['translation_mm']:.2f} mm / "
                   f"{d['rotation_deg']:.3f} deg")
    typer.echo("calibration holds" if result.ok else "calibration is stale: recalibrate")


IdColumn = Annotated[str | None, typer.Option("--id-column", help="Header name of the pose table's id column "
                                             "(default: its first column when that is not a number).",
                                             show_default=False)]
OrderFile = Annotated[Path | None, typer.Option("--order", help="Order file: one image/frame name per line, in the "
                                                "order of the pose rows (pairs by position).", exists=True,
                                                dir_okay=False, show_default=False)]
PairShift = Annotated[int, typer.Option("--pair-shift", help="Pair image i with the pose N places later (a known "
                                        "off-by-N in the data).")]
Force = Annotated[bool, typer.Option("--force", help="Keep the pairing and poses as given when a likely mistake "
                                     "(shifted, inverted) fits much better: a warning instead of an error.")]


class Refinement(StrEnum):
    """darp.calibration.anyarm.REFINEMENTS."""

    poses = "poses"
    poses_no_sag = "poses-no-sag"
    pixels = "pixels"


@calib_app.command("handeye")
def handeye_command(
    captures: Annotated[Path, input_argument("Generic captures folder (handeye.yaml, images/ or board_poses/, "
                                             "poses.csv or poses/; see docs/any-arm.md).")],
    out: Annotated[Path, out_option("Calibration JSON to write.")],
    intrinsics: Annotated[Path | None, typer.Option("--intrinsics", help="Camera intrinsics (3x3 .txt/.npy, .npz "
                                                    "or .json); default the folder's intrinsics.*, else solved "
                                                    "from the images.", exists=True, dir_okay=False,
                                                    show_default=False)] = None,
    eye_to_hand: Annotated[bool, typer.Option("--eye-to-hand", help="The camera is fixed and the board rides on "
                                              "the flange (default: handeye.yaml's mode, else eye-in-hand).")
                           ] = False,
    report: Annotated[Path | None, typer.Option(
        "--report", help="Report folder to write (figures, summary.md).", file_okay=False,
                                                show_default=False)] = None,
    folds: Folds = 5,
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of the fold assignment.")] = 0,
    compare: Annotated[bool, typer.Option("--compare/--no-compare", help="Also score each OpenCV calibrateHandEye "
                                          "method on the same held-out folds.")] = True,
    folds_file: Annotated[Path | None, typer.Option("--folds-file", help="The held-out split: 'capture_id fold' "
                                                    "lines (or JSON {id: fold}); replaces --folds/--seed.",
                                                    exists=True, dir_okay=False, show_default=False)] = None,
    refinement: Annotated[Refinement, typer.Option("--refinement", help="poses: boards placed together, "
                                                   "PnP-weighted, flange sag; poses-no-sag: without the sag "
                                                   "term; pixels: corner reprojection (darp's Z1 solver "
                                                   "without joint offsets).")] = Refinement.poses,
    id_column: IdColumn = None,
    order: OrderFile = None,
    pair_shift: PairShift = 0,
    force: Force = False,
) -> None:
    """Hand-eye calibration of any arm and camera from a generic captures folder, with held-out checks."""
    import warnings

    from darp.calibration.anyarm import solve_folder
    from darp.calibration.anyarm_report import write_handeye_report
    from darp.errors import DarpWarning
    from darp.formats.calibration import write_calibration
    from darp.formats.captures import PairingOptions

    outcome = solve_folder(captures, intrinsics=intrinsics, eye_to_hand=True if eye_to_hand else None,
                           folds=folds, seed=seed, compare=compare, folds_file=folds_file,
                           refinement=refinement.value, how=PairingOptions(id_column, order, pair_shift), force=force)
    for w in outcome.warnings:
        warnings.warn(w, DarpWarning, stacklevel=1)
    if report is not None:  # the report first: the calibration, written last, is the sign of a complete run
        write_handeye_report(outcome, report)
    write_calibration(out, outcome.calibration)
    r = outcome.calibration.report
    for line in outcome.pairing_lines:
        typer.echo(line)
    typer.echo(f"wrote {out} ({r['mode']}; captures used: "
               + ", ".join(f"{a} {n}" for a, n in r["n_captures"].items()) + ")")
    typer.echo(f"  fit: reprojection median {r['fit']['reprojection_px']['median']:.3f} px")
    held = r["heldout"]

    def cell(v: dict[str, Any]) -> str:
        return (f"centre {v['mm']['mean']:.3f} / {v['mm']['max']:.3f} mm, corner {v['corner_mm']['mean']:.3f} / "
                f"{v['corner_mm']['max']:.3f} mm, {v['deg']['mean']:.3f} / {v['deg']['max']:.3f} deg")

    if held.get("board_consistency_mm"):
        typer.echo(f"  held-out board consistency ({held['folds']} folds; mean / max): "
                   + cell({"mm": held["board_consistency_mm"], "corner_mm": held["board_corner_consistency_mm"],
                           "deg": held["board_consistency_deg"]}))
    for m, v in r.get("opencv_heldout_board_consistency", {}).items():
        typer.echo(f"  {m:30s} " + (cell(v) if "mm" in v else str(v.get("error", "failed"))))
    for name, T in r.get("base_to_base", {}).items():
        t = np.asarray(T)[:3, 3] * 1e3
        typer.echo(f"  base-to-base {name}: translation ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm")


@calib_app.command("export")
def export_command(
    captures: Annotated[Path, input_argument("darp capture folder (from `darp calib capture`).")],
    out: Annotated[Path, out_option("Generic captures folder to write (one sub-folder per arm).", folder=True)],
) -> None:
    """Write a darp capture folder as a generic any-arm captures folder (flange poses from the Z1 model)."""
    from darp.calibration.anyarm_export import export_captures
    from darp.calibration.captures import read_captures
    from darp.formats.io_output import unfinished_folder

    with unfinished_folder(out, "darp calib export"):
        n = export_captures(read_captures(captures), out)
    typer.echo(f"wrote {out} ({n} captures)")
