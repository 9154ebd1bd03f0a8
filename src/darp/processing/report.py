"""``darp report DIR``: every table and figure of a ``darp process`` output folder, as Markdown and HTML.

The report is built from ``results.json`` files and the figure files only (nothing is recomputed but
the observations panel): release composition, the held-out table next to the paper's, per-object
results, cross-arm consistency, truth metrics (twin surveys), and per object the cross-arm XY/XZ/YZ
figure, the partial/partial/fused figure and the held-out histogram, plus the multimodal observations
panel. ``report.md`` links the images by relative path; ``report.html`` embeds them (base64), so it
can be mailed on its own.

The report never passes over a survey silently: its first section lists the surveys that **failed**
(the batch summary's ``failed`` rows: stage and reason), are **unfinished** (an ``UNFINISHED.txt``
in their output folder: interrupted or failed runs, whose outputs are not results), are **missing**
(listed in the summary but without a completed ``results.json``), and those whose results are
**implausible** (their ``warnings``). ``darp report`` repeats each on stderr as a warning.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from darp.errors import DarpError, EvaluationError
from darp.evaluation.composition import SurveyComposition, format_composition
from darp.formats.atomic import write_text_atomic
from darp.processing.results import (
    RESULTS_FILE,
    aggregate_results,
    find_survey_results,
    find_unfinished,
    read_results,
)

MAX_OBSERVATION_OBJECTS = 4
OBSERVATIONS_FIGURE = "figures/observations.png"


@dataclass(frozen=True)
class Block:
    """One piece of the report: a heading, a paragraph, a table or an image."""

    kind: str  # h1, h2, h3, p, table, img, raw_md
    text: str = ""
    headers: tuple[str, ...] = ()
    rows: tuple[tuple[str, ...], ...] = ()
    path: str = ""  # image path relative to the report


def _mm(value: Any, digits: int = 2) -> str:
    return "-" if value is None else f"{float(value):.{digits}f}"


def _pct(value: Any) -> str:
    return "-" if value is None else f"{float(value):.2f}"


def _count(value: Any) -> str:
    return "-" if value is None else f"{int(value):,}"


def _stats_cells(s: dict[str, Any]) -> tuple[str, ...]:
    return (_count(s.get("count")), _mm(s.get("median_mm")), _mm(s.get("rmse_mm")), _mm(s.get("p90_mm")),
            _pct(s.get("within_5mm_pct")), _pct(s.get("within_10mm_pct")))


STATS_HEADERS = ("points", "median [mm]", "RMSE [mm]", "p90 [mm]", "within 5 mm [%]", "within 10 mm [%]")


def heldout_blocks(summary: dict[str, Any]) -> list[Block]:
    held = summary["heldout"]
    rows = [(o["object"], _count(o["keyframes"]), *_stats_cells(o["aggregate"])) for o in held["objects"]]
    agg = held["aggregate"]
    rows.append(("**all (pooled)**", _count(agg.get("keyframes")), *_stats_cells(agg)))
    p = held["paper"]
    rows.append(("paper (DARP, real rig)", _count(p["keyframes"]), _count(p["points"]), _mm(p["median_mm"]),
                 _mm(p["rmse_mm"]), _mm(p["p90_mm"]), _pct(p["within_5mm_pct"]), _pct(p["within_10mm_pct"])))
    arm_rows = [(arm, *_stats_cells(s)) for arm, s in held.get("arms", {}).items()]
    return [Block("h2", "Held-out RGB-D evaluation"),
            Block("p", "Distances of held-out keyframes' points (never fused) to the measured-surface mesh "
                       "(the paper's Table 'Held-Out RGB-D Geometric Evaluation'). Pooled over every point."),
            Block("table", headers=("object", "keyframes", *STATS_HEADERS), rows=tuple(rows)),
            Block("h3", "Per arm (pooled over objects)"),
            Block("table", headers=("arm", *STATS_HEADERS), rows=tuple(arm_rows))]


def object_blocks(per: Sequence[dict[str, Any]]) -> list[Block]:
    rows = []
    for r in per:
        kf, clouds, mesh = r.get("keyframes", {}), r.get("clouds", {}), r.get("mesh", {})
        cross = _cross_median(r.get("cross_arm"))
        truth = (r.get("truth") or {}).get("cloud", {}).get("accuracy", {})
        area_cm2 = None if mesh.get("area_m2") is None else mesh["area_m2"] * 1e4
        rows.append((r["object"], r.get("pose_source", "-"), f"{_count(kf.get('fuse'))} / {_count(kf.get('heldout'))}",
                     _count(clouds.get("arm110")), _count(clouds.get("arm111")), _count(clouds.get("fused")),
                     _count(mesh.get("triangles")), _mm(area_cm2, 1),
                     _mm(r["heldout"]["aggregate"].get("median_mm")), _mm(cross), _mm(truth.get("median_mm"))))
    headers = ("object", "poses", "keyframes fuse / held-out", "arm110 pts", "arm111 pts", "fused pts",
               "mesh triangles", "mesh area [cm²]", "held-out median [mm]", "cross-arm median [mm]",
               "accuracy vs truth median [mm]")
    return [Block("h2", "Per-object results"), Block("table", headers=headers, rows=tuple(rows))]


def _cross_median(cross: dict[str, Any] | None) -> float | None:
    if not cross:
        return None
    values = [d["point_to_plane"].get("median_mm") for d in cross["directions"] if d["point_to_plane"].get("count")]
    return max(values) if values else None


def cross_arm_blocks(per: Sequence[dict[str, Any]]) -> list[Block]:
    rows = []
    for r in per:
        for d in (r.get("cross_arm") or {}).get("directions", []):
            p2p, p2l = d["point_to_point"], d["point_to_plane"]
            rows.append((r["object"], f"{d['source']} → {d['target']}", _count(d["points"]),
                         _pct(d.get("co_observed_pct")), _mm(p2p.get("median_mm")), _mm(p2l.get("median_mm")),
                         _mm(p2l.get("p90_mm")), _pct(p2l.get("within_5mm_pct"))))
    headers = ("object", "direction", "points", "co-observed [%]", "point-to-point median [mm]",
               "point-to-plane median [mm]", "point-to-plane p90 [mm]", "within 5 mm [%]")
    return [Block("h2", "Cross-arm consistency"),
            Block("p", "Separation of the two arms' independently fused partial clouds where both saw the object "
                       "(no registration: it measures calibration and pose timing). Thin walls seen from both "
                       "sides (a mug's rim) count as co-observed and add their thickness."),
            Block("table", headers=headers, rows=tuple(rows) or (("-",) * len(headers),))]


def truth_blocks(summary: dict[str, Any], per: Sequence[dict[str, Any]]) -> list[Block]:
    truth = summary.get("truth")
    if not truth:
        return []
    rows = []
    for r in per:
        t = r.get("truth")
        if not t:
            continue
        acc, comp, f = t["cloud"]["accuracy"], t["cloud"]["completeness"], t["cloud"]["fscore_pct"]
        mesh = t.get("mesh") or {}
        pose = t.get("pose_error", {})
        pose_mm = max((p["translation_median_mm"] for p in pose.values()), default=None)
        gauge = t.get("world_gauge") or {}
        rows.append((r["object"], r.get("pose_source", "-"), _mm(gauge.get("translation_mm")),
                     _mm((gauge.get("accuracy_aligned") or {}).get("median_mm")),
                     _mm(acc.get("median_mm")), _mm(acc.get("rmse_mm")),
                     _mm(acc.get("p90_mm")), _pct(comp.get("within_2mm_pct")), _pct(comp.get("within_5mm_pct")),
                     _pct(comp.get("within_10mm_pct")), _pct(f.get("2mm")), _pct(f.get("5mm")), _pct(f.get("10mm")),
                     _mm((mesh.get("accuracy") or {}).get("median_mm")),
                     _pct((mesh.get("fscore_pct") or {}).get("5mm")), _mm(pose_mm, 3)))
    agg = truth.get("aggregate") or {}
    if agg:
        acc, comp, f = agg["accuracy"], agg["completeness"], agg["fscore_pct"]
        rows.append(("**all (pooled)**", "", "", "", _mm(acc.get("median_mm")), _mm(acc.get("rmse_mm")),
                     _mm(acc.get("p90_mm")), _pct(comp.get("within_2mm_pct")), _pct(comp.get("within_5mm_pct")),
                     _pct(comp.get("within_10mm_pct")), _pct(f.get("2mm")), _pct(f.get("5mm")), _pct(f.get("10mm")),
                     "", "", ""))
    headers = ("object", "poses", "world gauge [mm]", "accuracy, gauge removed, median [mm]",
               "accuracy median [mm]", "RMSE [mm]", "p90 [mm]", "completeness 2 mm [%]",
               "5 mm [%]", "10 mm [%]", "F 2 mm [%]", "F 5 mm [%]", "F 10 mm [%]", "mesh accuracy median [mm]",
               "mesh F 5 mm [%]", "keyframe pose error median [mm]")
    return [Block("h2", "Ground truth (digital twin)"),
            Block("p", "Fused cloud against the true object surface: accuracy (cloud → truth), completeness (seen "
                       "true surface → cloud) and F-score; the mesh's accuracy and F-score; how far the keyframes' "
                       "poses were from the true camera poses. The twin draws its truth in the world as the rig "
                       "defines it and a calibration realises it (midway between the bases, x base to base, z up), so "
                       "accuracy includes the calibration's error in placing the world. The 'world gauge' is the "
                       "part of it that is one rigid offset of the whole world frame at the object (Kabsch fit of "
                       "the keyframes' camera centres to the true ones), invisible to held-out and cross-arm "
                       "measures; accuracy is given with and without it."),
            Block("table", headers=headers, rows=tuple(rows))]


def composition_block(per: Sequence[dict[str, Any]]) -> list[Block]:
    items = []
    for r in per:
        c = r.get("composition")
        if c:
            items.append(SurveyComposition(**{**c, "notes": tuple(c.get("notes", ()))}))
    if not items:
        return []
    return [Block("h2", "Release composition"), Block("raw_md", format_composition(items, "markdown"))]


def figure_blocks(out: Path, folders: Sequence[Path], per: Sequence[dict[str, Any]]) -> list[Block]:
    captions = {"cross_arm": "cross-arm alignment: XY, XZ, YZ projections (arm110 red, arm111 blue)",
                "partial_fused": "arm110 partial, arm111 partial and fused clouds",
                "heldout": "held-out point-to-mesh distances"}
    blocks = [Block("h2", "Figures")]
    for folder, r in zip(folders, per, strict=True):
        blocks.append(Block("h3", r["object"]))
        for kind, caption in captions.items():
            rel = (r.get("figures") or {}).get(kind)
            if rel and (folder / rel).is_file():
                blocks.append(Block("img", text=f"{r['object']}: {caption}",
                                    path=(folder / rel).relative_to(out).as_posix()))
    return blocks


def observation_block(out: Path, folders: Sequence[Path], per: Sequence[dict[str, Any]]) -> list[Block]:
    from darp.evaluation.observations import observations_figure, survey_observations

    rows = []
    for folder, r in zip(folders, per, strict=True):
        found = survey_observations(folder)
        if found:
            rows.append((r["object"], found))
        if len(rows) == MAX_OBSERVATION_OBJECTS:
            break
    if not rows:
        return []
    observations_figure(rows, out / OBSERVATIONS_FIGURE)
    return [Block("h2", "Representative multimodal observations"),
            Block("img", text="RGB, metric depth (colour-mapped), IR left and IR right from each arm",
                  path=OBSERVATIONS_FIGURE)]


# -- rendering --------------------------------------------------------------------------------------------
def to_markdown(blocks: Sequence[Block]) -> str:
    lines: list[str] = []
    for b in blocks:
        if b.kind in ("h1", "h2", "h3"):
            lines += ["#" * int(b.kind[1]) + " " + b.text, ""]
        elif b.kind == "p":
            lines += [b.text, ""]
        elif b.kind == "raw_md":
            lines += [b.text.rstrip("\n"), ""]
        elif b.kind == "table":
            lines.append("| " + " | ".join(map(md_cell, b.headers)) + " |")
            lines.append("|" + "|".join(["---"] + ["---:"] * (len(b.headers) - 1)) + "|")
            lines += ["| " + " | ".join(map(md_cell, row)) + " |" for row in b.rows]
            lines.append("")
        elif b.kind == "img":
            lines += [f"![{b.text}]({b.path})", "", f"*{b.text}*", ""]
    return "\n".join(lines)


def _inline(text: str) -> str:
    escaped = html.escape(text)
    while escaped.count("**") >= 2:
        escaped = escaped.replace("**", "<b>", 1).replace("**", "</b>", 1)
    return escaped


def md_cell(text: str) -> str:
    """A Markdown table cell: ``|`` escaped (a survey named ``a|b`` stays one cell), line breaks as spaces."""
    return " ".join(str(text).replace("|", "\\|").split("\n"))


def _md_cells(line: str) -> list[str]:
    """The cells of one Markdown table row (``\\|`` is a ``|`` inside a cell)."""
    body = line.strip()
    body = body[1:] if body.startswith("|") else body
    body = body[:-1] if body.endswith("|") and not body.endswith("\\|") else body
    return [c.replace("\\|", "|") for c in re.split(r"(?<!\\)\|", body)]


def _md_table_to_html(text: str) -> str:
    rows = [_md_cells(line) for line in text.strip().splitlines() if line.strip().startswith("|")]
    rows = [r for r in rows if not all(set(c.strip()) <= set("-:") for c in r)]
    if not rows:
        return f"<pre>{html.escape(text)}</pre>"
    head = "".join(f"<th>{_inline(c.strip())}</th>" for c in rows[0])
    body = "".join("<tr>" + "".join(f"<td>{_inline(c.strip())}</td>" for c in r) + "</tr>" for r in rows[1:])
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_CSS = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:0.5em 0 1.5em;font-size:0.9em}"
        "th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eef5fa}"
        "td:first-child,th:first-child{text-align:left}img{max-width:100%}figcaption{font-style:italic}")


def to_html(blocks: Sequence[Block], root: Path, title: str) -> str:
    head = f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
    parts = [f"{head}<style>{_CSS}</style></head><body>"]
    for b in blocks:
        if b.kind in ("h1", "h2", "h3"):
            parts.append(f"<{b.kind}>{_inline(b.text)}</{b.kind}>")
        elif b.kind == "p":
            parts.append(f"<p>{_inline(b.text)}</p>")
        elif b.kind == "raw_md":
            parts.append(_md_table_to_html(b.text))
        elif b.kind == "table":
            parts.append(_md_table_to_html(to_markdown([b])))
        elif b.kind == "img":
            data = base64.b64encode((root / b.path).read_bytes()).decode("ascii")
            parts.append(f"<figure><img alt='{html.escape(b.text)}' src='data:image/png;base64,{data}'>"
                         f"<figcaption>{html.escape(b.text)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)


def survey_status(out: str | Path) -> dict[str, dict[str, str]]:
    """What the report must say about surveys that are not ordinary results, each ``{survey: reason}``:
    ``failed`` (batch summary), ``unfinished`` (UNFINISHED.txt), ``missing`` (in the summary, no completed
    results.json) and ``implausible`` (their warnings, joined)."""
    out = Path(out)
    done = {f.name for f in find_survey_results(out)}
    unfinished = find_unfinished(out)
    summary: dict[str, Any] = {}
    if (out / RESULTS_FILE).is_file():
        try:
            candidate = read_results(out)
        except DarpError:  # a damaged summary: the folders still tell what was done
            candidate = {}
        if candidate.get("schema") == "darp-results-summary/1":
            summary = candidate
    failed = {str(row.get("folder") or row.get("name")): f"{row.get('stage')} failed: {row.get('reason')}"
              for row in summary.get("failed") or [] if str(row.get("folder") or row.get("name")) not in done}
    listed = [str(row.get("folder") or row.get("name")) for row in summary.get("surveys") or []]
    missing = {name: f"in {RESULTS_FILE} but {out / name} holds no completed results" for name in listed
               if name not in done and name not in unfinished and name not in failed}
    implausible, untrusted = {}, {}
    for folder in find_survey_results(out):
        results = read_results(folder)
        warnings = results.get("warnings") or []
        if warnings:
            implausible[folder.name] = "; ".join(warnings)
        flags = (results.get("trust") or {}).get("flags") or []
        if flags:
            untrusted[folder.name] = "; ".join(flags)
    unfinished = {name: reason for name, reason in unfinished.items() if name not in failed}
    return {"failed": failed, "unfinished": unfinished, "missing": missing, "implausible": implausible,
            "not trusted": untrusted}


def status_blocks(status: dict[str, dict[str, str]]) -> list[Block]:
    """The report's first section: surveys that are not ordinary results."""
    rows = tuple((name, kind, reason) for kind in ("failed", "unfinished", "missing", "implausible", "not trusted")
                 for name, reason in sorted(status.get(kind, {}).items()))
    if not rows:
        return [Block("p", "Every survey completed with plausible results.")]
    return [Block("h2", "Surveys that are not ordinary results"),
            Block("p", "Failed, unfinished and missing surveys are not in the tables below; implausible ones "
                       "are, flagged (!), and those whose trust signals (cross-arm, hand-eye, per-arm tails, "
                       "coverage, truth) disagree with the held-out figures or leave their bounds, flagged (?)."),
            Block("table", headers=("survey", "status", "reason"), rows=rows)]


