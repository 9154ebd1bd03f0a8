"""The report folder of an any-arm hand-eye calibration (the figures ``darp calib solve --report`` makes).

    report.json                 the calibration's report block
    summary.md                  fit and held-out tables, darp beside each OpenCV method
    per_capture_error.png       per capture: held-out board consistency (mm) and fit reprojection (px)
    residual_vectors.png        final reprojection residuals over the image (magnified), one panel per arm
    heldout_histogram.png       held-out 3-D corner error and board consistency histograms
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from darp.calibration.anyarm import HandEyeOutcome
from darp.calibration.model import per_capture, reprojection_errors
from darp.calibration.report import save_png
from darp.formats.atomic import write_text_atomic
from darp.formats.schema import write_json_checked

COLOURS = ("tab:red", "tab:blue", "tab:green", "tab:orange")


def write_handeye_report(outcome: HandEyeOutcome, folder: str | Path) -> list[Path]:
    """Write the report folder; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    obs, rep = outcome.observations, outcome.calibration.report
    write_json_checked(folder / "report.json", rep)
    written = [folder / "report.json"]

    fit_px = per_capture_fit_px(outcome)
    held = outcome.consistency.get("per_capture", {})
    fig = Figure(figsize=(11, 5.5))
    x = np.arange(obs.n_captures)
    colours = [COLOURS[int(a) % len(COLOURS)] for a in obs.arm_index]
    ax = fig.add_subplot(2, 1, 1)
    ax.bar(x, [held.get(c, {}).get("mm", np.nan) for c in obs.capture_ids], color=colours)
    ax.set_ylabel("held-out board\nconsistency (mm)")
    ax.set_xticks(x, [])
    ax.set_title("Per capture: board placed by that capture vs the calibration made without it")
    ax = fig.add_subplot(2, 1, 2)
    ax.bar(x, fit_px, color=colours, alpha=0.6)
    ax.set_ylabel("fit reprojection\nmedian (px)")
    ax.set_xticks(x, obs.capture_ids, rotation=90, fontsize=6)
    fig.tight_layout()
    save_png(fig, folder / "per_capture_error.png")
    written.append(folder / "per_capture_error.png")

    res = darp_residual(outcome)
    fig = Figure(figsize=(6 * len(obs.arms), 4.8))
    scale = 50.0
    for a, arm in enumerate(obs.arms):
        ax = fig.add_subplot(1, len(obs.arms), a + 1)
        sel = obs.arm_index[obs.corner_capture] == a
        uv = obs.uv[sel]
        ax.quiver(uv[:, 0], uv[:, 1], res[sel, 0] * scale, res[sel, 1] * scale, angles="xy", scale_units="xy",
                  scale=1.0, width=0.002, color=COLOURS[a % len(COLOURS)])
        K = obs.K[obs.arm_index == a][0]
        ax.set_xlim(0, 2 * K[0, 2])
        ax.set_ylim(2 * K[1, 2], 0)
        ax.set_aspect("equal")
        rms = float(np.sqrt(np.mean(np.sum(res[sel] ** 2, axis=1)))) if sel.any() else 0.0
        ax.set_title(f"{arm}: residuals x{scale:.0f} (RMS {rms:.3f} px)")
    fig.tight_layout()
    save_png(fig, folder / "residual_vectors.png")
    written.append(folder / "residual_vectors.png")

    if outcome.heldout:
        fig = Figure(figsize=(11, 4))
        ax = fig.add_subplot(1, 2, 1)
        for a, arm in enumerate(obs.arms):
            v = outcome.heldout["per_arm"][arm]["corner_3d_mm"]
            ax.hist(v, bins=40, color=COLOURS[a % len(COLOURS)], alpha=0.6,
                    label=f"{arm}: median {np.median(v):.2f} mm")
        ax.set_xlabel("held-out 3-D corner error (mm)")
        ax.legend(fontsize=8)
        ax = fig.add_subplot(1, 2, 2)
        v = np.array([h["mm"] for h in held.values()])
        ax.hist(v, bins=20, color="grey")
        ax.axvline(float(np.mean(v)), color="black", lw=1, label=f"mean {np.mean(v):.2f} mm, max {np.max(v):.2f}")
        ax.set_xlabel("held-out board consistency (mm)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        save_png(fig, folder / "heldout_histogram.png")
        written.append(folder / "heldout_histogram.png")

    write_text_atomic(folder / "summary.md", summary_markdown(outcome))
    written.append(folder / "summary.md")
    return written


def per_capture_fit_px(outcome: HandEyeOutcome) -> np.ndarray:
    """(M,) each capture's median reprojection error with the flange poses the fit used (sag corrected), the
    same errors as the report's ``fit.reprojection_px``."""
    from darp.calibration.anyarm_refine import corrected_observations

    obs = corrected_observations(outcome.params, outcome.observations)
    return per_capture(reprojection_errors(outcome.params, obs), obs)


def darp_residual(outcome: HandEyeOutcome) -> np.ndarray:
    """(C, 2) final reprojection residuals of the calibration."""
    from darp.calibration.anyarm_refine import corrected_observations
    from darp.calibration.model import predict_pixels

    obs = corrected_observations(outcome.params, outcome.observations)
    return np.asarray(predict_pixels(outcome.params, obs) - obs.uv)


def summary_markdown(outcome: HandEyeOutcome) -> str:
    """Fit and held-out tables in Markdown."""
    rep = outcome.calibration.report
    lines = [f"# Hand-eye calibration ({rep['mode']})", "", f"- captures folder: {rep['captures_folder']}",
             f"- board: {rep['board']}", f"- captures used: {rep['n_captures']}", ""]
    if rep["rejected"]:
        lines += ["Rejected captures:", ""] + [f"- {k}: {v}" for k, v in rep["rejected"].items()] + [""]
    if rep["warnings"]:
        lines += ["Warnings:", ""] + [f"- {w}" for w in rep["warnings"]] + [""]
    for arm, a in outcome.calibration.arms.items():
        T = np.asarray(a.T_wrist_cam)
        lines += [f"## {arm}", "", "T_wrist_cam (flange -> camera, m):", "", "```",
                  "\n".join(" ".join(f"{v: .6f}" for v in row) for row in T), "```", ""]
    f = rep["fit"]
    lines += ["## Fit (all captures)", "",
              f"- reprojection median {f['reprojection_px']['median']:.3f} px",
              f"- board consistency mean {f['board_consistency_mm']['mean']:.3f} mm / max "
              f"{f['board_consistency_mm']['max']:.3f} mm", ""]
    h = rep["heldout"]
    if h.get("board_consistency_mm"):
        lines += [f"## Held-out board consistency ({h['folds']} folds; {h.get('split', '')})", "",
                  "Centre: the board's centre; corner: the board frame's origin (where most tools score).", "",
                  "| method | centre mean mm | centre max mm | corner mean mm | corner max mm | mean deg | max deg |",
                  "|---|---|---|---|---|---|---|",
                  _row(f"darp ({rep['refinement']})", h["board_consistency_mm"],
                       h.get("board_corner_consistency_mm") or h["board_consistency_mm"], h["board_consistency_deg"])]
        for m, v in rep.get("opencv_heldout_board_consistency", {}).items():
            lines.append(_row(m, v["mm"], v.get("corner_mm", v["mm"]), v["deg"]) if "mm" in v
                         else f"| {m} | failed | | | | | |")
    return "\n".join(lines) + "\n"


def _row(name: str, mm: dict[str, float], corner: dict[str, float], deg: dict[str, float]) -> str:
    return (f"| {name} | {mm['mean']:.3f} | {mm['max']:.3f} | {corner['mean']:.3f} | {corner['max']:.3f} | "
            f"{deg['mean']:.3f} | {deg['max']:.3f} |")


__all__ = ["per_capture_fit_px", "summary_markdown", "write_handeye_report"]
