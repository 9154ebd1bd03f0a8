"""The release-composition table (the DARP paper's Table "Release composition and recording statistics").

Definitions (checked against the paper's numbers, see docs/survey-format.md):

- Radius / Height / Standoff: ``radius_m``, ``height_m``, ``standoff_m`` of manip_envelope.json, in cm.
- Rows/Arm: joint-log rows of both arms divided by the number of arms (the paper's total 30,506 is half
  of its 61,012 logged rows); the per-arm counts are kept in :attr:`SurveyComposition.rows_by_arm`.
- Duration: span of the joint log, first to last row over both arms (the log brackets the recording).
- Rate: Rows/Arm / Duration, i.e. joint-log rows per second per arm.
- Depth_<n>: depth frames in arm<n>'s recording, counted from the recording's index (no decoding).
- Size: bytes of the survey's files (two recordings, arm_poses.csv, manip_envelope.json) / 1e9.
- Total / Range: min--max for radius, height and standoff; sums for rows, duration, depth frames and size,
  computed from unrounded values; '--' for the rate and for anything unknown.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from darp.errors import EvaluationError
from darp.formats.survey import Survey

FORMATS = ("table", "csv", "markdown", "latex")
TOTAL_LABEL = "Total / Range"


@dataclass(frozen=True)
class SurveyComposition:
    """The recording statistics of one survey (SI units; formatting converts to cm / GB)."""

    name: str
    radius_m: float | None
    height_m: float | None
    standoff_m: float | None
    rows_by_arm: dict[str, int]
    duration_s: float
    depth_frames: dict[str, int | None]  # None: the recording has no depth stream
    size_bytes: int
    notes: tuple[str, ...] = field(default=())

    @property
    def rows_total(self) -> int:
        return sum(self.rows_by_arm.values())

    @property
    def rows_per_arm(self) -> float:
        return self.rows_total / len(self.rows_by_arm) if self.rows_by_arm else 0.0

    @property
    def rate_hz(self) -> float | None:
        return self.rows_per_arm / self.duration_s if self.duration_s > 0 else None


def survey_composition(survey: Survey) -> SurveyComposition:
    """Compute one survey's statistics from its joint log, envelope and recording indexes."""
    log = survey.arm_poses()
    first_s, last_s = log.span()
    arms = tuple(survey.serials)
    rows_by_arm = {arm: (log.rows(arm) if arm in log.arms else 0) for arm in arms}
    depth: dict[str, int | None] = {}
    notes = list(survey.notes)
    for arm in arms:
        if arm not in survey.recording_paths:
            depth[arm] = None
            continue
        with survey.open_recording(arm) as recording:
            depth[arm] = recording.frame_count("depth") if "depth" in recording.streams else None
    envelope = survey.envelope()
    if log.truncated_tail_line is not None:
        notes.append(f"arm_poses.csv: cut-short last line {log.truncated_tail_line} ignored")
    return SurveyComposition(
        name=survey.name,
        radius_m=envelope.radius_m if envelope else None,
        height_m=envelope.height_m if envelope else None,
        standoff_m=envelope.standoff_m if envelope else None,
        rows_by_arm=rows_by_arm,
        duration_s=last_s - first_s,
        depth_frames=depth,
        size_bytes=survey.size_bytes,
        notes=tuple(notes),
    )


# -- the table as cells -------------------------------------------------------------------------
@dataclass(frozen=True)
class _Style:
    missing: str
    dash: str  # between the ends of a range
    thousands: bool  # separators in the total row, like the paper


_STYLES = {
    "table": _Style("--", "-", True),
    "csv": _Style("", "-", False),
    "markdown": _Style("--", "-", True),
    "latex": _Style("--", "--", True),
}


def _arms(items: Sequence[SurveyComposition]) -> list[str]:
    return list(dict.fromkeys(arm for item in items for arm in item.depth_frames))


def _depth_label(arm: str, latex: bool) -> str:
    suffix = arm[3:] if arm.startswith("arm") else arm
    return f"Depth$_{{{suffix}}}$" if latex else f"Depth_{suffix}"


def _headers(arms: list[str], latex: bool) -> list[str]:
    return [
        "Object", "Radius [cm]", "Height [cm]", "Standoff [cm]", "Rows/Arm", "Duration [s]", "Rate [Hz]",
        *(_depth_label(arm, latex) for arm in arms), "Size [GB]",
    ]


def _num(value: float | None, digits: int, style: _Style, thousands: bool = False) -> str:
    if value is None:
        return style.missing
    return f"{value:,.{digits}f}" if thousands and style.thousands else f"{value:.{digits}f}"


