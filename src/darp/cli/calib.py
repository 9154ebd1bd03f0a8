"""``darp calib``: ChArUco calibration of the rig (board, plan, capture, solve, check).

    darp calib board --out board.pdf [--squares-x 10 --squares-y 7 --square-mm 30 --marker-mm 22
                     --dictionary DICT_5X5_100 --paper auto]
    darp calib plan --out plan.json [--rig FILE] [--n 30] [--seed 0] [--board-yaw-deg 0] [--candidates 300]
    darp calib capture (--twin [--seed N --profile realistic --n 30] | --hardware RIG.yaml) --out DIR
                       [--plan plan.json] [--stream color|ir1] [--overwrite]
    darp calib solve CAPTURES --out calibration.json [--report DIR] [--folds 5] [--truth FILE] [--epoch NAME]
    darp calib check CALIBRATION CAPTURES [--board-unmoved] [--json FILE]

``check`` exits 0 when the calibration still holds and 1 when it is stale. See docs/calibration.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, fail

calib_app = typer.Typer(help="Calibrate the rig with a ChArUco board: hand-eye, bases, joint-zero offsets.",
                        no_args_is_help=True)
app.add_typer(calib_app, name="calib")

SquaresX = Annotated[int, typer.Option("--squares-x", help="Squares along the board's x.")]
SquaresY = Annotated[int, typer.Option("--squares-y", help="Squares along the board's y.")]
SquareMm = Annotated[float, typer.Option("--square-mm", help="Square side, millimetres.")]
MarkerMm = Annotated[float, typer.Option("--marker-mm", help="ArUco marker side, millimetres.")]
Dictionary = Annotated[str, typer.Option("--dictionary", help="OpenCV ArUco dictionary.")]


def _board(squares_x: int, squares_y: int, square_mm: float, marker_mm: float, dictionary: str) -> Any:
    from darp.calibration.board import make_board_spec

    return make_board_spec(squares_x, squares_y, square_mm / 1e3, marker_mm / 1e3, dictionary)


def _progress(quiet: bool) -> Any:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    console=Console(stderr=True), disable=quiet, transient=True)


@calib_app.command("board")
def board_command(
    out: Annotated[Path, typer.Option(help="PDF to write.", show_default=False)],
    squares_x: SquaresX = 10, squares_y: SquaresY = 7, square_mm: SquareMm = 30.0, marker_mm: MarkerMm = 22.0,
    dictionary: Dictionary = "DICT_5X5_100",
    paper: Annotated[str, typer.Option(help="Paper: auto, A4, A3, A2, A1, A0, letter, tabloid.")] = "auto",
) -> None:
    """Write a printable board at true scale (print at 100 %, check the 100 mm ruler)."""
    from darp.calibration.board import spec_text, write_board_pdf

    board = _board(squares_x, squares_y, square_mm, marker_mm, dictionary)
    layout = write_board_pdf(board, out, paper=paper)
    typer.echo(f"wrote {out} ({layout['paper']}, {layout['page_mm'][0]:.0f} x {layout['page_mm'][1]:.0f} mm): "
               f"{spec_text(board)}")


@calib_app.command("plan")
def plan_command(
    out: Annotated[Path, typer.Option(help="Plan JSON to write.", show_default=False)],
    rig_file: Annotated[Path | None, typer.Option("--rig", help="Rig YAML (default: packaged).", show_default=False)] = None,
    n: Annotated[int, typer.Option(help="Captures per arm.")] = 30,
    seed: Annotated[int, typer.Option(help="Seed of the random candidates.")] = 0,
    board_yaw_deg: Annotated[float, typer.Option(help="Board yaw on the table (centred on the workspace).")] = 0.0,
    candidates: Annotated[int, typer.Option(help="Random candidate poses tried per arm.")] = 300,
    squares_x: SquaresX = 10, squares_y: SquaresY = 7, square_mm: SquareMm = 30.0, marker_mm: MarkerMm = 22.0,
    dictionary: Dictionary = "DICT_5X5_100",
) -> None:
    """Plan diverse, feasible, collision-free capture poses for both arms (nominal rig)."""
    import numpy as np

    from darp.calibration.plan import PlanSettings, default_board_pose, plan_captures
    from darp.kinematics.rig import load_rig

    rig = load_rig(rig_file)
    board = _board(squares_x, squares_y, square_mm, marker_mm, dictionary)
    plan = plan_captures(rig, board, default_board_pose(rig, board, np.radians(board_yaw_deg)),
                         settings=PlanSettings(n_per_arm=n, n_candidates=max(candidates, n)), seed=seed)
    plan.save(out)
    counts = ", ".join(f"{a}: {len(p)} ({sum(x.via_park for x in p)} via park)" for a, p in plan.poses.items())
    typer.echo(f"wrote {out}: {counts}")


@calib_app.command("capture")
def capture_command(
    out: Annotated[Path, typer.Option(help="Capture folder to create.", show_default=False)],
    twin: Annotated[bool, typer.Option("--twin", help="Capture on the digital twin.")] = False,
    hardware: Annotated[Path | None, typer.Option("--hardware", help="Capture on the real rig described by this "
                                                  "rig YAML.", show_default=False)] = None,
    plan_file: Annotated[Path | None, typer.Option("--plan", help="Plan from `darp calib plan` (default: plan now).",
                                                   show_default=False)] = None,
    seed: Annotated[int, typer.Option(help="Twin seed (true rig errors) and plan seed.")] = 0,
    profile: Annotated[str, typer.Option(help="Twin error profile: ideal or realistic.")] = "realistic",
    n: Annotated[int, typer.Option(help="Captures per arm when planning now.")] = 30,
    stream: Annotated[str, typer.Option(help="Image stream: color or ir1.")] = "color",
    overwrite: Annotated[bool, typer.Option(help="Replace captures already in --out.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Take calibration captures (one arm moving at a time) on the twin or the real rig."""
    if twin == (hardware is not None):
        raise fail("give exactly one of --twin or --hardware RIG.yaml")
    from darp.calibration.plan import CapturePlan

    plan = CapturePlan.load(plan_file) if plan_file is not None else None
    total = sum(len(p) for p in plan.poses.values()) if plan is not None else 2 * n
    with _progress(quiet) as bar:
        task = bar.add_task("capturing", total=total)

        def tick(arm: str, k: int) -> None:
            bar.update(task, advance=1, description=f"capturing {arm}")

        if twin:
            from darp.cli._calib_twin import capture_twin

            caps = capture_twin(out, seed=seed, profile=profile, n_per_arm=n, plan=plan, stream=stream,
                                overwrite=overwrite, on_capture=tick)
        else:
            caps = _capture_hardware(hardware, out, plan, n, seed, stream, overwrite, tick)  # type: ignore[arg-type]
    counts = ", ".join(f"{a}: {len(caps.for_arm(a))}" for a in caps.arms)
    typer.echo(f"wrote {out} ({counts})")


