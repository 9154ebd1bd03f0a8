"""``results.json``: the machine-readable results of one processed survey and of all surveys together.

Per survey (``<out>/<survey>/results.json``, schema ``darp-results/1``)::

    survey, object, pose_source ("calibration" | "truth"), calibration {epoch, path}
    composition     the release-composition row (radius, height, standoff, rows, duration, depth frames, size)
    envelope        the object cylinder used:
                    {source: "manip_envelope.json" | "estimated", center_m, radius_m, height_m}
    keyframes       {total, fuse, heldout, arms: {arm: {frames, posed, settled, in_view, views, keyframes, heldout}}}
    clouds          {arm110, arm111, fused}: points per cloud;  mesh {vertices, triangles, area_m2, radii_m}
    heldout         {object, keyframes, aggregate, arms}: count, median/mean/rmse/p90/max in mm, % within 5/10 mm
    cross_arm       {cell_mm, directions: [{source, target, points, co_observed, point_to_point, point_to_plane}]}
    truth           null, or {samples, seen, cloud, mesh, pose_error[, seeable]}: accuracy and completeness
                    statistics (mm, % within 2/5/10 mm), F-score % at 2/5/10 mm, keyframe pose error vs the true
                    poses; seeable (surveys that recorded feasible poses): {poses, samples, of_mesh_pct,
                    co_seeable_pct, seen_by_keyframes_pct, completeness_pct[, missing_by_cause]} against the
                    surface any feasible pose can see (co_seeable_pct: the share of it feasible poses of both
                    arms see within the seeable rules); missing_by_cause {missing,
                    threshold_mm, count, share_pct}: where each seeable sample beyond 5 mm of the fused cloud
                    was lost (evaluation.truth_metrics)
    figures         {kind: path relative to the survey folder}
    stages          {stage: seconds}
    status          "ok", or "implausible" when ``warnings`` is not empty
    warnings        implausible results, each one line (:mod:`darp.processing.diagnostics`): an arm's cloud
                    empty, fewer keyframes per arm than keyframes.min_keyframes, a fused cloud almost empty (its
                    voxels cover less than evaluation.min_surface_pct of the envelope's top and side), no held-out
                    point, a held-out median above evaluation.max_heldout_median_mm, a twin survey's fused cloud
                    farther from the true surface than evaluation.max_truth_accuracy_mm, a partial survey
                    (PARTIAL.txt / *.bag.partial)
    trust           {signals, flags, bounds} (:mod:`darp.evaluation.trust`): the signals that can see a result the
                    held-out figures cannot (cross-arm disagreement, the calibration's held-out error, per-arm
                    held-out tails, coverage, on twin surveys the truth) and one line per signal that leaves its
                    bound or disagrees with the held-out median; shown (?) in the table and the report
    paper           the paper's held-out numbers (:data:`darp.paper.HELDOUT`: median, RMSE, p90, within 5 / 10 mm,
                    keyframes, points)

Across surveys (``<out>/results.json``, schema ``darp-results-summary/1``)::

    status          "ok", "warnings" (some survey implausible) or "failed" (some survey failed)
    surveys         [{name, object, pose_source, folder, status, warnings}] of the processed surveys
    failed          [{name, survey_path, folder, status, stage, reason}]: surveys that did not complete
    warnings        {survey: [warning]} of the processed surveys
    heldout         {objects: [per-object rows], aggregate (pooled points), arms (pooled per arm), paper}
    cross_arm       {survey: per-survey cross_arm}
    truth           {objects: {survey: truth}, aggregate: pooled accuracy/completeness/F-score} or null
    paper           as above

Pooled statistics are computed from the raw distances each survey keeps in ``evaluation/``, never by
averaging per-object statistics. The evaluation stage (:mod:`darp.processing.stages`) writes a survey's
document with :func:`survey_results`; ``darp process`` writes the summary with :func:`write_summary`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from darp import paper
from darp.errors import EvaluationError, FormatError
from darp.evaluation.heldout import HeldoutResult, HeldoutSummary
from darp.evaluation.point_to_mesh import distance_stats
from darp.evaluation.trust import envelope_coverage_pct, trust_signals
from darp.evaluation.truth_metrics import TRUTH_THRESHOLDS_M
from darp.formats.atomic import write_json_atomic
from darp.formats.io_input import LIMITS
from darp.formats.schema import to_jsonable
from darp.formats.text import read_utf8_text
from darp.processing.diagnostics import plausibility_warnings
from darp.processing.evaluate import EVALUATION_DIR, HELDOUT_DISTANCES, TRUTH_DISTANCES, load_distances
from darp.processing.job import SurveyJob
from darp.processing.runner import read_stage_state, unfinished_reason
from darp.processing.settings import DEPTH_FILTER_RULES, FUSION_RULES, MESH_RULES, ProcessSettings

RESULTS_FILE = "results.json"
SCHEMA = "darp-results/1"
SUMMARY_SCHEMA = "darp-results-summary/1"


def rules_used(settings: ProcessSettings) -> dict[str, Any]:
    """The values ``corrections.fusion`` and ``corrections.mesh`` used, per switch that is on (a value the
    settings file gave wins)."""
    out: dict[str, Any] = {}
    if settings.corrections.fusion:
        used = settings.fusion_used
        out["fusion"] = {**{k: getattr(used, k) for k in FUSION_RULES},
                         "depth": {k: getattr(used.depth, k) for k in DEPTH_FILTER_RULES}}
    if settings.corrections.mesh:
        out["mesh"] = {k: getattr(settings.mesh_used, k) for k in MESH_RULES}
    return out


def survey_results(job: SurveyJob, evaluation: dict[str, Any]) -> dict[str, Any]:
    """The per-survey results document from the stage summaries and the evaluation."""
    stages = read_stage_state(job.out).get("stages", {})
    summary = {name: state.get("summary") or {} for name, state in stages.items()}
    keyframes = summary.get("keyframes", {})
    heldout = evaluation["heldout"]
    results = {
        "schema": SCHEMA,
        "survey": job.survey.name,
        "survey_path": str(job.survey.path),
        "object": heldout.get("object") or job.survey.name,
        "pose_source": "truth" if job.truth_poses else "calibration",
        # darp's improvements applied ("paper" = none: poses from calibration and kinematics, as the paper)
        "corrections": {"mode": job.settings.corrections.label, "applied": list(job.settings.corrections.applied),
                        **({"kinematics": summary["poses"]["kinematics"]}
                           if "kinematics" in summary.get("poses", {}) else {}),
                        **({"depth": keyframes["depth_correction"]} if keyframes.get("depth_correction") else {}),
                        **({"time": summary["poses"]["time_alignment"]}
                           if (summary.get("poses") or {}).get("time_alignment") else {}),
                        **({"refine": keyframes["refine"]} if keyframes.get("refine") is not None else {}),
                        **({"table": summary["fusion"]["table"]}
                           if (summary.get("fusion") or {}).get("table") else {}),
                        **rules_used(job.settings)},
        "calibration": {"epoch": job.calibration.epoch,
                        "path": None if job.calibration_path is None else str(job.calibration_path)},
        "composition": evaluation.get("composition"),
        "envelope": keyframes.get("envelope"),
        "keyframes": {"total": keyframes.get("keyframes"), "fuse": keyframes.get("fuse"),
                      "heldout": keyframes.get("heldout"), "arms": keyframes.get("arms", {})},
        "clouds": summary.get("fusion", {}).get("points", {}),
        "mesh": summary.get("mesh", {}),
        "heldout": heldout,
        "cross_arm": evaluation.get("cross_arm"),
        "truth": evaluation.get("truth"),
        "figures": evaluation.get("figures", {}),
        "stages": {name: state.get("seconds") for name, state in stages.items()},
        "paper": paper.HELDOUT,
    }
    warnings = plausibility_warnings(results, job)
    results["status"] = "implausible" if warnings else "ok"
    results["warnings"] = warnings
    uncertainty = job.calibration_uncertainty()
    coverage = envelope_coverage_pct(int((results.get("clouds") or {}).get("fused", 0) or 0),
                                     results.get("envelope") or {}, job.settings.fusion_used.voxel_size_m)
    results["trust"] = trust_signals(results, handeye_p90_mm=None if uncertainty is None else 1000.0 * uncertainty,
                                     envelope_pct=coverage)
    return results


# -- reading and aggregating --------------------------------------------------------------------------------
def read_results(path: str | Path) -> dict[str, Any]:
    """A ``results.json`` (per survey or summary); ``path`` may be its folder."""
    path = Path(path)
    file = path / RESULTS_FILE if path.is_dir() else path
    try:
        data = json.loads(read_utf8_text(file, "a JSON file", limit=LIMITS["json"]))
    except FileNotFoundError:
        raise FormatError(f"no {RESULTS_FILE} (run darp process first)", path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise FormatError(f"invalid JSON: {err}", file) from err
    if not isinstance(data, dict) or data.get("schema") not in (SCHEMA, SUMMARY_SCHEMA):
        schema = data.get("schema") if isinstance(data, dict) else None
        raise FormatError(f"not a darp results file (schema {schema!r})", file)
    return data


def find_survey_results(out: str | Path) -> list[Path]:
    """Survey output folders under ``out`` holding a per-survey results.json of a COMPLETED run (no
    ``UNFINISHED.txt``), sorted by name; :func:`find_unfinished` lists the others."""
    out = Path(out)
    if not out.is_dir():
        raise EvaluationError("no such output folder", out)
    if (out / RESULTS_FILE).is_file() and read_results(out).get("schema") == SCHEMA:
        return [] if unfinished_reason(out) is not None else [out]
    return [p for p in sorted(out.iterdir())
            if p.is_dir() and (p / RESULTS_FILE).is_file() and unfinished_reason(p) is None]


def find_unfinished(out: str | Path) -> dict[str, str]:
    """Survey output folders under ``out`` (or ``out`` itself) whose processing did not complete:
    ``{folder name: reason}`` from their ``UNFINISHED.txt``."""
    out = Path(out)
    if not out.is_dir():
        return {}
    candidates = [out] if unfinished_reason(out) is not None else [p for p in sorted(out.iterdir()) if p.is_dir()]
    return {p.name: reason for p in candidates if (reason := unfinished_reason(p)) is not None}


def _heldout_result(folder: Path, results: dict[str, Any]) -> HeldoutResult:
    distances = load_distances(folder / EVALUATION_DIR / HELDOUT_DISTANCES)
    frames = {arm: int(row.get("keyframes", 0)) for arm, row in results["heldout"].get("arms", {}).items()}
    return HeldoutResult(results.get("object") or results["survey"], distances, frames)


def _pooled_truth(folders: Sequence[Path]) -> dict[str, Any] | None:
    parts: dict[str, list[np.ndarray]] = {"accuracy": [], "completeness": []}
    for folder in folders:
        arrays = load_distances(folder / EVALUATION_DIR / TRUTH_DISTANCES)
        for key, found in parts.items():
            if key in arrays:
                found.append(arrays[key])
    if not parts["accuracy"]:
        return None
    acc = distance_stats(np.concatenate(parts["accuracy"]), TRUTH_THRESHOLDS_M)
    comp = distance_stats(np.concatenate(parts["completeness"]) if parts["completeness"] else np.empty(0),
                          TRUTH_THRESHOLDS_M)
    fscore = {}
    for t in TRUTH_THRESHOLDS_M:
        p, r = acc.within_pct[t], comp.within_pct[t]
        fscore[f"{t * 1000:g}mm"] = None if np.isnan(p) or np.isnan(r) else round(
            0.0 if p + r == 0 else 2 * p * r / (p + r), 4)
    return {"surveys": len(parts["accuracy"]), "accuracy": acc.to_dict(), "completeness": comp.to_dict(),
            "fscore_pct": fscore}


def aggregate_results(folders: Sequence[str | Path],
                      failed: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:
    """The summary across processed surveys (pooled held-out points, per-object rows, truth), with the
    ``failed`` surveys (``SurveyOutcome.to_dict()`` rows) listed."""
    paths = [Path(f) for f in folders]
    if not paths and not failed:
        raise EvaluationError("no processed surveys to aggregate")
    per = [read_results(f) for f in paths]
    summary = HeldoutSummary(tuple(_heldout_result(f, r) for f, r in zip(paths, per, strict=True))) if per else None
    truth_rows = {r["survey"]: r["truth"] for r in per if r.get("truth")}
    warnings = {r["survey"]: list(r.get("warnings") or []) for r in per if r.get("warnings")}
    return {
        "schema": SUMMARY_SCHEMA,
        "status": "failed" if failed else "warnings" if warnings else "ok",
        "surveys": [{"name": r["survey"], "object": r.get("object"), "pose_source": r.get("pose_source"),
                     "folder": f.name, "status": r.get("status", "ok"), "warnings": list(r.get("warnings") or []),
                     **({"trust_flags": r["trust"]["flags"]} if (r.get("trust") or {}).get("flags") else {})}
                    for f, r in zip(paths, per, strict=True)],
        "failed": [dict(row) for row in failed],
        "warnings": warnings,
        "heldout": None if summary is None else summary.to_dict(),
        "cross_arm": {r["survey"]: r.get("cross_arm") for r in per},
        "truth": None if not truth_rows else {"objects": truth_rows, "aggregate": _pooled_truth(paths)},
        "paper": paper.HELDOUT,
    }


def write_summary(out: str | Path, folders: Sequence[str | Path], failed: Sequence[dict[str, Any]] = ()) -> Path:
    """Aggregate ``folders`` (and list ``failed``) and write ``<out>/results.json``."""
    path = Path(out) / RESULTS_FILE
    Path(out).mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, to_jsonable(aggregate_results(folders, failed)))
    return path


__all__ = [
    "RESULTS_FILE",
    "SCHEMA",
    "SUMMARY_SCHEMA",
    "aggregate_results",
    "find_survey_results",
    "find_unfinished",
    "read_results",
    "rules_used",
    "survey_results",
    "write_summary",
]
