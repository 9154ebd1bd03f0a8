"""The calibration report folder: figures and a readable summary of a solve.

    report.json                 the calibration's report block (same as in the calibration file)
    summary.md                  tables: per arm fit and held-out errors, identifiability, methods, truth
    per_capture_error.png       per-capture median reprojection error, fit and held-out, both arms
    residual_vectors.png        final residual vectors over the image (magnified), one panel per arm
    heldout_histogram.png       held-out 3-D corner error histogram per arm, next to the paper's values
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp import paper
from darp.calibration.model import per_capture, reprojection_errors
from darp.calibration.solve import METHOD_LABELS, SolveOutcome
from darp.colours import ARM_COLOURS
from darp.formats.atomic import atomic_path, write_text_atomic
from darp.formats.schema import write_json_checked

COLOURS = {0: ARM_COLOURS["arm110"], 1: ARM_COLOURS["arm111"]}  # by the rig's arm index


def save_png(fig: Any, path: Path) -> None:
    """Save a matplotlib figure as a PNG report figure, atomically."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)


def write_report(outcome: SolveOutcome, folder: str | Path) -> list[Path]:
    """Write the report folder; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    obs, params = outcome.observations, outcome.methods["darp"]
    written = []
    write_json_checked(folder / "report.json", outcome.calibration.report)
    written.append(folder / "report.json")

    # per-capture errors
    fit = per_capture(reprojection_errors(params, obs), obs)
    held = outcome.heldout.get("darp", {}).get("per_capture", {})
    fig = Figure(figsize=(11, 4))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(obs.n_captures)
    colours = [COLOURS.get(int(a), "grey") for a in obs.arm_index]
    ax.bar(x - 0.2, fit, width=0.4, color=colours, alpha=0.5, label="fit (all captures)")
    ax.bar(x + 0.2, [held.get(c, {}).get("reprojection_px", np.nan) for c in obs.capture_ids], width=0.4,
           color=colours, label="held-out (capture withheld)")
    ax.set_xticks(x, obs.capture_ids, rotation=90, fontsize=6)
    ax.set_ylabel("median reprojection error (px)")
    ax.set_title(f"Per-capture reprojection error ({obs.arms[0]} red, {obs.arms[1]} blue)")
    ax.legend()
    fig.tight_layout()
    save_png(fig, folder / "per_capture_error.png")
    written.append(folder / "per_capture_error.png")

    # residual vectors
    res = (outcome.core.paper or outcome.core.refined).residual_px
    fig = Figure(figsize=(12, 4.8))
    scale = arrow_scale(float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))) if len(res) else 0.0)
    for a, arm in enumerate(obs.arms):
        ax = fig.add_subplot(1, 2, a + 1)
        sel = obs.arm_index[obs.corner_capture] == a
        uv = obs.uv[sel]
        ax.quiver(uv[:, 0], uv[:, 1], res[sel, 0] * scale, res[sel, 1] * scale, angles="xy", scale_units="xy",
                  scale=1.0, width=0.002, color=COLOURS[a])
        K = obs.K[obs.arm_index == a]
        w = 2 * float(np.median(K[:, 0, 2])) if len(K) else 640
        h = 2 * float(np.median(K[:, 1, 2])) if len(K) else 480
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        rms = float(np.sqrt(np.mean(np.sum(res[sel] ** 2, axis=1)))) if sel.any() else 0.0
        ax.set_title(f"{arm}: residuals x{scale:g} (RMS {rms:.3f} px)")
    fig.tight_layout()
    save_png(fig, folder / "residual_vectors.png")
    written.append(folder / "residual_vectors.png")

    # held-out histogram
    if "darp" in outcome.heldout:
        fig = Figure(figsize=(10, 4))
        for a, arm in enumerate(obs.arms):
            ax = fig.add_subplot(1, 2, a + 1)
            v = outcome.heldout["darp"]["per_arm"][arm]["corner_3d_mm"]
            top = float(np.percentile(v, 99.5)) * 1.1 if len(v) else 1.0
            ax.hist(np.minimum(v, top), bins=40, range=(0.0, top), color=COLOURS[a], alpha=0.8)
            ax.axvline(float(np.median(v)), color="black", lw=1, label=f"median {np.median(v):.3f} mm")
            paper_mm = paper.HANDEYE_HELDOUT_MM.get(arm)
            if paper_mm is not None and paper_mm <= top:
                ax.axvline(paper_mm, color="grey", ls="--", lw=1, label=f"paper {paper_mm} mm")
            elif paper_mm is not None:
                ax.plot([], [], " ", label=f"paper {paper_mm} mm (off scale, "
                        f"x{paper_mm / max(np.median(v), 1e-9):.0f})")
            ax.set_xlim(0.0, top)
            ax.set_xlabel("held-out 3-D corner error (mm)")
            ax.set_title(arm)
            ax.legend(fontsize=8)
        fig.tight_layout()
        save_png(fig, folder / "heldout_histogram.png")
        written.append(folder / "heldout_histogram.png")

    write_text_atomic(folder / "summary.md", summary_markdown(outcome))
    written.append(folder / "summary.md")
    return written


def summary_markdown(outcome: SolveOutcome) -> str:
    """A readable summary of the solve (tables in Markdown)."""
    cal, rep = outcome.calibration, outcome.calibration.report
    lines = [f"# Calibration {cal.epoch}", "", f"- date: {cal.date}",
             f"- captures: {rep['n_captures']} ({rep['n_used']} used); pixel noise {rep['sigma_px']:.3f} px",
             f"- world frame: {cal.world_frame}", ""]
    if rep["rejected"]:
        lines += ["Rejected captures:", ""] + [f"- {k}: {v}" for k, v in rep["rejected"].items()] + [""]
    lines += ["## Per arm", "", ("| arm | captures | fit px (median) | held-out 3-D mm (median / p90) | "
                                 "held-out ray mm | held-out px | hand-eye std (mm, deg) |"),
              "|---|---|---|---|---|---|---|"]
    for arm, a in cal.arms.items():
        r = a.residuals
        h = r.get("heldout", {})
        he = r["hand_eye_std"]
        lines.append(
            f"| {arm} | {a.n_captures} | {r['fit_reprojection_px']['median']:.3f} | "
            + (f"{h['corner_3d_mm']['median']:.3f} / {h['corner_3d_mm']['p90']:.3f} | {h['ray_mm']['median']:.3f} | "
               f"{h['reprojection_px']['median']:.3f}" if h else "- | - | -")
            + f" | {max(he['translation_mm']):.3f}, {max(he['rotation_deg']):.4f} |")
    lines += ["", "## Joint-zero offsets (deg)", "", "| arm | " + " | ".join(f"joint{j}" for j in range(1, 7)) + " |",
              "|---|" + "---|" * 6]
    for arm, a in cal.arms.items():
        cells = []
        for j in range(6):
            if a.identifiable is not None and not a.identifiable[j]:
                cells.append("fixed (not identifiable)")
            else:
                std = a.joint_offsets_std_rad[j] if a.joint_offsets_std_rad is not None else 0.0
                cells.append(f"{np.degrees(a.joint_offsets_rad[j]):+.4f} +- {np.degrees(std):.4f}")
        lines.append(f"| {arm} | " + " | ".join(cells) + " |")
    ident = rep.get("identifiability")
    if ident:
        lines += ["", ("Identifiability: unique fraction rho of each offset's effect (0 = imitated exactly by "
                       "other unknowns):"), ""]
        for arm, rho in ident["rho"].items():
            lines.append(f"- {arm}: " + ", ".join(f"j{j + 1} {v:.2g}" for j, v in enumerate(rho)))
        for k, v in ident["degenerate_with"].items():
            lines.append(f"- {k} is imitated by {', '.join(v)}")
    kin = rep.get("kinematics")
    if kin:
        lines += ["", f"## Arm model: {kin['model']}", "",
                  "Fit reprojection RMS (px): " + "; ".join(
                      f"{m}: " + ", ".join(f"{a} {v:.3f}" for a, v in per.items())
                      for m, per in kin["fit_rms_px"].items() if per), "",
                  "| arm | parameter | status | value | std | prior std | unique fraction | reason |",
                  "|---|---|---|---|---|---|---|---|"]
        for arm, entry in cal.arms.items():
            k = entry.kinematics or {}
            values = np.concatenate([np.ravel(k.get("joint_origin_offsets_m", np.zeros(18))),
                                     np.ravel(k.get("joint_axis_tilts_rad", np.zeros(18))),
                                     np.ravel(k.get("compliance_rad_per_nm", np.zeros(6)))[1:4],
                                     np.ravel(k.get("backlash_rad", np.zeros(6)))])
            for i, row in enumerate(kin["table"].get(arm, [])):
                if row["status"] == "no effect":
                    continue
                std = k.get("std", {}).get(row["parameter"])
                lines.append(f"| {arm} | {row['parameter']} | {row['status']} | {values[i]:.3g} | "
                             f"{'-' if std is None else f'{std:.2g}'} | {row['prior_std']:.2g} | {row['rho']:.3f} | "
                             f"{row.get('reason', '')} |")
        lines += ["", "Units: origins m, tilts rad, compliance rad/N m, backlash rad. Tilts about a joint's own "
                  "axis change nothing and are not listed."]
    held = rep.get("heldout", {})
    if held:
        lines += ["", "## Methods: held-out 3-D corner error (median mm)", "", "| method | "
                  + " | ".join(cal.arms) + " |", "|---|" + "---|" * len(cal.arms)]
        for name, per_arm in held.items():
            lines.append(f"| {METHOD_LABELS.get(name, name)} | "
                         + " | ".join(f"{per_arm[a]['corner_3d_mm']['median']:.3f}" for a in cal.arms) + " |")
    truth = rep.get("truth")
    if truth:
        lines += ["", "## Against truth", "", ("| method | hand-eye mm (worse arm) | hand-eye deg | "
                                                "base-to-base mm | base-to-base deg | joint offsets deg (max) | "
                                                "camera pose mm (median) |"),
                  "|---|---|---|---|---|---|---|"]
        for name, t in truth.items():
            arms = t["arms"].values()
            dq = [a["max_identifiable_joint_offset_error_deg"] for a in arms]
            dq_text = "-" if any(v is None for v in dq) else f"{max(dq):.4f}"
            lines.append(
                f"| {name} | {max(a['hand_eye']['translation_mm'] for a in arms):.3f} | "
                f"{max(a['hand_eye']['rotation_deg'] for a in arms):.4f} | {t['base_to_base']['translation_mm']:.3f} | "
                f"{t['base_to_base']['rotation_deg']:.4f} | {dq_text} | "
                f"{max(a.get('camera_pose', {}).get('translation_mm_median', float('nan')) for a in arms):.3f} |")
    lines += ["", "Timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in rep["timings_s"].items()), ""]
    return "\n".join(lines)


__all__ = ["summary_markdown", "write_report"]


def arrow_scale(rms_px: float, target_px: float = 10.0) -> float:
    """The magnification that draws an RMS residual about ``target_px`` long, on a 1-2-5 scale (x200 for the
    realistic profile's ~0.05 px, x2 for the paper profile's ~4 px), so the arrows stay readable at any size."""
    if not np.isfinite(rms_px) or rms_px <= 0.0:
        return 1.0
    raw = target_px / rms_px
    decade = 10.0 ** np.floor(np.log10(raw))
    return float(max(step * decade for step in (1.0, 2.0, 5.0) if step * decade <= raw))