def _count(value: float | None, style: _Style, thousands: bool = False) -> str:
    if value is None:
        return style.missing
    digits = 0 if float(value).is_integer() else 1
    return _num(value, digits, style, thousands)


def _range(values: list[float | None], style: _Style) -> str:
    known = [v * 100.0 for v in values if v is not None]
    if not known:
        return style.missing
    return f"{min(known):.1f}{style.dash}{max(known):.1f}"


def _cm(value: float | None) -> float | None:
    return None if value is None else value * 100.0


def _cells(items: Sequence[SurveyComposition], style: _Style) -> tuple[list[list[str]], list[str]]:
    arms = _arms(items)
    rows = []
    for item in items:
        rows.append([
            item.name,
            _num(_cm(item.radius_m), 2, style),
            _num(_cm(item.height_m), 2, style),
            _num(_cm(item.standoff_m), 1, style),
            _count(item.rows_per_arm, style),
            _num(item.duration_s, 1, style),
            _num(item.rate_hz, 1, style),
            *(_count(item.depth_frames.get(arm), style) for arm in arms),
            _num(item.size_bytes / 1e9, 2, style),
        ])
    depth_totals = []
    for arm in arms:
        counts = [item.depth_frames.get(arm) for item in items]
        known = [c for c in counts if c is not None]
        depth_totals.append(_count(sum(known), style, thousands=True) if known else style.missing)
    total = [
        TOTAL_LABEL,
        _range([i.radius_m for i in items], style),
        _range([i.height_m for i in items], style),
        _range([i.standoff_m for i in items], style),
        _count(sum(i.rows_per_arm for i in items), style, thousands=True),
        _num(sum(i.duration_s for i in items), 1, style, thousands=False),
        style.missing,
        *depth_totals,
        _num(sum(i.size_bytes for i in items) / 1e9, 2, style),
    ]
    return rows, total


# -- rendering --------------------------------------------------------------------------------------
def format_composition(items: Sequence[SurveyComposition], fmt: str = "table") -> str:
    """Render the table in ``fmt`` (table, csv, markdown or latex); the text ends with a newline."""
    if fmt not in FORMATS:
        raise EvaluationError(f"unknown table format {fmt!r} (choose from {', '.join(FORMATS)})")
    if not items:
        raise EvaluationError("no surveys to tabulate")
    style = _STYLES[fmt]
    rows, total = _cells(items, style)
    headers = _headers(_arms(items), latex=fmt == "latex")
    if fmt == "csv":
        return _csv(headers, rows, total)
    if fmt == "markdown":
        return _markdown(headers, rows, total)
    if fmt == "latex":
        return _latex(headers, rows, total)
    return _text(headers, rows, total)


def _text(headers: list[str], rows: list[list[str]], total: list[str]) -> str:
    widths = [max(len(r[c]) for r in [headers, *rows, total]) for c in range(len(headers))]

    def line(cells: list[str]) -> str:
        return "  ".join(
            cell.ljust(w) if c == 0 else cell.rjust(w) for c, (cell, w) in enumerate(zip(cells, widths, strict=True))
        ).rstrip()

    rule = "-" * len(line(["x" * w for w in widths]))
    return "\n".join([line(headers), rule, *map(line, rows), rule, line(total)]) + "\n"


def _csv(headers: list[str], rows: list[list[str]], total: list[str]) -> str:
    import csv
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(headers)
    writer.writerows(rows)
    writer.writerow(total)
    return buffer.getvalue()


def _markdown(headers: list[str], rows: list[list[str]], total: list[str]) -> str:
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"

    align = "| " + " | ".join([":---", *["---:"] * (len(headers) - 1)]) + " |"
    bold_total = [f"**{c}**" if c and c != "--" else c for c in total]
    return "\n".join([line(headers), align, *map(line, rows), line(bold_total)]) + "\n"


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
    "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
}


def _latex_escape(text: str) -> str:
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in text)


def _latex(headers: list[str], rows: list[list[str]], total: list[str]) -> str:
    def line(cells: list[str]) -> str:
        return " & ".join(cells) + r" \\"

    head = [r"\textbf{" + (h if "$" in h else _latex_escape(h)) + "}" for h in headers]
    body = [[_latex_escape(r[0]), *r[1:]] for r in rows]
    bold_total = [r"\textbf{" + c + "}" if c != "--" else c for c in [_latex_escape(total[0]), *total[1:]]]
    lines = [
        r"\begin{tabular}{l" + "r" * (len(headers) - 1) + "}",
        r"\toprule",
        line(head),
        r"\midrule",
        *map(line, body),
        r"\midrule",
        line(bold_total),
        r"\bottomrule",
        r"\end{tabular}",
    ]
    return "\n".join(lines) + "\n"
