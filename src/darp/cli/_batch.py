"""The ``--executor ray[:ADDRESS]`` option and the batch runs behind it (``darp process``, ``darp twin generate``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

EXECUTOR_HELP = ("Run one task per survey on Ray: 'ray' starts a local Ray on this machine, 'ray:ADDRESS' joins a "
                 "cluster ('ray:auto': the one this node is in); default: one after another in this process.")


def parse_executor_option(value: str) -> Any:
    from darp.batch.executor import parse_executor
    from darp.errors import ConfigError

    try:
        return parse_executor(value)
    except ConfigError as err:
        raise typer.BadParameter(str(err)) from None


ExecutorOption = Annotated[Any, typer.Option("--executor", parser=parse_executor_option, metavar="ray[:ADDRESS]",
                                             help=EXECUTOR_HELP, show_default=False)]


def batch_progress(label: str, total: int) -> tuple[Any, Any]:
    """A rich progress bar on stderr for a batch and the ``progress(done, total)`` callback that drives it.

    Redrawn twice a second (rich's default is 10: 0.6 % of a core in the driver, measured, for a bar whose
    count changes once per survey); the callback redraws it at once when a task ends."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    from darp.cli._options import progress_bar

    bar = progress_bar(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       transient=False, refresh_per_second=2)
    task = bar.add_task(label, total=total)
    return bar, lambda done, all_: bar.update(task, completed=done, total=all_, refresh=True)


def process_on_executor(folders: list[Path], out: Path, calibration: Path | None, truth_poses: bool,
                        settings: Any, resume: bool, executor: Any) -> list[Any]:
    """``darp process`` of every survey, one task each on ``executor``, with a batch progress bar: the outcomes."""
    from darp.batch.tasks import process_batch

    bar, progress = batch_progress(f"surveys on {executor}", len(folders))
    with bar:
        return process_batch(folders, out, calibration, truth_poses, settings, resume, executor, progress)