def _capture_hardware(rig_file: Path, out: Path, plan: Any, n: int, seed: int, stream: str, overwrite: bool,
                      tick: Any) -> Any:
    """Captures on the real rig through the hardware backend (``darp.hardware.open_rig``)."""
    from darp.calibration.board import DEFAULT_BOARD
    from darp.calibration.capture_run import CaptureRunSettings, run_capture_plan
    from darp.calibration.captures import CaptureWriter
    from darp.calibration.plan import PlanSettings, default_board_pose, plan_captures
    from darp.hardware import open_rig
    from darp.kinematics.rig import load_rig

    rig = load_rig(rig_file)
    if plan is None:
        plan = plan_captures(rig, DEFAULT_BOARD, default_board_pose(rig, DEFAULT_BOARD),
                             settings=PlanSettings(n_per_arm=n), seed=seed)
    with open_rig(rig) as backend:  # connect first: a rig that fails to connect leaves no capture folder
        writer = CaptureWriter(out, plan.board, source=f"hardware:{rig.name}", overwrite=overwrite)
        run_capture_plan(backend, plan, writer, park_q={a: rig.arm(a).park_q_rad for a in rig.arm_ids},
                         settings=CaptureRunSettings(stream=stream), on_capture=tick)
    return writer.close()


@calib_app.command("solve")
def solve_command(
    captures: Annotated[Path, typer.Argument(help="Capture folder.", show_default=False)],
    out: Annotated[Path, typer.Option(help="Calibration JSON to write.", show_default=False)],
    report: Annotated[Path | None, typer.Option(help="Report folder (figures, summary.md).", show_default=False)] = None,
    folds: Annotated[int, typer.Option(help="k of the k-fold held-out evaluation (0: none).")] = 5,
    truth: Annotated[Path | None, typer.Option(help="True calibration to compare with (default: the captures' "
                                               "truth/calibration.json when present).", show_default=False)] = None,
    epoch: Annotated[str | None, typer.Option(help="Epoch label (default calib-<date>).", show_default=False)] = None,
    compare: Annotated[bool, typer.Option(help="Also solve with OpenCV alone, for the comparison table.")] = True,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Calibrate from captures: hand-eye per arm, bases in one world frame, joint-zero offsets."""
    from darp.calibration.captures import read_captures
    from darp.calibration.solve import SolveSettings, solve_captures
    from darp.formats.calibration import read_calibration, write_calibration

    caps = read_captures(captures)
    truth_path = truth if truth is not None else caps.truth_calibration_path()
    truth_cal = read_calibration(truth_path) if truth_path is not None else None
    with _progress(quiet) as bar:
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        outcome = solve_captures(caps, SolveSettings(folds=folds, compare=compare, epoch=epoch), truth=truth_cal,
                                 progress=progress)
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
    if outcome.truth is not None:
        t = outcome.truth["darp"]
        he = max(v["hand_eye"]["translation_mm"] for v in t["arms"].values())
        typer.echo(f"  against truth: hand-eye <= {he:.3f} mm, base-to-base {t['base_to_base']['translation_mm']:.3f} mm"
                   f" / {t['base_to_base']['rotation_deg']:.4f} deg")


@calib_app.command("check")
def check_command(
    calibration: Annotated[Path, typer.Argument(help="Calibration JSON.", show_default=False)],
    captures: Annotated[Path, typer.Argument(help="Folder of a few new captures.", show_default=False)],
    board_unmoved: Annotated[bool, typer.Option(help="The board is where it was at calibration (stricter).")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the result as JSON.", show_default=False)] = None,
) -> None:
    """Tell whether a calibration still holds (exit 0) or is stale (exit 1) from a few new captures."""
    from darp.calibration.captures import read_captures
    from darp.calibration.check import CheckSettings, check_calibration
    from darp.formats.calibration import read_calibration
    from darp.formats.schema import write_json_checked

    result = check_calibration(read_calibration(calibration), read_captures(captures),
                               CheckSettings(board_unmoved=board_unmoved))
    if json_out is not None:
        write_json_checked(json_out, result.to_dict())
    for arm, r in result.arms.items():
        state = "ok" if r.ok else "STALE"
        typer.echo(f"{arm}: {state}: {r.n_captures} captures, median 3-D corner error {r.corner_3d_mm['median']:.3f} mm "
                   f"(limit {r.limit_mm:.3f}), reprojection {r.reprojection_px['median']:.3f} px "
                   f"(limit {r.limit_px:.3f})" + ("" if r.ok else f": {'; '.join(r.reasons)}"))
    if result.board_disagreement is not None:
        d = result.board_disagreement
        typer.echo(f"board seen by the two arms differs by {d['translation_mm']:.2f} mm / {d['rotation_deg']:.3f} deg")
    typer.echo("calibration holds" if result.ok else "calibration is stale: recalibrate")
    if not result.ok:
        raise typer.Exit(code=1)
