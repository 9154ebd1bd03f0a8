"""``darp inspect``: the release-composition table of one or more survey folders.

Reads only the joint logs, the envelopes and the recordings' indexes (no pixel is decoded), so a
14 GB survey takes seconds. Definitions of every column: docs/survey-format.md.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from darp.cli._app import app
from darp.cli._options import CameraArm, input_argument, parse_camera_arm


class TableFormat(StrEnum):
    table = "table"
    csv = "csv"
    markdown = "markdown"
    latex = "latex"


@app.command("inspect")
def inspect_command(
    surveys: Annotated[list[Path], input_argument("Survey folders, or folders that hold survey folders.")],
    fmt: Annotated[TableFormat, typer.Option("--format", "-f", help="Output format.")] = TableFormat.table,
    camera: Annotated[list[CameraArm] | None, typer.Option(
        "--camera", parser=parse_camera_arm, metavar="SERIAL=ARM",
        help="Camera-to-arm mapping SERIAL=ARM (repeat per camera); default: the DARP rig's.",
        show_default=False)] = None,
) -> None:
    """Print the release-composition table (envelope, joint-log rows, duration, rate, depth frames, size)."""
    from darp.evaluation.composition import format_composition, survey_composition
    from darp.formats.survey import find_survey_folders, open_survey

    serial_to_arm = {c.serial: c.arm for c in camera} if camera else None
    items = []
    for folder in find_survey_folders(surveys):
        survey = open_survey(folder, serial_to_arm)
        item = survey_composition(survey)
        for note in item.notes:
            kind = "warning" if note.startswith("partial survey") else "note"  # an interrupted acquisition
            typer.echo(f"darp: {kind}: {folder}: {note}", err=True)
        items.append(item)
    typer.echo(format_composition(items, fmt.value), nl=False)