def write_report(out: str | Path) -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.html`` into ``out`` (a ``darp process`` output folder)."""
    out = Path(out)
    folders = find_survey_results(out)
    status = survey_status(out)
    if not folders:
        problems = [f"{name} ({kind}: {reason})" for kind in ("failed", "unfinished", "missing")
                    for name, reason in status[kind].items()]
        hint = f"; {', '.join(problems)}" if problems else ""
        raise EvaluationError(f"no processed survey here (no <survey>/{RESULTS_FILE} of a completed run; "
                              f"run darp process first){hint}", out)
    per = [read_results(f) for f in folders]
    summary_path = out / RESULTS_FILE
    summary = read_results(summary_path) if summary_path.is_file() and folders != [out] else None
    if (summary is None or summary.get("schema") != "darp-results-summary/1" or summary.get("heldout") is None
            or sorted(s.get("folder") for s in summary.get("surveys", [])) != sorted(f.name for f in folders)):
        summary = aggregate_results(folders)  # stale or partial summary: recomputed from the completed surveys
    sources = sorted({r.get("pose_source", "calibration") for r in per})
    title = "darp processing report"
    names = ", ".join(r["object"] + (" (!)" if r.get("warnings") else "")
                      + (" (?)" if (r.get("trust") or {}).get("flags") else "") for r in per)
    blocks = [Block("h1", title),
              Block("p", f"{len(per)} survey(s): {names}. Camera poses from: {', '.join(sources)}.")]
    blocks += status_blocks(status)
    blocks += composition_block(per)
    blocks += heldout_blocks(summary)
    blocks += object_blocks(per)
    blocks += cross_arm_blocks(per)
    blocks += truth_blocks(summary, per)
    blocks += observation_block(out, folders, per)
    blocks += figure_blocks(out, folders, per)
    md_path, html_path = out / "report.md", out / "report.html"
    write_text_atomic(md_path, to_markdown(blocks))
    write_text_atomic(html_path, to_html(blocks, out, title))
    return md_path, html_path


__all__ = ["Block", "status_blocks", "survey_status", "to_html", "to_markdown", "write_report"]
