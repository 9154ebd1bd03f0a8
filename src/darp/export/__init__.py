"""Exports of processed surveys into the formats other tools load (``darp export FORMAT``).

The conventions of each format are in :mod:`darp.export.cameras` (nerfstudio, Open3D), :mod:`darp.export.colmap`,
:mod:`darp.export.poses` (TUM), :mod:`darp.export.bop` and :mod:`darp.export.completion`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from darp.dataset import ProcessedSurvey, find_processed
from darp.errors import FormatError
from darp.export.bop import export_bop
from darp.export.cameras import export_nerfstudio, export_open3d, export_tum
from darp.export.colmap import export_colmap
from darp.export.completion import export_completion

PER_SURVEY: dict[str, Callable[[ProcessedSurvey, Path], dict[str, Any]]] = {
    "nerfstudio": export_nerfstudio, "colmap": export_colmap, "open3d": export_open3d, "tum": export_tum,
}
DATASET: dict[str, Callable[[list[ProcessedSurvey], Path], dict[str, Any]]] = {
    "bop": export_bop, "completion": export_completion,
}
FORMATS = (*PER_SURVEY, *DATASET)


def export(fmt: str, processed: str | Path, out: str | Path) -> dict[str, Any]:
    """Export every processed survey at ``processed`` in format ``fmt`` under ``out``.

    Per-survey formats (nerfstudio, colmap, open3d, tum) write ``out`` itself for one survey and
    ``out/<survey>/`` for several; bop and completion write one dataset folder for all of them.
    """
    surveys = find_processed(processed)
    out = Path(out)
    if fmt in DATASET:
        return {"format": fmt, "out": str(out), **DATASET[fmt](surveys, out)}
    if fmt not in PER_SURVEY:
        raise FormatError(f"unknown export format {fmt!r} (formats: {', '.join(FORMATS)})")
    summaries = {}
    for survey in surveys:
        target = out if len(surveys) == 1 else out / survey.name
        summary = {"out": str(target), **PER_SURVEY[fmt](survey, target)}
        carried = carry_envelope(survey, target)
        summaries[survey.name] = {**summary, **({"envelope": carried} if carried else {})}
    return {"format": fmt, "out": str(out), "surveys": summaries}


def carry_envelope(survey: ProcessedSurvey, target: Path) -> list[str]:
    """The survey's object envelope (``manip_envelope.json``, world frame of the exported poses) beside the
    export and in each per-arm sequence folder, so that ``darp import`` of any of them crops to the object as
    the survey did (without it, processing estimates a cylinder from the depth). Nothing when the survey's
    envelope has no geometry or the raw survey is gone."""
    from darp.formats.envelope import ENVELOPE_FILE, read_envelope, write_envelope
    from darp.formats.trajectories import detect_posed_folder

    source = survey.survey_path / ENVELOPE_FILE if survey.survey_path is not None else None
    if source is None or not source.is_file():
        return []
    envelope = read_envelope(source, known_arms=None)
    if not envelope.has_geometry:
        return []
    folders = [target, *(d for d in sorted(target.iterdir()) if d.is_dir() and detect_posed_folder(d))]
    for folder in folders:
        write_envelope(folder / ENVELOPE_FILE, envelope)
    return [str(folder / ENVELOPE_FILE) for folder in folders]


__all__ = ["FORMATS", "carry_envelope", "export"]
