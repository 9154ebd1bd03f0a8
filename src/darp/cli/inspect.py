"""``darp inspect``: the release-composition table of one or more survey folders.

Reads only the joint logs, the envelopes and the recordings' indexes (no pixel is decoded), so a
14 GB survey takes seconds. Definitions of every column: docs/survey-format.md.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from darp.cli._app import app
from darp.errors import DarpError


class TableFormat(str, Enum):
    table = "table"
    csv = "csv"
    markdown = "markdown"
    latex = "latex"


def _parse_cameras(pairs: list[str]) -> dict[str, str] | None:
    if not pairs:
        return None
    mapping: dict[str, str] = {}
    for pair in pairs:
        serial, sep, arm = pair.partition("=")
        if not sep or not serial.strip() or not arm.strip():
            raise DarpError(f"--camera expects SERIAL=ARM (e.g. 348522076490=arm110), got {pair!r}")
        mapping[serial.strip()] = arm.strip()
    return mapping


@app.command("inspect")
def inspect_command(
    surveys: Annotated[
        list[Path],
        typer.Argument(help="Survey folders, or folders that hold survey folders.", show_default=False),
    ],
    fmt: Annotated[
        TableFormat, typer.Option("--format", "-f", help="Output format.")
    ] = TableFormat.table,
    camera: Annotated[
        list[str] | None,
        typer.Option(
            "--camera",
            help="Camera-to-arm mapping SERIAL=ARM (repeat per camera); default: the DARP rig's.",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Print the release-composition table (envelope, joint-log rows, duration, rate, depth frames, size)."""
    from darp.evaluation.composition import format_composition, survey_composition
    from darp.formats.survey import find_survey_folders, open_survey

    serial_to_arm = _parse_cameras(camera or [])
    items = []
    for folder in find_survey_folders(surveys):
        survey = open_survey(folder, serial_to_arm)
        item = survey_composition(survey)
        for note in item.notes:
            typer.echo(f"darp: note: {folder}: {note}", err=True)
        items.append(item)
    typer.echo(format_composition(items, fmt.value), nl=False)
