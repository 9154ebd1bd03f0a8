"""``darp keyframes``, ``darp process`` and ``darp report``: from survey folders to clouds, meshes and tables."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from darp.cli._app import app, error
from darp.cli._batch import ExecutorOption, process_on_executor
from darp.cli._options import calibration_option, input_argument, out_option, refuse_output_over_inputs

CALIBRATION_HELP = "Calibration JSON of the rig epoch."
SETTINGS_HELP = "Processing settings YAML/JSON (docs/processing-pipeline.md)."
TruthPoses = Annotated[bool, typer.Option("--truth-poses", help="Twin surveys: the true camera poses (truth/) "
                                          "instead of eq. 1 (the accuracy floor).")]
SettingsFile = Annotated[Path | None, typer.Option("--settings", help=SETTINGS_HELP, exists=True, dir_okay=False,
                                                   show_default=False)]


def _warn(message: str) -> None:
    typer.echo(f"darp: warning: {message}", err=True)


def _warn_corrections(survey: str, corrections: dict[str, Any] | None) -> None:
    """One line per switched-on correction that had nothing to apply for some arm (paper mode there)."""
    for name in ("depth", "time"):
        warning = ((corrections or {}).get(name) or {}).get("warning")
        if warning:
            _warn(f"{survey}: {warning}")


def _warn_estimated_envelope(survey: str, envelope: dict[str, Any] | None) -> None:
    """One line when the envelope was estimated from the survey (manip_envelope.json had no geometry)."""
    if envelope and envelope.get("source") == "estimated":
        x, y, z = (1000 * v for v in envelope["center_m"])
        _warn(f"{survey}: manip_envelope.json has no object centre/radius/height; used the envelope estimated from "
              f"the survey: centre ({x:.0f}, {y:.0f}, {z:.0f}) mm, radius {1000 * envelope['radius_m']:.0f} mm, "
              f"height {1000 * envelope['height_m']:.0f} mm")


Corrections = Annotated[str | None, typer.Option(
    "--corrections", help="darp's improvements over the paper's method: paper (none), all, or a comma-separated "
    "subset of kinematics, time, depth, refine, table, fusion, mesh (docs/accuracy.md). Overrides the settings file's "
    "'corrections'.")]


def _settings(path: Path | None, corrections: str | None = None) -> Any:
    import dataclasses

    from darp.errors import ConfigError
    from darp.processing.settings import CorrectionSettings, ProcessSettings, load_settings

    settings = ProcessSettings() if path is None else load_settings(path)
    if corrections is None:
        return settings
    try:
        return dataclasses.replace(settings, corrections=CorrectionSettings.parse(corrections))
    except ConfigError as err:
        raise typer.BadParameter(err.message, param_hint="'--corrections'") from None


def _need_calibration(calibration: Path | None, truth_poses: bool) -> None:
    if calibration is None and not truth_poses:
        raise typer.BadParameter("required (only --truth-poses on a twin survey can do without)",
                                 param_hint="'--calibration'")


def _progress_bars() -> Any:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        SpinnerColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    return Progress(SpinnerColumn(), TextColumn("{task.description:<34}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=Console(stderr=True), transient=True,
                    disable=not Console(stderr=True).is_terminal)  # no stray blank line before an error


def _stage_callback(progress: Any, label: str) -> Any:
    tasks: dict[str, Any] = {}

    def report(stage: str, done: float, total: float | None) -> None:
        if stage not in tasks:
            tasks[stage] = progress.add_task(f"{label}: {stage}", total=total)
        progress.update(tasks[stage], completed=done, total=total)

    return report


@app.command("keyframes")
def keyframes(
    survey: Annotated[Path, input_argument("Survey folder (cam<serial>.bag x2, arm_poses.csv, "
                                           "manip_envelope.json).")],
    out: Annotated[Path, out_option("Keyframes folder (keyframes.json, <arm>/<frame>.npz, poses/).", folder=True)],
    calibration: Annotated[Path | None, calibration_option(CALIBRATION_HELP)] = None,
    truth_poses: TruthPoses = False,
    settings_file: SettingsFile = None,
    corrections: Corrections = None,
) -> None:
    """Select settled, view-diverse keyframes per arm and export them (aligned RGB, depth, IR, mask, pose)."""
    _need_calibration(calibration, truth_poses)
    refuse_output_over_inputs(out, [survey], "--out", folder_output=True)
    from rich.console import Console
    from rich.table import Table

    from darp.processing.job import open_job, survey_calibration
    from darp.processing.stages import stage_keyframes, stage_poses

    settings = _settings(settings_file, corrections)
    with _progress_bars() as progress:
        job = open_job(survey, out, survey_calibration(survey, calibration), calibration_path=calibration,
                       settings=settings, truth_poses=truth_poses, progress=_stage_callback(progress, survey.name),
                       keyframes_folder=out)
        for note in job.survey.notes:
            _warn(f"{job.survey.name}: {note}")
        try:
            stage_poses(job)
            summary = stage_keyframes(job)
        finally:
            job.close()
    table = Table(title=f"{job.survey.name}: keyframes")
    for column in ("arm", "frames", "settled", "in view", "views", "keyframes", "held out", "still <= rad/s"):
        table.add_column(column, justify="right")
    keys = ("frames", "settled", "in_view", "views", "keyframes", "heldout")
    for arm, c in summary["arms"].items():
        table.add_row(arm, *(str(c.get(k, 0)) for k in keys), f"{c.get('still_threshold_rad_s', 0):.3f}")
    Console().print(table)
    _warn_estimated_envelope(job.survey.name, summary.get("envelope"))
    _warn_corrections(job.survey.name, {"depth": summary.get("depth_correction"),
                                        "time": job.time_alignment_record()})
    typer.echo(f"wrote {out}")


@app.command("process")
def process(
    surveys: Annotated[list[Path], input_argument("Survey folders, or folders holding survey folders.")],
    out: Annotated[Path, out_option("Output folder: <out>/<survey>/ per survey, results.json.")],
    calibration: Annotated[Path | None, calibration_option(CALIBRATION_HELP)] = None,
    truth_poses: TruthPoses = False,
    settings_file: SettingsFile = None,
    resume: Annotated[bool, typer.Option("--resume", help="Skip stages already done with the same inputs and "
                                         "settings.")] = False,
    executor: ExecutorOption = None,
    corrections: Corrections = None,
) -> None:
    """Poses -> keyframes -> fusion -> mesh -> evaluation for each survey; results.json per survey and overall.

    A folder written by ``darp import`` is processed from its keyframes (fusion, mesh, held-out evaluation).
    """
    from darp.processing.imported import is_imported

    imported = [s for s in surveys if is_imported(s)]
    surveys = [s for s in surveys if not is_imported(s)]

    from darp.formats.survey import find_survey_folders
    from darp.processing.batch import FAILED
    from darp.processing.results import write_summary

    found = find_survey_folders(surveys) if surveys else []  # a folder with no survey is named before -c
    if surveys:
        _need_calibration(calibration, truth_poses)
    settings = _settings(settings_file, corrections)
    folders = imported + found
    for folder in folders:  # <out>/<survey>/ must not be (or be inside, or hold) a raw survey
        refuse_output_over_inputs(out / folder.name, [folder], "--out", folder_output=True)
    names = [f.name for f in folders]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise typer.BadParameter(f"two surveys share the folder name {duplicated[0]!r}: their outputs would collide",
                                 param_hint="'SURVEYS...'")
    cal = None
    if calibration is not None:  # one file for the whole batch: a bad one is one line, not a failure per survey
        from darp.formats.calibration import read_calibration

        cal = read_calibration(calibration)
    if executor is not None:  # one task per survey on Ray (darp.batch), failures contained the same way
        outcomes = process_on_executor(folders, out, calibration, truth_poses, settings, resume, executor)
    else:
        outcomes = _process_here(folders, out, calibration, cal, truth_poses, settings, resume)
    done = [o.out for o in outcomes if o.status != FAILED]
    failed = [o for o in outcomes if o.status == FAILED]
    for o in failed:  # after the progress display is gone: one clean line each
        error(o.message)
    try:
        summary_path = write_summary(out, done, [o.to_dict() for o in failed])
    except OSError:
        if failed:  # a full disk already failed the survey(s), in their own lines: one cause, said once
            raise typer.Exit(2) from None
        raise
    _print_table(done, failed)
    for o in outcomes:
        for warning in o.warnings:
            _warn(f"{o.name}: {warning}")
    typer.echo(f"wrote {summary_path}")
    if failed:
        if len(outcomes) > 1:
            error(f"{len(failed)} of {len(outcomes)} surveys failed: {', '.join(o.name for o in failed)} "
                  f"(listed in {summary_path})")
        raise typer.Exit(2)


def _process_here(folders: list[Path], out: Path, calibration: Path | None, cal: Any, truth_poses: bool,
                  settings: Any, resume: bool) -> list[Any]:
    """The batch in this process, one survey after another, with per-stage progress bars
    (:func:`darp.processing.batch.process_folder` for each, as a Ray task runs it); ``cal`` is the calibration
    file ``calibration`` already read."""
    from darp.processing.batch import process_batch, process_folder

    with _progress_bars() as progress:
        overall = progress.add_task("surveys", total=len(folders))

        def run_one(folder: Path, target: Path) -> dict[str, Any]:
            return process_folder(folder, target, calibration, settings=settings, truth_poses=truth_poses,
                                  resume=resume, calibration=cal,
                                  progress=_stage_callback(progress, folder.name),
                                  on_note=lambda note: _warn(f"{folder.name}: {note}"))

        return process_batch(folders, out, run_one, on_outcome=lambda _: progress.advance(overall))


def _print_table(done: list[Path], failed: list[Any]) -> None:
    """The held-out table: one row per processed survey (implausible ones flagged), one per failed survey."""
    from rich import box
    from rich.console import Console
    from rich.table import Table

    from darp.processing.results import read_results

    def mm(value: Any) -> str:
        return "-" if value is None else f"{value:.2f}"

    # fits 80 columns: held-out point-to-mesh median / RMSE [mm] and % within 10 mm; truth: fused-cloud accuracy
    table = Table(title="held-out evaluation (mm) and clouds", box=box.SIMPLE_HEAD,
                  caption="kf: keyframes; truth: fused cloud to the true mesh, median (mm); "
                          "(!) implausible, see the warnings; (?) not to be trusted, why is below; "
                          "FAILED: see the error lines")
    table.add_column("survey", justify="left", overflow="fold")
    for column in ("poses", "kf", "fused", "median", "RMSE", "<=10mm %", "truth"):
        table.add_column(column, justify="right", no_wrap=True)
    results = [read_results(folder) for folder in done]
    for r in results:
        h = r["heldout"]["aggregate"]
        acc = ((r.get("truth") or {}).get("cloud") or {}).get("accuracy", {}).get("median_mm")
        source = {"calibration": "calib"}.get(r["pose_source"], r["pose_source"])
        name = r["survey"] + (" (!)" if r.get("warnings") else "") + (
            " (?)" if (r.get("trust") or {}).get("flags") else "")
        table.add_row(name, source, str(r["keyframes"]["total"]), f"{r['clouds'].get('fused', 0):,}",
                      mm(h.get("median_mm")), mm(h.get("rmse_mm")), mm(h.get("within_10mm_pct")), mm(acc))
    for o in failed:
        table.add_row(o.name, "FAILED", "-", "-", "-", "-", "-", "-")
    Console().print(table)
    for folder, r in zip(done, results, strict=True):
        _warn_estimated_envelope(folder.name, r.get("envelope"))
        _warn_corrections(folder.name, r.get("corrections"))
        for flag in (r.get("trust") or {}).get("flags") or []:
            _warn(f"{folder.name}: not to be trusted: {flag}")


@app.command("report")
def report(
    processed: Annotated[Path, input_argument("Output folder of darp process.")],
) -> None:
    """Write report.md and report.html (every table and figure across the processed surveys)."""
    from darp.processing.report import survey_status, write_report

    md_path, html_path = write_report(processed)
    for kind, rows in survey_status(processed).items():
        for name, reason in sorted(rows.items()):
            _warn(f"{name}: {kind}: {reason}")
    typer.echo(f"wrote {md_path}")
    typer.echo(f"wrote {html_path}")
