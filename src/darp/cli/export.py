"""``darp export FORMAT PROCESSED_DIR -o DIR``: processed surveys in the formats other tools load.

Formats and their exact conventions: docs/ecosystem.md (and darp.export.cameras, .colmap, .bop, .completion).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from darp.cli._app import app
from darp.cli._options import ExportFormat, input_argument, out_option


@app.command("export")
def export_command(
    fmt: Annotated[ExportFormat, typer.Argument(help="Target format: nerfstudio, colmap, open3d, tum, bop "
                                                "(twin surveys), completion (twin surveys).", show_default=False,
                                                metavar="FORMAT")],
    processed: Annotated[Path, input_argument("Output folder of darp process (one survey's folder or the "
                                              "folder of several).")],
    out: Annotated[Path, out_option("Folder to write the export into.", folder=True)],
) -> None:
    """Export processed surveys for nerfstudio, COLMAP, Open3D, TUM RGB-D, BOP or PCN/PoinTr completion."""
    from darp.export import export
    from darp.formats.io_output import unfinished_folder

    with unfinished_folder(out, "darp export"):
        summary = export(fmt.value, processed, out)
    typer.echo(json.dumps(summary))
    typer.echo(f"wrote {out}")
